"""Training-data restyling of procedural towns and the runtime's channel argmax."""

import numpy as np

from common.classes import Cls
from common.segmentation import argmax_channels
from services.segtrain.data import _strip_halves, restyled
from services.sim.worlds import load_world


def _widths(world, cls, kinds):
    out = []
    for m in world.markings:
        half = _strip_halves(m.polygon_xy_m) if m.cls == cls and m.kind in kinds else None
        if half is not None:
            out.append(2.0 * float(np.median(np.linalg.norm(half[1], axis=1))))
    return np.array(out)


def test_restyled_town_has_thick_lines_fewer_edge_lines_and_narrower_roads():
    world = load_world("town:0.8", 3)
    thick_seen, narrower_seen = False, False
    for seed in range(6):
        new = restyled(world, np.random.default_rng(seed))
        lines = _widths(new, Cls.LANE_LINE, ("solid", "dashed"))
        assert lines.min() >= 0.099 and lines.max() <= 0.301
        thick_seen |= bool((lines > 0.19).any())
        assert len(new.markings) <= len(world.markings)
        roads_old = _widths(world, Cls.ROAD, ("road",))
        roads_new = _widths(new, Cls.ROAD, ("road",))
        assert len(roads_new) == len(roads_old) and (roads_new <= roads_old + 1e-6).all()
        narrower_seen |= bool((roads_new < roads_old - 0.1).any())
        others = lambda w: sum(m.cls not in (Cls.LANE_LINE, Cls.ROAD) for m in w.markings)  # noqa: E731
        assert others(new) == others(world)  # stop lines, crossings, signs untouched
    assert thick_seen and narrower_seen


def test_argmax_channels_matches_numpy_including_ties(rng):
    scores = rng.normal(size=(6, 37, 53)).astype(np.float32)
    scores[4, :5] = scores[2, :5]  # ties: the first maximum wins, as in np.argmax
    got = argmax_channels(scores)
    assert got.dtype == np.uint8
    assert (got == scores.argmax(axis=0)).all()


def test_training_chunks_are_seeded_and_do_not_depend_on_the_worker_count(tmp_path):
    """The training set is a sequence of per-town chunks seeded by (seed, chunk) alone: one
    process and a pool of two render the same frames (the GPU run used 16 processes)."""
    from services.segtrain.data import CHUNK_FRAMES, training_set

    kw = dict(seed=3, input_size=(160, 96), budget_s=1e9, max_frames=CHUNK_FRAMES, cache=False)
    f1, l1 = training_set(workers=1, **kw)
    f2, l2 = training_set(workers=2, **kw)
    assert f1.shape == (CHUNK_FRAMES, 96, 160, 3) and l1.shape == (CHUNK_FRAMES, 96, 160)
    assert np.array_equal(f1, f2) and np.array_equal(l1, l2)
    assert (l1 >= Cls.LANE_LINE).any()  # paint in view, not an empty road
    f3, _ = training_set(workers=1, **{**kw, "seed": 4})
    assert not np.array_equal(f1, f3)
