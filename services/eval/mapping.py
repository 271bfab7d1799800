"""Quality of one vehicle's local map: per-class precision and recall against the world's truth.

Consumes the local label raster (0.1 m cells, world ENU, south-west corner x0/y0) and a World;
produces {class: {precision, recall, cells_pred, cells_true}} at 0.1 m tolerance. Truth is only
counted where the vehicle saw the ground (cells with any vote, dilated by the tolerance), since a
single traversal cannot recall paint outside its camera's ROI."""

import cv2
import numpy as np

from common.evaluation import per_class_precision_recall
from common.world import World


def local_map_quality(
    labels: np.ndarray, x0_m: float, y0_m: float, world: World, tol_cells: int = 1
) -> dict:
    """Per marking class precision/recall of `labels` vs `world` inside the observed area."""
    truth = world.rasterize(x0_m, y0_m, labels.shape[0], labels.shape[1])
    seen = labels > 0
    if tol_cells > 0:
        k = np.ones((2 * tol_cells + 1, 2 * tol_cells + 1), np.uint8)
        seen = cv2.dilate(seen.astype(np.uint8), k).astype(bool)
    truth[~seen] = 0
    return per_class_precision_recall(labels, truth, tol_cells=tol_cells)
