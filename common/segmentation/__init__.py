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
           "segmenter_for", "session_metadata", "sky_rows_of"]

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
    return configured_onnx(cfg.segmentation, min_margin=role_cfg.paint_min_margin, camera=camera)
