"""Hostile input at the ingest path (DurableShard.ingest: decode -> check -> store -> apply),
fuzzed with hypothesis on a real SQLite store: a refused batch gets an error ack and changes
nothing (no patch id, no stored row, no vote, no counter); one that still decodes as a valid
batch is applied whole. Memory stays bounded on bombs. Bounded in time (a few hundred
examples per strategy, no deadline)."""

import tracemalloc

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common import codec
from common.messages import ACCEPTED, DUPLICATE, IngestBatch
from services.merger.durable import DurableShard
from services.merger.shard import MergerShard
from services.merger.store import ShardStore
from tests.security import hostile

FUZZ = settings(max_examples=250, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@pytest.fixture(scope="module")
def durable(tmp_path_factory):
    store = ShardStore(tmp_path_factory.mktemp("fuzz") / "s0.sqlite", synchronous="OFF")
    shard = DurableShard(MergerShard(), store, ident="s0")
    ack = shard.ingest(codec.encode(IngestBatch([hostile.sample_patch(i) for i in (7, 8)])))
    assert ack.error is None
    shard.flush()
    yield shard
    store.close()


def _state(d: DurableShard):
    s = d.shard
    return (frozenset(s.seen), d.store.count_patches(), dict(s.counters),
            {t: (len(st.traversals), sum(len(tr.pieces) for tr in st.traversals.values()))
             for t, st in s.tiles_state.items()})


def _ingest_and_check(d: DurableShard, payload: bytes) -> None:
    before = _state(d)
    errors = d.errors
    ack = d.ingest(payload)
    if ack.error is not None:
        assert not ack.results
        assert _state(d) == before, "a refused batch changed the shard"
        assert d.errors == errors + 1
        return
    batch = codec.decode(payload, expect=IngestBatch)  # it was a valid batch after all
    assert set(ack.results) == {p.patch_id for p in batch.patches}
    assert set(ack.results.values()) <= {ACCEPTED, DUPLICATE}
    assert {p.patch_id for p in batch.patches} <= d.shard.seen


@FUZZ
@given(st.binary(max_size=4096))
def test_random_bytes_are_refused(durable, payload):
    before = _state(durable)
    assert durable.ingest(payload).error
    assert _state(durable) == before


@FUZZ
@given(hostile.mutated(hostile.VALID_BATCHES))
def test_mutated_batches(durable, payload):
    _ingest_and_check(durable, payload)


@FUZZ
@given(hostile.wrong_field(hostile.VALID_BATCHES))
def test_batches_with_a_field_of_any_type(durable, payload):
    _ingest_and_check(durable, payload)


@pytest.mark.parametrize("payload", [
    *hostile.huge_counts(), hostile.deep_nesting(1_000_000), hostile.zlib_bomb_patch(),
    hostile.type_field_array(), hostile.nan_pose(), codec.encode(hostile.sample_patch(0)),
], ids=lambda p: p[:4].hex())
def test_crafted_payloads_are_refused_in_bounded_memory(durable, payload):
    before = _state(durable)
    tracemalloc.start()
    try:
        ack = durable.ingest(payload)
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert ack.error and _state(durable) == before
    assert peak < 8 * 2**20
