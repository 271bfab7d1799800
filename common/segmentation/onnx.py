"""The ONNX runtime segmenter: our packaged RoadSegNet (or any ONNX model) run by onnxruntime on
the CPU, camera image -> class image; sky rows skipped, mirror passes, confidence gate, paint
borders re-decided (common.segmentation.refine)."""

import json
import logging
import os
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from common import camera as cameras
from common.classes import NUM_CLASSES
from common.config import FLIP_MODES, SegmentationConfig
from common.errors import ConfigError
from common.segmentation.base import Segmenter
from common.segmentation.refine import (
    BORDER_BOX,
    REFINE_DEFAULTS,
    BorderNet,
    refine_paint_borders,
    unsure_paint_unknown,
)
from common.segmentation.scores import (
    UpsampledScores,
    argmax_channels,
    mean_with_mirrored,
    mirror_columns,
    mirrored_back,
    resize_channels,
    rows_below,
    scores_at,
    subpixel_argmax,
    subpixel_scores_at,
)

logger = logging.getLogger(__name__)


# The model trained by training/, packaged with the library (see models/MODEL_CARD.md).
DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "models" / "roadseg.onnx"


# ONNX metadata key under which a model describes its own input (written by training/).
META_KEY = "roadmap.segmentation"


# sky rows are skipped in steps of the network's coarsest stride (RoadSegNet: 1/16), so the
# network's grid stays the full frame's. (The rows below, 312 at 640x360, are no multiple of
# 16, so onnxruntime leaves its blocked layout around the 1/16 -> 1/8 resize: 320 rows run
# 0.6 ms faster. But skipping 40 rows instead of 48 shifts the grid, and the packaged model's
# mean lane-line IoU falls from 0.751 to 0.741; 312 rows padded to 320 at the bottom give
# 0.740 with the last row repeated and 0.665 with zeros. 2026-11-25, every second benchmark
# frame, with border_net.)
SKY_ROW_STEP = 16


# rows above a pixel that BorderNet's decision there reads: the labels' 3x3 neighbourhood
# (whether it lies on a paint border) and its box of BORDER_BOX rows; the row above the sky
# rows, none, is the outer side of a border where paint reaches the first row segmented
BORDER_REACH_ROWS = 1 + BORDER_BOX // 2


# the sky margin (degrees above level) of a model whose metadata names none: `s` networks such
# as run B1 lost no IoU when the rows above it were left out, and the packaged m64 files (runs
# KM64 and G2R) were benchmarked with it
DEFAULT_SKY_MARGIN_DEG = 10.0


# rows of context kept above the first row a caller uses (`first_row`, at the image's size):
# the network's top rows see zero padding where the crop cuts the road off, and its 1/16 stage
# reads far context. Held-out ROI IoU, 50 frames a world, two passes (2026-12-02): 16 rows
# lost 0.015 lane line, 0.04 crosswalk and 0.08 sign-facing ground sign against every row;
# 48 rows 0.008 lane line; 80 rows none (lane line 0.8615 / 0.8619, crosswalk 0.935 / 0.937,
# stop-facing stop line 0.883 / 0.889, ground sign 0.752 / 0.745), at 0.82 of the time
FIRST_ROW_CONTEXT = 80


