"""Localizer transport: tiles over a real local router, and `roadmap localize` end to end.

The tile server is a real Zenoh queryable in a second session serving Tile messages (contour/1
and raw/1) on roadmap/tile/<tx>/<ty>, as a merger shard does."""

import argparse
import json
import time

import numpy as np
import pytest

from common import codec, keys
from common.bus import open_session
from common.camera import camera_from_config
from common.config import BusConfig, load_config
from common.contours import CODEC, RAW_CODEC, encode_raw, encode_tile
from common.messages import Pose, Tile
from services.localizer.map_cache import TileCache
from services.localizer.tiles import TileClient, tiles_needed
from tests.localizer.synthetic import fill_cache, straight_road, synthetic_drive, write_log


@pytest.fixture(scope="module")
def world_cache():
    return fill_cache(TileCache(capacity=40), straight_road())


def _serve(session, world_cache, version=1):
    """One complete queryable per tile, like a merger shard; ?codec=raw answers raw/1."""
    entities = []
    for tile in world_cache.tiles():
        labels = world_cache.labels(tile)

        def on_query(q, tile=tile, labels=labels):
            with q:
                raw = dict(q.parameters).get("codec") == "raw"
                data = encode_raw(labels) if raw else encode_tile(labels)
                msg = Tile(tile, version, RAW_CODEC if raw else CODEC, data)
                q.reply(q.key_expr, codec.encode(msg))

        entities.append(session.declare_queryable(keys.tile(*tile), on_query, complete=True))
    return entities


@pytest.mark.parametrize("codec_name", ["contour", "raw"])
def test_tile_client_fetches_over_router(router, world_cache, codec_name):
    bus = BusConfig(connect=[router])
    with open_session(bus) as server, open_session(bus) as client_session:
        _serve(server, world_cache)
        time.sleep(0.3)
        cache = TileCache(capacity=4)
        client = TileClient(client_session, cache, codec_name=codec_name, timeout_s=3.0)
        try:
            wanted = tiles_needed(60.0, 28.0, 0.0, radius_m=20.0, ahead_m=40.0)
            assert client.ensure(wanted) >= 2
            assert (1, 0) in cache and (2, 0) in cache  # ahead along +x
            assert len(cache.tiles()) <= 4  # bounded
            assert client.fetch((50, 50)) is False  # nobody holds it: no reply
            src = world_cache.labels((1, 0))
            got = cache.labels((1, 0))
            if codec_name == "raw":
                assert np.array_equal(src, got)
            else:
                paint = src >= 2
                assert np.mean(got[paint] == src[paint]) > 0.95
        finally:
            client.close()


def test_tile_client_follows_updates(router, world_cache):
    bus = BusConfig(connect=[router])
    with open_session(bus) as server, open_session(bus) as client_session:
        _serve(server, world_cache)
        time.sleep(0.3)
        cache = TileCache(capacity=8)
        client = TileClient(client_session, cache, timeout_s=3.0)
        try:
            client.ensure([(1, 0)])
            time.sleep(0.3)
            newer = world_cache.labels((1, 0)).copy()
            newer[100:110, 100:200] = 3
            server.put(
                keys.tile_update(1, 0), codec.encode(Tile((1, 0), 2, CODEC, encode_tile(newer)))
            )
            server.put(
                keys.tile_update(7, 7), codec.encode(Tile((7, 7), 1, CODEC, encode_tile(newer)))
            )
            deadline = time.monotonic() + 5.0
            while cache.version((1, 0)) != 2 and time.monotonic() < deadline:
                client.poll_updates()
                time.sleep(0.05)
            assert cache.version((1, 0)) == 2
            assert (cache.labels((1, 0))[100:110, 100:200] == 3).mean() > 0.9
            assert (7, 7) not in cache  # not held: not followed
        finally:
            client.close()


def test_localize_command_end_to_end(router, world_cache, rng, tmp_path):
    cfg0 = load_config()
    streams = synthetic_drive(rng, duration_s=8.0, gnss_bias_m=(2.5, -3.0))
    log = write_log(tmp_path / "log", world_cache, streams, camera_from_config(cfg0.camera))
    cfg = load_config(sets=[f'bus.connect=["{router}"]'])
    poses = []
    with open_session(BusConfig(connect=[router])) as server:
        _serve(server, world_cache)
        server.declare_subscriber(
            keys.pose("prod-0"), lambda s: poses.append(codec.decode(s.payload.to_bytes(), Pose))
        )
        time.sleep(0.3)
        from services.localizer.node import main

        assert main(argparse.Namespace(log=str(log), out=str(tmp_path / "out"), id=None), cfg) == 0
        time.sleep(0.5)
    report = json.loads((tmp_path / "out" / "localization.json").read_text())
    assert report["convergence_s"] is not None and report["convergence_s"] < 5.0
    assert report["availability_0_5m"] == 1.0
    assert report["x_m"]["p90"] < 0.15 and report["y_m"]["p90"] < 0.1
    tum = np.loadtxt(tmp_path / "out" / "trajectory.tum")
    assert tum.shape[1] == 8 and len(tum) > 40
    assert np.allclose(np.linalg.norm(tum[:, 4:], axis=1), 1.0)
    rows = (tmp_path / "out" / "diagnostics.jsonl").read_text().splitlines()
    assert len(rows) == len(streams["frame_t_ns"])
    assert len(poses) > 40 and poses[-1].ok
