"""MergerShard: exactly-once apply, merged labels, the map-updating rule, order independence."""

import numpy as np
import pytest

from common.errors import TileError
from common.messages import GridPatch
from services.merger.shard import UNSEEN_PAINT, MergerShard, TileCodecCache
from tests.merger.helpers import island_tile, lane_tile, patches_from_labels

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


def _follow(shard, new_traversals, want) -> int | None:
    """Apply new traversals one at a time; the count after which the map equals `want`."""
    for k, patches in enumerate(new_traversals, start=1):
        shard.apply_batch(patches)
        shard.flush()
        if np.array_equal(shard.labels((0, 0)), want):
            return k
    return None


def _new_paint(labels, n=5, **kw):
    return [patches_from_labels(labels, traversal=f"new{k}", t_ns=(100 + k) * 3600 * S, **kw)
            for k in range(1, n + 1)]


@pytest.mark.parametrize("change", ["repaint", "removal", "line_onto_nothing", "line_off_nothing"])
def test_repaint_after_50_traversals_follows_within_3(change):
    """Old paint seen by 50 traversals, then the new paint: the map equals the new paint after
    at most 3 traversals (the paint after 2). "line_onto_nothing": the old line's ground
    becomes nothing (a 0.7 m strip the new traversals give no votes) and the line moves 1 m;
    the reverse: a line moves off such a strip onto the road."""
    old, new = lane_tile(), lane_tile(offset_cells=10)
    if change == "removal":
        new = lane_tile()
        new[new == 3] = 1  # stop line removed
    elif change == "line_onto_nothing":
        new = island_tile(offset_cells=10, island=(198, 205))
    elif change == "line_off_nothing":
        old = island_tile(island=(203, 210))
    shard = MergerShard()
    shard.apply_batch(_traversals(old, 50))
    shard.flush()
    assert np.array_equal(shard.labels((0, 0)), old)
    followed = _follow(shard, _new_paint(new), new)
    assert followed is not None and followed <= 3, followed


def test_repaint_follows_within_3_when_each_traversal_misses_part():
    """Each new traversal misses a third of the tile (another lane, a truck): every cell is
    still seen by 2 of the first 3 new traversals, and the map follows after 3."""
    old, new = lane_tile(), lane_tile(offset_cells=10)
    shard = MergerShard()
    shard.apply_batch(_traversals(old, 50))
    partial = []
    for k, rows in enumerate((slice(0, 170), slice(170, 340), slice(340, 512))):
        seen = new.copy()
        seen[rows] = 0  # not observed at all
        partial.append(patches_from_labels(seen, traversal=f"new{k}", t_ns=(100 + k) * 3600 * S))
    assert _follow(shard, partial, new) == 3


def test_line_removed_from_wide_nothing_follows_with_explicit_none_votes():
    """Paint on a wide island (4 m of nothing, beyond any footprint closing) goes away when the
    traversals say they saw nothing there (class-0 votes): the rule takes them as ballots."""
    old = island_tile(offset_cells=20, island=(190, 230))
    new = island_tile(offset_cells=20, island=(190, 230))
    new[new == 2] = 0
    nothing = np.zeros_like(new, bool)
    nothing[:, 190:230] = True
    shard = MergerShard()
    shard.apply_batch(_traversals(old, 50))
    followed = _follow(shard, _new_paint(new, seen_nothing=nothing), new)
    assert followed is not None and followed <= 3, followed


def test_unobserved_cells_keep_their_label():
    """No evidence, no change: traversals that do not see a part of the tile leave it as is."""
    old = lane_tile()
    shard = MergerShard()
    shard.apply_batch(_traversals(old, 5))
    other = np.zeros_like(old)
    other[:, 350:450] = 1  # a road elsewhere in the tile, far from the old one
    for patches in _new_paint(other, n=5):
        shard.apply_batch(patches)
    shard.flush()
    labels = shard.labels((0, 0))
    assert np.array_equal(labels[:, :320], old[:, :320])
    assert np.array_equal(labels[:, 350:450], other[:, 350:450])


