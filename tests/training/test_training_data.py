"""Training-data restyling of procedural towns and the runtime's channel argmax."""

import cv2
import numpy as np
import pytest

from common.classes import Cls
from common.errors import ConfigError
from common.segmentation.scores import argmax_channels
from services.sim.worlds import load_world
from training.data import (
    _inside,
    _save_cache,
    _strip_halves,
    junction_lines,
    restyled,
    town_world,
)


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


def test_junction_lines_are_dashed_lane_lines_inside_the_intersections():
    world = load_world("town:0.8", 3)
    boxes = [m.polygon_xy_m for m in world.markings if m.kind == "intersection"]
    added = []
    for seed in range(4):
        new = junction_lines(world, np.random.default_rng(seed))
        assert new.markings[:len(world.markings)] == world.markings  # nothing else touched
        added += new.markings[len(world.markings):]
    assert len(added) > 10
    for m in added:
        assert m.cls == Cls.LANE_LINE and m.kind == "dashed"
        centre = m.polygon_xy_m.mean(axis=0)[None]
        assert any(_inside(box, centre)[0] for box in boxes)  # in a junction, not on a road
        length = np.linalg.norm(np.ptp(m.polygon_xy_m, axis=0))
        assert length < 4.0  # dashes of at most 3.5 m, not solid lines


def test_heavy_junction_lines_are_more_and_keep_their_widths_through_restyling():
    """The heavy dose (a --soup run's other towns) paints lines through more junctions, before
    `restyled`, as dashes of kind "junction" that it leaves at their drawn width; the light
    dose is the recipe's towns."""
    world = load_world("town:0.8", 3)
    light = [len(junction_lines(world, np.random.default_rng(s)).markings) for s in range(6)]
    heavy = [len(junction_lines(world, np.random.default_rng(s), "heavy").markings)
             for s in range(6)]
    assert sum(heavy) > sum(light) > 6 * len(world.markings)
    town = town_world(7, np.random.default_rng(7), "heavy")
    dashes = _widths(town, Cls.LANE_LINE, ("junction",))
    assert len(dashes) > 10
    assert ((dashes > 0.099) & (dashes < 0.161) | (dashes > 0.199) & (dashes < 0.301)).all()
    junctions = sum(m.kind == "intersection" for m in town.markings)
    assert len(set(np.round(dashes, 4))) <= junctions < len(dashes)  # a width per junction
    with pytest.raises(ConfigError, match="one of light, heavy"):
        town_world(7, np.random.default_rng(7), "wide")


def test_argmax_channels_matches_numpy_including_ties(rng):
    scores = rng.normal(size=(6, 37, 53)).astype(np.float32)
    scores[4, :5] = scores[2, :5]  # ties: the first maximum wins, as in np.argmax
    got = argmax_channels(scores)
    assert got.dtype == np.uint8
    assert (got == scores.argmax(axis=0)).all()


def test_training_chunks_are_seeded_and_do_not_depend_on_the_worker_count(tmp_path):
    """The training set is a sequence of per-town chunks seeded by (seed, chunk) alone: one
    process and a pool of two render the same frames (the GPU run used 16 processes)."""
    from training.data import CHUNK_FRAMES, training_set

    kw = dict(seed=3, input_size=(160, 96), budget_s=1e9, max_frames=CHUNK_FRAMES, cache=False)
    f1, l1 = training_set(workers=1, **kw)
    f2, l2 = training_set(workers=2, **kw)
    assert f1.shape == (CHUNK_FRAMES, 96, 160, 3) and l1.shape == (CHUNK_FRAMES, 96, 160)
    assert np.array_equal(f1, f2) and np.array_equal(l1, l2)
    assert (l1 >= Cls.LANE_LINE).any()  # paint in view, not an empty road
    f3, _ = training_set(workers=1, **{**kw, "seed": 4})
    assert not np.array_equal(f1, f3)
    f4, _ = training_set(workers=1, **{**kw, "turn_prob": 0.0})  # --turn-prob reaches the poses
    assert not np.array_equal(f1, f4)
    # --synth-share reaches the workers: chunk 0 (synth.py's by default) from the simulator
    f5, _ = training_set(workers=2, **{**kw, "synth_share": 0.0})
    assert not np.array_equal(f1, f5)


