"""Global initialization: find the pose from a consumer GNSS fix (up to ~5 m off) and no heading.

A coarse search scores every pose of a grid (x, y within +-radius of the GNSS fix, yaw over the
whole circle or around a GNSS-track heading) by the weighted fraction of the frame's points that
land within a dilation radius of a map cell of their class; the best distinct candidates are then
refined by ICP and ranked by their fine overlap and their distance to the GNSS fix."""

import math
from dataclasses import dataclass

import cv2
import numpy as np

from common.classes import Cls
from common.config import LocalizerConfig
from common.grid import CELL_M

CLASS_WEIGHT = {
    Cls.ROAD: 0.3,
    Cls.LANE_LINE: 1.0,
    Cls.STOP_LINE: 2.0,
    Cls.CROSSWALK: 1.5,
    Cls.GROUND_SIGN: 2.0,
}


@dataclass(frozen=True)
class Candidate:
    pose: np.ndarray
    score: float


def class_bits_window(cache, x0_m: float, y0_m: float, size_cells: int, dilate_cells: int):
    """Window of the map (rows north) as per-class bit masks, each class dilated by a radius."""
    win = np.zeros((size_cells, size_cells), dtype=np.uint8)
    ys = y0_m + (np.arange(size_cells) + 0.5) * CELL_M
    xs = x0_m + (np.arange(size_cells) + 0.5) * CELL_M
    gx, gy = np.meshgrid(xs, ys)
    labels = cache.class_at(np.stack([gx.ravel(), gy.ravel()], axis=1)).reshape(win.shape)
    k = 2 * dilate_cells + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    for cls in CLASS_WEIGHT:
        mask = (labels == cls).astype(np.uint8)
        if mask.any():
            win |= cv2.dilate(mask, kernel) << np.uint8(cls)
    return win


class CoarseSearch:
    """Exhaustive pose search on a dilated class window; pure numpy."""

    def __init__(
        self,
        *,
        radius_m: float = LocalizerConfig.init_radius_m,
        step_m: float = 0.5,
        yaw_step_deg: float = 2.0,
        yaw_window_deg: float = 25.0,
        dilate_m: float = 0.35,
        max_points: int = 400,
        top_k: int = 6,
        seed: int = 0,
    ):
        self.radius_m, self.step_m = radius_m, step_m
        self.yaw_step = math.radians(yaw_step_deg)
        self.yaw_window = math.radians(yaw_window_deg)
        self.dilate_cells = max(int(round(dilate_m / CELL_M)), 1)
        self.max_points, self.top_k = max_points, top_k
        self._rng = np.random.default_rng(seed)

    def yaw_candidates(self, heading_rad: float | None) -> np.ndarray:
        if heading_rad is None:
            return np.arange(-math.pi, math.pi, self.yaw_step)
        half = self.yaw_window
        return heading_rad + np.arange(-half, half + 1e-9, self.yaw_step)

    def search(self, points_v, classes, centre_of_yaw, heading_rad, cache) -> list[Candidate]:
        """Best distinct candidate poses of the vehicle, best first.

        centre_of_yaw(yaw) -> (x, y): the GNSS position prior, which may depend on the heading."""
        pts, cls = self._thin(np.asarray(points_v, float), np.asarray(classes))
        if len(pts) == 0:
            return []
        yaws = self.yaw_candidates(heading_rad)
        centres = np.array([centre_of_yaw(y) for y in yaws])
        reach = self.radius_m + float(np.max(np.hypot(pts[:, 0], pts[:, 1]))) + 1.0
        x0, y0 = centres.min(axis=0) - reach
        size = int(math.ceil((np.ptp(centres, axis=0).max() + 2 * reach) / CELL_M))
        win = class_bits_window(cache, x0, y0, size, self.dilate_cells)
        bit = np.uint8(1) << cls.astype(np.uint8)
        weight = np.array([CLASS_WEIGHT.get(Cls(int(c)), 0.0) for c in cls])
        offs = np.arange(-self.radius_m, self.radius_m + 1e-9, self.step_m)
        gx, gy = np.meshgrid(offs, offs)
        offsets = np.stack([gx.ravel(), gy.ravel()], axis=1)
        scored = []
        for yaw, centre in zip(yaws, centres, strict=True):
            grid = offsets + centre
            scores = self._score_yaw(pts, bit, weight, yaw, grid, win, x0, y0, size)
            best = np.argsort(scores)[-self.top_k :]
            scored.extend(Candidate(np.array([*grid[i], yaw]), float(scores[i])) for i in best)
        return distinct(sorted(scored, key=lambda c: -c.score), lambda c: c.pose, k=self.top_k)

    def _score_yaw(self, pts, bit, weight, yaw, grid, win, x0, y0, size):
        c, s = math.cos(yaw), math.sin(yaw)
        rx = c * pts[:, 0] - s * pts[:, 1]
        ry = s * pts[:, 0] + c * pts[:, 1]
        col = np.floor((grid[:, 0:1] + rx[None, :] - x0) / CELL_M).astype(np.int64)
        row = np.floor((grid[:, 1:2] + ry[None, :] - y0) / CELL_M).astype(np.int64)
        inside = (col >= 0) & (col < size) & (row >= 0) & (row < size)
        hit = (win[np.clip(row, 0, size - 1), np.clip(col, 0, size - 1)] & bit[None, :]) > 0
        return ((hit & inside) * weight[None, :]).sum(axis=1) / max(weight.sum(), 1e-9)

    def _thin(self, pts, cls):
        keep = np.isin(cls, [int(c) for c in CLASS_WEIGHT])
        pts, cls = pts[keep], cls[keep]
        if len(pts) > self.max_points:
            idx = self._rng.choice(len(pts), self.max_points, replace=False)
            pts, cls = pts[idx], cls[idx]
        return pts, cls


def far_apart(a, b, min_sep_m: float = 1.0, min_sep_rad: float = math.radians(5)) -> bool:
    """Poses (x, y, yaw) more than min_sep_m apart or turned more than min_sep_rad."""
    return bool(np.hypot(a[0] - b[0], a[1] - b[1]) > min_sep_m
                or abs(math.remainder(a[2] - b[2], 2 * math.pi)) > min_sep_rad)


def distinct(items: list, pose_of, *, k: int | None = None, min_sep_m: float = 1.0,
             min_sep_rad: float = math.radians(5)) -> list:
    """The items in order, each kept when its pose is far_apart from every kept one (at most
    k): the best of every cluster of near-identical poses, for ranked lists."""
    out: list = []
    for item in items:
        if all(far_apart(pose_of(item), pose_of(o), min_sep_m, min_sep_rad) for o in out):
            out.append(item)
        if k is not None and len(out) == k:
            break
    return out


def class_distances(points_v, slots, pose, cache) -> np.ndarray:
    """Each point's distance (m) at pose to the nearest map cell of its class (inf: none)."""
    from services.localizer.icp import _to_world

    world = _to_world(np.asarray(points_v, float), pose)
    nearest, valid = cache.nearest(world, slots)
    return np.where(valid, np.hypot(*(world - nearest).T), np.inf)


def fine_overlap(points_v, slots, pose, cache, tol_m: float = 0.15) -> float:
    """Fraction of points within tol of a map cell of their class at pose."""
    d = class_distances(points_v, slots, pose, cache)
    return float(np.mean(d < tol_m)) if len(d) else 0.0
