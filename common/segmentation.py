"""Segmentation strategies: camera image -> class image (H, W) uint8 in our classes.

`GroundTruthSegmenter` (simulated logs) corrupts the true labels realistically, so mapping and
localization can be tested without the model; `OnnxSegmenter` runs a real ONNX model. Both have
one verb: `segment(image_rgb, labels_true=None) -> labels`. `get_segmenter(...)` chooses."""

import json
import logging
import os
from dataclasses import dataclass
from functools import cache, partial
from pathlib import Path

import cv2
import numpy as np
from threadpoolctl import ThreadpoolController

from common import camera as cameras
from common.classes import NUM_CLASSES, Cls
from common.config import FLIP_MODES
from common.errors import ConfigError

logger = logging.getLogger(__name__)

# The model trained by services/segtrain, packaged with the library (see models/MODEL_CARD.md).
DEFAULT_MODEL = Path(__file__).resolve().parent / "models" / "roadseg.onnx"
# ONNX metadata key under which a model describes its own input (written by services/segtrain).
META_KEY = "roadmap.segmentation"
# sky rows are skipped in steps of the network's coarsest stride (RoadSegNet: 1/16), so the
# network's grid stays the full frame's. (The rows below, 312 at 640x360, are no multiple of
# 16, so onnxruntime leaves its blocked layout around the 1/16 -> 1/8 resize: 320 rows run
# 0.6 ms faster. But skipping 40 rows instead of 48 shifts the grid, and the packaged model's
# mean lane-line IoU falls from 0.751 to 0.741; 312 rows padded to 320 at the bottom give
# 0.740 with the last row repeated and 0.665 with zeros. 2026-11-25, every second benchmark
# frame, with border_net.)
SKY_ROW_STEP = 16
# the sky margin (degrees above level) of a model whose metadata names none: `s` networks such
# as run B1 lost no IoU when the rows above it were left out, and the packaged m64 files (runs
# KM64 and G2R) were benchmarked with it
DEFAULT_SKY_MARGIN_DEG = 10.0


def sky_rows_of(sky_fraction: float, height: int) -> int:
    """The top rows OnnxSegmenter leaves out of a `height`-row input for a sky share
    `sky_fraction` (camera.sky_fraction): whole steps of SKY_ROW_STEP (a share of whole rows
    comes back as those rows, not one fewer by rounding: 208 / 360 * 360 < 208)."""
    return int(sky_fraction * height + 1e-6) // SKY_ROW_STEP * SKY_ROW_STEP


class Segmenter:
    name = "segmenter"

    def segment(self, image_rgb: np.ndarray | None, labels_true: np.ndarray | None = None):
        raise NotImplementedError


@dataclass
class GroundTruthSegmenter(Segmenter):
    """True labels with realistic errors: ragged boundaries, missed blobs and spurious blobs.

    boundary_flip: probability that a pixel on a class boundary takes its neighbour's class;
    miss_rate: expected fraction of marking area dropped as blobs per frame;
    spurious_per_frame: expected number of small false marking blobs on the road per frame."""

    boundary_flip: float = 0.3
    miss_rate: float = 0.03
    spurious_per_frame: float = 0.5
    seed: int = 0
    name: str = "ground-truth+corruption"

    def __post_init__(self):
        self._rng = np.random.default_rng(self.seed)

    def segment(self, image_rgb=None, labels_true=None) -> np.ndarray:
        if labels_true is None:
            raise ValueError("GroundTruthSegmenter needs the true label image of the frame")
        labels = labels_true.copy()
        self._ragged_boundaries(labels, labels_true)
        self._drop_blobs(labels)
        self._add_spurious(labels)
        return labels

    def _ragged_boundaries(self, labels, truth):
        if self.boundary_flip <= 0:
            return
        shifted = np.roll(truth, self._rng.choice([-1, 1]), axis=int(self._rng.integers(2)))
        edge = shifted != truth
        flip = edge & (self._rng.random(truth.shape) < self.boundary_flip)
        labels[flip] = shifted[flip]

    def _drop_blobs(self, labels):
        marking = labels >= Cls.LANE_LINE
        area = int(marking.sum())
        if area == 0 or self.miss_rate <= 0:
            return
        h, w = labels.shape
        ys, xs = np.nonzero(marking)
        n = self._rng.poisson(self.miss_rate * area / 150.0)
        for i in self._rng.integers(0, len(ys), n):
            r = int(self._rng.integers(3, 9))
            y0, y1 = max(ys[i] - r, 0), min(ys[i] + r, h)
            x0, x1 = max(xs[i] - r, 0), min(xs[i] + r, w)
            window = labels[y0:y1, x0:x1]
            window[window >= Cls.LANE_LINE] = Cls.ROAD

    def _add_spurious(self, labels):
        road = np.argwhere(labels == Cls.ROAD)
        if len(road) == 0:
            return
        for _ in range(self._rng.poisson(self.spurious_per_frame)):
            y, x = road[self._rng.integers(len(road))]
            cls = int(self._rng.choice([Cls.LANE_LINE, Cls.GROUND_SIGN, Cls.STOP_LINE]))
            axes = (int(self._rng.integers(1, 4)), int(self._rng.integers(1, 6)))
            cv2.ellipse(labels, (int(x), int(y)), axes, float(self._rng.uniform(0, 180)), 0, 360,
                        cls, -1)


def _identity_head(num_outputs: int) -> dict[int, int]:
    """Single-head default: output class i is our class i; classes beyond ours map to 0."""
    return {i: (i if i < NUM_CLASSES else 0) for i in range(num_outputs)}


