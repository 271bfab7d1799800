"""The read path that scales (services/localizer/tiles.py TileSource, services/merger/
tileserver.py): real `roadmap tileserver` processes on a real router and the private PostgreSQL
server. The client finds the servers by liveliness and spreads its reads as server_order says;
`?since=` and `?codec=raw` work on a server's own key; a hung server costs one timeout, a killed
one none."""

import signal
import time

import numpy as np
import pytest

from common import codec, keys
from common.bus import open_session
from common.config import BusConfig
from common.contours import CODEC, RAW_CODEC, decode_raw, encode_raw, encode_tile
from common.grid import region_of_tile
from common.messages import Stats, Tile
from services.localizer.map_cache import TileCache
from services.localizer.tiles import TileClient, TileSource, server_order
from tests.conftest import kill_all, spawn

pytestmark = [pytest.mark.integration, pytest.mark.postgres, pytest.mark.timeout(180)]

TILES = [(tx, ty) for tx in range(4) for ty in range(4)]
VERSION = 3


def _labels(tile) -> np.ndarray:
    labels = np.zeros((512, 512), np.uint8)
    labels[100 + 10 * tile[0]:140 + 10 * tile[0], 50:450] = 2 + tile[1] % 2
    return labels


def _store_tiles(url) -> None:
    from services.merger.pgstore import UPSERT_TILE, wait_for_database

    db = wait_for_database(url)
    with db.transaction() as cur:
        cur.executemany(UPSERT_TILE, [(*region_of_tile(t), *t, VERSION, CODEC,
                                       encode_tile(_labels(t)), encode_raw(_labels(t)))
                                      for t in TILES])
    db.close()


class Servers:
    def __init__(self, router, url, tmp_path):
        self.router, self.url, self.tmp = router, url, tmp_path
        self.procs = {}

    def start(self, ident):
        log = open(self.tmp / f"{ident}.log", "ab")
        self.procs[ident] = spawn("tileserver", "--id", ident, "--store", self.url, "--connect",
                                  self.router, "--log-level", "WARNING", stderr=log)

    def log(self, ident):
        return (self.tmp / f"{ident}.log").read_text()[-3000:]

    def close(self):
        kill_all(self.procs.values())


@pytest.fixture
def cloud(router, pg_url, tmp_path):
    _store_tiles(pg_url)
    servers = Servers(router, pg_url, tmp_path)
    with open_session(BusConfig(connect=[router])) as session:
        try:
            yield servers, session
        finally:
            servers.close()


def _wait_live(source: TileSource, want: list[str], servers: Servers, timeout_s=60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while source.live() != want:
        assert time.monotonic() < deadline, "\n".join(servers.log(i) for i in servers.procs)
        time.sleep(0.1)


def _tile(payload: bytes) -> Tile:
    return codec.decode(payload, expect=Tile)


def _direct(session, ident) -> int:
    for reply in session.get(keys.stats("tileserver", ident), timeout=10.0):
        if reply.ok is not None:
            return int(codec.decode(reply.ok.payload.to_bytes(), expect=Stats).counters["direct"])
    raise AssertionError(f"no stats from {ident}")


def test_reads_spread_over_two_tile_servers_as_server_order_says(cloud):
    servers, session = cloud
    servers.start("t0")
    servers.start("t1")
    sources = [TileSource(session, client_id=f"car-{k}", timeout_s=5.0) for k in range(3)]
    try:
        for s in sources:
            _wait_live(s, ["t0", "t1"], servers)
        for s in sources:
            for t in TILES:
                (payload,) = s.get(t)
                assert _tile(payload).tile == t and _tile(payload).version == VERSION
        want = {i: sum(server_order(s.client_id, t, ["t0", "t1"])[0] == i
                       for s in sources for t in TILES) for i in ("t0", "t1")}
        got = {i: sum(s.answered[i] for s in sources) for i in ("t0", "t1")}
        assert got == want and min(got.values()) > 0  # both serve, each its rendezvous share
        assert {i: _direct(session, i) for i in ("t0", "t1")} == want
        assert all(s.no_reply == 0 and s.answered[""] == 0 for s in sources)
    finally:
        for s in sources:
            s.close()


def test_since_raw_and_missing_on_a_tile_servers_own_key(cloud):
    servers, session = cloud
    servers.start("t0")
    source = TileSource(session, client_id="car-1", timeout_s=5.0)
    try:
        _wait_live(source, ["t0"], servers)
        (raw,) = source.get((1, 2), keys.tile_params(codec="raw"))
        assert _tile(raw).codec == RAW_CODEC
        assert np.array_equal(decode_raw(_tile(raw).data), _labels((1, 2)))
        assert source.get((1, 2), keys.tile_params(since=VERSION)) == []  # not newer
        (newer,) = source.get((1, 2), keys.tile_params(since=VERSION - 1, codec="raw"))
        assert _tile(newer).version == VERSION and _tile(newer).codec == RAW_CODEC
        assert source.get((50, 50)) == []  # no such tile
        # every one answered by t0 (a delete reply for none): no fallback, no skipping
        assert source.answered == {"t0": 4} and source.no_reply == 0
    finally:
        source.close()


def test_tile_client_fetches_through_the_tile_servers(cloud):
    servers, session = cloud
    servers.start("t0")
    servers.start("t1")
    client = TileClient(session, TileCache(capacity=32), codec_name="raw", timeout_s=5.0,
                        follow_updates=False, client_id="car-7")
    try:
        _wait_live(client.source, ["t0", "t1"], servers)
        assert client.ensure(TILES) == len(TILES)
        assert np.array_equal(client.cache.labels((3, 1)), _labels((3, 1)))
        assert sum(client.source.answered.values()) == len(TILES) and client.fetched == len(TILES)
    finally:
        client.close()


def test_a_hung_tile_server_costs_one_timeout_and_a_killed_one_none(cloud):
    servers, session = cloud
    servers.start("t0")
    servers.start("t1")
    source = TileSource(session, client_id="car-1", timeout_s=1.0)
    try:
        _wait_live(source, ["t0", "t1"], servers)
        on_t1 = [t for t in TILES if server_order("car-1", t, ["t0", "t1"])[0] == "t1"]
        assert len(on_t1) >= 2
        servers.procs["t1"].send_signal(signal.SIGSTOP)  # hung: its token lives until the lease
        took = []
        for t in on_t1:
            t0 = time.monotonic()
            (payload,) = source.get(t)
            took.append(time.monotonic() - t0)
            assert _tile(payload).tile == t
        assert took[0] >= 1.0 and max(took[1:]) < 1.0  # one timeout, then t1 is skipped
        assert source.no_reply == 1 and source.answered["t0"] == len(on_t1)
        assert source.live() == ["t0"]
        servers.procs["t1"].kill()  # gone: its liveliness goes at once
        servers.procs["t0"].kill()
        deadline = time.monotonic() + 10.0
        while source.live():  # t0's token goes in milliseconds (t1 is skipped already)
            assert time.monotonic() < deadline
            time.sleep(0.05)
        t0 = time.monotonic()
        assert source.get(TILES[0]) == []  # no tile server, no worker: the plain key, no reply
        assert time.monotonic() - t0 < 1.0 and source.no_reply == 1
    finally:
        source.close()
