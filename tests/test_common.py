"""Unit tests of the conventions in common/: grid math, owner shards, keys, codec, config."""

import numpy as np
import pytest

from common import codec, grid, keys
from common.config import RoadmapConfig, load_config, to_toml, with_sections
from common.errors import CodecError, ConfigError
from common.geometry import (
    ecef_to_geodetic,
    enu_rotation,
    geodetic_to_ecef,
    se2,
    se2_between,
    se2_compose,
    se2_inverse,
    se2_params,
    wrap_angle,
)
from common.messages import GridPatch, IngestAck, IngestBatch, Pose, Tile


def _patch(cells=(1, 5, 9), tile=(-3, 2), pid="v1-0"):
    cells = np.array(cells, np.uint32)
    return GridPatch(pid, "v1", tile, cells, np.ones((len(cells), 6), np.uint16), 1, 2, "d1")


def test_tile_and_cell_of_negative_coordinates():
    tiles, flat = grid.split_global_cells(grid.global_cells(np.array([[-0.05, 51.25]])))
    assert tiles.tolist() == [[-1, 1]]
    assert flat.tolist() == [0 * 512 + 511]
    centre = grid.cell_centers_m((-1, 1), flat)
    assert np.allclose(centre, [[-0.05, 51.25]])


def test_owner_shard_is_stable_and_balanced():
    regions = [(x, y) for x in range(-10, 10) for y in range(-10, 10)]
    owners = [grid.owner_shard(r, 4) for r in regions]
    assert owners == [grid.owner_shard(r, 4) for r in regions]
    counts = np.bincount(owners, minlength=4)
    assert counts.min() > len(regions) / 4 * 0.6


def test_adding_a_shard_moves_only_its_share():
    regions = [(x, y) for x in range(30) for y in range(30)]
    moved = sum(grid.owner_shard(r, 4) != grid.owner_shard(r, 5) for r in regions)
    assert moved / len(regions) < 0.3  # ideal: 1/5


def test_shard_map_overrides_hashing():
    assert grid.owner_shard((1, 2), 3, {"1,2": 2}) == 2


def test_keys_round_trip():
    assert keys.parse_tile(keys.tile(-3, 4)) == (-3, 4)
    assert keys.parse_tile(keys.tile_update(5, -1)) == (5, -1)
    assert keys.parse_ingest(keys.ingest(12)) == 12
    with pytest.raises(CodecError):
        keys.parse_tile("roadmap/tile/a/b")


def test_codec_round_trips_every_message():
    batch = codec.decode(codec.encode(IngestBatch([_patch()])))
    assert batch.patches[0].tile == (-3, 2)
    assert batch.patches[0].cells.tolist() == [1, 5, 9]
    ack = codec.decode(codec.encode(IngestAck({"a": "accepted", "b": "duplicate"})))
    assert ack.results == {"a": "accepted", "b": "duplicate"}
    tile = codec.decode(codec.encode(Tile((1, 2), 7, "contour/1", b"xyz")))
    assert (tile.version, tile.data) == (7, b"xyz")
    pose = codec.decode(codec.encode(Pose("car", 5, 1.0, 2.0, 0.5, np.eye(3), True)))
    assert pose.ok and np.allclose(pose.cov, np.eye(3))


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda e: e.update(v=2), "unsupported version"),
        (lambda e: e.update(type="Nope"), "unknown message type"),
        (lambda e: e["body"]["patches"][0].pop("vehicle"), "missing field 'vehicle'"),
        (lambda e: e["body"]["patches"][0]["cells"].update(dtype="<u2"), "expected dtype <u4"),
        (lambda e: e["body"]["patches"][0]["votes"].update(shape=[3, 5]), "last dimension 6"),
    ],
)
def test_codec_rejects_malformed_batches(mutate, message):
    import msgpack

    env = msgpack.unpackb(codec.encode(IngestBatch([_patch()]), packed=False), raw=False)
    mutate(env)
    with pytest.raises(CodecError, match=message):
        codec.decode(msgpack.packb(env, use_bin_type=True))


def _packed_env(patch=None):
    import msgpack

    return msgpack.unpackb(codec.encode(IngestBatch([patch or _patch()])), raw=False)


def _deflated(raw: bytes) -> bytes:
    import zlib

    return zlib.compress(raw, 1)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda p: p["packed"].update(codec="zlib-dcv/9"), "unknown codec"),
        (lambda p: p["packed"].update(n=4), "exactly 4 cells"),
        (lambda p: p["packed"].update(n=2), "exactly 2 cells"),
        (lambda p: p["packed"].update(n=512 * 512 + 1), "n must be an int"),
        (lambda p: p["packed"].update(data=b"not zlib"), "not zlib-dcv/1 data"),
        (lambda p: p["packed"].update(data=p["packed"]["data"] + b"tail"), "exactly 3 cells"),
        (lambda p: p["packed"].update(data=p["packed"]["data"][:-3]), "exactly 3 cells"),
        (lambda p: p.update(cells={"dtype": "<u4", "shape": [0], "data": b""}), "not both"),
        (lambda p: p["packed"].pop("n"), "expected a map"),
        # deltas 1, 0, 4: a repeated cell; 1, 262143: past the tile's last cell
        (lambda p: p["packed"].update(data=_deflated(
            np.array([1, 0, 4], "<u4").tobytes() + bytes(36))), "sorted and unique"),
        (lambda p: p["packed"].update(n=2, data=_deflated(
            np.array([1, 512 * 512 - 1], "<u4").tobytes() + bytes(24))), "out of range"),
    ],
)
def test_codec_rejects_malformed_packed_patches(mutate, message):
    import msgpack

    env = _packed_env()
    mutate(env["body"]["patches"][0])
    with pytest.raises(CodecError, match=message):
        codec.decode(msgpack.packb(env, use_bin_type=True))


