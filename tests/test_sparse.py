"""The sparse/1 patch form (common/sparse.py) and its messages: exact payload and codec round
trips, strict decoding, and expansion back to the ballots of the cells it came from."""

import zlib
from dataclasses import replace

import msgpack
import numpy as np
import pytest

from common import codec, sparse
from common.errors import CodecError
from common.messages import (
    GridPatch,
    IngestBatch,
    SparseBatch,
    SparsePatch,
    batch_of,
    patch_id,
)
from services.merger.shard import _Traversal
from services.vehicle.patchform import SparseForm
from tests.merger.helpers import DEMO_ROI, lane_tile, observed_traversal

ROI = sparse.Roi(**DEMO_ROI)


@pytest.fixture(scope="module")
def traversal():
    """[(GridPatch, poses)] of one drive through lane_tile, with stray paint."""
    return observed_traversal(lane_tile(), traversal="d0", t_ns=0, x_m=22.5,
                              rng=np.random.default_rng(0), stray_rate=0.01)


def _sparse(pairs) -> list[SparsePatch]:
    form = SparseForm(ROI)
    return [form.finish([p], poses)[0] for p, poses in pairs]


def test_payload_round_trips_exactly(traversal):
    p, poses = traversal[1]
    g = sparse.sparsify(p.cells, p.votes, p.tile, poses, ROI)
    back = sparse.unpack(sparse.pack(g))
    assert back.roi == g.roi and back.n_frames == g.n_frames == len(poses)
    assert np.array_equal(back.keys, g.keys)
    assert np.array_equal(back.strong_at, g.strong_at)
    assert np.array_equal(back.strong_k, g.strong_k)
    for a, b in zip(back.layers, g.layers, strict=True):
        assert len(a) == len(b)
        for ca, cb in zip(a, b, strict=True):
            assert all(np.array_equal(x, y) for x, y in zip(ca, cb, strict=True))


def test_codec_round_trips_sparse_patches_and_batches(traversal):
    patches = _sparse(traversal)
    assert codec.decode(codec.encode(patches[0])) == patches[0]
    batch = codec.decode(codec.encode(SparseBatch(patches)))
    assert isinstance(batch, SparseBatch) and batch.patches == patches
    assert isinstance(batch_of(patches), SparseBatch)
    assert isinstance(batch_of([p for p, _ in traversal]), IngestBatch)


def test_a_batch_keeps_ids_vehicles_and_order_of_any_patches(traversal):
    """Ids a vehicle makes travel as their seq, any other id as it is; a batch may mix
    vehicles and traversals and keeps its order."""
    a, b, c = _sparse(traversal)[:3]
    odd = replace(b, patch_id="anything/at-all", vehicle="map-9")
    later = replace(c, traversal="d1", patch_id=patch_id(c.vehicle, "d1", c.tile, 7))
    batch = SparseBatch([a, odd, later, replace(a, patch_id=a.patch_id + "0")])
    assert codec.decode(codec.encode(batch)) == batch


def test_a_sparse_batch_is_a_tenth_of_the_packed_cells(traversal):
    """(Synthetic votes are smooth and pack unusually well; the demo's real ones: 1 %.)"""
    cells = len(codec.encode(IngestBatch([p for p, _ in traversal])))
    sparse_bytes = len(codec.encode(SparseBatch(_sparse(traversal))))
    assert sparse_bytes < cells / 10


def _body(patches) -> dict:
    return msgpack.unpackb(codec.encode(SparseBatch(patches)), raw=False)


def _repack(envelope: dict, change) -> None:
    """Apply `change` to the uncompressed groups of a SparseBatch envelope and recompress."""
    body = envelope["body"]
    raw = codec._decompressed(body["compression"], body["data"], body["size"], "test")
    groups = msgpack.unpackb(raw, raw=False)
    change(groups)
    raw = msgpack.packb(groups, use_bin_type=True)
    body.update(compression="zlib", size=len(raw), data=zlib.compress(raw))


@pytest.mark.parametrize("mutate, message", [
    (lambda b: b["body"].update(compression="brotli"), "unknown compression"),
    (lambda b: b["body"].update(size=b["body"]["size"] + 1), "exactly"),
    (lambda b: b["body"].update(size=b["body"]["size"] - 1), "exactly"),
    (lambda b: b["body"].update(data=b["body"]["data"][:-3]), "SparseBatch"),
    (lambda b: b["body"].update(data=b"\x00" * 40), "SparseBatch"),
    (lambda b: b["body"].pop("size"), "missing field 'size'"),
    (lambda b: _repack(b, lambda g: g[0].pop("form")), "a group must be a map"),
    (lambda b: _repack(b, lambda g: g[0]["patches"][0].pop()), "a patch must be"),
    (lambda b: _repack(b, lambda g: g[0]["patches"][0].__setitem__(4, -1)), "a patch must be"),
    (lambda b: _repack(b, lambda g: g[0]["patches"][0].__setitem__(0, -1)), "patch id must"),
    (lambda b: _repack(b, lambda g: g[0].update(form="sparse/0")), "unknown form"),
    (lambda b: _repack(b, lambda g: g[0]["patches"][0].__setitem__(5, b"\x80")), "varint"),
])
def test_codec_rejects_malformed_sparse_batches(traversal, mutate, message):
    body = _body(_sparse(traversal)[:2])
    mutate(body)
    with pytest.raises(CodecError, match=message):
        codec.decode(msgpack.packb(body, use_bin_type=True))