class OnnxSegmenter(Segmenter):
    """An ONNX segmentation network run by onnxruntime on the CPU.

    Per frame: resize the RGB image to the model's input size (W, H), normalize
    ((rgb * scale - mean) / std, NCHW float32), run, argmax every head over its class axis, map
    each head's classes to ours (`head_map`: output name -> {model class -> our class}; heads are
    applied in `priority` order, later heads painting over earlier ones, class 0 never paints),
    and resize the labels back to the image size (nearest; or `upsample="bilinear"`: the logits
    are resized before the argmax, smoother but slower). Missing settings are read from the
    model's own metadata (key `roadmap.segmentation`) or its input shape.

    `min_margin` > 0 keeps only confident markings: a pixel whose winning class is a marking
    (lane line, stop line, crosswalk, ground sign) but whose score beats the runner-up by less
    than `min_margin` (logits) is labelled 0, unknown (with several heads: that head paints
    nothing there, so the heads under it keep their say). For the stages that turn pixels into
    points (mapping votes), where a wrong point costs more than a missing one; the IoU benchmark
    measures the plain argmax (0).

    `sky_fraction` > 0: that share of the image's rows, from the top, lies above the horizon
    (common.camera.sky_rows: rays rising some degrees above level), holds no road marking, and
    is labelled 0 without running the network there; the network sees only the rows below
    (rounded down to SKY_ROW_STEP rows at the model's input size, its coarsest stride, so its
    grid stays the full frame's). Only for a model whose input height is dynamic (ours since
    2026-11-25); a fixed-height model segments every row (a warning says so). Or, given the
    `camera` (CameraModel) instead, the rows above the rays rising `sky_margin_deg` above
    level; None takes the model's own margin (metadata `sky_margin_deg`; < 0: every row, for a
    network whose coarsest stage reads the whole frame), else DEFAULT_SKY_MARGIN_DEG."""

    def __init__(
        self,
        model_path: str | os.PathLike = DEFAULT_MODEL,
        *,
        input_size: tuple[int, int] | None = None,
        scale: float | None = None,
        mean: tuple[float, float, float] | None = None,
        std: tuple[float, float, float] | None = None,
        head_map: dict[str, dict[int, int]] | None = None,
        priority: list[str] | None = None,
        intra_op_threads: int = 1,
        upsample: str = "nearest",
        refine: dict | None = None,
        border_net: dict | bool | None = None,
        min_margin: float = 0.0,
        sky_fraction: float = 0.0,
        camera: cameras.CameraModel | None = None,
        sky_margin_deg: float | None = None,
        flip: str | None = None,
        name: str | None = None,
    ):
        path = Path(model_path)
        if not path.is_file():
            raise ConfigError(f"segmentation model not found: {path}")
        self._session = _session(path, intra_op_threads)
        meta = session_metadata(self._session)
        inp = self._session.get_inputs()[0]
        self._input_name = inp.name
        self.input_size = tuple(input_size or meta.get("input_size")
                                or (inp.shape[3], inp.shape[2]))
        if not all(isinstance(v, int) for v in self.input_size):
            raise ConfigError(f"{path}: the model's input size is dynamic ({inp.shape}); "
                              "give input_size=(W, H)")
        self.sky_margin_deg = None  # the margin the sky rows follow from, given a camera
        if camera is not None:
            if sky_fraction:
                raise ConfigError("give sky_fraction or a camera (and sky_margin_deg), not both")
            if sky_margin_deg is None:  # the model's own (null: none named)
                sky_margin_deg = meta.get("sky_margin_deg")
            self.sky_margin_deg = float(DEFAULT_SKY_MARGIN_DEG if sky_margin_deg is None
                                        else sky_margin_deg)
            sky_fraction = cameras.sky_fraction(camera, self.sky_margin_deg)
        elif sky_margin_deg is not None:
            raise ConfigError("sky_margin_deg needs the camera it is measured in")
        if not 0.0 <= sky_fraction < 1.0:
            raise ConfigError(f"sky_fraction must be in [0, 1), got {sky_fraction}")
        h = self.input_size[1]
        self.sky_rows = sky_rows_of(sky_fraction, h)  # at input size
        height = inp.shape[2]
        if isinstance(height, str):  # dynamic: a second session with the height fixed, so
            # onnxruntime plans the graph as a static one
            self._session = _session(path, intra_op_threads, {height: h - self.sky_rows})
        elif self.sky_rows:
            logger.warning("%s: fixed input height %s, so every row is segmented "
                           "(sky_fraction %.2f ignored)", path, height, sky_fraction)
            self.sky_rows = 0
        self.scale = float(scale if scale is not None else meta.get("scale", 1.0 / 255.0))
        self.mean = np.asarray(mean if mean is not None else meta.get("mean", (0.0, 0.0, 0.0)),
                               np.float32)
        self.std = np.asarray(std if std is not None else meta.get("std", (1.0, 1.0, 1.0)),
                              np.float32)
        # sub-pixel logits: s * s per class at 1/s of the input (channel c * s * s + i * s + j:
        # class c at pixel (s y + i, s x + j)), argmaxed per sub-pixel, no upsampling
        self.subpixel = int(meta.get("subpixel", 1))
        self.head_map, self.priority = self._heads(head_map, priority)
        self.name = name or meta.get("name", path.stem)
        if upsample not in ("nearest", "bilinear"):
            raise ConfigError(f"upsample must be 'nearest' or 'bilinear', got {upsample!r}")
        self.upsample = upsample
        self.min_margin = float(min_margin)
        if self.min_margin < 0:
            raise ConfigError(f"min_margin must be >= 0 (logits), got {min_margin}")
        # paint borders re-decided on the image's brightness (refine_paint_borders): settings
        # set for the model's own classes on town frames by services/segtrain ride in its
        # metadata, and apply unless a head_map remaps those classes; {} turns it off
        if refine is None:
            refine = meta.get("refine") if head_map is None else None
        self.refine = dict(refine or {})
        unknown = set(self.refine) - set(REFINE_DEFAULTS)
        if unknown:
            raise ConfigError(f"unknown refine setting(s) {sorted(unknown)}; "
                              f"known: {sorted(REFINE_DEFAULTS)}")
        # the learned border classifier (BorderNet), fitted on town frames by services/segtrain,
        # decides the paint borders in place of `refine` where the labels are at the model's
        # input size and come from one head: None takes the model's own (metadata
        # `border_net`) if it has one and no head_map remaps its classes, True insists on it,
        # a dict is a spec; False or {}: off (the brightness rule, 1-2 ms a frame less)
        if border_net is None:
            border_net = (meta.get("border_net") if head_map is None and len(self.priority) == 1
                          else None)
        elif border_net is True:
            if "border_net" not in meta or head_map is not None:
                raise ConfigError(f"{path}: no border classifier for its own classes (metadata "
                                  "`border_net`; roadmap train-seg --border-only fits one)")
            border_net = meta["border_net"]
        self.border_net = BorderNet(border_net, intra_op_threads) if border_net else None
        if self.border_net and len(self.priority) != 1:
            raise ConfigError("border_net needs a model with one output head")
        # the mirror image (FLIP_MODES): "average" runs the network on the image and on its
        # mirror, the mirror's scores mirrored back, and averages the two (test-time flip
        # averaging; twice the network's time); "alternate" runs it once a call, on the image
        # and on its mirror in turn; "off" on the image alone. None: the model's own
        # (model_flip_mode)
        self.flip = model_flip_mode(meta) if flip is None else flip
        if self.flip not in FLIP_MODES:
            raise ConfigError(f"flip must be one of {FLIP_MODES}, got {self.flip!r}")
        self._mirror_next = False  # "alternate": whether the next call runs on the mirror

    def _heads(self, head_map, priority):
        outputs = self._session.get_outputs()
        names = [o.name for o in outputs]
        if head_map is None:
            head_map = {names[0]: _identity_head(int(outputs[0].shape[1]) // self.subpixel ** 2)}
        head_map = {str(h): {int(k): int(v) for k, v in m.items()} for h, m in head_map.items()}
        unknown = [h for h in head_map if h not in names]
        if unknown:
            raise ConfigError(f"model has no output(s) {unknown}; it has {names}")
        bad = [v for m in head_map.values() for v in m.values() if not 0 <= v < NUM_CLASSES]
        if bad:
            raise ConfigError(f"head_map targets classes outside 0..{NUM_CLASSES - 1}: {bad}")
        priority = list(priority or head_map)
        if sorted(priority) != sorted(head_map):
            raise ConfigError(f"priority {priority} must list exactly the heads {list(head_map)}")
        return head_map, priority

    def preprocess(self, image_rgb: np.ndarray) -> np.ndarray:
        """RGB (H, W, 3) uint8 -> model input (1, 3, h - sky_rows, w) float32: the image at
        the model's input size (w, h), without its sky rows."""
        w, h = self.input_size
        img = image_rgb
        if img.shape[1] != w or img.shape[0] != h:
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        img = img[self.sky_rows:]
        h -= self.sky_rows
        # per channel, straight into the NCHW buffer: x = img * (scale / std) - mean / std
        # (from contiguous planes: cv2.split then multiply is 1.5x faster than strided reads)
        x = np.empty((1, 3, h, w), np.float32)
        gain, offset = self.scale / self.std, -self.mean / self.std
        for c, plane in enumerate(cv2.split(img)):
            np.multiply(plane, gain[c], out=x[0, c], casting="unsafe")
            if offset[c]:
                x[0, c] += offset[c]
        return x

    def segment_model_size(self, image_rgb: np.ndarray, out_size=None) -> np.ndarray:
        """Labels (h, w) uint8 at the model's input size, or at out_size (W, H) when the logits
        are upsampled bilinearly before the argmax (smoother class boundaries): network_labels,
        then the paint borders re-decided on the image (refined_borders)."""
        small, labels, score_at = self.network_labels(image_rgb, out_size)
        return self.refined_borders(small, image_rgb, labels, score_at)

    def network_labels(self, image_rgb: np.ndarray, out_size=None):
        """(the image at the model's input size, labels as the network gives them, score_at).

        Logits coarser than the input (our model's are at 1/2) are upsampled bilinearly before
        the argmax (OpenCV: half-pixel centres, as torch's align_corners=False), unless they
        are sub-pixel logits (metadata `subpixel`): labels at the input size, resized to
        out_size (nearest) when one is given. `score_at(ys, xs)` -> (C, N) gives the upsampled
        scores of the last head at label pixels (ys, xs) (for sub-pixel logits, those of the
        full-resolution pixel's own sub-grid)."""
        w, h = self.input_size
        small = image_rgb  # resized once, for the network and the refinement
        if small.shape[:2] != (h, w):
            small = cv2.resize(small, (w, h), interpolation=cv2.INTER_AREA)
        outs = self.run_network(self.preprocess(small))
        out_w, out_h = out_size or (w, h)
        sky = round(self.sky_rows * out_h / h)  # rows labelled 0, at the output size
        band = (out_w, out_h - sky)  # (W, H) of the labels the network gives
        labels, score_at = None, None
        for head, logits in zip(self.priority, outs, strict=True):
            scores = logits[0]
            if self.subpixel > 1:
                arg = _subpixel_argmax(scores, self.subpixel)
                scale = (arg.shape[0] / band[1], arg.shape[1] / band[0])
                if band != arg.shape[::-1]:
                    arg = cv2.resize(arg, band, interpolation=cv2.INTER_NEAREST)
                score_at = partial(_subpixel_scores_at, scores, self.subpixel, scale=scale)
            elif band == (2 * scores.shape[2], 2 * scores.shape[1]):
                upsampled = UpsampledScores(scores)  # our model: only the mixed 2x2 blocks
                arg, score_at = upsampled.labels, upsampled
            else:
                if band != scores.shape[:0:-1]:
                    scores = _resize_channels(scores, band)
                arg = argmax_channels(scores)
                score_at = partial(_scores_at, scores)
            lut = np.zeros(len(scores) // self.subpixel ** 2, np.uint8)  # unmapped classes -> 0
            for k, v in self.head_map[head].items():
                if k < len(lut):
                    lut[k] = v
            # our own model's classes map to themselves: skip the gather (0.3 ms a frame)
            mapped = arg if np.array_equal(lut, np.arange(len(lut))) else lut[arg]
            if self.min_margin:
                mapped = _unsure_paint_unknown(score_at, mapped, self.min_margin)
            if labels is None:
                labels = mapped
            else:
                labels = np.where(mapped > 0, mapped, labels)
        if sky:
            full = np.zeros((out_h, out_w), np.uint8)
            full[sky:] = labels
            labels = full
            if score_at is not None:
                score_at = partial(_rows_below, score_at, sky)
        return small, labels.astype(np.uint8), score_at

    def run_network(self, x: np.ndarray) -> list[np.ndarray]:
        """The outputs of the heads in `priority` for model input `x` (1, 3, h, w), as
        `preprocess` gives it: the network's part of network_labels. With `flip` "average",
        the mean of those of `x` and of its mirror image (mirrored back); with "alternate",
        those of `x` on one call and of its mirror image (mirrored back) on the next."""
        if self.flip == "alternate":
            mirrored, self._mirror_next = self._mirror_next, not self._mirror_next
            if mirrored:
                outs = self._session.run(self.priority, {self._input_name: mirror_columns(x)})
                return [mirrored_back(o, self.subpixel) for o in outs]
        outs = self._session.run(self.priority, {self._input_name: x})
        if self.flip != "average":
            return outs
        mirrored = self._session.run(self.priority, {self._input_name: mirror_columns(x)})
        return [mean_with_mirrored(a, b, self.subpixel)
                for a, b in zip(outs, mirrored, strict=True)]

    def refined_borders(self, small, image_rgb, labels, score_at) -> np.ndarray:
        """The paint borders of network_labels' `labels` re-decided on the image: by the
        learned border classifier (`border_net`) where the labels are at the model's input
        size, else by their brightness (`refine`, refine_paint_borders) when the model's
        settings ask for it. Either runs after the `min_margin` gate, so a border pixel the
        gate left unknown can be given back to the paint beside it."""
        if self.border_net and score_at is not None and labels.shape == small.shape[:2]:
            return self.border_net(cv2.cvtColor(small, cv2.COLOR_RGB2GRAY), labels, score_at)
        if self.refine:
            img = small if labels.shape == small.shape[:2] else image_rgb
            if img.shape[:2] != labels.shape:  # labels at an out_size other than the frame's
                img = cv2.resize(img, labels.shape[::-1], interpolation=cv2.INTER_AREA)
            labels = refine_paint_borders(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), labels,
                                          **self.refine)
        return labels

    def segment(self, image_rgb, labels_true=None) -> np.ndarray:
        if image_rgb is None:
            raise ValueError("OnnxSegmenter needs the camera image of the frame")
        h, w = image_rgb.shape[:2]
        labels = self.segment_model_size(image_rgb, (w, h) if self.upsample == "bilinear" else None)
        if labels.shape != (h, w):
            labels = cv2.resize(labels, (w, h), interpolation=cv2.INTER_NEAREST)
        return labels


def model_flip_mode(meta: dict) -> str:
    """The flip mode a model's metadata asks for: `flip` if it names one, else "average" where
    its `flip_average` is true (files before 2026-11-29), else "off"."""
    return meta.get("flip") or ("average" if meta.get("flip_average") else "off")


def session_metadata(session) -> dict:
    """The `roadmap.segmentation` metadata of an onnxruntime session's model ({} without)."""
    return json.loads(session.get_modelmeta().custom_metadata_map.get(META_KEY, "{}"))


def _session(path: Path, threads: int, fixed_dims: dict | None = None):
    """An onnxruntime CPU session of `threads` threads; `fixed_dims` names the model's dynamic
    dimensions to fix (free dimension overrides: a dynamic-height graph planned for one height
    runs as fast as a static one, 1 ms a frame faster than left dynamic)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads)
    opts.inter_op_num_threads = 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    for name, value in (fixed_dims or {}).items():
        opts.add_free_dimension_override_by_name(name, int(value))
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


REFINE_DEFAULTS = {"window": 5, "level": 0.6, "min_contrast": 10.0}
_K3 = np.ones((3, 3), np.uint8)


def paint_border_pixels(labels: np.ndarray) -> np.ndarray:
    """Flat indices (ascending) of the pixels on a paint border: one pixel either side of
    where a marking class meets road or none."""
    return _border_of(_paint_mask(labels))


def _paint_mask(labels: np.ndarray) -> np.ndarray:
    """uint8 (H, W): 1 where the label is a marking class."""
    return (labels >= Cls.LANE_LINE).view(np.uint8)


def _border_of(paint: np.ndarray) -> np.ndarray:
    return np.flatnonzero(cv2.dilate(paint, _K3) != cv2.erode(paint, _K3))


def _box_means(gray: np.ndarray, labels: np.ndarray, paint: np.ndarray, border: np.ndarray,
               window: int):
    """At each border pixel (flat indices, ascending), over the `window` x `window` box around
    it (cut at the image's edges): (pixels labelled road, pixels of paint (`paint`: the
    labels' _paint_mask), mean grey of the road pixels, mean grey of the paint pixels),
    float32 (N,) each; a mean is 0 where its box holds none. Box sums from one integral image
    of the band of rows the boxes reach (paint lies below the horizon: the band is about half
    the frame)."""
    h, w = labels.shape
    r = int(window) // 2
    ys, xs = np.divmod(border, w)
    y0, y1 = max(int(ys[0]) - r, 0), min(int(ys[-1]) + r + 1, h)  # flat order: ys ascending
    road = (labels[y0:y1] == Cls.ROAD).view(np.uint8)
    paint_band, gray_band = paint[y0:y1], gray[y0:y1]
    sums = cv2.integral(cv2.merge([road, paint_band, gray_band * road, gray_band * paint_band]))
    sums = sums.reshape(-1, 4)
    ys = ys - y0
    top, bottom = np.maximum(ys - r, 0) * (w + 1), np.minimum(ys + r + 1, y1 - y0) * (w + 1)
    left, right = np.maximum(xs - r, 0), np.minimum(xs + r + 1, w)
    box = (np.take(sums, bottom + right, axis=0) - np.take(sums, top + right, axis=0)
           - np.take(sums, bottom + left, axis=0) + np.take(sums, top + left, axis=0))
    box = box.astype(np.float32)
    return (box[:, 0], box[:, 1], box[:, 2] / np.maximum(box[:, 0], 1),
            box[:, 3] / np.maximum(box[:, 1], 1))


def refine_paint_borders(gray: np.ndarray, labels: np.ndarray, *, window: int = 5,
                         level: float = 0.6, min_contrast: float = 10.0) -> np.ndarray:
    """Labels with the pixels on a paint border (one pixel either side of where a marking
    class meets road or none) re-decided by their brightness: paint is brighter than the road.

    A network whose logits are coarser than the image (ours: 1/2) places a line's edge to
    within one of its pixels, so a 2-4 px line comes out a pixel too wide or too thin. Around
    each border pixel, in a `window` x `window` box, the mean grey of the pixels labelled road
    (r) and of those labelled paint (p) set the threshold r + level x (p - r): a paint pixel
    darker than it becomes road, a road or none pixel brighter than it takes the class of the
    paint beside it. Only where p exceeds r by `min_contrast` grey levels and the box holds
    road. About 0.9 ms for a 640x360 road frame: box sums from one integral image, read at the
    border pixels only."""
    paint = _paint_mask(labels)
    border = _border_of(paint)
    if len(border) == 0:
        return labels
    n_road, _, road_grey, paint_grey = _box_means(gray, labels, paint, border, window)
    decided = (n_road > 0) & (paint_grey > road_grey + min_contrast)
    bright = np.take(gray, border) > road_grey + level * (paint_grey - road_grey)
    was_paint = np.take(labels, border) >= Cls.LANE_LINE
    out = labels.copy()
    flat = out.reshape(-1)
    flat[border[decided & was_paint & ~bright]] = Cls.ROAD
    grow = border[decided & ~was_paint & bright]
    if len(grow):  # the paint class beside it (the largest id where two meet)
        flat[grow] = np.take(cv2.dilate(labels * paint, _K3), grow)
    return out


class BorderNet:
    """A learned classifier of paint-border pixels: the class of each pixel on a paint border
    (paint_border_pixels) from its 5x5 neighbourhood in the image and in the labels and the
    network's scores there (border_features), by a small multilayer perceptron (ReLU between
    layers). Where refine_paint_borders thresholds one brightness, this one is fitted on
    town frames (services/segtrain/border.py) to what the truth says at such pixels: edges a
    pixel off, paint halos, worn gaps, the shading of curbs.

    `spec` (the model's metadata `border_net`): {"layers": [{"w": (in, out) nested lists, "b":
    (out,)}, ...], "max_margin": logits (optional: border pixels the network is surer of keep
    its label)}. About 2-3 ms a 640x360 road frame (a few thousand border pixels): 1.3 ms
    more than refine_paint_borders at p50, 2.2 ms at p95 (common/models/HISTORY.md).

    The perceptron's matrix products run on at most `threads` BLAS threads (the segmenter's
    own budget, OnnxSegmenter's intra_op_threads), not on the BLAS library's pool of one
    thread per core: on a busy machine that pool's threads wait on each other, and the same
    products took 40 ms instead of 1.8 (common/models/HISTORY.md, 2026-11-27 evening). The
    limit is the process's while the products run: BLAS calls of other threads of the same
    process meanwhile get it too."""

    def __init__(self, spec: dict, threads: int = 1):
        try:
            self.layers = [(np.asarray(layer["w"], np.float32), np.asarray(layer["b"], np.float32))
                           for layer in spec["layers"]]
        except (KeyError, TypeError) as exc:
            raise ConfigError(f"border_net: malformed spec ({exc!r})") from None
        shapes = [w.shape for w, _ in self.layers]
        if (not shapes or shapes[0][0] != BORDER_FEATURES or shapes[-1][1] != NUM_CLASSES
                or any(a[1] != b[0] for a, b in zip(shapes, shapes[1:], strict=False))
                or any(b.shape != (w.shape[1],) for w, b in self.layers)):
            raise ConfigError(f"border_net: layer shapes {shapes} do not chain "
                              f"{BORDER_FEATURES} features to {NUM_CLASSES} classes")
        self.max_margin = float(spec.get("max_margin", np.inf))
        if threads < 1:
            raise ConfigError(f"border_net: threads must be >= 1, got {threads}")
        self.threads = int(threads)
        # (out, in) weights and (out, 1) biases, for features as columns
        self._columns = [(np.ascontiguousarray(w.T), b[:, None]) for w, b in self.layers]

    def scores(self, features: np.ndarray) -> np.ndarray:
        """(N, NUM_CLASSES) class scores of (N, BORDER_FEATURES) features, computed on their
        transpose (border_features' own layout: contiguous feature rows)."""
        x = features.T
        with _blas().limit(limits=self.threads, user_api="blas"):
            for i, (w, b) in enumerate(self._columns):
                x = w @ x
                x += b
                if i < len(self._columns) - 1:
                    np.maximum(x, 0, out=x)
        return x.T

    def __call__(self, gray: np.ndarray, labels: np.ndarray, score_at) -> np.ndarray:
        paint = _paint_mask(labels)
        border, scores = unsure_paint_border(labels, score_at, self.max_margin, paint)
        if len(border) == 0:
            return labels
        decided = self.scores(border_features(gray, labels, scores, border, paint)).T
        out = labels.copy()
        out.reshape(-1)[border] = argmax_channels(np.ascontiguousarray(decided))
        return out


@cache
def _blas() -> ThreadpoolController:
    """The BLAS libraries loaded in this process (numpy's among them), looked up once: a
    thread limit set through it costs ~0.01 ms."""
    return ThreadpoolController()


def unsure_paint_border(labels: np.ndarray, score_at, max_margin: float = np.inf,
                        paint: np.ndarray | None = None):
    """(flat indices, (C, N) network scores `score_at` gives there) of the paint-border
    pixels whose winning class leads the runner-up by less than `max_margin` logits: the
    pixels BorderNet decides (where the network is surer than that, the classifier agrees
    with it almost always, and leaving them out saves a quarter of its time). `paint`: the
    labels' _paint_mask, when the caller has it."""
    border = _border_of(_paint_mask(labels) if paint is None else paint)
    if len(border) == 0:
        return border, np.zeros((NUM_CLASSES, 0), np.float32)
    scores = score_at(*np.divmod(border, labels.shape[1]))
    if np.isfinite(max_margin):
        unsure = _lead(scores) < max_margin
        border, scores = border[unsure], scores[:, unsure]
    return border, scores


BORDER_PATCH = 2  # border_features: a (2 r + 1)^2 patch of grey and of paint around the pixel
BORDER_BOX = 9  # and the mean grey of road and of paint in this box
_PATCH = (2 * BORDER_PATCH + 1) ** 2
BORDER_FEATURES = 2 * _PATCH + NUM_CLASSES + 4


def border_features(gray: np.ndarray, labels: np.ndarray, scores: np.ndarray,
                    border: np.ndarray, paint: np.ndarray | None = None) -> np.ndarray:
    """(N, BORDER_FEATURES) float32 for BorderNet at border pixels (flat indices, ascending)
    whose network scores are `scores` (C, N):
    - the 5x5 grey patch, as (grey - r) / max(p - r, 10), clipped to [-3, 3], where r and p
      are the mean grey of the road and of the paint pixels in the 9x9 box (r: the patch's
      darkest grey where the box holds no road);
    - the 5x5 patch of paint (1) and not (0) in the labels;
    - the network's scores at the pixel less their maximum, floored at -8, / 4;
    - (p - r) / 64, r / 128, and the shares of road and of paint in the box.
    Patches reaching past the image's edges repeat its edge pixels. `paint`: the labels'
    _paint_mask, when the caller has it. The array is the transpose of a C-contiguous
    (BORDER_FEATURES, N) buffer: numpy reduces along a feature block 50x faster in that
    layout than across a row of an (N, F) array."""
    h, w = labels.shape
    r = BORDER_PATCH
    ys, xs = np.divmod(border, w)
    if paint is None:
        paint = _paint_mask(labels)
    n_road, n_paint, road_grey, paint_grey = _box_means(gray, labels, paint, border, BORDER_BOX)
    # the band of rows the patches reach, edges repeated r pixels out
    y0, y1 = max(int(ys[0]) - r, 0), min(int(ys[-1]) + r + 1, h)
    pad = (r - (int(ys[0]) - y0), r - (y1 - int(ys[-1]) - 1), r, r)
    grey_band = cv2.copyMakeBorder(gray[y0:y1], *pad, cv2.BORDER_REPLICATE).astype(np.float32)
    paint_band = cv2.copyMakeBorder(paint[y0:y1], *pad, cv2.BORDER_REPLICATE).astype(np.float32)
    width = w + 2 * r
    offsets = (np.arange(-r, r + 1)[:, None] * width + np.arange(-r, r + 1)).reshape(-1, 1)
    idx = offsets + ((ys - (int(ys[0]) - r)) * width + xs + r)  # (patch, N) in the padded band
    out = np.empty((BORDER_FEATURES, len(border)), np.float32)
    grey = out[:_PATCH]
    np.take(grey_band, idx, out=grey, mode="clip")
    road_grey = np.where(n_road > 0, road_grey, grey.min(axis=0))
    contrast = paint_grey - road_grey
    grey -= road_grey
    grey /= np.maximum(contrast, 10.0)
    np.clip(grey, -3.0, 3.0, out=grey)
    np.take(paint_band, idx, out=out[_PATCH:2 * _PATCH], mode="clip")
    rel = out[2 * _PATCH:2 * _PATCH + NUM_CLASSES]
    rel[...] = scores
    rel -= scores.max(axis=0)
    np.maximum(rel, -8.0, out=rel)
    rel *= 0.25
    area = float(BORDER_BOX * BORDER_BOX)
    stats = out[2 * _PATCH + NUM_CLASSES:]
    np.multiply(contrast, 1.0 / 64.0, out=stats[0])
    np.multiply(road_grey, 1.0 / 128.0, out=stats[1])
    np.multiply(n_road, 1.0 / area, out=stats[2])
    np.multiply(n_paint, 1.0 / area, out=stats[3])
    return out.T


def _rows_below(score_at, rows: int, ys, xs):
    """score_at of labels that gained `rows` rows on top (the sky rows)."""
    return score_at(np.asarray(ys) - rows, xs)


def _unsure_paint_unknown(score_at, labels: np.ndarray, min_margin: float):
    """labels (H, W) with the marking pixels whose best score leads the second best by less
    than min_margin set to 0 (unknown), in place. `score_at(ys, xs)` gives the (C, N) scores of
    pixels (ys, xs) (the logits as upsampled for the argmax). Only the marking pixels (a few
    per cent of a frame) are gathered, so it costs ~0.3 ms at 640x360."""
    ys, xs = np.nonzero(labels >= Cls.LANE_LINE)
    if len(ys):
        picked = score_at(ys, xs)
        if len(picked) < 2:  # a one-channel head has no runner-up to lead
            return labels
        unsure = _lead(picked) < min_margin
        labels[ys[unsure], xs[unsure]] = Cls.NONE
    return labels


def _lead(scores: np.ndarray) -> np.ndarray:
    """(N,): how far the best of (C, N) scores leads the runner-up (C >= 2; 0 where two
    share the best). Row maxima, not np.partition along axis 0: 3x faster."""
    best = scores.max(axis=0)
    hit = scores == best
    lead = best - np.where(hit, -np.inf, scores).max(axis=0)
    lead[hit.sum(axis=0) > 1] = 0.0
    return lead


def _scores_at(scores: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """(C, N) scores of (C, H, W) `scores` at pixels (ys, xs)."""
    return scores[:, ys, xs]


def _subpixel_scores_at(scores: np.ndarray, s: int, ys: np.ndarray, xs: np.ndarray,
                        scale: tuple[float, float] = (1.0, 1.0)):
    """(C, N) scores of sub-pixel logits (C * s * s, h, w) at full-resolution pixels (ys, xs);
    with `scale` (full-resolution rows, columns per label pixel), at label pixels of a nearest
    resize of the full-resolution labels (as cv2.INTER_NEAREST picks: floor(y * scale))."""
    if scale != (1.0, 1.0):
        ys = np.minimum((ys * scale[0]).astype(np.int64), s * scores.shape[1] - 1)
        xs = np.minimum((xs * scale[1]).astype(np.int64), s * scores.shape[2] - 1)
    sub = scores.reshape(-1, s * s, *scores.shape[1:])
    return sub[:, (ys % s) * s + xs % s, ys // s, xs // s]


def upsampled_at(scores: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """(C, N): (C, h, w) scores upsampled 2x bilinearly, at full-resolution pixels (ys, xs),
    as cv2.resize(INTER_LINEAR) to (2w, 2h) computes them (half-pixel centres, edges
    replicated): pixel y sits at y / 2 - 0.25 in the coarse grid, between coarse rows
    (y - 1) // 2 and the next, 3/4 of the way to the next for even y, 1/4 for odd y."""
    c, h, w = scores.shape
    ys, xs = np.asarray(ys, np.int64), np.asarray(xs, np.int64)
    wy = np.where(ys & 1, np.float32(0.25), np.float32(0.75))
    wx = np.where(xs & 1, np.float32(0.25), np.float32(0.75))
    r0, k0 = (ys - 1) >> 1, (xs - 1) >> 1  # floor division, -1 at the first row and column
    r1, k1 = np.minimum(r0 + 1, h - 1) * w, np.minimum(k0 + 1, w - 1)
    r0, k0 = np.maximum(r0, 0) * w, np.maximum(k0, 0)
    flat = scores.reshape(c, -1)
    top = np.take(flat, r0 + k0, axis=1) * (1 - wx) + np.take(flat, r0 + k1, axis=1) * wx
    bottom = np.take(flat, r1 + k0, axis=1) * (1 - wx) + np.take(flat, r1 + k1, axis=1) * wx
    return top * (1 - wy) + bottom * wy


def upsampled_argmax(scores: np.ndarray) -> np.ndarray:
    """argmax_channels(scores upsampled 2x bilinearly) -> (2h, 2w) uint8 labels
    (UpsampledScores(scores).labels)."""
    return UpsampledScores(scores).labels


class UpsampledScores:
    """(C, h, w) scores upsampled 2x bilinearly (as cv2.resize INTER_LINEAR to (2w, 2h)),
    without upsampling the score planes. `labels`: their argmax, (2h, 2w) uint8; calling it
    with pixels (ys, xs) gives their (C, N) upsampled scores (upsampled_at).

    A full-resolution pixel blends the 2x2 coarse pixels around it with weights >= 0, so where
    those four share their winning class, the blend's winner is that class too. Only the four
    pixels of each 'mixed' 2x2 block (about 1 in 10 on road frames) are blended and decided;
    the rest copy their block's class. The blends are kept: a paint border runs through mixed
    blocks (88 % of its pixels lie in one), so the scores BorderNet reads there are a lookup.
    Same labels as the resize then argmax (but for exact ties of blended scores); each mixed
    block's four corners are gathered once for its four pixels. Logits of 200 benchmark road
    frames (640x312), thread CPU time p50 / p95: 0.88 / 1.15 ms, against 1.32 / 1.88 blending
    each pixel alone (before 2026-11-25 night) and 1.26 / 1.61 resizing every plane then the
    argmax."""

    def __init__(self, scores: np.ndarray):
        c, h, w = scores.shape
        self.scores = scores
        coarse = argmax_channels(scores)
        padded = cv2.copyMakeBorder(coarse, 1, 1, 1, 1, cv2.BORDER_REPLICATE)
        # block (i, j): coarse pixels (i - 1 .. i, j - 1 .. j), edges replicated; it holds the
        # full-resolution pixels (2i - 1 .. 2i, 2j - 1 .. 2j)
        corner = padded[:-1, :-1]
        mixed = ((corner != padded[1:, :-1]) | (corner != padded[:-1, 1:])
                 | (corner != padded[1:, 1:]))
        labels = cv2.resize(corner, (2 * w + 2, 2 * h + 2), interpolation=cv2.INTER_NEAREST)
        blocks = np.flatnonzero(mixed)
        self._mixed = len(blocks)
        self._block = np.full(mixed.shape, -1, np.int32)  # a mixed block's column in _blend
        self._blend = np.zeros((c, 0), np.float32)
        if len(blocks):
            self._block.reshape(-1)[blocks] = np.arange(len(blocks), dtype=np.int32)
            bi, bj = np.divmod(blocks, w + 1)
            edged = np.empty((c, h + 2, w + 2), np.float32)
            for k in range(c):
                cv2.copyMakeBorder(scores[k], 1, 1, 1, 1, cv2.BORDER_REPLICATE, dst=edged[k])
            edged = edged.reshape(c, -1)
            top_left = bi * (w + 2) + bj  # the block's corners in the edged planes
            tl, tr = np.take(edged, top_left, axis=1), np.take(edged, top_left + 1, axis=1)
            bl, br = (np.take(edged, top_left + w + 2, axis=1),
                      np.take(edged, top_left + w + 3, axis=1))
            # (C, 2 dy + dx, block): a pixel weighs its own corner 3/4 along each axis
            blend = np.empty((c, 4, len(blocks)), np.float32)
            for dx, (near, far) in enumerate(((0.75, 0.25), (0.25, 0.75))):
                upper, lower = tl * near + tr * far, bl * near + br * far
                blend[:, dx] = upper * 0.75 + lower * 0.25
                blend[:, 2 + dx] = upper * 0.25 + lower * 0.75
            self._blend = blend.reshape(c, -1)
            decided = argmax_channels(self._blend).reshape(2, 2, -1)
            pixels = labels.reshape(h + 1, 2, w + 1, 2)  # [i, dy, j, dx]
            for dy in (0, 1):
                for dx in (0, 1):
                    pixels[bi, dy, bj, dx] = decided[dy, dx]
        self.labels = labels[1:-1, 1:-1]

    def __call__(self, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        ys, xs = np.asarray(ys, np.int64), np.asarray(xs, np.int64)
        block = self._block[(ys + 1) >> 1, (xs + 1) >> 1]
        column = block + (((ys + 1) & 1) * 2 + ((xs + 1) & 1)) * self._mixed
        kept = block >= 0
        if kept.all():
            return np.take(self._blend, column, axis=1)
        out = np.empty((len(self.scores), len(ys)), np.float32)
        out[:, kept] = np.take(self._blend, column[kept], axis=1)
        out[:, ~kept] = upsampled_at(self.scores, ys[~kept], xs[~kept])
        return out


def mirror_columns(x: np.ndarray) -> np.ndarray:
    """A float32 (..., h, w) array with its columns reversed, contiguous: OpenCV's flip of the
    (rows, w) view, 3x faster than copying numpy's reversed view (0.07 against 0.22 ms for a
    640x312 input)."""
    flat = np.ascontiguousarray(x).reshape(-1, x.shape[-1])
    return cv2.flip(flat, 1).reshape(x.shape)


def mirrored_back(logits: np.ndarray, s: int = 1) -> np.ndarray:
    """mirror_logits as a contiguous array (plain float32 logits by OpenCV's flip)."""
    if s == 1 and logits.dtype == np.float32 and logits.ndim >= 2:
        return mirror_columns(logits)
    return np.ascontiguousarray(mirror_logits(logits, s))


def mean_with_mirrored(logits: np.ndarray, mirrored: np.ndarray, s: int = 1) -> np.ndarray:
    """The mean of the logits of an image and those of its mirror image (mirror_logits):
    flip averaging. For plain float32 logits by OpenCV (0.09 against 0.22 ms at 6 x 156 x 320,
    the same values: halving is exact)."""
    if s != 1 or logits.dtype != np.float32 or logits.ndim < 2:
        return 0.5 * (logits + mirror_logits(mirrored, s))
    w = logits.shape[-1]
    a = np.ascontiguousarray(logits).reshape(-1, w)
    b = mirror_columns(mirrored).reshape(-1, w)
    return cv2.addWeighted(a, 0.5, b, 0.5, 0.0).reshape(logits.shape)


def mirror_logits(logits: np.ndarray, s: int = 1) -> np.ndarray:
    """Logits (..., C * s * s, h, w) of a mirrored image -> those of the image: columns
    reversed and, for sub-pixel logits (channel c * s * s + s * i + j is class c at pixel
    (s y + i, s x + j)), each sub-pixel column j swapped with s - 1 - j, since full-resolution
    column s x + j of the mirror is column s (w - 1 - x) + (s - 1 - j) of the image."""
    flipped = logits[..., ::-1]
    if s == 1:
        return flipped
    *lead, c, h, w = flipped.shape
    return flipped.reshape(*lead, c // (s * s), s, s, h, w)[..., ::-1, :, :].reshape(
        *lead, c, h, w)


def _subpixel_argmax(scores: np.ndarray, s: int) -> np.ndarray:
    """(C * s * s, h, w) sub-pixel logits -> (s h, s w) labels: the argmax of each of the s * s
    sub-grids at (h, w), interleaved (what F.pixel_shuffle then an argmax gives, without moving
    the float planes)."""
    _, h, w = scores.shape
    sub = scores.reshape(-1, s * s, h, w)
    labels = np.empty((s * h, s * w), np.uint8)
    for k in range(s * s):
        labels[k // s::s, k % s::s] = argmax_channels(sub[:, k])  # planes stay contiguous
    return labels


def _resize_channels(scores: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(C, h, w) float32 -> (C, H, W) for size (W, H), bilinear, channel by channel into one
    contiguous buffer (an interleaved (H, W, C) resize leaves a strided array that made the
    argmax after it 1.7x slower)."""
    out = np.empty((len(scores), size[1], size[0]), np.float32)
    for c, channel in enumerate(scores):
        cv2.resize(np.ascontiguousarray(channel, np.float32), size, dst=out[c],
                   interpolation=cv2.INTER_LINEAR)
    return out


def argmax_channels(scores: np.ndarray) -> np.ndarray:
    """np.argmax(scores, axis=0) for a few channels (first maximum wins, like np.argmax): the
    running maximum, then each channel from the last to the first claims the pixels where it
    equals the maximum; all in place, about 4x faster than numpy's strided axis-0 argmax on a
    6x360x640 array (NaN scores are not supported)."""
    best = scores[0].copy()
    for c in range(1, len(scores)):
        np.maximum(best, scores[c], out=best)
    arg = np.full(best.shape, len(scores) - 1, np.uint8 if len(scores) < 256 else np.int64)
    hit = np.empty(best.shape, bool)
    for c in range(len(scores) - 2, -1, -1):
        np.equal(scores[c], best, out=hit)
        np.copyto(arg, arg.dtype.type(c), where=hit)
    return arg


def get_segmenter(kind: str = "onnx", **kw) -> Segmenter:
    """Factory: "truth" -> GroundTruthSegmenter(**kw); "onnx" -> OnnxSegmenter(**kw) with the
    packaged model unless a non-empty `model_path` is given (from a SegmentationConfig:
    `configured_onnx`)."""
    if kind == "truth":
        return GroundTruthSegmenter(**kw)
    if kind == "onnx":
        if not kw.get("model_path"):
            kw.pop("model_path", None)
        return OnnxSegmenter(**kw)
    raise ConfigError(f"unknown segmenter {kind!r} (expected 'onnx' or 'truth')")


def configured_onnx(seg, *, min_margin: float = 0.0, camera=None) -> OnnxSegmenter:
    """The ONNX segmenter a SegmentationConfig `seg` names (the packaged model when its
    model_path is empty), with the caller's `min_margin`: the mapping vehicles and the car
    each set their own (vehicle.paint_min_margin, localizer.paint_min_margin). Given the
    `camera` (CameraModel), the rows above rays rising `seg.sky_margin_deg` above level (None:
    the model's own margin, else DEFAULT_SKY_MARGIN_DEG; < 0: none) are not segmented
    (OnnxSegmenter's camera and sky_margin_deg). The model's learned border classifier runs
    if it has one, unless `seg.border_net` is off (then its brightness rule), and the mirror
    image is used as the model asks (flip averaging or alternation), unless `seg.flip` names
    another of FLIP_MODES."""
    return get_segmenter("onnx", model_path=seg.model_path,
                         intra_op_threads=seg.intra_op_threads, min_margin=min_margin,
                         camera=camera,
                         sky_margin_deg=None if camera is None else seg.sky_margin_deg,
                         border_net=None if seg.border_net else False,
                         flip=seg.flip or None)
