"""Sparse patches at the shard: the map they merge to against the cells form's of the same
traversals, order independence, and DurableShard ingest + replay of both forms side by side."""

import sqlite3
from dataclasses import replace

import numpy as np
import pytest

from common import codec, sparse
from common.evaluation import per_class_precision_recall
from common.messages import IngestBatch, SparseBatch
from services.merger.durable import DurableShard
from services.merger.shard import MergerShard
from services.merger.store import ShardStore
from services.vehicle.patchform import SparseForm
from tests.merger.helpers import DEMO_ROI, lane_tile, observed_traversal

FORM = SparseForm(sparse.Roi(**DEMO_ROI))


@pytest.fixture(scope="module")
def drives():
    """Three traversals of lane_tile a lane apart, with stray paint: [(cells, sparse)]."""
    rng = np.random.default_rng(3)
    out = []
    for i, x_m in enumerate((19.0, 22.5, 26.0)):
        pairs = observed_traversal(lane_tile(), traversal=f"d{i}", t_ns=i * 10**12, x_m=x_m,
                                   rng=rng, stray_rate=0.01)
        out.append(([p for p, _ in pairs], [FORM.finish([p], poses)[0] for p, poses in pairs]))
    return out


def _merged(patches) -> MergerShard:
    shard = MergerShard()
    shard.apply_batch(patches)
    shard.flush()
    return shard


def test_map_from_sparse_patches_matches_the_cells_forms(drives):
    """Per marking class, the sparse map against the cells map of the same drives at 0.1 m:
    precision and recall >= 0.98."""
    cells = _merged([p for c, _ in drives for p in c])
    expanded = _merged([sparse.expand_patch(s) for _, ss in drives for s in ss])
    q = per_class_precision_recall(expanded.labels((0, 0)), cells.labels((0, 0)))
    for name in ("lane_line", "stop_line", "crosswalk"):
        assert q[name]["cells_true"] > 0
        assert q[name]["precision"] >= 0.98 and q[name]["recall"] >= 0.98, (name, q[name])


def test_sparse_map_does_not_depend_on_arrival_order(drives, rng):
    patches = [sparse.expand_patch(s) for _, ss in drives for s in ss]
    shuffled = [patches[i] for i in rng.permutation(len(patches))]
    assert _merged(patches).digest() == _merged(shuffled).digest()


def test_both_forms_ingest_and_replay_to_the_same_map(drives, tmp_path):
    """One shard takes a cells traversal and two sparse ones; a restart replays the stored
    rows (the sparse ones as they came) to the same digest."""
    path = tmp_path / "s0.sqlite"
    first = DurableShard(MergerShard(), ShardStore(path), ident="s0")
    first.recover()
    payloads = [codec.encode(IngestBatch(drives[0][0])),
                codec.encode(SparseBatch(drives[1][1])), codec.encode(SparseBatch(drives[2][1]))]
    for payload in payloads:
        ack = first.ingest(payload)
        assert ack.error is None and set(ack.results.values()) == {"accepted"}
    assert set(first.ingest(payloads[1]).results.values()) == {"duplicate"}
    digest = first.stats().counters["digest"]
    first.store.close()
    forms = sqlite3.connect(path).execute(
        "SELECT form, COUNT(*) FROM patches GROUP BY form ORDER BY form").fetchall()
    assert forms == [(None, len(drives[0][0])),
                     (sparse.FORM, len(drives[1][1]) + len(drives[2][1]))]
    again = DurableShard(MergerShard(), ShardStore(path), ident="s0")
    assert again.recover() == sum(len(c) for c, _ in drives)
    assert again.stats().counters["digest"] == digest


def test_a_sparse_batch_with_a_bad_payload_is_refused_whole(drives, tmp_path):
    durable = DurableShard(MergerShard(), ShardStore(tmp_path / "s0.sqlite"), ident="s0")
    good, bad = drives[1][1][0], drives[1][1][1]
    g = sparse.unpack(bad.data)
    g.strong_at = np.array([10**6])
    g.strong_k = np.array([-3], np.int8)
    ack = durable.ingest(codec.encode(SparseBatch([good, replace(bad, data=sparse.pack(g))])))
    assert ack.error and "share for paint cell" in ack.error
    assert durable.store.count_patches() == 0 and not durable.shard.tiles()
