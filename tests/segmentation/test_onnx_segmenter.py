"""OnnxSegmenter runtime: the packaged model, head mapping, factory, and the real TwinLiteNet."""

from functools import partial

import cv2
import numpy as np
import pytest

from common.classes import NUM_CLASSES, Cls
from common.config import FLIP_MODES
from common.errors import ConfigError
from common.segmentation import DEFAULT_MODEL, OnnxSegmenter, get_segmenter, model_flip_mode
from services.sim.truth_segmenter import GroundTruthSegmenter

needs_model = pytest.mark.skipif(not DEFAULT_MODEL.is_file(), reason="no packaged model yet")


@needs_model
def test_packaged_model_labels_have_image_shape_and_our_classes(rng):
    seg = get_segmenter("onnx")
    image = rng.integers(0, 255, (360, 640, 3), dtype=np.uint8)
    labels = seg.segment(image)
    assert labels.shape == (360, 640) and labels.dtype == np.uint8
    assert labels.max() < NUM_CLASSES


@needs_model
def test_packaged_model_describes_its_input_in_metadata():
    seg = OnnxSegmenter()
    assert seg.input_size == (640, 360)
    assert seg.scale == pytest.approx(1.0 / 255.0)
    assert seg.name == "roadseg"


@needs_model
def test_head_map_remaps_and_drops_classes(rng):
    image = rng.integers(0, 255, (176, 320, 3), dtype=np.uint8)
    image[100:, :] = 90  # some road-like area
    # a head_map turns the model's refine and border classifier off
    plain = OnnxSegmenter(refine={}, border_net=False).segment(image)
    # model class 2 (lane line) -> ground sign, every other class -> 0
    remapped = OnnxSegmenter(head_map={"logits": {2: int(Cls.GROUND_SIGN)}}).segment(image)
    np.testing.assert_array_equal(remapped == Cls.GROUND_SIGN, plain == Cls.LANE_LINE)
    assert set(np.unique(remapped)) <= {0, int(Cls.GROUND_SIGN)}


@needs_model
def test_head_map_rejects_unknown_heads_and_classes():
    with pytest.raises(ConfigError, match="no output"):
        OnnxSegmenter(head_map={"da": {1: 1}})
    with pytest.raises(ConfigError, match="outside"):
        OnnxSegmenter(head_map={"logits": {1: 9}})


def test_factory_picks_the_strategy():
    assert isinstance(get_segmenter("truth", seed=3), GroundTruthSegmenter)
    with pytest.raises(ConfigError):
        get_segmenter("yolo")
    with pytest.raises(ConfigError, match="not found"):
        get_segmenter("onnx", model_path="/nonexistent/model.onnx")