def test_synth_share_is_in_tenths():
    from training.data import check_synth_share

    for share in (0.0, 0.3, 1.0):
        check_synth_share(share)
    for share in (-0.1, 0.35, 1.5):
        with pytest.raises(ConfigError, match="synth-share"):
            check_synth_share(share)


def test_permute_rows_in_place_equals_fancy_indexing(rng):
    """The training set is shuffled in place (a copy of 12000 frames is 11 GB)."""
    from training.data import permute_rows

    for n in (0, 1, 2, 7, 100):
        a = rng.integers(0, 255, (n, 3, 4), dtype=np.uint8)
        for order in (np.arange(n), rng.permutation(n)):
            b = a.copy()
            permute_rows(b, order)
            assert np.array_equal(b, a[order])


def test_raised_curbs_get_the_auxiliary_training_label_only_when_asked():
    """Training labels mark raised curbs (face and top) as their own class; without it, the
    same pixels are none and nothing else changes."""
    from common.camera import camera_from_config
    from common.config import CameraConfig
    from services.sim.render import FrameRenderer
    from training.data import CURB_AUX
    from training.synth import random_pose

    world = load_world("town:0.6", 2)
    camera = camera_from_config(CameraConfig())
    renderer = FrameRenderer(world, camera, seed=5)
    renderer.look.curb = True
    rng = np.random.default_rng(1)
    seen = 0
    for _ in range(4):
        pose = random_pose(world, rng, rare_prob=0.0)
        _, plain = renderer.render(pose, camera.T_vehicle_camera, 0.0)
        _, aux = renderer.render(pose, camera.T_vehicle_camera, 0.0, curb_label=CURB_AUX)
        curb = aux == CURB_AUX
        assert (plain[curb] == 0).all() and np.array_equal(plain[~curb], aux[~curb])
        assert CURB_AUX not in plain
        # a curb borders the road: every connected piece of curb touches road pixels
        n, pieces = cv2.connectedComponents(curb.astype(np.uint8))
        near_road = cv2.dilate((plain >= Cls.ROAD).astype(np.uint8), np.ones((3, 3), np.uint8))
        assert set(np.unique(pieces[curb & (near_road > 0)])) == set(range(1, n))
        seen += int(curb.sum())
    assert seen > 500


def test_synth_frames_label_curbs_only_in_looks_that_draw_them():
    from training.data import CURB_AUX
    from training.synth import render_town_frames

    world = load_world("town:0.6", 4)
    frames = list(render_town_frames(world, 2, 4, np.random.default_rng(0), supersample=1,
                                     curb_label=CURB_AUX))
    with_curb = [lab for _, lab in frames if (lab == CURB_AUX).any()]
    assert 0 < len(with_curb) and all(lab.max() <= CURB_AUX for _, lab in frames)
    plain = list(render_town_frames(world, 2, 4, np.random.default_rng(0), supersample=1))
    assert all(lab.max() < CURB_AUX for _, lab in plain)


def test_turned_training_poses_keep_the_position_and_the_benchmark_poses_are_unchanged():
    """Training turns a share of poses 15-90 deg off the route; the held-out benchmark (turn
    probability 0) draws exactly the poses it drew before."""
    import math

    from training.synth import _route_pose, random_pose

    world = load_world("town:0.6", 2)
    for seed in range(5):
        base = _route_pose(world, np.random.default_rng(seed), 0.3)
        assert random_pose(world, np.random.default_rng(seed), 0.3) == base
        turned = random_pose(world, np.random.default_rng(seed), 0.3, turn_prob=1.0)
        assert turned[:2] == base[:2]
        off = abs(math.remainder(turned[2] - base[2], 2 * math.pi))
        assert math.radians(15) <= off <= math.radians(90)


