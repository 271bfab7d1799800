"""The tile client's server choice (services/localizer/tiles.py server_order), pure: rendezvous
hashing over (client, tile) spreads reads over the tile servers and moves only a leaving server's
share; and the tile-server keys it queries (common/keys.py)."""

from collections import Counter

import pytest

from common import keys
from common.errors import CodecError
from services.localizer.tiles import server_order

TILES = [(tx, ty) for tx in range(-8, 8) for ty in range(-8, 8)]  # 256 tiles


def test_server_order_ranks_every_server_once_and_is_deterministic():
    servers = ["t0", "t1", "t2"]
    order = server_order("car-1", (3, -4), servers)
    assert sorted(order) == servers
    assert server_order("car-1", (3, -4), list(reversed(servers))) == order
    assert server_order("car-1", (3, -4), []) == []


def test_one_clients_tiles_spread_evenly_over_two_servers():
    share = Counter(server_order("car-1", t, ["t0", "t1"])[0] for t in TILES)
    assert set(share) == {"t0", "t1"}
    assert abs(share["t0"] - share["t1"]) < 0.2 * len(TILES)  # binomial: sd 8 of 128


def test_different_clients_pick_different_servers_for_one_tile():
    share = Counter(server_order(f"car-{k}", (5, 5), ["t0", "t1"])[0] for k in range(200))
    assert abs(share["t0"] - share["t1"]) < 0.2 * 200


def test_a_leaving_server_moves_only_its_own_tiles():
    three = {t: server_order("car-1", t, ["t0", "t1", "t2"])[0] for t in TILES}
    two = {t: server_order("car-1", t, ["t0", "t2"])[0] for t in TILES}
    moved = [t for t in TILES if three[t] != two[t]]
    assert moved and all(three[t] == "t1" for t in moved)
    # ... and they go to where the fallback order already sent them
    assert all(server_order("car-1", t, ["t0", "t1", "t2"])[1] == two[t] for t in moved)


def test_tileserver_tile_key_round_trip_and_errors():
    key = keys.tileserver_tile("t0", -3, 4)
    assert key == "roadmap/tileserver/t0/tile/-3/4"
    assert keys.parse_tileserver_tile(key) == ("t0", (-3, 4))
    for bad in ("roadmap/tile/1/2", "roadmap/tileserver/t0/tile/a/2",
                "roadmap/tileserver/t0/x/1/2"):
        with pytest.raises(CodecError):
            keys.parse_tileserver_tile(bad)


def test_tile_params_join_since_and_codec():
    assert keys.tile_params() == ""
    assert keys.tile_params(since=3) == "?since=3"
    assert keys.tile_params(codec="raw") == "?codec=raw"
    assert keys.tile_params(since=3, codec="raw") == "?since=3;codec=raw"
    assert keys.tile_selector(1, 2, since=7) == "roadmap/tile/1/2?since=7"