def sky_rows_of(sky_fraction: float, height: int) -> int:
    """The top rows OnnxSegmenter leaves out of a `height`-row input for a sky share
    `sky_fraction` (camera.sky_fraction): whole steps of SKY_ROW_STEP (a share of whole rows
    comes back as those rows, not one fewer by rounding: 208 / 360 * 360 < 208)."""
    return int(sky_fraction * height + 1e-6) // SKY_ROW_STEP * SKY_ROW_STEP


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
    measures the plain argmax (0). `class_min_margin` ({class: logits}) sets other margins
    for some classes (the mapping vehicles: stop lines and ground signs,
    vehicle.symbol_min_margin).

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
        intra_op_threads: int = SegmentationConfig.intra_op_threads,
        upsample: str = "nearest",
        refine: dict | None = None,
        border_net: dict | bool | None = None,
        min_margin: float = 0.0,
        class_min_margin: dict[int, float] | None = None,
        sky_fraction: float = 0.0,
        camera: cameras.CameraModel | None = None,
        sky_margin_deg: float | None = SegmentationConfig.sky_margin_deg,
        first_row: int = 0,
        flip: str | None = None,
        name: str | None = None,
    ):
        path = Path(model_path)
        if not path.is_file():
            raise ConfigError(f"segmentation model not found: {path}")
        meta, inp = self._open(path, input_size, intra_op_threads)
        self._sky_rows(path, meta, inp, intra_op_threads, sky_fraction=sky_fraction,
                       camera=camera, sky_margin_deg=sky_margin_deg, first_row=first_row)
        self._normalization(meta, scale, mean, std)
        # sub-pixel logits: s * s per class at 1/s of the input (channel c * s * s + i * s + j:
        # class c at pixel (s y + i, s x + j)), argmaxed per sub-pixel, no upsampling
        self.subpixel = int(meta.get("subpixel", 1))
        self.head_map, self.priority = self._heads(head_map, priority)
        self.name = name or meta.get("name", path.stem)
        if upsample not in ("nearest", "bilinear"):
            raise ConfigError(f"upsample must be 'nearest' or 'bilinear', got {upsample!r}")
        self.upsample = upsample
        self.min_margin = float(min_margin)
        # per class: min_margin, or class_min_margin's own for the classes it names
        self.class_min_margin = {int(c): float(m) for c, m in (class_min_margin or {}).items()}
        margins = np.full(NUM_CLASSES, self.min_margin, np.float32)
        for c, m in self.class_min_margin.items():
            margins[c] = m
        if (margins < 0).any():
            raise ConfigError(f"min_margin must be >= 0 (logits), got {min_margin}, "
                              f"{class_min_margin}")
        self._margins = margins if margins.any() else None
        self._border_rules(path, meta, remapped=head_map is not None, refine=refine,
                           border_net=border_net, threads=intra_op_threads)
        # the mirror image (FLIP_MODES): "average" runs the network on the image and on its
        # mirror, the mirror's scores mirrored back, and averages the two (test-time flip
        # averaging; twice the network's time); "alternate" runs it once a call, on the image
        # and on its mirror in turn; "off" on the image alone. None: the model's own
        # (model_flip_mode)
        self.flip = model_flip_mode(meta) if flip is None else flip
        if self.flip not in FLIP_MODES:
            raise ConfigError(f"flip must be one of {FLIP_MODES}, got {self.flip!r}")
        self._mirror_next = False  # "alternate": whether the next call runs on the mirror

    def _open(self, path: Path, input_size, threads: int):
        """The session, the model's metadata and its input; the input size (W, H) it runs at."""
        self._session = _session(path, threads)
        meta = session_metadata(self._session)
        inp = self._session.get_inputs()[0]
        self._input_name = inp.name
        self.input_size = tuple(input_size or meta.get("input_size")
                                or (inp.shape[3], inp.shape[2]))
        if not all(isinstance(v, int) for v in self.input_size):
            raise ConfigError(f"{path}: the model's input size is dynamic ({inp.shape}); "
                              "give input_size=(W, H)")
        return meta, inp

    def _sky_rows(self, path: Path, meta: dict, inp, threads: int, *, sky_fraction: float,
                  camera, sky_margin_deg, first_row: int = 0) -> None:
        """The top rows left out (sky_rows, at input size), from a share or from the camera's
        rays `sky_margin_deg` above level, or more down to the caller's `first_row` (of an
        image of the camera's height, else the input's); a dynamic-height model gets a session
        planned for the rows it runs on."""
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
        self.first_row = int(first_row)
        if self.first_row < 0:
            raise ConfigError(f"first_row must be >= 0, got {first_row}")
        image_h = camera.height if camera is not None else h
        self._first_row_in = int(self.first_row * h / image_h)  # at input size
        if self.first_row:  # the caller's first row, less the context, in whole steps
            top = self.first_row * h / image_h - FIRST_ROW_CONTEXT * h / image_h
            self.sky_rows = max(self.sky_rows, int(max(top, 0)) // SKY_ROW_STEP * SKY_ROW_STEP)
        height = inp.shape[2]
        if isinstance(height, str):  # dynamic: a second session with the height fixed, so
            # onnxruntime plans the graph as a static one
            self._session = _session(path, threads, {height: h - self.sky_rows})
        elif self.sky_rows:
            logger.warning("%s: fixed input height %s, so every row is segmented "
                           "(sky_fraction %.2f ignored)", path, height, sky_fraction)
            self.sky_rows = 0

    def _normalization(self, meta: dict, scale, mean, std) -> None:
        """x = (rgb * scale - mean) / std: given values, else the model's metadata's."""
        self.scale = float(scale if scale is not None else meta.get("scale", 1.0 / 255.0))
        self.mean = np.asarray(mean if mean is not None else meta.get("mean", (0.0, 0.0, 0.0)),
                               np.float32)
        self.std = np.asarray(std if std is not None else meta.get("std", (1.0, 1.0, 1.0)),
                              np.float32)

    def _border_rules(self, path: Path, meta: dict, *, remapped: bool, refine, border_net,
                      threads: int) -> None:
        """How paint borders are re-decided on the image.

        `refine`: the brightness rule (refine_paint_borders); settings set for the model's own
        classes on town frames by training/ ride in its metadata, and apply unless a head_map
        remaps those classes (`remapped`); {} turns it off. `border_net`: the learned border
        classifier (BorderNet), fitted on town frames by training/, decides the paint borders
        in place of `refine` where the labels are at the model's input size and come from one
        head: None takes the model's own (metadata `border_net`) if it has one and its classes
        are not remapped, True insists on it, a dict is a spec; False or {}: off (the
        brightness rule, 1-2 ms a frame less)."""
        if refine is None:
            refine = None if remapped else meta.get("refine")
        self.refine = dict(refine or {})
        unknown = set(self.refine) - set(REFINE_DEFAULTS)
        if unknown:
            raise ConfigError(f"unknown refine setting(s) {sorted(unknown)}; "
                              f"known: {sorted(REFINE_DEFAULTS)}")
        if border_net is None:
            border_net = (meta.get("border_net") if not remapped and len(self.priority) == 1
                          else None)
        elif border_net is True:
            if "border_net" not in meta or remapped:
                raise ConfigError(f"{path}: no border classifier for its own classes (metadata "
                                  "`border_net`; python -m training train-seg --border-only "
                                  "fits one)")
            border_net = meta["border_net"]
        self.border_net = BorderNet(border_net, threads) if border_net else None
        if self.border_net and len(self.priority) != 1:
            raise ConfigError("border_net needs a model with one output head")

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
        full-resolution pixel's own sub-grid). The sky rows are labelled none, and so are,
        given a `first_row`, the rows above it less BORDER_REACH_ROWS: the network reads the
        context rows above the caller's first row, but its labels there are not upsampled
        nor refined (since 2026-12-02: before, a full-frame IoU counted them)."""
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
                arg = subpixel_argmax(scores, self.subpixel)
                scale = (arg.shape[0] / band[1], arg.shape[1] / band[0])
                if band != arg.shape[::-1]:
                    arg = cv2.resize(arg, band, interpolation=cv2.INTER_NEAREST)
                score_at = partial(subpixel_scores_at, scores, self.subpixel, scale=scale)
            elif band == (2 * scores.shape[2], 2 * scores.shape[1]):
                # our model: only the mixed 2x2 blocks, from the first row decided on
                first = round(self._first_decided_row() * out_h / h) - sky
                upsampled = UpsampledScores(scores, max(first, 0))
                arg, score_at = upsampled.labels, upsampled
            else:
                if band != scores.shape[:0:-1]:
                    scores = resize_channels(scores, band)
                arg = argmax_channels(scores)
                score_at = partial(scores_at, scores)
            lut = np.zeros(len(scores) // self.subpixel ** 2, np.uint8)  # unmapped classes -> 0
            for k, v in self.head_map[head].items():
                if k < len(lut):
                    lut[k] = v
            # our own model's classes map to themselves: skip the gather (0.3 ms a frame)
            mapped = arg if np.array_equal(lut, np.arange(len(lut))) else lut[arg]
            if self._margins is not None:
                mapped = unsure_paint_unknown(score_at, mapped, self._margins)
            if labels is None:
                labels = mapped
            else:
                labels = np.where(mapped > 0, mapped, labels)
        labels = self._in_frame(labels, sky, out_h / h)
        if sky and score_at is not None:
            score_at = partial(rows_below, score_at, sky)
        return small, labels.astype(np.uint8), score_at

    def _in_frame(self, labels: np.ndarray, sky: int, scale: float) -> np.ndarray:
        """The labels of the rows from `sky` down in the whole frame (output rows per input
        row `scale`): the sky rows none, and the context rows above the first row decided
        (the network reads them; the caller uses none of them)."""
        none = max(sky, round(self._first_decided_row() * scale))
        if not none:
            return labels
        full = np.zeros((sky + labels.shape[0], labels.shape[1]), np.uint8)
        full[none:] = labels[none - sky:]
        return full

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
            return self._border_net_below_sky(small, labels, score_at)
        if self.refine:
            img = small if labels.shape == small.shape[:2] else image_rgb
            if img.shape[:2] != labels.shape:  # labels at an out_size other than the frame's
                img = cv2.resize(img, labels.shape[::-1], interpolation=cv2.INTER_AREA)
            labels = refine_paint_borders(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), labels,
                                          **self.refine)
        return labels

    def _first_decided_row(self) -> int:
        """The first row (at input size) of which the paint borders are decided, and so of
        which the upsampled argmax is needed: BORDER_REACH_ROWS above the caller's
        `first_row` (0 without one)."""
        return max(self._first_row_in - BORDER_REACH_ROWS, 0)

    def _border_net_below_sky(self, small, labels, score_at) -> np.ndarray:
        """border_net on the rows from BORDER_REACH_ROWS above the first row it must decide
        down: the first row segmented (the sky rows are labelled none, so no paint border
        lies higher than the row just above them) or, lower, the caller's `first_row`. Every
        row from that one down gets the labels of a run on the whole frame, bit for bit (rows
        above the caller's first row keep the network's labels, but for the reach's rows,
        which may differ), without a third of the frame's grey conversion, masks and
        morphology and the quarter of its border pixels that lie in the context rows above
        the IPM ROI (2026-12-02: 27 % of those decided on benchmark frames)."""
        top = max(self.sky_rows - BORDER_REACH_ROWS, self._first_decided_row(), 0)
        view = labels[top:]
        band = self.border_net(cv2.cvtColor(small[top:], cv2.COLOR_RGB2GRAY), view,
                               partial(rows_below, score_at, -top) if top else score_at)
        if band is view:  # no border to re-decide
            return labels
        out = labels.copy()
        out[top:] = band
        return out

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
