"""The learned paint-border classifier (BorderNet): features, decisions, the runtime switch and
its fitting (the fitting tests need the optional torch extra)."""

from pathlib import Path

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from common.classes import NUM_CLASSES, Cls
from common.config import SegmentationConfig
from common.errors import ConfigError
from common.segmentation import DEFAULT_MODEL, OnnxSegmenter, configured_onnx
from common.segmentation.refine import (
    BORDER_FEATURES,
    BorderNet,
    border_features,
    paint_border_pixels,
    unsure_paint_border,
)
from tests.segmentation.test_refine import _town_frame

ROAD_GREY, PAINT_GREY = 80, 200
PATCH = 25  # 5x5
CENTRE = 12  # the pixel itself in a flattened 5x5 patch


def _scene():
    """A road with a 3 px vertical line (columns 20-22), and its true labels."""
    gray = np.full((40, 48), ROAD_GREY, np.uint8)
    gray[:, 20:23] = PAINT_GREY
    truth = np.full(gray.shape, Cls.ROAD, np.uint8)
    truth[:, 20:23] = Cls.LANE_LINE
    return gray, truth


def _unsure(labels):
    """score_at of a network that leads by 0.5 logits everywhere: every border pixel unsure."""
    def score_at(ys, xs):
        scores = np.zeros((NUM_CLASSES, len(ys)), np.float32)
        scores[labels[ys, xs], np.arange(len(ys))] = 0.5
        return scores
    return score_at


def _brightness_net(max_margin=np.inf):
    """A one-layer BorderNet: lane line where the pixel's own normalized grey passes 0.5."""
    w = np.zeros((BORDER_FEATURES, NUM_CLASSES))
    w[CENTRE, Cls.LANE_LINE] = 10.0
    b = np.zeros(NUM_CLASSES)
    b[Cls.LANE_LINE], b[Cls.ROAD] = -5.0, 0.0
    b[[Cls.NONE, Cls.STOP_LINE, Cls.CROSSWALK, Cls.GROUND_SIGN]] = -100.0
    return BorderNet({"layers": [{"w": w.tolist(), "b": b.tolist()}], "max_margin": max_margin})


def test_features_normalise_the_patch_between_road_and_paint():
    gray, truth = _scene()
    border = paint_border_pixels(truth)
    ys, xs = np.divmod(border, truth.shape[1])
    assert set(xs) == {19, 20, 22, 23}  # a pixel either side of each edge
    feats = border_features(gray, truth, _unsure(truth)(ys, xs), border)
    assert feats.shape == (len(border), BORDER_FEATURES) and feats.dtype == np.float32
    row = feats[np.flatnonzero((ys == 20) & (xs == 19))[0]]  # road, left of the line
    grey = row[:PATCH].reshape(5, 5)  # columns 17..21: road, road, road, paint, paint
    np.testing.assert_allclose(grey[:, :3], 0.0)
    np.testing.assert_allclose(grey[:, 3:], 1.0)  # (200 - 80) / (200 - 80)
    np.testing.assert_array_equal(row[PATCH:2 * PATCH].reshape(5, 5)[:, 3:], 1.0)
    np.testing.assert_array_equal(row[PATCH:2 * PATCH].reshape(5, 5)[:, :3], 0.0)
    scores = row[2 * PATCH:2 * PATCH + NUM_CLASSES]
    assert scores[Cls.ROAD] == 0.0 and scores[Cls.LANE_LINE] == -0.125  # (0 - 0.5) / 4
    contrast, road, n_road, n_paint = row[-4:]
    assert contrast == pytest.approx(120 / 64) and road == pytest.approx(80 / 128)
    # the 9x9 box: columns 15..23, road in 15..19 and 23
    assert n_road == pytest.approx(6 * 9 / 81) and n_paint == pytest.approx(3 * 9 / 81)


