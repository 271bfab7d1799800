"""Map quality against ground truth: per-class precision and recall with a distance tolerance.

A predicted cell of class c is correct if a true cell of class c lies within `tol_cells` (Chebyshev
distance, i.e. a (2 tol + 1)^2 window); recall is the same the other way round. At 0.1 m cells,
tol_cells=1 is the 0.1 m tolerance of DESIGN.md."""

import cv2
import numpy as np

from common.classes import MARKINGS, NAMES


def _dilate(mask: np.ndarray, tol_cells: int) -> np.ndarray:
    if tol_cells <= 0:
        return mask
    k = np.ones((2 * tol_cells + 1, 2 * tol_cells + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), k).astype(bool)


def precision_recall(pred: np.ndarray, truth: np.ndarray, cls: int, tol_cells: int = 1):
    """(precision, recall, n_pred, n_true) of one class between two aligned label rasters."""
    p, t = pred == cls, truth == cls
    n_pred, n_true = int(p.sum()), int(t.sum())
    precision = float((p & _dilate(t, tol_cells)).sum() / n_pred) if n_pred else float("nan")
    recall = float((t & _dilate(p, tol_cells)).sum() / n_true) if n_true else float("nan")
    return precision, recall, n_pred, n_true


def per_class_precision_recall(pred, truth, tol_cells: int = 1, classes=MARKINGS) -> dict:
    """{name: {precision, recall, cells_pred, cells_true}} for the marking classes."""
    out = {}
    for c in classes:
        pr, rc, n_pred, n_true = precision_recall(pred, truth, int(c), tol_cells)
        out[NAMES[c]] = {"precision": pr, "recall": rc, "cells_pred": n_pred, "cells_true": n_true}
    return out


def iou(pred: np.ndarray, truth: np.ndarray, cls: int) -> float:
    p, t = pred == cls, truth == cls
    union = int((p | t).sum())
    return float((p & t).sum() / union) if union else float("nan")