@pytest.mark.parametrize(
    "noise", ["other_paint", "road_over_paint", "paint_missed", "paint_on_nothing"]
)
def test_one_noisy_traversal_never_flips_a_stable_cell(noise):
    """A stable map (2, 3 or 50 agreeing traversals) and one newest traversal that saw it
    wrong, with huge votes: the map does not change."""
    truth = island_tile(island=(260, 266))  # a 0.6 m strip of nothing inside the road
    wrong = truth.copy()
    if noise == "other_paint":
        wrong = island_tile(offset_cells=10, island=(260, 266))
        wrong[wrong == 4] = 5  # crosswalk seen as a sign
    elif noise == "road_over_paint":
        wrong[wrong >= 2] = 1
    elif noise == "paint_missed":
        wrong[wrong >= 2] = 0  # holes: seen, but as nothing
    elif noise == "paint_on_nothing":
        wrong[:, 260:266] = 2
    for n_stable in (2, 3, 50):
        shard = MergerShard()
        shard.apply_batch(_traversals(truth, n_stable))
        shard.apply_batch(patches_from_labels(wrong, traversal="noisy", t_ns=10**6 * S,
                                              votes_per_cell=60000))
        shard.flush()
        assert np.array_equal(shard.labels((0, 0)), truth), n_stable


def test_gaps_in_votes_do_not_erase_road():
    """Two newer traversals with the same small gap in their votes on the road (a car in
    front, sparse far pixels): no evidence against road, the road stays (paint would go; road
    goes only when no road ballot is left in the window, after 3 such traversals)."""
    truth = lane_tile()
    shard = MergerShard()
    shard.apply_batch(_traversals(truth, 5))
    gappy = truth.copy()
    gappy[100:105, 160:165] = 0  # 0.5 m gap in the road
    for patches in _new_paint(gappy, n=2):
        shard.apply_batch(patches)
    shard.flush()
    assert np.array_equal(shard.labels((0, 0)), truth)


def test_time_not_arrival_decides_which_paint_is_current():
    """The new paint arrives first, the 50 older traversals after it: the map is the new one."""
    old, new = lane_tile(), lane_tile(offset_cells=10)
    shard = MergerShard()
    for patches in _new_paint(new, n=2):
        shard.apply_batch(patches)
    shard.apply_batch(_traversals(old, 50))
    shard.flush()
    assert np.array_equal(shard.labels((0, 0)), new)


def test_footprint_closes_narrow_gaps_only():
    """Unvoted cells between voted ones up to 0.8 m apart were in view (none ballots); wider
    gaps and the outside of the voted area were not, also at the tile's edges."""
    labels = np.zeros((512, 512), np.uint8)
    labels[:, 100:200] = 1
    labels[:, 120:128] = 0  # 0.8 m gap: closed
    labels[:, 150:160] = 0  # 1.0 m gap: open
    (p,) = patches_from_labels(labels, traversal="d0", t_ns=0, n_patches=1)
    shard = MergerShard()
    shard.apply_patch(p)
    cells, ballot, _ = shard.tiles_state[(0, 0)].traversals["d0"].ballots(shard.footprint_cells)
    observed = np.zeros(512 * 512, bool)
    observed[cells] = True
    observed = observed.reshape(512, 512)
    assert observed[:, 120:128].all() and not observed[:, 150:160].any()
    assert not observed[:, :100].any() and not observed[:, 200:].any()
    assert (ballot[~np.isin(cells, p.cells)] == UNSEEN_PAINT).all()


def test_map_is_independent_of_arrival_order(rng):
    patches = _traversals(lane_tile(), 8, rng=rng, flip_rate=0.3)
    patches += _traversals(island_tile(offset_cells=10, island=(196, 205)), 3, t0=50, prefix="r",
                           rng=rng, flip_rate=0.3)
    patches += _traversals(lane_tile(offset_cells=-10), 2, t0=60, prefix="q", rng=rng,
                           flip_rate=0.3)
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