def test_patches_at_the_image_edge_repeat_its_pixels():
    gray, truth = _scene()
    truth[0:3, :] = Cls.LANE_LINE  # paint along the top edge
    gray[0:3, :] = PAINT_GREY
    border = paint_border_pixels(truth)
    ys, xs = np.divmod(border, truth.shape[1])
    feats = border_features(gray, truth, _unsure(truth)(ys, xs), border)
    assert np.isfinite(feats).all()
    top = feats[np.flatnonzero((ys == 3) & (xs == 5))[0], :PATCH].reshape(5, 5)
    np.testing.assert_allclose(top[:2], 1.0)  # rows 1, 2: paint
    np.testing.assert_allclose(top[2:], 0.0)  # rows 3..5: road


def test_a_line_labelled_a_pixel_too_wide_or_too_thin_is_put_right():
    gray, truth = _scene()
    net = _brightness_net()
    wide = truth.copy()
    wide[:, 19] = Cls.LANE_LINE
    np.testing.assert_array_equal(net(gray, wide, _unsure(wide)), truth)
    thin = truth.copy()
    thin[:, 22] = Cls.ROAD
    np.testing.assert_array_equal(net(gray, thin, _unsure(thin)), truth)


def test_pixels_the_network_is_sure_of_keep_its_label():
    gray, truth = _scene()
    wide = truth.copy()
    wide[:, 19] = Cls.LANE_LINE
    # the network leads by 0.5 logits: below a max_margin of 1 the classifier decides, not
    # below one of 0.25
    np.testing.assert_array_equal(_brightness_net(1.0)(gray, wide, _unsure(wide)), truth)
    np.testing.assert_array_equal(_brightness_net(0.25)(gray, wide, _unsure(wide)), wide)
    border, scores = unsure_paint_border(wide, _unsure(wide), 0.25)
    assert len(border) == 0 and scores.shape == (NUM_CLASSES, 0)


def test_frames_without_paint_come_back_unchanged():
    labels = np.full((30, 30), Cls.ROAD, np.uint8)
    gray = np.full(labels.shape, 90, np.uint8)
    np.testing.assert_array_equal(_brightness_net()(gray, labels, _unsure(labels)), labels)


def test_a_malformed_spec_is_refused():
    with pytest.raises(ConfigError, match="malformed"):
        BorderNet({"weights": []})
    with pytest.raises(ConfigError, match="do not chain"):
        BorderNet({"layers": [{"w": np.zeros((BORDER_FEATURES, 8)).tolist(), "b": [0.0] * 8}]})
    with pytest.raises(ConfigError, match="do not chain"):
        BorderNet({"layers": [{"w": np.zeros((10, NUM_CLASSES)).tolist(),
                               "b": [0.0] * NUM_CLASSES}]})


def _blas_threads() -> set[int]:
    return {lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}


class _BlasProbe(np.ndarray):
    """A weight matrix that notes the BLAS libraries' thread counts when it is multiplied."""

    seen: list[set[int]] = []

    def __matmul__(self, other):
        _BlasProbe.seen.append(_blas_threads())
        return np.asarray(self) @ other


@pytest.mark.skipif(max(_blas_threads(), default=1) < 2, reason="BLAS runs one thread here")
def test_the_perceptron_runs_on_the_segmenters_threads_not_the_blas_pool():
    rng = np.random.default_rng(0)
    spec = {"layers": [{"w": rng.normal(size=(BORDER_FEATURES, 16)).tolist(), "b": [0.1] * 16},
                       {"w": rng.normal(size=(16, NUM_CLASSES)).tolist(),
                        "b": [0.0] * NUM_CLASSES}]}
    feats = rng.normal(size=(5000, BORDER_FEATURES)).astype(np.float32)
    pool = _blas_threads()
    plain = BorderNet(spec).scores(feats)
    net = BorderNet(spec, threads=1)
    w, b = net._columns[0]
    net._columns[0] = (w.view(_BlasProbe), b)
    _BlasProbe.seen.clear()
    np.testing.assert_allclose(net.scores(feats), plain, rtol=1e-5, atol=1e-4)
    assert _BlasProbe.seen == [{1}]  # limited while it ran
    assert _blas_threads() == pool  # and given back after
    with pytest.raises(ConfigError, match="threads"):
        BorderNet(spec, threads=0)


