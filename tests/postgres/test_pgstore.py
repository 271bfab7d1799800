"""The PostgreSQL store in-process: idempotent patch log, tiles, leases with fencing epochs, and
region tables that claim, rebalance and take over regions with the same map as one merge."""

import numpy as np
import pytest

from common import codec, sparse
from common.config import MergerConfig
from common.grid import REGION_TILES, owner_among
from common.messages import SparseBatch
from services.merger.durable import grid_batch
from services.merger.pgstore import Fenced, Leases, PgDatabase, RegionStore, all_patches, read_tile
from services.merger.shard import MergerShard
from services.merger.worker import RegionTable
from services.vehicle.patchform import SparseForm
from tests.merger.helpers import DEMO_ROI, lane_tile, observed_traversal, patches_from_labels

pytestmark = [pytest.mark.postgres, pytest.mark.timeout(120)]


def _db(url, name="t"):
    db = PgDatabase(url, name=name)
    db.create_schema()
    return db


def _patches(tiles, traversals=3):
    rng = np.random.default_rng(0)
    out = []
    for i in range(traversals):
        for tile in tiles:
            out += patches_from_labels(lane_tile(), tile=tile, traversal=f"d{i}",
                                       t_ns=i * 10**12, rng=rng, flip_rate=0.05, n_patches=2)
    return out


def _reference(patches) -> str:
    shard = MergerShard()
    shard.apply_batch(patches)
    shard.flush()
    return shard.digest()


def test_patch_log_is_idempotent_and_round_trips(pg_url):
    db = _db(pg_url)
    leases = Leases(db, "w0", 5.0)
    epoch = leases.claim((0, 0), None)
    assert epoch == 1 and leases.claim((0, 0), None) is None  # taken
    store = RegionStore(db, db, (0, 0), owner="w0", epoch=epoch)
    patches = _patches([(0, 0), (1, 2)], traversals=1)
    store.save_patches(patches)
    store.save_patches(patches[:2])  # a retry: ON CONFLICT DO NOTHING
    assert store.count_patches() == len(patches)
    back = {p.patch_id: p for p in store.load_patches()}
    for p in patches:
        q = back[p.patch_id]
        assert np.array_equal(q.cells, p.cells) and np.array_equal(q.votes, p.votes)
        assert (q.tile, q.traversal, q.t_first_ns) == (tuple(p.tile), p.traversal, p.t_first_ns)
    with pytest.raises(Fenced):  # a tile of another region never lands here
        store.save_patches(_patches([(REGION_TILES, 0)], traversals=1))


def test_sparse_patches_are_kept_as_they_came_and_replay_to_the_same_map(pg_url):
    form = SparseForm(sparse.Roi(**DEMO_ROI))
    pairs = observed_traversal(lane_tile(), traversal="d0", t_ns=0, stray_rate=0.01)
    wire = [form.finish([p], poses)[0] for p, poses in pairs]
    expanded = grid_batch(codec.decode(codec.encode(SparseBatch(wire)))).patches
    db = _db(pg_url, "sparse")
    store = RegionStore(db, db, (0, 0), owner="w0", epoch=Leases(db, "w0", 5.0).claim((0, 0), None))
    store.save_patches(expanded)
    with db.transaction() as cur:
        cur.execute("SELECT form, octet_length(packed) FROM patches WHERE form IS NOT NULL")
        rows = cur.fetchall()
    assert len(rows) == len(wire) and {f for f, _ in rows} == {sparse.FORM}
    assert sum(n for _, n in rows) == sum(len(p.data) for p in wire)  # the payload, not cells
    assert _reference(list(store.load_patches())) == _reference(expanded)