@pytest.mark.parametrize("mutate, message", [
    (lambda b: b.update(form="sparse/9"), "unknown form"),
    (lambda b: b.update(data=b["data"][:-1]), "sparse/1|varint|payload"),
    (lambda b: b.update(data=b["data"] + b"\x01"), "after the end"),
    (lambda b: b.update(t_last_ns=b["t_first_ns"] - 1), "t_last_ns before"),
    (lambda b: b.pop("traversal"), "missing field 'traversal'"),
])
def test_codec_rejects_malformed_sparse_patches(traversal, mutate, message):
    body = codec._enc_sparse_patch(_sparse(traversal)[0])
    mutate(body)
    data = msgpack.packb({"v": 1, "type": "SparsePatch", "body": body}, use_bin_type=True)
    with pytest.raises(CodecError, match=message):
        codec.decode(data)


def test_unpack_rejects_points_outside_the_tile(traversal):
    p, poses = traversal[1]
    g = sparse.sparsify(p.cells, p.votes, p.tile, poses, ROI)
    g.layers[0][0][0] = g.layers[0][0][0] + 600
    with pytest.raises(CodecError, match="outside the tile"):
        sparse.unpack(sparse.pack(g))


def test_expand_refuses_shares_beyond_the_paint_cells(traversal):
    p, poses = traversal[1]
    g = sparse.sparsify(p.cells, p.votes, p.tile, poses, ROI)
    g.strong_at = np.array([10**6])
    g.strong_k = np.array([-3], np.int8)
    with pytest.raises(CodecError, match="share for paint cell"):
        sparse.expand(sparse.unpack(sparse.pack(g)), p.tile)


def test_expanded_ballots_match_the_cells_they_came_from(traversal):
    """Per cell the traversal's ballot (services/merger/shard.py: the voted class, the
    footprint's no-paint ballots) from the expanded sparse patches against the cells form:
    the same slot on >= 99 % of the cells either observes and of the paint (1.0 measured)."""
    old, new = _Traversal(t_first_ns=0), _Traversal(t_first_ns=0)
    for (p, _), sp in zip(traversal, _sparse(traversal), strict=True):
        old.add(p.cells, p.votes, p.t_first_ns)
        g = sparse.expand_patch(sp)
        new.add(g.cells, g.votes, g.t_first_ns)
    slot_old, slot_new = np.full(512 * 512, 255), np.full(512 * 512, 255)
    for slots, trav in ((slot_old, old), (slot_new, new)):
        cells, ballot, _ = trav.ballots(9)
        slots[cells] = ballot
    either = (slot_old != 255) | (slot_new != 255)
    assert np.mean(slot_old[either] == slot_new[either]) >= 0.99
    paint = (slot_old >= 2) & (slot_old <= 5)
    assert np.mean(slot_new[paint] == slot_old[paint]) >= 0.99


def test_shares_keep_weak_and_strong_paint(traversal):
    """Stray paint (a twentieth of the cell's pixels) expands to a twentieth of the field,
    within an octave; ordinary paint to the field."""
    p, poses = traversal[2]
    g = sparse.sparsify(p.cells, p.votes, p.tile, poses, ROI)
    cells, votes = sparse.expand(g, p.tile)
    field = np.maximum(sparse.evidence_field(g, p.tile), 1.0)
    weak = np.isin(cells, p.cells[(p.votes[:, 2] > 0) & (p.votes[:, 1] == 0)
                                  & (p.votes[:, 2] < 0.1 * field[p.cells])])
    assert weak.sum() >= 5
    ratio = votes[:, 2].astype(float) / field[cells]
    assert np.all(ratio[weak] < 0.12)
    strong = (votes[:, 2] > 0) & ~weak
    assert np.median(ratio[strong]) > 0.5


def test_expansion_is_deterministic(traversal):
    sp = _sparse(traversal)[1]
    a, b = sparse.expand_patch(sp), sparse.expand_patch(codec.decode(codec.encode(sp)))
    assert np.array_equal(a.cells, b.cells) and np.array_equal(a.votes, b.votes)
    assert isinstance(a, GridPatch) and a.sparse == sp.data and a.patch_id == sp.patch_id


def test_roi_of_a_lookup_covers_its_points():
    from common.camera import build_ipm_lookup
    from services.vehicle.synthetic import mapping_camera

    cam = mapping_camera()
    ipm = build_ipm_lookup(cam, x_min_m=3.0, length_m=8.0, width_m=8.0)
    roi = sparse.roi_of_lookup(ipm.ground_xy_m, camera_x_m=cam.T_vehicle_camera[0, 3],
                               width_m=8.0, stride=2)
    xy = ipm.ground_xy_m
    assert roi.x_min_dm * 0.1 <= xy[:, 0].min() and (roi.x_min_dm + roi.length_dm) * 0.1 >= (
        xy[:, 0].max())
    ahead = xy[:, 0] - roi.camera_x_dm * 0.1
    assert np.all(np.abs(xy[:, 1]) <= roi.fov_slope_milli / 1000 * ahead + 1e-6)
    assert roi.pixels_per_frame == round(len(xy) / 4)