needs_model = pytest.mark.skipif(not DEFAULT_MODEL.is_file(), reason="no packaged model")


@needs_model
def test_the_packaged_classifier_runs_by_default_and_changes_only_border_pixels():
    image = _town_frame()
    learned = OnnxSegmenter()
    assert learned.border_net is not None  # the default: the model's own classifier
    assert OnnxSegmenter(border_net=False).border_net is None  # its brightness rule
    assert OnnxSegmenter(border_net=True).border_net is not None
    raw = OnnxSegmenter(refine={}, border_net=False).segment(image)
    out = learned.segment(image)
    assert (out >= Cls.LANE_LINE).sum() > 500
    changed = out != raw
    assert changed.any()
    border = np.zeros(raw.size, bool)
    border[paint_border_pixels(raw)] = True
    assert not (changed.reshape(-1) & ~border).any()
    assert configured_onnx(SegmentationConfig()).border_net is not None
    assert configured_onnx(SegmentationConfig(border_net=False)).border_net is None


@needs_model
def test_asking_for_a_classifier_the_model_lacks_is_an_error(tmp_path):
    import json

    import onnx

    proto = onnx.load(str(DEFAULT_MODEL))
    entry = next(e for e in proto.metadata_props if e.key == "roadmap.segmentation")
    meta = json.loads(entry.value)
    meta.pop("border_net", None)
    entry.value = json.dumps(meta)
    path = tmp_path / "plain.onnx"
    onnx.save(proto, str(path))
    assert OnnxSegmenter(path).border_net is None  # by default: the rule, quietly
    with pytest.raises(ConfigError, match="no border classifier"):
        OnnxSegmenter(path, border_net=True)
    # a head_map remaps the classes the classifier was fitted for: off unless insisted on
    assert OnnxSegmenter(head_map={"logits": {2: int(Cls.LANE_LINE)}}).border_net is None
    with pytest.raises(ConfigError, match="no border classifier"):
        OnnxSegmenter(head_map={"logits": {2: int(Cls.LANE_LINE)}}, border_net=True)


def test_fitting_learns_a_rule_and_the_spec_decides_as_torch_does():
    pytest.importorskip("torch", reason="fitting needs the .[train] extra (torch)")
    from training.border import fit_border_net

    rng = np.random.default_rng(0)
    x = rng.normal(size=(200_000, BORDER_FEATURES)).astype(np.float32)
    y = np.where(x[:, CENTRE] > 0.3, Cls.LANE_LINE, Cls.ROAD).astype(np.int64)
    spec = fit_border_net(x, y, seed=0)
    net = BorderNet(spec)
    assert (net.scores(x).argmax(1) == y).mean() > 0.97
    assert spec["max_margin"] == 3.0
    with pytest.raises(ValueError, match="too few"):
        fit_border_net(x[:100], y[:100])


def test_border_only_refuses_the_seed_the_model_was_trained_on(tmp_path, capsys):
    pytest.importorskip("torch", reason="train-seg needs the .[train] extra (torch)")
    pytest.importorskip("onnx", reason="train-seg needs the .[train] extra (onnx)")
    if not DEFAULT_MODEL.is_file():
        pytest.skip("no packaged model")
    from training.cli import main
    from training.train import _metadata

    model = tmp_path / "m.onnx"
    model.write_bytes(DEFAULT_MODEL.read_bytes())
    trained_seed = _metadata(model)["seed"]  # the towns it was trained on
    assert main(["train-seg", "--border-only", str(model), "--seed", str(trained_seed),
                 "--frames", "24", "--out", str(tmp_path)]) == 1
    assert "another --seed" in capsys.readouterr().err