@pytest.mark.shared_data
def test_twinlitenet_finds_lane_lines_in_the_lower_half_of_a_real_frame(shared_data):
    from training.external import (
        assumed_camera,
        lane_ground_points,
        read_rgb,
        twinlitenet_segmenter,
    )

    model = shared_data / "models" / "twinlitenet" / "twinlitenet.onnx"
    frame = shared_data / "comma2k19" / "segment40" / "preview.png"
    if not model.is_file() or not frame.is_file():
        pytest.skip("TwinLiteNet or the comma2k19 preview frame is missing")
    rgb = read_rgb(frame)
    labels = twinlitenet_segmenter(shared_data, threads=2).segment(rgb)
    assert labels.shape == rgb.shape[:2]
    h = labels.shape[0]
    lane = labels == Cls.LANE_LINE
    assert lane[h // 2:].sum() > 2000  # painted lines on the road ahead
    assert lane[: int(0.4 * h)].sum() < 0.05 * lane.sum()  # not in the sky
    assert (labels == Cls.ROAD).sum() > 0.05 * labels.size
    # projected with the comma2k19 calibration, lane paint lies a few metres left/right ahead
    ground = lane_ground_points(labels, assumed_camera("comma2k19", rgb.shape[1], rgb.shape[0]))
    near = ground[ground[:, 0] < 25.0]
    assert len(near) > 1000
    assert np.all(near[:, 0] > 3.0)
    assert np.median(np.abs(near[:, 1])) < 6.0


@needs_model
def test_bilinear_upsampling_agrees_with_nearest_on_most_pixels(rng):
    image = rng.integers(0, 255, (360, 640, 3), dtype=np.uint8)
    nearest = OnnxSegmenter().segment(image)
    smooth = OnnxSegmenter(upsample="bilinear").segment(image)
    assert smooth.shape == nearest.shape and smooth.dtype == np.uint8
    assert (smooth == nearest).mean() > 0.9
    with pytest.raises(ConfigError):
        OnnxSegmenter(upsample="cubic")


def test_unsure_paint_becomes_unknown_and_confident_paint_stays():
    from common.segmentation.refine import unsure_paint_unknown
    from common.segmentation.scores import scores_at

    # 4 pixels, 6 classes: a sure lane line, an unsure lane line (lead 0.5), an unsure road
    # pixel (road is never dropped), a crosswalk leading by exactly the margin
    scores = np.zeros((6, 1, 4), np.float32)
    scores[Cls.LANE_LINE, 0, 0], scores[Cls.ROAD, 0, 0] = 5.0, 1.0
    scores[Cls.LANE_LINE, 0, 1], scores[Cls.STOP_LINE, 0, 1] = 3.0, 2.5
    scores[Cls.ROAD, 0, 2], scores[Cls.LANE_LINE, 0, 2] = 1.1, 1.0
    scores[Cls.CROSSWALK, 0, 3], scores[Cls.NONE, 0, 3] = 2.0, 0.0
    labels = scores.argmax(axis=0).astype(np.uint8)
    out = unsure_paint_unknown(partial(scores_at, scores), labels.copy(), 2.0)
    assert out.tolist() == [[Cls.LANE_LINE, Cls.NONE, Cls.ROAD, Cls.CROSSWALK]]


@needs_model
def test_min_margin_drops_exactly_the_marking_pixels_the_model_is_unsure_of():
    from tests.segmentation.test_refine import _town_frame

    image = _town_frame()  # worn paint, curbs and shade: things for the network to doubt
    plain = OnnxSegmenter(refine={}, border_net=False).segment(image)
    gated_seg = OnnxSegmenter(refine={}, border_net=False, min_margin=2.0)
    gated = gated_seg.segment(image)
    # the margin from the network's logits (flip-averaged, as the model asks), upsampled as
    # the runtime does
    (logits,) = gated_seg.run_network(gated_seg.preprocess(image))
    up = np.stack([cv2.resize(c, (640, 360), interpolation=cv2.INTER_LINEAR) for c in logits[0]])
    top2 = np.sort(up, axis=0)[-2:]
    unsure = (plain >= Cls.LANE_LINE) & (top2[1] - top2[0] < 2.0)
    assert (plain >= Cls.LANE_LINE).sum() > 500 and unsure.sum() > 20
    np.testing.assert_array_equal(gated, np.where(unsure, Cls.NONE, plain))
    with pytest.raises(ConfigError, match="min_margin"):
        OnnxSegmenter(min_margin=-1.0)


def test_upsampled_argmax_equals_the_resize_then_argmax(rng):
    from common.segmentation.scores import (
        UpsampledScores,
        argmax_channels,
        resize_channels,
        upsampled_argmax,
        upsampled_at,
    )

    # blobs of classes (as logits are: smooth, with a few thin structures) and pure noise
    smooth = cv2.resize(rng.normal(0, 3, (6, 12, 20)).transpose(1, 2, 0), (33, 19),
                        interpolation=cv2.INTER_CUBIC).transpose(2, 0, 1)
    for scores in (np.ascontiguousarray(smooth, np.float32),
                   rng.normal(0, 1, (6, 19, 33)).astype(np.float32)):
        up = resize_channels(scores, (66, 38))
        np.testing.assert_array_equal(upsampled_argmax(scores), argmax_channels(up))
        ys, xs = np.nonzero(np.ones((38, 66), bool))
        np.testing.assert_allclose(upsampled_at(scores, ys, xs), up.reshape(6, -1), atol=1e-5)
        # the kept blends of the mixed blocks and the computed scores elsewhere, in any order
        upsampled = UpsampledScores(scores)
        order = rng.permutation(len(ys))
        np.testing.assert_allclose(upsampled(ys[order], xs[order]), up.reshape(6, -1)[:, order],
                                   atol=1e-5)
        assert upsampled(ys[:0], xs[:0]).shape == (6, 0)
        # from a first row on, the same labels and scores; above it the class of each
        # pixel's block's first coarse pixel (up and left of it, edges replicated)
        coarse = argmax_channels(scores)
        corner = coarse[np.maximum((np.arange(38) - 1) >> 1, 0)][:, np.maximum(
            (np.arange(66) - 1) >> 1, 0)]
        for first in (1, 6, 7):
            part = UpsampledScores(scores, first)
            np.testing.assert_array_equal(part.labels[first:], upsampled.labels[first:])
            np.testing.assert_array_equal(part.labels[:first - 1], corner[:first - 1])
            np.testing.assert_allclose(part(ys, xs), up.reshape(6, -1), atol=1e-5)
    flat = UpsampledScores(np.zeros((6, 4, 5), np.float32))  # no mixed block: nothing kept
    assert (flat.labels == 0).all() and flat([1, 7], [2, 9]).shape == (6, 2)


@needs_model
def test_sky_rows_are_labelled_none_and_the_network_sees_only_the_rows_below():
    from tests.segmentation.test_refine import _town_frame

    image = _town_frame()
    full = OnnxSegmenter(refine={}, border_net=False)
    # 72 rows, in steps of 16: 64
    sky = OnnxSegmenter(refine={}, border_net=False, sky_fraction=0.2)
    assert full.sky_rows == 0 and sky.sky_rows == 64
    assert sky.preprocess(image).shape == (1, 3, 360 - 64, 640)
    a, b = full.segment(image), sky.segment(image)
    assert (b[:64] == Cls.NONE).all()
    paint = a[64:] >= Cls.LANE_LINE
    assert paint.sum() > 500
    # below the sky the network's context changes only at the top of its input: 99.8 % of the
    # labels agree and 99.3 % of the paint for the m64 network of 2026-11-28 (99.6 % for B1).
    # (A line drawing instead of a rendered frame moved 10 % of m64's paint: its 1/16 stage
    # sees the whole frame, and the drawing is far from any frame it learned from.)
    assert (a[64:] == b[64:]).mean() > 0.99 and (b[64:][paint] == a[64:][paint]).mean() > 0.97
    # bilinear labels at another size keep the sky in proportion
    big = OnnxSegmenter(refine={}, border_net=False, sky_fraction=0.2, upsample="bilinear")
    labels = big.segment(np.repeat(np.repeat(image, 2, 0), 2, 1))
    assert labels.shape == (720, 1280) and (labels[:128] == Cls.NONE).all()
    with pytest.raises(ConfigError, match="sky_fraction"):
        OnnxSegmenter(sky_fraction=1.0)


@needs_model
def test_the_packaged_models_sky_cut_leaves_every_row_of_climbing_road():
    """With the default camera the packaged model's sky cut (its own margin, else the
    runtime's default) leaves out sky rows (its time) but only rows above rays rising 3 deg
    or more, so road that climbs towards the horizon by up to that is still segmented, and so
    is every row of level ground."""
    from common.camera import camera_from_config, sky_rows
    from common.config import CameraConfig

    camera = camera_from_config(CameraConfig())
    seg = OnnxSegmenter(camera=camera)
    assert seg.sky_margin_deg >= 3.0
    assert 0 < seg.sky_rows <= sky_rows(camera, 3.0) < sky_rows(camera, 0.0)


@needs_model
def test_a_fixed_height_model_segments_every_row(tmp_path, caplog):
    onnx = pytest.importorskip("onnx")

    proto = onnx.load(str(DEFAULT_MODEL))
    proto.graph.input[0].type.tensor_type.shape.dim[2].dim_value = 360  # was dynamic
    path = tmp_path / "fixed.onnx"
    onnx.save(proto, str(path))
    with caplog.at_level("WARNING"):
        seg = OnnxSegmenter(path, sky_fraction=0.3)
    assert seg.sky_rows == 0 and "every row is segmented" in caplog.text
    assert seg.segment(np.zeros((360, 640, 3), np.uint8)).shape == (360, 640)


@needs_model
def test_configured_segmenter_leaves_out_the_cameras_sky(tmp_path):
    import dataclasses

    from common.camera import camera_from_config, sky_rows
    from common.config import RoadmapConfig, load_config
    from common.segmentation import DEFAULT_SKY_MARGIN_DEG, configured_onnx
    from training.train import set_metadata

    cfg = RoadmapConfig()
    camera = camera_from_config(cfg.camera)
    assert cfg.segmentation.sky_margin_deg is None  # each model's own
    # a model that names no margin (null: as if absent) gets the default one
    plain = tmp_path / "plain.onnx"
    plain.write_bytes(DEFAULT_MODEL.read_bytes())
    set_metadata(plain, sky_margin_deg=None)
    seg = configured_onnx(dataclasses.replace(cfg.segmentation, model_path=str(plain)),
                          camera=camera)
    rows = sky_rows(camera, DEFAULT_SKY_MARGIN_DEG)
    assert seg.sky_margin_deg == DEFAULT_SKY_MARGIN_DEG
    assert 0 < seg.sky_rows <= rows < seg.sky_rows + 16
    # a model that asks for every row gets every row, and one with a lower margin more sky
    whole, low = tmp_path / "whole.onnx", tmp_path / "low.onnx"
    for path, margin in ((whole, -1.0), (low, 5.0)):
        path.write_bytes(plain.read_bytes())
        set_metadata(path, sky_margin_deg=margin)
    own = {path: configured_onnx(dataclasses.replace(cfg.segmentation, model_path=str(path)),
                                 camera=camera) for path in (whole, low)}
    assert own[whole].sky_rows == 0 and own[whole].sky_margin_deg == -1.0
    assert own[low].sky_rows > seg.sky_rows
    # the configuration overrides any model's own margin
    forced = load_config(sets=[f'segmentation.model_path="{whole}"',
                               "segmentation.sky_margin_deg=10"]).segmentation
    assert configured_onnx(forced, camera=camera).sky_rows == seg.sky_rows
    off = dataclasses.replace(cfg.segmentation, model_path=str(plain), sky_margin_deg=-1.0)
    assert configured_onnx(off, camera=camera).sky_rows == 0
    assert configured_onnx(cfg.segmentation).sky_rows == 0  # no camera: every row
    with pytest.raises(ConfigError, match="not both"):
        OnnxSegmenter(plain, camera=camera, sky_fraction=0.2)
    with pytest.raises(ConfigError, match="camera"):
        OnnxSegmenter(plain, sky_margin_deg=10.0)


@needs_model
def test_flip_averaging_mirrors_the_mirror_images_scores_back(rng):
    """The scores of the image and of its mirror image, mirrored back, averaged: so those of a
    mirrored image are exactly the mirror of the image's."""
    plain = OnnxSegmenter(flip="off")
    flip = OnnxSegmenter(flip="average")
    image = rng.integers(0, 255, (360, 640, 3), dtype=np.uint8)
    x, mirrored = flip.preprocess(image), flip.preprocess(np.ascontiguousarray(image[:, ::-1]))
    (scores,), (of_mirror,) = flip.run_network(x), flip.run_network(mirrored)
    np.testing.assert_array_equal(of_mirror, scores[..., ::-1])
    (a,), (b,) = plain.run_network(x), plain.run_network(mirrored)
    np.testing.assert_allclose(scores, 0.5 * (a + b[..., ::-1]), atol=1e-6)
    assert not np.allclose(a, scores, atol=1e-3)  # the network itself is not symmetric


@needs_model
def test_alternation_runs_the_image_and_its_mirror_in_turn(rng):
    """flip "alternate": one pass a call, on the image, then on its mirror image with the
    scores mirrored back, then on the image again; labels as one pass of either gives."""
    plain = OnnxSegmenter(flip="off")
    alternate = OnnxSegmenter(flip="alternate")
    image = rng.integers(0, 255, (360, 640, 3), dtype=np.uint8)
    x, mirrored = plain.preprocess(image), plain.preprocess(np.ascontiguousarray(image[:, ::-1]))
    (straight,), (of_mirror,) = plain.run_network(x), plain.run_network(mirrored)
    calls = [alternate.run_network(x)[0] for _ in range(3)]
    np.testing.assert_array_equal(calls[0], straight)
    np.testing.assert_array_equal(calls[1], of_mirror[..., ::-1])
    assert calls[1].flags.c_contiguous
    np.testing.assert_array_equal(calls[2], straight)
    fresh = OnnxSegmenter(flip="alternate")  # the network's labels; the paint borders are
    first, second = (fresh.network_labels(image)[1] for _ in range(2))  # decided on the image
    np.testing.assert_array_equal(first, plain.network_labels(image)[1])
    np.testing.assert_array_equal(
        second, plain.network_labels(np.ascontiguousarray(image[:, ::-1]))[1][:, ::-1])


def test_an_unknown_flip_mode_is_refused():
    with pytest.raises(ConfigError, match="flip must be one of"):
        OnnxSegmenter(flip="twice")


def test_flip_average_by_opencv_matches_numpy_exactly(rng):
    """The OpenCV flip and weighted sum the runtime uses give numpy's reversed columns and
    0.5 * (a + b) bit for bit, for inputs and logits of any layout (also not contiguous)."""
    from common.segmentation.scores import mean_with_mirrored, mirror_columns, mirror_logits

    for shape in ((1, 3, 312, 640), (1, 6, 156, 320), (2, 7, 5, 9)):
        x = rng.normal(scale=20.0, size=shape).astype(np.float32)
        np.testing.assert_array_equal(mirror_columns(x), x[..., ::-1])
        y = rng.normal(scale=20.0, size=shape).astype(np.float32)
        np.testing.assert_array_equal(mean_with_mirrored(x, y), 0.5 * (x + y[..., ::-1]))
        np.testing.assert_array_equal(mean_with_mirrored(x[..., ::2], y[..., ::2]),
                                      0.5 * (x[..., ::2] + y[..., ::2][..., ::-1]))
    sub = rng.normal(size=(1, 24, 5, 9)).astype(np.float32)  # sub-pixel logits: numpy's path
    np.testing.assert_array_equal(mean_with_mirrored(sub, sub, 2),
                                  0.5 * (sub + mirror_logits(sub, 2)))


def test_sub_pixel_logits_mirror_and_score_at_full_resolution(rng):
    """Sub-pixel logits of a mirrored image, mirrored back, are the image's: the full-resolution
    planes they shuffle into mirror exactly (a plain column flip would put each pixel one
    full-resolution column off)."""
    from common.segmentation.scores import mirror_logits, subpixel_argmax, subpixel_scores_at

    def unshuffled(full, s):  # (C, s h, s w) -> (C s s, h, w), as the model's sub-pixel head
        c, hh, ww = full.shape
        return full.reshape(c, hh // s, s, ww // s, s).transpose(0, 2, 4, 1, 3).reshape(
            c * s * s, hh // s, ww // s)

    for s in (1, 2, 3):
        full = rng.normal(size=(6, 4 * s, 5 * s)).astype(np.float32)
        got = mirror_logits(unshuffled(np.ascontiguousarray(full[..., ::-1]), s)[None], s)
        np.testing.assert_array_equal(got[0], unshuffled(full, s))
    # applied to an image's logits, the argmax is the mirror of the image's labels
    full = rng.normal(size=(6, 8, 10)).astype(np.float32)
    back = subpixel_argmax(mirror_logits(unshuffled(full, 2), 2), 2)
    np.testing.assert_array_equal(back, full.argmax(0)[:, ::-1])
    # and the scores at full-resolution pixels (for the border classifier) are the full planes'
    ys, xs = rng.integers(0, 8, 50), rng.integers(0, 10, 50)
    np.testing.assert_array_equal(subpixel_scores_at(unshuffled(full, 2), 2, ys, xs),
                                  full[:, ys, xs])
    # and at the pixels of labels resized (nearest) to another size, those of the pixel picked
    for size in ((7, 5), (25, 19)):  # (W, H)
        resized = np.stack([cv2.resize(plane, size, interpolation=cv2.INTER_NEAREST)
                            for plane in full])
        ys, xs = np.divmod(np.arange(size[0] * size[1]), size[0])
        got = subpixel_scores_at(unshuffled(full, 2), 2, ys, xs,
                                  scale=(8 / size[1], 10 / size[0]))
        np.testing.assert_array_equal(got, resized[:, ys, xs])


@needs_model
def test_the_flip_mode_is_the_configured_one_or_the_models_own():
    import dataclasses

    import onnxruntime as ort

    from common.config import RoadmapConfig
    from common.segmentation import configured_onnx, session_metadata

    session = ort.InferenceSession(str(DEFAULT_MODEL), providers=["CPUExecutionProvider"])
    asks = model_flip_mode(session_metadata(session))  # what the file asks for
    assert OnnxSegmenter().flip == asks
    for mode in FLIP_MODES:
        assert OnnxSegmenter(flip=mode).flip == mode
    cfg = RoadmapConfig().segmentation
    assert cfg.flip == "alternate"  # the product: one pass a frame (the 15 ms budget)
    assert configured_onnx(cfg).flip == "alternate"
    assert configured_onnx(dataclasses.replace(cfg, flip="")).flip == asks  # the file's own
    assert configured_onnx(dataclasses.replace(cfg, flip="off")).flip == "off"
    assert configured_onnx(dataclasses.replace(cfg, flip="alternate")).flip == "alternate"


def test_a_models_flip_mode_reads_files_from_before_the_mode():
    assert model_flip_mode({}) == "off"
    assert model_flip_mode({"flip_average": False}) == "off"
    assert model_flip_mode({"flip_average": True}) == "average"
    assert model_flip_mode({"flip_average": False, "flip": "alternate"}) == "alternate"


@needs_model
def test_rows_above_the_first_row_a_caller_uses_are_none_and_not_segmented(rng):
    """first_row (the IPM ROI's top row): the network runs on the rows from FIRST_ROW_CONTEXT
    above it (whole SKY_ROW_STEP steps), the rows above are labelled 0; the rows it runs on
    get the labels of a network run on them alone."""
    from common.camera import camera_from_config
    from common.config import CameraConfig
    from common.segmentation import roi_first_row
    from common.segmentation.onnx import FIRST_ROW_CONTEXT, SKY_ROW_STEP

    camera = camera_from_config(CameraConfig())
    row = roi_first_row(camera, 3.0, 8.0, 8.0)
    assert 150 < row < camera.height  # the ROI lies in the lower part of the frame
    seg = OnnxSegmenter(camera=camera, first_row=row, flip="off")
    assert seg.sky_rows == (row - FIRST_ROW_CONTEXT) // SKY_ROW_STEP * SKY_ROW_STEP
    image = rng.integers(0, 255, (camera.height, camera.width, 3), dtype=np.uint8)
    labels = seg.segment(image)
    assert labels.shape == (camera.height, camera.width)
    assert not labels[: seg.sky_rows].any()
    assert seg.preprocess(image).shape[2] == camera.height - seg.sky_rows
    with pytest.raises(ConfigError, match="first_row"):
        OnnxSegmenter(camera=camera, first_row=-1)


@needs_model
def test_a_class_margin_leaves_only_that_classes_unsure_pixels_unknown(rng):
    image = rng.integers(0, 255, (360, 640, 3), dtype=np.uint8)
    plain = OnnxSegmenter(flip="off", border_net=False, refine={}).segment(image)
    strict = OnnxSegmenter(flip="off", border_net=False, refine={},
                           class_min_margin={5: 1e6}).segment(image)
    assert not (strict == 5).any()
    others = (plain != 5) & (strict != 0)
    assert np.array_equal(strict[others], plain[others])


@needs_model
def test_border_net_below_the_sky_gives_the_whole_frames_labels():
    """With sky rows, the border classifier runs on the rows just above them and below only:
    on rendered town frames, bit for bit the labels it gives run on the whole frame, with and
    without the mirror image. (The sky cut here, 208 rows, lies in the road's paint, so that
    borders meet the first row segmented; the product's, 80 rows above the ROI, sees no
    paint there.)"""
    from services.bench.heldout import render_heldout

    seg = OnnxSegmenter(sky_fraction=0.6, flip="alternate")
    assert seg.border_net is not None and seg.sky_rows == 208
    pairs, _ = render_heldout("town:0.6", frames=4, seed=5)
    changed = top = 0
    for image, _ in pairs:
        for _ in range(2):  # the image, then its mirror
            small, labels, score_at = seg.network_labels(image)
            whole = seg.border_net(cv2.cvtColor(small, cv2.COLOR_RGB2GRAY), labels, score_at)
            np.testing.assert_array_equal(seg.refined_borders(small, small, labels, score_at),
                                          whole)
            changed += int((whole != labels).sum())
            top += int((labels[seg.sky_rows] >= Cls.LANE_LINE).sum())
    assert changed > 100 and top > 0  # borders re-decided, paint in the first row segmented


def _resize_graph(channels: int):
    """x (1, C, h, w) resized to skip's (H, W) as the exported decoder does (sizes from the
    shapes, linear, half-pixel)."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    i64 = lambda name, v: numpy_helper.from_array(np.array(v, np.int64), name)  # noqa: E731
    nodes = [helper.make_node("Shape", ["x"], ["sx"]), helper.make_node("Shape", ["skip"], ["ss"]),
             helper.make_node("Slice", ["sx", "z", "two"], ["nc"]),
             helper.make_node("Slice", ["ss", "two", "four"], ["hw"]),
             helper.make_node("Concat", ["nc", "hw"], ["sizes"], axis=0),
             helper.make_node("Resize", ["x", "", "", "sizes"], ["y"], mode="linear",
                              coordinate_transformation_mode="half_pixel")]
    io = lambda name, dims: helper.make_tensor_value_info(name, TensorProto.FLOAT, dims)  # noqa: E731
    graph = helper.make_graph(nodes, "resize", [io("x", [1, channels, "h", "w"]),
                                                io("skip", [1, 1, "H", "W"])],
                              [io("y", [1, channels, "H", "W"])],
                              [i64("z", [0]), i64("two", [2]), i64("four", [4])])
    return onnx.helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def test_a_resize_as_matrix_products_computes_the_resize(rng):
    """training.onnx_graph.resizes_as_matmuls: the same interpolation as onnxruntime's Resize
    at the odd sizes the packaged network's deepest one meets (16 -> 31 rows at 248, 15 -> 29
    at 232, 20 -> 39 at 312) and at 2x, within float rounding."""
    import onnxruntime as ort

    from training.onnx_graph import resizes_as_matmuls

    plain = _resize_graph(8)
    fast = _resize_graph(8)
    assert resizes_as_matmuls(fast) == 1 and resizes_as_matmuls(_resize_graph(8), first=0) == 0
    assert not [n for n in fast.graph.node if n.op_type == "Resize"]
    runs = [ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"])
            for m in (plain, fast)]
    for (h, w), (big_h, big_w) in (((16, 40), (31, 80)), ((15, 40), (29, 80)),
                                   ((20, 40), (39, 80)), ((5, 7), (10, 14)), ((3, 4), (3, 9))):
        feed = {"x": rng.normal(0, 3, (1, 8, h, w)).astype(np.float32),
                "skip": np.zeros((1, 1, big_h, big_w), np.float32)}
        want, got = (r.run(None, feed)[0] for r in runs)
        assert got.shape == want.shape == (1, 8, big_h, big_w)
        np.testing.assert_allclose(got, want, atol=1e-5)


@needs_model
def test_the_packaged_model_runs_its_deepest_resize_as_matrix_products(tmp_path):
    """The packaged file is its export with the 1/16 -> 1/8 Resize rewritten (python -m
    training.onnx_graph); its two 2x Resizes stay, and a second rewrite is refused."""
    onnx = pytest.importorskip("onnx")
    from training.onnx_graph import RESIZE_MATMUL, main

    graph = onnx.load(str(DEFAULT_MODEL)).graph
    assert len([n for n in graph.node if n.op_type == "Resize"]) == 2
    assert [n.name for n in graph.node if n.op_type == "MatMul"] == [
        f"/Resize{RESIZE_MATMUL}/rows", f"/Resize{RESIZE_MATMUL}/cols"]
    with pytest.raises(SystemExit, match="already rewritten"):
        main([str(DEFAULT_MODEL), str(tmp_path / "again.onnx")])


@needs_model
def test_border_net_decides_only_from_the_callers_first_row_on():
    """With a `first_row` (the car's IPM ROI), the border classifier decides the rows from it
    down exactly as on the whole frame, and leaves the network's labels on the context rows
    above it (less the rows its decisions reach up to)."""
    from common.camera import camera_from_config
    from common.config import CameraConfig
    from common.segmentation import roi_first_row
    from common.segmentation.onnx import BORDER_REACH_ROWS
    from services.bench.heldout import render_heldout

    camera = camera_from_config(CameraConfig())
    row = roi_first_row(camera, 3.0, 12.0, 8.0)
    seg = OnnxSegmenter(camera=camera, first_row=row, flip="off")
    assert seg.sky_rows < row - BORDER_REACH_ROWS
    pairs, _ = render_heldout("town:0.6", frames=4, seed=5)
    changed = 0
    for image, _ in pairs:
        small, labels, score_at = seg.network_labels(image)
        whole = seg.border_net(cv2.cvtColor(small, cv2.COLOR_RGB2GRAY), labels, score_at)
        got = seg.refined_borders(small, small, labels, score_at)
        np.testing.assert_array_equal(got[row:], whole[row:])
        np.testing.assert_array_equal(got[:row - BORDER_REACH_ROWS],
                                      labels[:row - BORDER_REACH_ROWS])
        changed += int((whole[row:] != labels[row:]).sum())
    assert changed > 100  # the classifier re-decided borders in the ROI's rows