def test_codec_packs_patches_small_and_refuses_a_batch_that_would_inflate_too_far(rng):
    import msgpack

    cells = np.sort(rng.choice(512 * 512, 20000, replace=False)).astype(np.uint32)
    votes = np.zeros((len(cells), 6), np.uint16)
    votes[np.arange(len(cells)), rng.integers(1, 6, len(cells))] = rng.integers(1, 13, len(cells))
    patch = GridPatch("p", "v", (0, 0), cells, votes, 1, 2, "d")
    packed, raw = codec.encode(patch), codec.encode(patch, packed=False)
    assert len(packed) < len(raw) / 4
    for data in (packed, raw):
        q = codec.decode(data, expect=GridPatch)
        assert np.array_equal(q.cells, cells) and np.array_equal(q.votes, votes)
    # 17 full tiles declared: more cells than a 64 MB message of raw arrays could carry
    env = _packed_env()
    env["body"]["patches"] *= 17
    for body in env["body"]["patches"]:
        body["packed"] = {**body["packed"], "n": 512 * 512}
    with pytest.raises(CodecError, match="at most 4194304 cells"):
        codec.decode(msgpack.packb(env, use_bin_type=True))


def test_codec_rejects_out_of_range_and_unsorted_cells():
    for cells in ([1, 512 * 512], [5, 1]):
        for packed in (True, False):
            data = codec.encode(IngestBatch([_patch(cells=cells)]), packed=packed)
            with pytest.raises(CodecError):
                codec.decode(data)


def test_codec_rejects_garbage_and_nan():
    with pytest.raises(CodecError):
        codec.decode(b"\xc1\xc1garbage")
    with pytest.raises(CodecError, match="finite"):
        codec.decode(codec.encode(Pose("car", 5, float("nan"), 2.0, 0.5, np.eye(3), True)))


def test_config_precedence_file_env_set(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text("[grid]\nshards = 3\n[camera]\nfx = 400\n")
    cfg = load_config(f, env={"ROADMAP_GRID__SHARDS": "5"}, sets=["camera.fy=410"])
    assert (cfg.grid.shards, cfg.camera.fx, cfg.camera.fy) == (5, 400.0, 410.0)
    assert load_config(env={}) == RoadmapConfig()


def test_config_rejects_unknown_keys_and_bad_types():
    with pytest.raises(ConfigError, match="unknown config key"):
        load_config(env={"ROADMAP_GRID__SHARDZ": "3"})
    with pytest.raises(ConfigError, match="expected int"):
        load_config(env={"ROADMAP_GRID__SHARDS": "many"})
    with pytest.raises(ConfigError, match="shards"):
        load_config(env={"ROADMAP_GRID__SHARDS": "0"})


def test_a_stored_runs_config_reads_back_as_it_ran():
    """A run's config.toml (to_toml: None as "") over today's defaults, as services.eval.replay
    reads a stored drive's: same config, its None values None again, bad values refused."""
    import tomllib

    ran = load_config(sets=["segmentation.sky_margin_deg=4.5", "roi.x_min_m=3.5"])
    stored = tomllib.loads(to_toml(ran))
    assert with_sections(RoadmapConfig(), stored) == ran
    assert with_sections(ran, {"segmentation": {"sky_margin_deg": ""}}).segmentation \
        .sky_margin_deg is None
    with pytest.raises(ConfigError):
        with_sections(ran, {"grid": {"shards": 0}})


def test_se2_helpers_are_consistent(rng):
    for _ in range(20):
        a = np.array([*rng.normal(0, 10, 2), rng.uniform(-3, 3)])
        d = np.array([*rng.normal(0, 2, 2), rng.uniform(-1, 1)])
        b = se2_compose(a, d)
        assert np.allclose(se2_between(a, b), d)
        assert np.allclose(se2_params(se2(*a) @ se2(*d)), b)
        assert np.allclose(se2_inverse(se2(*a)) @ se2(*a), np.eye(3))
    assert np.isclose(wrap_angle(3 * np.pi), -np.pi)


def test_wgs84_round_trip_and_local_enu_axes():
    lat, lon, h = 49.0069, 8.4037, 115.0  # Karlsruhe
    p = geodetic_to_ecef(lat, lon, h)
    assert np.allclose(ecef_to_geodetic(p), (lat, lon, h), atol=1e-9)
    R = enu_rotation(lat, lon)
    assert np.allclose(R @ R.T, np.eye(3))
    north = R @ (geodetic_to_ecef(lat + 100.0 / 111_200.0, lon, h) - p)  # ~100 m north
    east = R @ (geodetic_to_ecef(lat, lon + 100.0 / 72_950.0, h) - p)  # ~100 m east
    up = R @ (geodetic_to_ecef(lat, lon, h + 10.0) - p)
    assert abs(north[1] - 100.0) < 0.3 and abs(north[0]) < 1e-6 and abs(north[2]) < 0.01
    assert abs(east[0] - 100.0) < 0.3 and abs(east[1]) < 0.01 and abs(east[2]) < 0.01
    assert np.allclose(up, (0.0, 0.0, 10.0), atol=1e-6)
