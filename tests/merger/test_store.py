"""DurableShard over a real SQLite store: ack after commit, restart rebuilds the same map."""

import dataclasses
import sqlite3

import numpy as np
import pytest

from common import codec
from common.contours import decode_tile
from common.messages import IngestBatch
from services.merger.durable import DurableShard
from services.merger.shard import MergerShard
from services.merger.store import ShardStore
from tests.merger.helpers import lane_tile, patches_from_labels


def _open(path, owns=lambda t: True):
    durable = DurableShard(MergerShard(owns=owns), ShardStore(path), ident="s0")
    durable.recover()
    return durable


def _batches():
    out = []
    for i in range(4):
        for tile in ((0, 0), (1, 0)):
            out.append(patches_from_labels(lane_tile(), tile=tile, traversal=f"d{i}",
                                           t_ns=i * 10**12))
    return out


def test_restart_replays_every_acked_patch_once(tmp_path):
    path = tmp_path / "s0.sqlite"
    first = _open(path)
    for b in _batches():
        ack = first.ingest(codec.encode(IngestBatch(b)))
        assert ack.error is None and set(ack.results.values()) == {"accepted"}
    stats = first.stats().counters
    versions = {t: first.tile(t).version for t in first.tiles()}
    first.store.close()

    second = _open(path)
    again = second.stats().counters
    assert again["digest"] == stats["digest"]
    assert again["patches_applied"] == stats["patches_applied"] == 16
    assert {t: second.tile(t).version for t in second.tiles()} == versions
    ack = second.ingest(codec.encode(IngestBatch(_batches()[0])))
    assert set(ack.results.values()) == {"duplicate"}
    assert second.stats().counters["digest"] == stats["digest"]
    second.store.close()


def test_tile_versions_grow_and_decode(tmp_path):
    durable = _open(tmp_path / "s0.sqlite")
    durable.ingest(codec.encode(IngestBatch(_batches()[0])))
    durable.ingest(codec.encode(IngestBatch(_batches()[2])))
    durable.flush()
    tile = durable.tile((0, 0))
    assert tile.version == 1 and tile.codec == "contour/2"
    assert (decode_tile(tile.data) == lane_tile()).mean() > 0.99
    for k in range(3):  # a repaint seen by three newer traversals
        durable.ingest(codec.encode(IngestBatch(patches_from_labels(
            lane_tile(offset_cells=20), traversal=f"x{k}", t_ns=10**15 + k))))
    assert [t.version for t in durable.flush()] == [2]
    assert [t.tile for t in durable.take_changed()] == [(0, 0)]
    durable.store.close()


@pytest.mark.parametrize("payload", [b"", b"\xc1", codec.encode(IngestBatch([]))[:-3]])
def test_malformed_batch_gets_an_error_ack_and_changes_nothing(tmp_path, payload):
    durable = _open(tmp_path / "s0.sqlite")
    ack = durable.ingest(payload)
    assert ack.error and not ack.results
    assert durable.store.count_patches() == 0 and durable.stats().counters["errors"] == 1
    durable.store.close()


def test_batch_with_a_foreign_tile_is_refused_whole(tmp_path):
    durable = _open(tmp_path / "s0.sqlite", owns=lambda t: t == (0, 0))
    batch = _batches()[0] + _batches()[1]  # tiles (0,0) and (1,0)
    ack = durable.ingest(codec.encode(IngestBatch(batch)))
    assert "not owned" in ack.error
    assert durable.store.count_patches() == 0 and not durable.shard.seen
    durable.store.close()


def test_failed_store_write_means_no_ack_and_no_apply(tmp_path):
    durable = _open(tmp_path / "s0.sqlite")
    durable.store.db.execute("DROP TABLE patches")
    with pytest.raises(sqlite3.Error):
        durable.ingest(codec.encode(IngestBatch(_batches()[0])))
    assert not durable.shard.seen
    durable.store.close()


def test_store_is_in_wal_mode(tmp_path):
    store = ShardStore(tmp_path / "s.sqlite")
    assert store.db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    store.close()


@pytest.mark.parametrize("votes_per_cell", [6, 255, 256, 65535])
def test_store_round_trips_patches(tmp_path, votes_per_cell):
    store = ShardStore(tmp_path / "s.sqlite")
    patches = patches_from_labels(lane_tile(), traversal="d0", t_ns=0,
                                  votes_per_cell=votes_per_cell)
    store.save_patches(patches)
    back = list(store.load_patches())
    assert [p.patch_id for p in back] == [p.patch_id for p in patches]
    assert all(np.array_equal(a.votes, b.votes) and np.array_equal(a.cells, b.cells)
               for a, b in zip(back, patches, strict=True))
    store.close()


