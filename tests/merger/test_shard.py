"""MergerShard: exactly-once apply, merged labels, the map-updating rule, order independence."""

import numpy as np
import pytest

from common.errors import TileError
from common.messages import GridPatch
from services.merger.shard import MergerShard, TileCodecCache
from tests.merger.helpers import lane_tile, patches_from_labels

S = 1_000_000_000  # ns per s


def _traversals(labels, n, *, t0=0, prefix="d", rng=None, flip_rate=0.0):
    out = []
    for i in range(n):
        out += patches_from_labels(labels, traversal=f"{prefix}{i:03d}", t_ns=(t0 + i) * 3600 * S,
                                   rng=rng, flip_rate=flip_rate)
    return out


def _merged(patches, **kw):
    shard = MergerShard(**kw)
    shard.apply_batch(patches)
    shard.flush()
    return shard


def test_duplicates_are_acked_but_not_applied():
    patches = _traversals(lane_tile(), 1)
    shard = MergerShard()
    assert set(shard.apply_batch(patches).values()) == {"accepted"}
    assert set(shard.apply_batch(patches).values()) == {"duplicate"}
    assert shard.apply_patch(patches[0]) == "duplicate"
    assert shard.counters["patches_applied"] == len(patches)
    assert shard.counters["duplicates"] == len(patches) + 1


def test_same_id_twice_in_one_batch_applies_once():
    p = _traversals(lane_tile(), 1)[0]
    shard = MergerShard()
    assert shard.apply_batch([p, p]) == {p.patch_id: "accepted"}
    assert shard.counters["patches_applied"] == 1


def test_merge_reproduces_the_observed_map():
    truth = lane_tile()
    shard = _merged(_traversals(truth, 3))
    assert np.array_equal(shard.labels((0, 0)), truth)


def test_noisy_votes_are_outvoted(rng):
    truth = lane_tile()
    shard = _merged(_traversals(truth, 5, rng=rng, flip_rate=0.1))
    labelled = truth > 0
    assert (shard.labels((0, 0))[labelled] == truth[labelled]).mean() > 0.99


def test_cells_below_minimum_evidence_stay_unknown():
    truth = lane_tile()
    p = patches_from_labels(truth, traversal="d0", t_ns=0, votes_per_cell=1)
    assert not _merged(p).labels((0, 0)).any()


@pytest.mark.parametrize("change", ["repaint", "removal"])
def test_repaint_after_50_traversals_follows_within_3(change):
    old = lane_tile()
    new = lane_tile(offset_cells=10) if change == "repaint" else lane_tile()
    if change == "removal":
        new[new == 3] = 1  # stop line removed
    shard = MergerShard()
    shard.apply_batch(_traversals(old, 50))
    followed_after = None
    for k in range(1, 6):
        shard.apply_batch(patches_from_labels(new, traversal=f"new{k}", t_ns=(100 + k) * 3600 * S))
        shard.flush()
        if np.array_equal(shard.labels((0, 0)), new):
            followed_after = k
            break
    assert followed_after is not None and followed_after <= 3


def test_one_noisy_traversal_never_flips_a_stable_cell():
    truth = lane_tile()
    wrong = lane_tile(offset_cells=10)
    wrong[wrong == 4] = 5  # crosswalk seen as a sign
    for n_stable in (2, 3, 50):
        shard = MergerShard()
        shard.apply_batch(_traversals(truth, n_stable))
        shard.apply_batch(patches_from_labels(wrong, traversal="noisy", t_ns=10**6 * S,
                                              votes_per_cell=60000))
        shard.flush()
        assert np.array_equal(shard.labels((0, 0)), truth), n_stable


def test_map_is_independent_of_arrival_order(rng):
    patches = _traversals(lane_tile(), 8, rng=rng, flip_rate=0.3)
    patches += _traversals(lane_tile(offset_cells=10), 3, t0=50, prefix="r", rng=rng, flip_rate=0.3)
    digests = set()
    for _ in range(4):
        order = rng.permutation(len(patches))
        shard = MergerShard()
        for i in order:  # one at a time, with flushes in between
            shard.apply_patch(patches[i])
            if rng.random() < 0.3:
                shard.flush()
        shard.flush()
        digests.add(shard.digest())
    assert len(digests) == 1


def _bad_patch(**kw):
    base = dict(patch_id="x", vehicle="v", tile=(0, 0), cells=np.array([1, 2], np.uint32),
                votes=np.ones((2, 6), np.uint16), t_first_ns=0, t_last_ns=1, traversal="d")
    base.update(kw)
    return GridPatch(**base)


@pytest.mark.parametrize(
    "bad",
    [
        dict(cells=np.array([1, 300000], np.uint32)),
        dict(cells=np.array([2, 1], np.uint32)),
        dict(votes=np.ones((3, 6), np.uint16)),
        dict(tile=(99, 99)),
    ],
)
def test_bad_batch_is_refused_and_leaves_state_untouched(bad):
    shard = MergerShard(owns=lambda t: t != (99, 99))
    good = _traversals(lane_tile(), 1)
    shard.apply_batch(good[:1])
    shard.flush()
    before = (shard.digest(), dict(shard.counters), set(shard.seen))
    with pytest.raises(TileError):
        shard.apply_batch(good[1:] + [_bad_patch(patch_id="bad", **bad)])
    shard.flush()
    assert (shard.digest(), dict(shard.counters), set(shard.seen)) == before


def test_oversize_batch_is_refused():
    shard = MergerShard(max_batch_patches=2)
    with pytest.raises(TileError):
        shard.apply_batch(_traversals(lane_tile(), 2))
    assert not shard.seen


def test_codec_cache_versions_grow_only_on_change():
    cache = TileCodecCache()
    labels = lane_tile()
    assert cache.update((0, 0), labels) and cache.get((0, 0))[0] == 1
    assert not cache.update((0, 0), labels.copy())
    assert cache.update((0, 0), lane_tile(offset_cells=5)) and cache.get((0, 0))[0] == 2
