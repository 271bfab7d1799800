"""Segmentation: camera image -> class image (H, W) uint8 in our classes (common.classes).

One verb, `segment(image_rgb, labels_true=None) -> labels`, two strategies: `OnnxSegmenter`
(common.segmentation.onnx: our packaged model, or any ONNX model, on onnxruntime) and the
simulator's `GroundTruthSegmenter` (services.sim.truth_segmenter: corrupted true labels of
simulated logs, for tests and ablations). `segmenter_for(cfg, role)` is the one place that
chooses between them for the mapping vehicles and the production car (`segmentation.kind`).

The package: `base` (the interface), `onnx` (the runtime), `refine` (paint-border refinement:
brightness rule and learned classifier), `scores` (logit utilities: upsampling, mirroring,
argmax, confidence)."""

import importlib
import logging

from common.classes import Cls
from common.config import SEGMENTER_KINDS
from common.errors import ConfigError
from common.segmentation.base import Segmenter
from common.segmentation.onnx import (
    DEFAULT_MODEL,
    DEFAULT_SKY_MARGIN_DEG,
    META_KEY,
    OnnxSegmenter,
    model_flip_mode,
    session_metadata,
    sky_rows_of,
)

logger = logging.getLogger(__name__)

__all__ = ["DEFAULT_MODEL", "DEFAULT_SKY_MARGIN_DEG", "META_KEY", "ROLES", "SEGMENTER_KINDS",
           "OnnxSegmenter", "Segmenter", "configured_onnx", "get_segmenter", "model_flip_mode",
           "role_roi", "roi_first_row", "segmenter_for", "session_metadata", "sky_rows_of",
           "symbol_margins"]

ROLES = ("vehicle", "localizer")  # who segments: the mapping vehicles or the production car
# The truth strategy is the simulator's (it needs a simulated log's true labels), imported only
# when chosen, so that the product's runtime does not load the simulator.
_TRUTH = "services.sim.truth_segmenter"


def get_segmenter(kind: str = "onnx", **kw) -> Segmenter:
    """Factory: "truth" -> GroundTruthSegmenter(**kw); "onnx" -> OnnxSegmenter(**kw) with the
    packaged model unless a non-empty `model_path` is given (from a SegmentationConfig:
    `configured_onnx`)."""
    if kind == "truth":
        return importlib.import_module(_TRUTH).GroundTruthSegmenter(**kw)
    if kind == "onnx":
        if not kw.get("model_path"):
            kw.pop("model_path", None)
        return OnnxSegmenter(**kw)
    raise ConfigError(f"unknown segmenter {kind!r} (expected 'onnx' or 'truth')")


def configured_onnx(seg, *, min_margin: float = 0.0, camera=None, first_row: int = 0,
                    class_min_margin: dict[int, float] | None = None) -> OnnxSegmenter:
    """The ONNX segmenter a SegmentationConfig `seg` names (the packaged model when its
    model_path is empty), with the caller's `min_margin`: the mapping vehicles and the car
    each set their own (vehicle.paint_min_margin, localizer.paint_min_margin). Given the
    `camera` (CameraModel), the rows above rays rising `seg.sky_margin_deg` above level (None:
    the model's own margin, else DEFAULT_SKY_MARGIN_DEG; < 0: none) are not segmented
    (OnnxSegmenter's camera and sky_margin_deg). The model's learned border classifier runs
    if it has one, unless `seg.border_net` is off (then its brightness rule), and the mirror
    image is used as the model asks (flip averaging or alternation), unless `seg.flip` names
    another of FLIP_MODES. `first_row`: the first image row the caller uses (roi_first_row;
    0: every row below the sky)."""
    return get_segmenter("onnx", model_path=seg.model_path,
                         intra_op_threads=seg.intra_op_threads, min_margin=min_margin,
                         class_min_margin=class_min_margin, camera=camera, first_row=first_row,
                         sky_margin_deg=None if camera is None else seg.sky_margin_deg,
                         border_net=None if seg.border_net else False,
                         flip=seg.flip or None)


def segmenter_for(cfg, role: str, *, camera=None, images: bool = True) -> Segmenter:
    """The segmenter `role` ("vehicle": the mapping fleet, "localizer": the production car) runs
    under a RoadmapConfig `cfg`: `cfg.segmentation.kind`, with the role's own confidence gate
    (vehicle.paint_min_margin, localizer.paint_min_margin) and truth corruption seed
    (vehicle.truth_seed, localizer.truth_seed). A log without camera `images` can only be
    segmented from its true labels: "onnx" falls back to "truth" there, with a warning."""
    if role not in ROLES:
        raise ConfigError(f"unknown segmenter role {role!r} (expected one of {ROLES})")
    role_cfg = getattr(cfg, role)
    kind = cfg.segmentation.kind
    if kind == "onnx" and not images:
        logger.warning("log has no camera images: using the ground-truth segmenter")
        kind = "truth"
    if kind == "truth":
        return get_segmenter("truth", seed=role_cfg.truth_seed)
    first_row = (roi_first_row(camera, *role_roi(cfg, role))
                 if camera is not None and cfg.segmentation.roi_rows_only else 0)
    return configured_onnx(cfg.segmentation, min_margin=role_cfg.paint_min_margin, camera=camera,
                           first_row=first_row, class_min_margin=symbol_margins(cfg, role))


def symbol_margins(cfg, role: str) -> dict[int, float] | None:
    """The mapping vehicles' own margin for stop lines and ground signs
    (vehicle.symbol_min_margin), the classes the model paints where there are none; the car
    keeps one margin for every class."""
    if role != "vehicle":
        return None
    m = cfg.vehicle.symbol_min_margin
    return {int(Cls.STOP_LINE): m, int(Cls.GROUND_SIGN): m}


def role_roi(cfg, role: str) -> tuple[float, float, float]:
    """(x_min_m, length_m, width_m) of the IPM ROI `role` turns into points: the car's is
    cfg.roi; the mapping vehicles' ends at vehicle.max_range_m (services/vehicle/node.py)."""
    roi = cfg.roi
    length = roi.length_m
    if role == "vehicle":
        length = min(length, cfg.vehicle.max_range_m - roi.x_min_m)
    return roi.x_min_m, length, roi.width_m


def roi_first_row(camera, x_min_m: float, length_m: float, width_m: float) -> int:
    """The first image row with a pixel in the IPM ROI (common.camera.build_ipm_lookup): no
    stage reads the labels above it."""
    from common.camera import build_ipm_lookup

    ipm = build_ipm_lookup(camera, x_min_m=x_min_m, length_m=length_m, width_m=width_m)
    if not len(ipm.pixel_index):
        return 0
    return int(ipm.pixel_index.min()) // camera.width