def test_retiring_traversals_out_of_every_window_keeps_the_map_and_bounds_memory(rng):
    """40 traversals an hour apart (the paint moves after 30), flushed after each: a shard that
    retires traversals holds a handful and has, after every flush, the same map as one that
    keeps all 40."""
    old, new = lane_tile(), lane_tile(offset_cells=20)
    keep, retire = MergerShard(retire_after_s=-1), MergerShard(retire_after_s=3600)
    for k in range(40):
        patches = patches_from_labels(old if k < 30 else new, traversal=f"d{k:03d}",
                                      t_ns=k * 3600 * S, rng=rng, flip_rate=0.05)
        for shard in (keep, retire):
            shard.apply_batch(patches)
            shard.flush()
        assert np.array_equal(keep.labels((0, 0)), retire.labels((0, 0))), k
    assert keep.traversals_held() == 40 and keep.counters["traversals_retired"] == 0
    assert retire.traversals_held() <= 8
    assert retire.counters["traversals_retired"] == 40 - retire.traversals_held()
    assert keep.digest() == retire.digest()
    assert (retire.labels((0, 0))[new > 0] == new[new > 0]).mean() > 0.99  # follows the new paint


def test_a_late_patch_of_a_retired_traversal_revives_it():
    shard = MergerShard(retire_after_s=0)
    shard.apply_batch(_traversals(lane_tile(), 8))
    shard.flush()
    held = shard.traversals_held()
    assert held < 8
    late = patches_from_labels(lane_tile(), traversal="d000", t_ns=0)[0]
    late = GridPatch("late-0", late.vehicle, late.tile, late.cells, late.votes, 0, 0, "d000")
    assert shard.apply_patch(late) == "accepted"
    assert shard.counters["traversals_revived"] == 1 and shard.traversals_held() == held + 1
    shard.flush()
    assert np.array_equal(shard.labels((0, 0)), lane_tile())


def _signs(tile_labels: np.ndarray, *, traversals=3, **kw):
    return _merged(_traversals(tile_labels, traversals), **kw).labels((0, 0))


def test_a_ground_sign_blob_too_small_for_a_sign_is_decided_without_its_sign_ballots():
    seen = lane_tile()
    seen[100:104, 200:202] = 5  # 8 cells of "sign" on the lane line: a model's confusion
    seen[100:104, 260:263] = 5  # 12 cells of "sign" on bare road, seen as nothing else
    lane_seen = seen.copy()
    lane_seen[100:104, 200:202] = 2  # a third traversal saw the lane line there
    patches = _traversals(seen, 2) + _traversals(lane_seen, 1, t0=10, prefix="e")
    out = _merged(patches).labels((0, 0))
    assert not (out == 5).any()
    assert (out[100:104, 200:202] == 2).all()  # the lane line's ballot wins there
    assert (out[100:104, 260:263] == 0).all()  # no other ballot: unknown, not road
    assert (_merged(patches, min_sign_cells=0).labels((0, 0)) == 5).sum() == 20


def test_a_sign_of_parts_joined_across_small_gaps_stays():
    labels = lane_tile()
    labels[100:112, 260:263] = 5  # arrow shaft: 36 cells
    labels[114:118, 258:265] = 5  # head, 0.2 m above it: together one sign
    labels[130:134, 260:263] = 5  # 12 cells 1.2 m away: a blob of its own, too small
    out = _signs(labels)
    assert (out[100:118] == 5).sum() == 36 + 28
    assert not (out[130:134] == 5).any()


def test_a_small_sign_blob_at_the_tile_edge_stays_and_the_rule_can_be_turned_off():
    labels = lane_tile()
    labels[0:3, 260:263] = 5  # cut by the tile's edge: may be part of the neighbour's sign
    labels[100:104, 260:263] = 5
    assert (_signs(labels)[0:3, 260:263] == 5).all()
    assert (_signs(labels, min_sign_cells=0)[100:104, 260:263] == 5).all()


def test_a_stop_line_blob_too_small_for_a_stop_line_is_decided_without_its_stop_ballots():
    labels = lane_tile()
    labels[200:204, 100:135] = 3  # a stop line across a lane: 0.4 m x 3.5 m, 140 cells
    labels[300:302, 260:263] = 3  # 6 cells of "stop line" on bare road: a model's confusion
    out = _signs(labels, min_stop_cells=20)
    assert (out[200:204, 100:135] == 3).all()
    assert not (out[300:302, 260:263] == 3).any()
    assert (_signs(labels, min_stop_cells=0)[300:302, 260:263] == 3).all()  # the rule off
