"""Voting grid: key packing, votes and argmax, saturation, per-tile patches and their codec."""

import numpy as np
import pytest

from common import codec
from common.classes import NUM_CLASSES, Cls
from common.errors import CodecError
from common.grid import CELL_M, TILE_M, cell_centers_m
from common.messages import GridPatch
from services.vehicle.voting import COUNT_MAX, VotingGrid, pack_keys, patch_id, unpack_keys


def test_keys_round_trip_with_negative_cells(rng):
    gxy = rng.integers(-3_000_000, 3_000_000, (1000, 2))
    cls = rng.integers(0, NUM_CLASSES, 1000).astype(np.uint8)
    back, back_cls = unpack_keys(pack_keys(gxy, cls))
    np.testing.assert_array_equal(back, gxy)
    np.testing.assert_array_equal(back_cls, cls)


def test_votes_count_per_class_and_label_is_argmax():
    g = VotingGrid()
    pts = np.array([[0.05, 0.05]] * 3 + [[0.05, 0.05]] * 2 + [[0.15, 0.05]])
    cls = np.array([Cls.LANE_LINE] * 3 + [Cls.ROAD] * 2 + [Cls.STOP_LINE], np.uint8)
    g.add_points(pts, cls, t_ns=5)
    raster = g.label_raster(0.0, 0.0, 2, 3)
    assert raster[0, 0] == Cls.LANE_LINE and raster[0, 1] == Cls.STOP_LINE
    assert raster[1].sum() == 0 and raster[0, 2] == 0
    (p,) = g.patches("v", "t", 0)
    np.testing.assert_array_equal(p.cells, [0, 1])
    np.testing.assert_array_equal(p.votes[0], [0, 2, 3, 0, 0, 0])
    np.testing.assert_array_equal(p.votes[1], [0, 0, 0, 1, 0, 0])


def test_counts_saturate_at_uint16():
    g = VotingGrid()
    for _ in range(3):
        g.add_points(np.zeros((30000, 2)) + 0.05, np.full(30000, Cls.ROAD, np.uint8))
    _, counts = g.items()
    assert counts.dtype == np.uint16 and counts[0] == COUNT_MAX


def test_patches_split_by_tile_with_sorted_unique_cells(rng):
    g = VotingGrid()
    pts = rng.uniform(-TILE_M, TILE_M, (20000, 2))
    cls = rng.integers(1, NUM_CLASSES, 20000).astype(np.uint8)
    g.add_points(pts, cls, t_ns=10)
    g.add_points(pts[:10], cls[:10], t_ns=20)
    patches = g.patches("map-0", "d0", 7)
    assert sorted(p.tile for p in patches) == [(-1, -1), (-1, 0), (0, -1), (0, 0)]
    assert sum(int(p.votes.sum()) for p in patches) == 20010
    for p in patches:
        assert p.cells.dtype == np.uint32 and p.votes.dtype == np.uint16
        assert np.all(np.diff(p.cells.astype(np.int64)) > 0)
        assert p.patch_id == patch_id("map-0", "d0", p.tile, 7)
        assert (p.t_first_ns, p.t_last_ns) == (10, 20)
        centres = cell_centers_m(p.tile, p.cells)
        assert np.all(np.abs(centres) < TILE_M + CELL_M)


def test_merge_adds_votes():
    a, b = VotingGrid(), VotingGrid()
    a.add_points(np.array([[1.0, 1.0]]), np.array([2], np.uint8))
    b.add_points(np.array([[1.0, 1.0], [5.0, 5.0]]), np.array([2, 1], np.uint8))
    a.merge(b)
    keys, counts = a.items()
    assert sorted(counts.tolist()) == [1, 2]


def _patch():
    g = VotingGrid()
    g.add_points(np.array([[0.05, 0.05], [1.05, 2.05]]), np.array([2, 4], np.uint8), t_ns=1)
    return g.patches("map-0", "d0", 0)[0]


def test_patch_round_trip():
    p = _patch()
    q = codec.decode(codec.encode(p), expect=GridPatch)
    assert (q.patch_id, q.tile, q.t_first_ns, q.traversal) == (p.patch_id, p.tile, 1, "d0")
    np.testing.assert_array_equal(q.cells, p.cells)
    np.testing.assert_array_equal(q.votes, p.votes)


@pytest.mark.parametrize(
    "mutate",
    [
        lambda p: {"cells": p.cells[::-1].copy()},  # not sorted
        lambda p: {"cells": np.array([0, 512 * 512], np.uint32)},  # out of the tile
        lambda p: {"votes": p.votes[:1]},  # one row short
        lambda p: {"t_first_ns": 5, "t_last_ns": 4},
        lambda p: {"patch_id": ""},
    ],
)
def test_malformed_patches_are_rejected(mutate):
    p = _patch()
    fields = {**p.__dict__, **mutate(p)}
    with pytest.raises(CodecError):
        codec.decode(codec.encode(GridPatch(**fields)), expect=GridPatch)


def test_wrong_votes_dtype_is_rejected():
    import msgpack

    p = _patch()
    msg = msgpack.unpackb(codec.encode(p, packed=False), raw=False)
    msg["body"]["votes"]["dtype"] = "<f4"
    with pytest.raises(CodecError):
        codec.decode(msgpack.packb(msg), expect=GridPatch)


def test_paint_seen_in_too_few_frames_is_dropped_and_road_is_kept():
    """The mapper's hallucination rule (VehicleMapper.min_paint_frames): paint votes of a cell
    that fewer than 3 frames saw go, however many points one frame put there; road stays."""
    votes, frames = VotingGrid(), VotingGrid()
    lane, ghost, road = [0.05, 0.05], [0.15, 0.05], [0.25, 0.05]  # cells 0, 1, 2
    for k in range(3):
        pts = np.array([lane, lane] + ([ghost] * 9 if k == 0 else []) + [road])
        cls = np.array([Cls.LANE_LINE] * 2 + [Cls.GROUND_SIGN] * (9 if k == 0 else 0)
                       + [Cls.ROAD], np.uint8)
        votes.add_points(pts, cls)
        paint = cls >= Cls.LANE_LINE
        frames.add_presence(pts[paint], cls[paint])
    assert votes.drop_unconfirmed(frames, 3, first_class=Cls.LANE_LINE) == 1
    raster = votes.label_raster(0.0, 0.0, 1, 3)
    np.testing.assert_array_equal(raster[0], [Cls.LANE_LINE, 0, Cls.ROAD])
    (p,) = votes.patches("v", "t", 0)
    np.testing.assert_array_equal(p.votes[0], [0, 0, 6, 0, 0, 0])  # every vote of 3 frames


def test_a_sign_on_a_cell_frames_saw_as_lane_line_is_dropped():
    """VehicleMapper.symbol_lane_frames: the model calls pieces of thick lane lines ground sign;
    a sign's votes go where frames saw lane line in the same cell, elsewhere they stay."""
    votes, frames = VotingGrid(), VotingGrid()
    pts = np.array([[0.05, 0.05]] * 3 + [[0.15, 0.05]] * 2)
    cls = np.array([Cls.GROUND_SIGN] * 2 + [Cls.LANE_LINE] + [Cls.GROUND_SIGN] * 2, np.uint8)
    votes.add_points(pts, cls)
    frames.add_presence(pts, cls)
    assert votes.drop_class_where(Cls.GROUND_SIGN, frames, other=Cls.LANE_LINE,
                                  min_count=1) == 1
    np.testing.assert_array_equal(votes.label_raster(0.0, 0.0, 1, 2)[0],
                                  [Cls.LANE_LINE, Cls.GROUND_SIGN])
