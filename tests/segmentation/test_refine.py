"""Paint borders re-decided on the image (refine_paint_borders): runtime and calibration."""

import numpy as np
import pytest

from common.classes import Cls
from common.errors import ConfigError
from common.segmentation import DEFAULT_MODEL, OnnxSegmenter, session_metadata
from common.segmentation.refine import refine_paint_borders

ROAD_GREY, PAINT_GREY = 80, 200


def _scene(paint_grey=PAINT_GREY, cls=Cls.LANE_LINE):
    """A road with a 3 px vertical line (columns 20-22), and its true labels."""
    gray = np.full((40, 48), ROAD_GREY, np.uint8)
    gray[:, 20:23] = paint_grey
    truth = np.full(gray.shape, Cls.ROAD, np.uint8)
    truth[:, 20:23] = cls
    return gray, truth


def test_a_line_labelled_a_pixel_too_wide_loses_its_dark_border():
    gray, truth = _scene()
    labels = truth.copy()
    labels[:, 19] = Cls.LANE_LINE  # one road column called paint
    np.testing.assert_array_equal(refine_paint_borders(gray, labels), truth)


def test_a_line_labelled_a_pixel_too_thin_grows_with_its_own_class():
    gray, truth = _scene(cls=Cls.STOP_LINE)
    labels = truth.copy()
    labels[:, 22] = Cls.NONE  # the line's right column missed
    np.testing.assert_array_equal(refine_paint_borders(gray, labels), truth)


def test_low_contrast_and_interior_pixels_are_left_alone():
    gray, truth = _scene(paint_grey=ROAD_GREY + 5)  # worn paint barely brighter than road
    labels = truth.copy()
    labels[:, 19] = Cls.LANE_LINE
    np.testing.assert_array_equal(refine_paint_borders(gray, labels), labels)
    gray, truth = _scene()
    gray[5:8, 30:33] = PAINT_GREY  # a bright spot in the road, away from any paint label
    out = refine_paint_borders(gray, truth)
    np.testing.assert_array_equal(out, truth)
    assert out is not truth or not (truth >= Cls.LANE_LINE).any()


def test_frames_without_paint_come_back_unchanged():
    gray = np.full((30, 30), 90, np.uint8)
    labels = np.full(gray.shape, Cls.ROAD, np.uint8)
    np.testing.assert_array_equal(refine_paint_borders(gray, labels), labels)


needs_model = pytest.mark.skipif(not DEFAULT_MODEL.is_file(), reason="no packaged model")


def _road_with_lines():
    """A grey road with bright lane lines, in perspective enough for the model to see."""
    import cv2

    image = np.full((360, 640, 3), 60, np.uint8)
    image[:150] = (150, 170, 200)  # sky
    image[150:] = (85, 85, 88)
    for x_bottom, x_top in ((120, 300), (520, 340), (320, 320)):
        cv2.line(image, (x_bottom, 359), (x_top, 160), (225, 225, 220), 6)
    return image


def _town_frame():
    """A town frame as the training renderers draw it (worn paint, curbs, shade): what the
    packaged model is sure and unsure of on real-looking paint. (A line drawing is unlike any
    training frame; the m64 network of 2026-11-28 finds little paint on _road_with_lines.)"""
    from services.bench.heldout import render_heldout

    (image, _), = render_heldout("town:0.6", frames=1, seed=3)[0]
    return image


@needs_model
def test_packaged_model_carries_refine_settings_and_the_runtime_applies_them():
    seg = OnnxSegmenter()
    assert set(seg.refine) <= {"window", "level", "min_contrast"} and seg.refine
    image = _town_frame()
    raw = OnnxSegmenter(refine={}, border_net=False).segment(image)
    refined = seg.segment(image)
    assert (raw >= Cls.LANE_LINE).sum() > 500  # the model sees the lines
    changed = raw != refined
    assert changed.any()
    # only pixels on a paint border change
    import cv2

    paint = (raw >= Cls.LANE_LINE).astype(np.uint8)
    k = np.ones((3, 3), np.uint8)
    border = cv2.dilate(paint, k) != cv2.erode(paint, k)
    assert not (changed & ~border).any()


@needs_model
def test_remapped_heads_do_not_inherit_the_models_refine_settings():
    assert OnnxSegmenter(head_map={"logits": {2: int(Cls.LANE_LINE)}}).refine == {}
    with pytest.raises(ConfigError, match="unknown refine"):
        OnnxSegmenter(refine={"radius": 3})


@needs_model
def test_calibration_keeps_labels_that_need_no_refinement(tmp_path):
    """calibrate_refine returns {} when the truth is the unrefined output itself, and a setting
    when the truth is what that setting makes of it; set_metadata stores it for the runtime."""
    import cv2

    from training.train import calibrate_refine, set_metadata

    frames = np.stack([_road_with_lines(), cv2.flip(_road_with_lines(), 1)])
    plain = OnnxSegmenter(refine={}, border_net=False)
    raw = np.stack([plain.segment_model_size(f) for f in frames])
    assert calibrate_refine(DEFAULT_MODEL, frames, raw) == {}
    target = {"window": 7, "level": 0.5}
    truth = np.stack([refine_paint_borders(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY), r, **target)
                      for f, r in zip(frames, raw, strict=True)])
    found = calibrate_refine(DEFAULT_MODEL, frames, truth)
    assert found
    model = tmp_path / "m.onnx"
    model.write_bytes(DEFAULT_MODEL.read_bytes())
    set_metadata(model, refine=found)
    seg = OnnxSegmenter(model)
    assert seg.refine == found
    meta = session_metadata(seg._session)
    assert meta["input_size"] == [640, 360]  # the other keys kept
