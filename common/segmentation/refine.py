"""Paint-border refinement of a label image: the brightness rule (refine_paint_borders) and the
learned border classifier (BorderNet), each re-deciding the pixels on a paint border."""

import logging
from functools import cache

import cv2
import numpy as np
from threadpoolctl import ThreadpoolController

from common.classes import NUM_CLASSES, Cls
from common.errors import ConfigError
from common.segmentation.scores import argmax_channels, lead_of

logger = logging.getLogger(__name__)


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
    town frames (training/border.py) to what the truth says at such pixels: edges a
    pixel off, paint halos, worn gaps, the shading of curbs.

    `spec` (the model's metadata `border_net`): {"layers": [{"w": (in, out) nested lists, "b":
    (out,)}, ...], "max_margin": logits (optional: border pixels the network is surer of keep
    its label)}. About 2-3 ms a 640x360 road frame (a few thousand border pixels): 1.3 ms
    more than refine_paint_borders at p50, 2.2 ms at p95 (training/HISTORY.md).

    The perceptron's matrix products run on at most `threads` BLAS threads (the segmenter's
    own budget, OnnxSegmenter's intra_op_threads), not on the BLAS library's pool of one
    thread per core: on a busy machine that pool's threads wait on each other, and the same
    products took 40 ms instead of 1.8 (training/HISTORY.md, 2026-11-27 evening). The
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
        unsure = lead_of(scores) < max_margin
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
    grey_band = cv2.copyMakeBorder(gray[y0:y1], *pad, cv2.BORDER_REPLICATE)
    paint_band = cv2.copyMakeBorder(paint[y0:y1], *pad, cv2.BORDER_REPLICATE)
    width = w + 2 * r
    offsets = (np.arange(-r, r + 1)[:, None] * width + np.arange(-r, r + 1)).reshape(-1, 1)
    idx = offsets + ((ys - (int(ys[0]) - r)) * width + xs + r)  # (patch, N) in the padded band
    out = np.empty((BORDER_FEATURES, len(border)), np.float32)
    grey = out[:_PATCH]
    # gathered as bytes, then widened: the bands stay uint8 (no float copy of the band)
    grey[...] = np.take(grey_band, idx, mode="clip")
    road_grey = np.where(n_road > 0, road_grey, grey.min(axis=0))
    contrast = paint_grey - road_grey
    grey -= road_grey
    grey /= np.maximum(contrast, 10.0)
    np.clip(grey, -3.0, 3.0, out=grey)
    out[_PATCH:2 * _PATCH] = np.take(paint_band, idx, mode="clip")
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


def unsure_paint_unknown(score_at, labels: np.ndarray, min_margin):
    """labels (H, W) with the marking pixels whose best score leads the second best by less
    than min_margin set to 0 (unknown), in place; `min_margin` is one value for every class or
    an array of one per class (indexed by the label). `score_at(ys, xs)` gives the (C, N)
    scores of pixels (ys, xs) (the logits as upsampled for the argmax). Only the marking pixels
    (a few per cent of a frame) are gathered, so it costs ~0.3 ms at 640x360."""
    ys, xs = np.nonzero(labels >= Cls.LANE_LINE)
    if len(ys):
        picked = score_at(ys, xs)
        if len(picked) < 2:  # a one-channel head has no runner-up to lead
            return labels
        margin = np.asarray(min_margin, np.float32)
        unsure = lead_of(picked) < (margin[labels[ys, xs]] if margin.ndim else margin)
        labels[ys[unsure], xs[unsure]] = Cls.NONE
    return labels
