"""The packaged model on frames of a world it never saw (Karlsruhe, rendered by the simulator):
a floor well under the benchmark's targets, to catch a broken model, export or preprocessing."""

import pytest

from common.segmentation import DEFAULT_MODEL, get_segmenter

# measured 0.95 0.70 0.92 0.93
FLOORS = {"road": 0.85, "lane_line": 0.50, "crosswalk": 0.70, "stop_line": 0.60}


@pytest.mark.shared_data
@pytest.mark.skipif(not DEFAULT_MODEL.is_file(), reason="no packaged model yet")
def test_packaged_model_iou_floor_on_heldout_karlsruhe_frames(shared_data):
    from services.bench.heldout import IouAccumulator, render_heldout

    osm = shared_data / "lanelet2-karlsruhe" / "mapping_example.osm"
    if not osm.is_file():
        pytest.skip("Karlsruhe Lanelet2 map missing")
    pairs, _ = render_heldout(f"lanelet2:{osm}", frames=8, seed=5, rare_prob=0.6)
    seg = get_segmenter("onnx", intra_op_threads=2)
    acc = IouAccumulator()
    for rgb, truth in pairs:
        acc.add(seg.segment(rgb), truth)
    iou = acc.result()
    for name, floor in FLOORS.items():
        if iou[name] is not None:
            assert iou[name] >= floor, f"{name} IoU {iou[name]:.3f} < {floor} ({iou})"
    assert iou["lane_line"] is not None


@pytest.mark.shared_data
@pytest.mark.skipif(not DEFAULT_MODEL.is_file(), reason="no packaged model yet")
def test_packaged_model_finds_ground_signs_painted_in_the_heldout_karlsruhe_world(shared_data):
    """The benchmark's `sign_facing` frames: the Karlsruhe map has no ground signs, arrows and
    words no town paints are added to its lanes (measured 0.88 on these 8 frames)."""
    from common.classes import Cls
    from services.bench.heldout import IouAccumulator, render_heldout

    osm = shared_data / "lanelet2-karlsruhe" / "mapping_example.osm"
    if not osm.is_file():
        pytest.skip("Karlsruhe Lanelet2 map missing")
    pairs, _ = render_heldout(f"lanelet2:{osm}", frames=8, seed=5, facing=Cls.GROUND_SIGN)
    seg = get_segmenter("onnx", intra_op_threads=2)
    acc = IouAccumulator()
    for rgb, truth in pairs:
        acc.add(seg.segment(rgb), truth)
    assert acc.result()["ground_sign"] >= 0.55, acc.result()


def test_ground_signs_go_on_bare_road_apart_and_face_the_camera():
    """with_ground_signs paints arrows and words only where the map has bare road (never over
    other paint or off the road), at least `spacing_m` apart, the same for the same seed; the
    sign-facing frames all show one."""
    import numpy as np

    from common.classes import Cls
    from common.world import World
    from services.bench.heldout import HELDOUT_TEXTS, render_heldout, with_ground_signs
    from services.sim.town import TEXTS
    from services.sim.worlds import load_world

    assert not set(HELDOUT_TEXTS) & set(TEXTS)
    world = load_world("town:0.6", 2)
    painted, anchors = with_ground_signs(world, 3, spacing_m=30.0)
    again, same = with_ground_signs(world, 3, spacing_m=30.0)
    assert same == anchors and len(again.markings) == len(painted.markings)
    added = painted.markings[len(world.markings):]
    assert len(anchors) >= 3 and added and all(m.cls == Cls.GROUND_SIGN for m in added)
    xy = np.array(anchors)[:, :2]
    gaps = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1))
    assert gaps[~np.eye(len(xy), dtype=bool)].min() >= 30.0
    before, x0, y0 = world.rasterize_all(4.0, 0.1)
    signs = World("signs", added).rasterize(x0, y0, *before.shape, 0.1)
    under = before[signs == Cls.GROUND_SIGN]
    assert len(under) > 100 and (under == Cls.ROAD).all()
    pairs, _ = render_heldout("town:0.6", frames=4, seed=2, facing=Cls.GROUND_SIGN)
    assert all((truth == Cls.GROUND_SIGN).sum() > 30 for _, truth in pairs)