def test_group_commit_acks_each_batch_on_its_own(tmp_path):
    """Several waiting batches in one transaction: the bad one gets its error, a patch sent
    in two batches of the group is stored and applied once, the rest is accepted."""
    durable = _open(tmp_path / "s0.sqlite", owns=lambda t: t == (0, 0))
    a, b = _batches()[0], _batches()[2]  # tile (0, 0), traversals d0 and d1
    foreign = _batches()[1]  # tile (1, 0): not owned
    acks = durable.ingest_many([codec.encode(IngestBatch(a)), b"\xc1",
                                codec.encode(IngestBatch(foreign)),
                                codec.encode(IngestBatch(b + a[:1]))])
    assert set(acks[0].results.values()) == {"accepted"} and acks[0].error is None
    assert acks[1].error and acks[2].error and "not owned" in acks[2].error
    assert acks[3].results[a[0].patch_id] == "duplicate"
    assert {acks[3].results[p.patch_id] for p in b} == {"accepted"}
    assert durable.store.count_patches() == len(a) + len(b)
    assert durable.shard.counters["patches_applied"] == len(a) + len(b)
    durable.store.db.execute("DROP TABLE patches")
    with pytest.raises(sqlite3.Error):
        durable.ingest_many([codec.encode(IngestBatch(p)) for p in _batches()[4:8:2]])
    assert durable.shard.counters["patches_applied"] == len(a) + len(b)
    durable.store.close()


def test_a_store_written_by_the_older_codec_keeps_its_tile_versions_growing(tmp_path):
    """contour/1 tiles in the store: the restart re-encodes them as contour/2 under a newer version
    (a localizer holding version v must never be offered a lower one)."""
    path = tmp_path / "s0.sqlite"
    first = _open(path)
    first.ingest(codec.encode(IngestBatch(_batches()[0])))
    first.flush()
    first.store.save_tiles([((0, 0), 7, "contour/1", b"RMC1 legacy bytes")])
    first.store.close()
    second = _open(path)
    tile = second.tile((0, 0))
    assert tile.codec == "contour/2" and tile.version == 8
    assert (decode_tile(tile.data) == lane_tile()).mean() > 0.99
    second.store.close()


def test_a_recovery_that_retires_as_it_replays_rebuilds_the_same_map(tmp_path, monkeypatch):
    from services.merger import durable as durable_mod

    path = tmp_path / "s0.sqlite"
    first = DurableShard(MergerShard(retire_after_s=0), ShardStore(path), ident="s0")
    for k in range(12):
        first.ingest(codec.encode(IngestBatch(patches_from_labels(
            lane_tile(), traversal=f"d{k:02d}", t_ns=k * 3600 * 10**9))))
    first.flush()
    digest, versions = first.stats().counters["digest"], {t: first.tile(t).version
                                                           for t in first.tiles()}
    first.store.close()
    monkeypatch.setattr(durable_mod, "RECOVERY_CHUNK", 2)  # flush every 2 x 1 patches
    monkeypatch.setattr(durable_mod, "RECOVERY_FLUSH_EVERY", 1)
    second = DurableShard(MergerShard(retire_after_s=0), ShardStore(path), ident="s0")
    assert second.recover() == 24
    assert second.shard.counters["traversals_retired"] > 0
    assert second.stats().counters["digest"] == digest
    assert {t: second.tile(t).version for t in second.tiles()} == versions
    second.store.close()


def test_a_store_from_before_packed_patches_replays_to_the_same_map(tmp_path):
    """Rows of the old layout (cells uint32, votes uint8 / uint16 blobs, no packed_n column)
    replay next to new packed rows: the map equals one built from packed rows only."""
    batches = _batches()
    first = [_with_count(p, 300) if k % 2 == 0 else p  # a count only uint16 holds: the
             for k, p in enumerate(batches[0] + batches[1])]  # old layout's reason for it
    old = tmp_path / "old.sqlite"
    db = sqlite3.connect(old)
    db.executescript("""CREATE TABLE patches (
        patch_id TEXT PRIMARY KEY, tx INTEGER NOT NULL, ty INTEGER NOT NULL,
        vehicle TEXT NOT NULL, traversal TEXT NOT NULL,
        t_first_ns INTEGER NOT NULL, t_last_ns INTEGER NOT NULL,
        cells BLOB NOT NULL, votes BLOB NOT NULL);""")
    for k, p in enumerate(first):  # both blob widths of the old layout
        votes = np.asarray(p.votes, "<u2" if k % 2 == 0 else np.uint8)
        db.execute("INSERT INTO patches VALUES (?,?,?,?,?,?,?,?,?)",
                   (p.patch_id, *p.tile, p.vehicle, p.traversal, p.t_first_ns, p.t_last_ns,
                    np.asarray(p.cells, "<u4").tobytes(), votes.tobytes()))
    db.commit()
    db.close()
    upgraded = _open(old)
    assert upgraded.shard.counters["patches_applied"] == len(first)
    for b in batches[2:]:
        upgraded.ingest(codec.encode(IngestBatch(b)))
    reopened = _open(old)

    fresh = _open(tmp_path / "new.sqlite")
    for b in [first, *batches[2:]]:
        fresh.ingest(codec.encode(IngestBatch(b)))
    fresh.flush()
    assert reopened.shard.digest() == fresh.shard.digest()
    assert reopened.shard.counters["patches_applied"] == sum(len(b) for b in batches)


def _with_count(p, count):
    votes = np.asarray(p.votes, np.uint16).copy()
    votes[0, 0] = count
    return dataclasses.replace(p, votes=votes)
