"""Fitting the learned border classifier (common.segmentation.BorderNet) of an exported model.

The network's logits are at 1/2 of the image, so it places a line's edge to within a pixel;
thin paint is a few pixels wide, and most of what separates its IoU from a perfect one lies
on the one-pixel ring around the paint it finds. BorderNet re-decides that ring from the
image and the network's scores there. It is fitted here, on town frames the network never
trained on (their own seed), to what the truth says at those pixels, and written into the
model's metadata (`border_net`), which OnnxSegmenter reads.

`roadmap train-seg --border-only MODEL --seed S --frames N` renders N town frames of seed S
(cached like the training frames), fits on the first 90 % and keeps the classifier only if it
beats the model's brightness rule (`refine`) in mean paint IoU on the last 10 %."""

import logging
import time

import cv2
import numpy as np

from common.classes import NUM_CLASSES, Cls
from common.segmentation import OnnxSegmenter
from common.segmentation.refine import BORDER_FEATURES, border_features, unsure_paint_border
from services.bench.heldout import mean_paint_iou, segmenter_iou

logger = logging.getLogger(__name__)

HIDDEN = 64  # two hidden layers: 60 -> 64 -> 64 -> 6, 8.4 k weights (0.25 ms a frame more than 32)
EPOCHS = 10
BATCH = 4096
LR = 3e-3
LR_END = 0.6 ** 6  # the rate falls geometrically to this share of LR over the epochs
MAX_MARGIN = 3.0  # logits: border pixels the network is surer of keep its label (BorderNet)
PER_FRAME = 3000  # border pixels drawn per frame (a road frame has 1-11 k)
CHECK_SHARE = 0.1  # the last frames, on which the classifier must beat the brightness rule


def raw_segmenter(model_path, threads: int = 2, sky_fraction: float = 0.0) -> OnnxSegmenter:
    """The model as the runtime runs it, without any border refinement."""
    return OnnxSegmenter(model_path, intra_op_threads=threads, refine={}, border_net={},
                         sky_fraction=sky_fraction)


def border_samples(seg: OnnxSegmenter, frames, labels, rng, per_frame: int = PER_FRAME,
                   max_margin: float = MAX_MARGIN):
    """(X (N, BORDER_FEATURES) float32, y (N,) int64): border_features of up to `per_frame`
    random pixels of each frame (model input size) that BorderNet decides (paint-border
    pixels `seg`'s network is unsure of by `max_margin`), and their true class (training
    labels' auxiliary classes, e.g. curbs, are none)."""
    xs, ys = [], []
    for frame, truth in zip(frames, labels, strict=True):
        small, raw, score_at = seg.network_labels(frame)
        border, scores = unsure_paint_border(raw, score_at, max_margin)
        if len(border) > per_frame:
            keep = np.sort(rng.choice(len(border), per_frame, replace=False))
            border, scores = border[keep], scores[:, keep]
        if len(border) == 0:
            continue
        gray = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
        xs.append(border_features(gray, raw, scores, border))
        y = truth.reshape(-1)[border].astype(np.int64)
        y[y >= NUM_CLASSES] = Cls.NONE
        ys.append(y)
    if not xs:
        return np.zeros((0, BORDER_FEATURES), np.float32), np.zeros(0, np.int64)
    return np.concatenate(xs), np.concatenate(ys)


def fit_border_net(x: np.ndarray, y: np.ndarray, *, seed: int = 0, hidden: int = HIDDEN,
                   epochs: int = EPOCHS, max_margin: float = MAX_MARGIN) -> dict:
    """A BorderNet spec fitted by cross-entropy (Adam, the rate falling geometrically from LR
    to LR x LR_END over the epochs) on samples from border_samples."""
    import torch

    if len(x) < BATCH:
        raise ValueError(f"{len(x)} border samples are too few to fit a border classifier")
    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], hidden), torch.nn.ReLU(),
                              torch.nn.Linear(hidden, hidden), torch.nn.ReLU(),
                              torch.nn.Linear(hidden, NUM_CLASSES))
    opt = torch.optim.Adam(net.parameters(), LR)
    xt, yt = torch.from_numpy(x), torch.from_numpy(y)
    gen = torch.Generator().manual_seed(seed)
    for epoch in range(epochs):
        order = torch.randperm(len(xt), generator=gen)
        total = 0.0
        for i in range(0, len(order), BATCH):
            batch = order[i:i + BATCH]
            loss = torch.nn.functional.cross_entropy(net(xt[batch]), yt[batch])
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += loss.item() * len(batch)
        for group in opt.param_groups:
            group["lr"] *= LR_END ** (1 / epochs)
        logger.info("border net epoch %d: loss %.4f", epoch, total / len(order))
    layers = [m for m in net if isinstance(m, torch.nn.Linear)]
    return {"layers": [{"w": _rounded(m.weight.detach().T.numpy()),
                        "b": _rounded(m.bias.detach().numpy())} for m in layers],
            "max_margin": max_margin}


def _rounded(a: np.ndarray) -> list:
    """Nested lists of 6 significant digits (the metadata is JSON: 40 KB, not 70)."""
    return np.vectorize(lambda v: float(f"{v:.6g}"), otypes=[float])(a).tolist()


def paint_iou(seg: OnnxSegmenter, frames, labels) -> dict:
    """Per-class IoU of `seg` as the runtime segments town frames, and the mean over the
    markings present ("paint")."""
    ious = segmenter_iou(seg, frames, labels)
    return {**ious, "paint": mean_paint_iou(ious)}


def calibrate_border_net(model_path, frames, labels, *, seed: int = 0,
                         sky_fraction: float = 0.0) -> dict:
    """Fit BorderNet on the first (1 - CHECK_SHARE) of the town frames, check it on the rest
    against the model's own border rule, each segmented without the top `sky_fraction` of its
    rows as the runtime leaves them out (OnnxSegmenter) -> {"border_net": spec or None (it did
    not beat the rule), "check": {"rule": ious, "border_net": ious}, "samples": n, "fit_s": s}."""
    t0 = time.perf_counter()
    n_check = max(int(len(frames) * CHECK_SHARE), 1)
    fit_frames, fit_labels = frames[:-n_check], labels[:-n_check]
    check_frames, check_labels = frames[-n_check:], labels[-n_check:]
    seg = raw_segmenter(model_path, sky_fraction=sky_fraction)
    x, y = border_samples(seg, fit_frames, fit_labels, np.random.default_rng(seed))
    logger.info("%d border samples from %d frames (classes %s)", len(x), len(fit_frames),
                np.bincount(y, minlength=NUM_CLASSES).tolist())
    spec = fit_border_net(x, y, seed=seed)
    rule = OnnxSegmenter(model_path, intra_op_threads=2, border_net={},
                         sky_fraction=sky_fraction)
    learned = OnnxSegmenter(model_path, intra_op_threads=2, border_net=spec,
                            sky_fraction=sky_fraction)
    check = {"rule": paint_iou(rule, check_frames, check_labels),
             "border_net": paint_iou(learned, check_frames, check_labels)}
    better = check["border_net"]["paint"] > check["rule"]["paint"]
    logger.info("border net on %d check frames: mean paint IoU %.4f (rule %.4f)%s", n_check,
                check["border_net"]["paint"], check["rule"]["paint"],
                "" if better else ": not kept")
    return {"border_net": spec if better else None, "check": check, "samples": len(x),
            "fit_frames": len(fit_frames), "check_frames": n_check,
            "fit_s": round(time.perf_counter() - t0, 1)}

