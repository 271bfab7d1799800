"""How far one vehicle with valid credentials can push false patches into the merged map
(services/merger/shard.py's evidence rule; deploy/README.md's threat model states the bound):
a traversal casts one ballot per cell however many patches and votes it sends, and only the
window (3) newest traversals of a cell count. So one false traversal never flips a cell that
two others agree on; two can (the price of following a repaint in 2), and two honest newer
traversals undo it."""

import numpy as np

from common.classes import NUM_CLASSES
from common.messages import GridPatch
from services.merger.shard import MergerShard
from tests.merger.helpers import lane_tile, patches_from_labels

T = 10**12  # one traversal a T apart (their own t_first_ns decides which are newest)


def _honest(shard: MergerShard, labels: np.ndarray, first: int, n: int) -> None:
    for i in range(first, first + n):
        shard.apply_batch(patches_from_labels(labels, traversal=f"honest-{i}", t_ns=i * T,
                                              vehicle=f"veh-{i}"))


def _false_traversal(traversal: str, t_ns: int, *, copies: int, fake: np.ndarray):
    """`copies` patches of one traversal, each covering every cell of `fake` with the largest
    vote a patch can carry (65535) for the fake class: flooding, inside one traversal."""
    cells = np.flatnonzero(fake.ravel() > 0).astype(np.uint32)
    votes = np.zeros((len(cells), NUM_CLASSES), np.uint16)
    votes[np.arange(len(cells)), fake.ravel()[cells]] = np.iinfo(np.uint16).max
    return [GridPatch(patch_id=f"evil/{traversal}/{k}", vehicle="evil", tile=(0, 0),
                      cells=cells, votes=votes, t_first_ns=t_ns, t_last_ns=t_ns + 1,
                      traversal=traversal) for k in range(copies)]


def _fake_map() -> np.ndarray:
    """The attacker's map: the lane line moved by 40 cells, a stop line over the whole road."""
    fake = lane_tile(offset_cells=40)
    fake[100:110, 150:300] = 3
    return fake


def _flipped(shard: MergerShard, truth: np.ndarray) -> int:
    shard.flush()
    return int(np.count_nonzero(shard.labels((0, 0)) != truth))


def test_one_vehicle_flooding_one_traversal_flips_no_cell():
    truth = lane_tile()
    shard = MergerShard()
    _honest(shard, truth, first=1, n=2)
    assert _flipped(shard, truth) == 0
    # 40 patches, 65535 votes a cell, the newest traversal of all: still one ballot of three
    patches = _false_traversal("evil-1", 10 * T, copies=40, fake=_fake_map())
    for k in range(0, len(patches), 10):
        shard.apply_batch(patches[k : k + 10])
    assert _flipped(shard, truth) == 0


def test_many_vehicle_ids_in_one_traversal_are_still_one_ballot():
    truth = lane_tile()
    shard = MergerShard()
    _honest(shard, truth, first=1, n=2)
    patches = _false_traversal("evil-1", 10 * T, copies=10, fake=_fake_map())
    for k, p in enumerate(patches):
        object.__setattr__(p, "vehicle", f"forged-{k}")  # claims 10 vehicles
    shard.apply_batch(patches)
    assert _flipped(shard, truth) == 0


def test_two_forged_traversals_flip_cells_until_two_honest_ones_pass():
    truth, fake = lane_tile(), _fake_map()
    shard = MergerShard()
    _honest(shard, truth, first=1, n=5)
    for k in (1, 2):  # forged traversal ids, newest timestamps: 2 of the window's 3 ballots
        shard.apply_batch(_false_traversal(f"evil-{k}", (10 + k) * T, copies=1, fake=fake))
    assert _flipped(shard, truth) > 0  # the bound is per traversal, not per vehicle
    _honest(shard, truth, first=20, n=2)  # two honest traversals after them
    assert _flipped(shard, truth) == 0


def test_against_a_single_traversal_the_votes_decide():
    """One ballot each: the tie goes to the votes behind them, which a vehicle sets itself.
    The bound needs two traversals that agree."""
    truth = lane_tile()
    shard = MergerShard()
    _honest(shard, truth, first=1, n=1)
    shard.apply_batch(_false_traversal("evil-1", 10 * T, copies=1, fake=_fake_map()))
    assert _flipped(shard, truth) > 0