def test_streamed_chunks_are_the_training_set_in_order_and_stopping_leaves_nothing():
    """FrameStream (GPU runs: frames rendered while the model trains) hands over chunk k =
    (seed, k) in order, the same frames training_set renders, whatever its worker count;
    close() kills the workers and removes their folder."""
    from training.data import CHUNK_FRAMES, FrameStream, training_set

    size = (160, 96)
    want_f, want_l = training_set(seed=3, input_size=size, budget_s=1e9,
                                  max_frames=2 * CHUNK_FRAMES, cache=False)
    order = np.argsort(np.random.default_rng(3).permutation(len(want_f)))  # undo its shuffle
    stream = FrameStream(seed=3, input_size=size, max_frames=2 * CHUNK_FRAMES, workers=2)
    try:
        got_f, got_l = stream.wait(2 * CHUNK_FRAMES, timeout_s=300)
        assert stream.take() is None  # nothing more to come
    finally:
        stream.close()
    assert np.array_equal(got_f, want_f[order]) and np.array_equal(got_l, want_l[order])
    assert not stream._dir.exists()
    assert not any(proc.is_alive() for proc in stream._procs)


def test_a_stream_mixes_junction_doses_chunk_by_chunk(tmp_path, capsys):
    """--stream-junctions light,heavy: chunk k of the stream is training_set's chunk k of
    dose k mod 2; a dose it does not know, or the flag without --stream, is refused before
    anything renders."""
    from training.cli import main
    from training.data import (
        CHUNK_FRAMES,
        SYNTH_SHARE,
        TURN_PROB,
        FrameStream,
        _render_chunk,
        _sim_available,
    )

    size = (160, 96)
    stream = FrameStream(seed=3, input_size=size, max_frames=2 * CHUNK_FRAMES, workers=2,
                         junctions=("light", "heavy"))
    try:
        got_f, got_l = stream.wait(2 * CHUNK_FRAMES, timeout_s=300)
    finally:
        stream.close()
    # chunk 0 is the light one every stream starts with (the test above); chunk 1:
    job = (3, 1, size, _sim_available(), TURN_PROB, SYNTH_SHARE)
    want_f, want_l = _render_chunk((*job, "heavy"))
    assert np.array_equal(got_f[CHUNK_FRAMES:], want_f)
    assert np.array_equal(got_l[CHUNK_FRAMES:], want_l)
    assert not np.array_equal(want_l, _render_chunk((*job, "light"))[1])  # the dose tells
    with pytest.raises(ConfigError, match="junction lines 'none'"):
        FrameStream(seed=3, input_size=size, max_frames=CHUNK_FRAMES, workers=1,
                    junctions=("light", "none"))
    out = tmp_path / "out"
    assert main(["train-seg", "--out", str(out), "--stream-junctions", "heavy"]) == 1
    assert "give --stream" in capsys.readouterr().err
    assert main(["train-seg", "--out", str(out), "--stream", "--stream-junctions",
                 "light,none"]) == 1
    assert "junction lines 'none'" in capsys.readouterr().err
    assert not any(out.iterdir())


def test_training_crops_are_windows_of_the_frames_or_the_whole_frame():
    from training.train import _crop_batch, crop_size

    assert crop_size("384x224", (360, 640)) == (224, 384)
    assert crop_size("full", (360, 640)) == (360, 640)
    for bad in ("700x100", "384", "wide"):
        with pytest.raises(ConfigError, match="--crop"):
            crop_size(bad, (360, 640))
    rng = np.random.default_rng(0)
    x = np.arange(2 * 3 * 360 * 640).reshape(2, 3, 360, 640)
    y = x[:, 0] % 7
    xb, yb, top, half = _crop_batch(x, y, rng, (360, 640))
    assert top == 0 and np.array_equal(xb, x) and np.array_equal(yb, y) and half is None
    xb, yb, top, _ = _crop_batch(x, y, rng, (224, 384))
    assert xb.shape == (2, 3, 224, 384) and yb.shape == (2, 224, 384)
    left = int(xb[0, 0, 0, 0]) - top * 640  # x holds each pixel's flat index
    assert np.array_equal(xb, x[:, :, top:top + 224, left:left + 384])
    assert np.array_equal(yb, y[:, top:top + 224, left:left + 384])