def test_a_fenced_owner_cannot_write_patches_or_tiles(pg_url):
    db_a, db_b = _db(pg_url, "a"), _db(pg_url, "b")
    a, b = Leases(db_a, "a", 0.2), Leases(db_b, "b", 5.0)
    epoch_a = a.claim((0, 0), None)
    store_a = RegionStore(db_a, db_a, (0, 0), owner="a", epoch=epoch_a,
                          labels_of=lambda t: np.zeros((512, 512), np.uint8))
    first, second = _patches([(0, 0)], traversals=2)[:2], _patches([(1, 1)], traversals=1)
    store_a.save_patches(first)
    # a is paused past its lease; b takes the region over at the next epoch
    epoch_b = b.claim((0, 0), epoch_a)
    assert epoch_b == epoch_a + 1
    with pytest.raises(Fenced):
        store_a.save_patches(second)
    with pytest.raises(Fenced):
        store_a.save_tiles([((0, 0), 7, "contour/2", b"x")])
    assert a.renew({(0, 0): epoch_a}) == set()  # and it learns it lost the lease
    store_b = RegionStore(db_b, db_b, (0, 0), owner="b", epoch=epoch_b)
    assert store_b.count_patches() == len(first)  # b's replay sees everything a committed
    assert read_tile(db_b, (0, 0)) is None


def _table(url, ident, lease_s=5.0):
    return RegionTable(ident=ident, write_db=_db(url, ident + "w"), control_db=_db(url, ident),
                       lease_s=lease_s, merger_cfg=MergerConfig())


def _ingest(table, members, patches):
    by_region = {}
    for p in patches:
        by_region.setdefault((p.tile[0] // REGION_TILES, p.tile[1] // REGION_TILES), []).append(p)
    for region, ps in by_region.items():
        holder = table.get(region) or table.claim_on_ingest(region, members, True)
        assert holder is not None
        from common import codec
        from common.messages import IngestBatch

        (ack,) = holder.durable.ingest_many([codec.encode(IngestBatch(ps))])
        assert ack.error is None


def _combined_digest(tables):
    import hashlib

    items = sorted((t, h) for table in tables for h in table.holders()
                   for t in h.durable.shard.tiles() if h.durable.flush() is not None)
    d = hashlib.sha256()
    for t, h in sorted(items, key=lambda x: x[0]):
        d.update(np.asarray(t, dtype="<i8").tobytes())
        d.update(h.durable.shard.labels(t).tobytes())
    return d.hexdigest()


TILES = [(0, 0), (9, 1), (17, 3), (2, 10), (-5, -7), (30, 30)]  # six regions


def test_a_joining_worker_takes_its_regions_with_the_same_map(pg_url):
    patches = _patches(TILES)
    half = len(patches) // 2
    a = _table(pg_url, "a")
    _ingest(a, {"a"}, patches[:half])
    assert len(a.held) == len({(t[0] // 8, t[1] // 8) for t in TILES})
    b = _table(pg_url, "b")
    members = {"a", "b"}
    _, released = a.tick(members, True)  # a hands b's regions back ...
    gained, _ = b.tick(members, True)  # ... and b claims and replays them
    assert released and sorted(h.region for h in gained) == sorted(released)
    assert all(owner_among(r, ["a", "b"]) == "b" for r in released)
    _ingest(a, members, [p for p in patches[half:] if (p.tile[0] // 8, p.tile[1] // 8) in a.held])
    _ingest(b, members, [p for p in patches[half:] if (p.tile[0] // 8, p.tile[1] // 8) in b.held])
    applied = sum(a.stats()["patches_applied"] for a in (a, b))
    assert applied == len(patches)
    assert _combined_digest([a, b]) == _reference(patches)
    replay = MergerShard()
    replay.apply_batch(list(all_patches(a.control_db)))
    replay.flush()
    assert replay.digest() == _reference(patches)  # the stored log alone gives the same map


def test_a_dead_workers_regions_are_taken_over(pg_url):
    patches = _patches(TILES)
    a, b = _table(pg_url, "a"), _table(pg_url, "b")
    members = {"a", "b"}
    for t in (a, b):
        _ingest(t, members, [p for p in patches
                             if owner_among((p.tile[0] // 8, p.tile[1] // 8), ["a", "b"])
                             == t.ident])
    assert a.held and b.held
    gained, _ = b.tick({"b"}, True)  # a is gone (liveliness): b takes its regions at once
    assert {h.region for h in gained} == set(a.held)
    assert all(h.epoch == 2 and h.previous_owner == "a" for h in gained)
    assert b.stats()["patches_applied"] == len(patches)
    assert _combined_digest([b]) == _reference(patches)