def test_a_training_run_refuses_its_own_seed_for_the_border_classifier(tmp_path, capsys):
    """`--border-frames` fits the classifier after training on --border-seed's towns (default
    --seed + 31); the network's own towns are refused before any rendering."""
    from training.cli import main

    assert main(["train-seg", "--out", str(tmp_path), "--seed", "4", "--border-frames", "64",
                 "--border-seed", "4"]) == 1
    assert "another seed" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing rendered, trained or written


def _finish_a_run(tmp_path, *flags, flip_average: bool | None = None) -> tuple[Path, dict]:
    """The end of a training run (`_finish`) of train-seg `flags` on a copy of the packaged
    model (its metadata `flip_average` set first, if given) -> the model and train_log.json."""
    import json

    from training.cli import build_parser
    from training.train import _finish, set_metadata

    model = tmp_path / "roadseg.onnx"
    model.write_bytes(DEFAULT_MODEL.read_bytes())
    if flip_average is not None:
        set_metadata(model, flip_average=flip_average)
    args = build_parser().parse_args(["train-seg", "--out", str(tmp_path), *flags])
    args.turn_prob, args.synth_share, args.border_seed = 0.2, 0.3, 31
    result = {"frames": 24, "model_bytes": model.stat().st_size, "params": 26011, "steps": 1,
              "train_s": 1.0, "class_weights": [1.0] * 7, "onnx_max_abs_diff": 0.0,
              "onnx_argmax_agreement": 1.0, "val_iou_town": {}, "init": None}
    assert _finish(args, tmp_path, result, 0.0) == 0
    return model, json.loads((tmp_path / "train_log.json").read_text())


@pytest.mark.parametrize("flag, expected", [([], True), (["--no-flip-average"], False)])
def test_a_training_run_sets_flip_averaging_before_its_border_classifier(tmp_path, flag, expected):
    """The end of a training run (`_finish`) switches flip averaging on in the export's metadata
    (unless --no-flip-average), before any border fit, and writes it to the log, card and the
    command it reports, so that one command gives the packaged file's settings."""
    pytest.importorskip("onnx")
    from training.train import _metadata

    model, log = _finish_a_run(tmp_path, *flag, flip_average=not expected)
    assert _metadata(model)["flip_average"] is expected
    assert log["flip_average"] is expected
    assert ("--no-flip-average" in log["command"]) is not expected
    card = (tmp_path / "MODEL_CARD.md").read_text()
    assert ("**Flip averaging**: on" in card) is expected
    assert "--sky-margin-deg" not in log["command"] and "sky_margin_deg" not in log


def test_a_training_run_writes_the_sky_margin_it_is_given(tmp_path):
    """--sky-margin-deg -1 (a network that needs every row) lands in the export's metadata, so
    the runtime's default segments every row of it, and in its log, command and card."""
    pytest.importorskip("onnx")
    from common.camera import camera_from_config
    from common.config import CameraConfig
    from training.train import _metadata

    model, log = _finish_a_run(tmp_path, "--sky-margin-deg", "-1")
    assert _metadata(model)["sky_margin_deg"] == -1.0
    assert log["sky_margin_deg"] == -1.0 and "--sky-margin-deg -1" in log["command"]
    assert "**Sky rows**: every row segmented" in (tmp_path / "MODEL_CARD.md").read_text()
    assert OnnxSegmenter(model, camera=camera_from_config(CameraConfig())).sky_rows == 0


def test_border_only_writes_its_log_beside_the_model_unless_told_otherwise(tmp_path):
    """`--border-only /elsewhere/m.onnx` without --out once wrote border_log.json into the
    packaged model's folder (common/models) of whatever checkout it ran in."""
    from training.cli import build_parser
    from training.train import DEFAULT_OUT, out_dir

    model = tmp_path / "run" / "m.onnx"
    parse = build_parser().parse_args
    assert out_dir(parse(["train-seg", "--border-only", str(model)])) == model.parent
    assert out_dir(parse(["train-seg", "--border-only", str(model), "--out", "x"])) == Path("x")
    assert out_dir(parse(["train-seg", "--seed", "3"])) == DEFAULT_OUT == Path("common/models")