def test_a_teachers_half_resolution_logits_are_cropped_with_the_frame():
    """With a teacher's 1/2-resolution logits, crops start on even rows and columns, and the
    logits' crop covers the same pixels of the frame."""
    from training.train import _crop_batch

    rng = np.random.default_rng(1)
    x = np.arange(2 * 3 * 360 * 640).reshape(2, 3, 360, 640)
    half = x[:, :, ::2, ::2]  # each 1/2-resolution cell holds its top-left pixel's index
    for _ in range(20):
        xb, _, top, hb = _crop_batch(x, x[:, 0] % 7, rng, (224, 384), half)
        left = int(xb[0, 0, 0, 0]) - top * 640
        assert top % 2 == 0 and left % 2 == 0
        assert hb.shape == (2, 3, 112, 192) and np.array_equal(hb, xb[:, :, ::2, ::2])
    with pytest.raises(ConfigError, match="even crop"):
        _crop_batch(x, x[:, 0] % 7, rng, (225, 384), half)


def test_streamed_held_out_halves_have_the_training_mix():
    """A streamed run's held-out frames arrive in chunk order (chunks 0-2 of every 10 from
    synth.py): its calibration and validation halves each get the training set's share."""
    from training.data import CHUNK_FRAMES, SYNTH_SHARE
    from training.train import STREAM_VAL_FRAMES, interleaved_halves

    n = STREAM_VAL_FRAMES
    synth = (np.arange(n) // CHUNK_FRAMES) % 10 < round(10 * SYNTH_SHARE)
    order = interleaved_halves(n)
    assert sorted(order) == list(range(n))
    first, second = synth[order[:n // 2]], synth[order[n // 2:]]
    assert first.mean() == pytest.approx(SYNTH_SHARE)
    assert second.mean() == pytest.approx(SYNTH_SHARE)
    assert synth[:n // 2].mean() > 0.5  # as they came: the first half was mostly synth.py's


def test_synth_labels_are_the_class_at_each_pixel_centre_as_the_simulator_labels():
    from training.synth import GroundMap, WorldRaster, random_camera, random_pose, render

    world = load_world("town:0.6", 4)
    rng = np.random.default_rng(3)
    raster, camera = WorldRaster(world, rng), random_camera(rng)
    fine, centre = GroundMap(camera, 2), GroundMap(camera, 1)
    paint_px = 0
    for _ in range(3):
        pose = random_pose(world, rng)
        seed = int(rng.integers(1 << 30))
        _, labels = render(raster, fine, pose, np.random.default_rng(seed))
        _, truth = render(raster, centre, pose, np.random.default_rng(seed))
        # 2x2 supersampled colours, labels sampled where the simulator samples them: a
        # majority of the sub-samples would label lines half a pixel thinner than drawn
        np.testing.assert_array_equal(labels, truth)
        paint_px += int((labels >= Cls.LANE_LINE).sum())
    assert paint_px > 500


def test_frame_cache_is_written_whole_or_not_at_all(tmp_path, caplog):
    frames = np.zeros((2, 4, 6, 3), np.uint8)
    labels = np.ones((2, 4, 6), np.uint8)
    good = tmp_path / "sets" / "a.npz"
    _save_cache(good, frames, labels)
    with np.load(good) as z:
        assert (z["labels"] == labels).all() and z["frames"].shape == frames.shape
    assert not list(good.parent.glob("*.part"))

    blocker = tmp_path / "not-a-dir"
    blocker.write_text("")  # the cache folder cannot be made: an OSError, as a full disk
    with caplog.at_level("WARNING"):
        _save_cache(blocker / "b.npz", frames, labels)  # the run goes on
    assert "not cached" in caplog.text
    assert blocker.read_text() == ""