def test_iou_is_pooled_over_frames_and_its_bootstrap_interval_spans_the_frames():
    import numpy as np

    from services.bench.heldout import IouAccumulator

    truth = np.zeros((10, 10), np.uint8)
    truth[:, :5] = 2  # lane line: 50 px
    perfect, half = truth.copy(), truth.copy()
    half[:, :5] = 0  # the line missed, and 25 road pixels called lane line instead
    half[:5, 5:] = 2
    acc = IouAccumulator()
    for pred in (perfect, half, half, half):
        acc.add(pred, truth)
    assert acc.result()["lane_line"] == round(50 / (50 + 3 * 75), 4)  # not the mean of frames
    assert acc.result()["stop_line"] is None and acc.true_px[2] == 200
    low, high = acc.interval(n=400)["lane_line"]
    assert 0.0 <= low < acc.result()["lane_line"] < high <= 1.0
    assert acc.interval(n=400)["stop_line"] is None
    same = IouAccumulator()
    for _ in range(4):
        same.add(half, truth)
    assert same.interval(n=50)["lane_line"] == [0.0, 0.0]
    # precision: 50 of 50 + 3 x 25 predicted pixels are true; recall: 50 of 200 true pixels
    assert acc.precision_recall()["lane_line"] == {"precision": 0.4, "recall": 0.25}
    assert acc.precision_recall()["stop_line"] == {"precision": None, "recall": None}


def test_stop_facing_frames_each_show_a_stop_line_ahead_of_a_camera_on_the_road():
    """The benchmark's stop-line frames (`facing`): every pose stands on the road with a stop
    line 4-20 m ahead, and the rendered truth shows it."""
    import math

    import numpy as np

    from common.classes import Cls
    from services.bench.heldout import FacingPoses, render_heldout
    from services.sim.worlds import load_world

    world = load_world("town:0.6", 2)
    poses = FacingPoses(world, Cls.STOP_LINE)
    stops = [m.polygon_xy_m for m in world.markings if m.cls == Cls.STOP_LINE]
    rng = np.random.default_rng(0)
    for _ in range(40):
        x, y, yaw = poses.draw(rng)
        assert poses.on_road(np.array([[x, y]]))[0]
        ahead = []
        for poly in stops:  # the stop line's points in the vehicle frame
            d = poly - [x, y]
            fwd = d @ [math.cos(yaw), math.sin(yaw)]
            left = d @ [-math.sin(yaw), math.cos(yaw)]
            if ((fwd > 0) & (np.abs(left) < 0.6 * fwd)).any():  # inside a +-31 deg cone
                ahead.append(float(np.hypot(*(poly.mean(axis=0) - [x, y]))))
        assert ahead and 3.5 <= min(ahead) <= 20.5
    pairs, _ = render_heldout("town:0.6", frames=6, seed=2, facing=Cls.STOP_LINE)
    assert all((truth == Cls.STOP_LINE).sum() > 100 for _, truth in pairs)


def test_paired_draws_score_both_models_on_the_same_frames():
    """bench --baseline: the interval of a difference between two models on the same frames.
    A model against itself differs by exactly 0 on every draw; one that is better on every
    frame stays above 0."""
    import numpy as np

    from services.bench.heldout import IouAccumulator, bootstrap_interval

    truth = np.zeros((10, 10), np.uint8)
    good, bad = IouAccumulator(), IouAccumulator()
    for width in range(1, 9):  # lane lines from 1 to 8 px wide: frames differ a lot
        truth = np.zeros((10, 10), np.uint8)
        truth[:, :width] = 2
        worse = truth.copy()
        worse[:, width:width + 1] = 2  # one column too wide
        good.add(truth, truth)
        bad.add(worse, truth)
    rng = np.random.default_rng(0)
    assert bootstrap_interval(bad.draws(200, rng, minus=bad))["lane_line"] == [0.0, 0.0]
    diff = bootstrap_interval(good.draws(200, rng, minus=bad))["lane_line"]
    assert 0.0 < diff[0] < diff[1] < 0.5
    assert bootstrap_interval(good.draws(200, rng, minus=bad))["stop_line"] is None
    short = IouAccumulator()
    short.add(truth, truth)
    with pytest.raises(ValueError, match="frames"):
        good.draws(10, rng, minus=short)
