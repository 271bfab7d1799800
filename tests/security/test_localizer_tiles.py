"""A localizer fed bad tiles over a real router: a tile that fails to decode, names another tile
than its key, or carries an unknown codec is rejected (counted) and the last good map stays."""

import time

import numpy as np
import pytest

from common import codec, keys
from common.bus import open_session
from common.config import BusConfig
from common.contours import CODEC, encode_tile
from common.messages import Tile
from services.localizer.map_cache import TileCache
from services.localizer.tiles import TileClient

pytestmark = pytest.mark.integration


def _labels(col: int) -> np.ndarray:
    labels = np.zeros((512, 512), np.uint8)
    labels[:, 150:300] = 1
    labels[:, col : col + 2] = 2
    return labels


def _wait(predicate, timeout_s=3.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def test_bad_tiles_are_rejected_and_the_last_good_map_kept(router):
    good, newer = _labels(200), _labels(220)
    bad_payloads = [
        b"\xc1 not msgpack",
        codec.encode(Tile((0, 0), 2, CODEC, b"RMC2\x00 corrupt")),  # fails to decode
        codec.encode(Tile((5, 5), 3, CODEC, encode_tile(newer))),  # another tile's key
        codec.encode(Tile((0, 0), 4, "bogus/9", encode_tile(newer))),  # unknown codec
    ]
    bus = BusConfig(connect=[router])
    with open_session(bus) as server, open_session(bus) as client_session:
        def on_query(q):
            with q:
                key = str(q.key_expr)
                data = (codec.encode(Tile((0, 0), 1, CODEC, encode_tile(good)))
                        if key == keys.tile(0, 0) else bad_payloads[1])
                q.reply(q.key_expr, data)

        qs = [server.declare_queryable(keys.tile(*t), on_query, complete=True)
              for t in ((0, 0), (1, 0))]
        time.sleep(0.3)
        cache = TileCache(capacity=4)
        client = TileClient(client_session, cache, timeout_s=3.0)
        try:
            assert client.fetch((0, 0)) and cache.version((0, 0)) == 1
            assert client.fetch((1, 0)) is False  # corrupt: rejected, not cached, no exception
            assert (1, 0) not in cache and client.rejected == 1

            for data in bad_payloads:
                server.put(keys.tile_update(0, 0), data)
            assert _wait(lambda: (client.poll_updates(), client.rejected)[1] == 1 + 4)
            assert cache.version((0, 0)) == 1
            assert np.array_equal(cache.labels((0, 0)), good)  # the last good map

            server.put(keys.tile_update(0, 0),
                       codec.encode(Tile((0, 0), 5, CODEC, encode_tile(newer))))
            assert _wait(lambda: client.poll_updates() or cache.version((0, 0)) == 5)
            assert np.array_equal(cache.labels((0, 0)), newer)  # good updates still apply
        finally:
            client.close()
            for q in qs:
                q.undeclare()
