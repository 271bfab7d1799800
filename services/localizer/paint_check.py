"""The frame's paint as an integrity monitor of the map-matched pose.

ICP matches road-surface points too, and those fit anywhere along a road: a match they made can
be metres off with a covariance of centimetres (held-out Karlsruhe s433: ok 1.7-6.6 m off, none
of a frame's 133-3372 marking points within 0.3 m of the map's markings; 50-98 % of them at
the true pose). So every accepted match is asked whether its frame's marking points lie on the
map's markings. Where, not which: the class of a painted cell is the segmenter's least sure
call (a stop line's end read as lane line, a crosswalk stripe as a sign); asking it too cost the
suite 5 % of its ok frames and caught nothing more. A frame of imagined paint now and then is
the model's (4-12 % of a healthy Karlsruhe drive's matches); a run of misses is a pose off the
paint."""

from collections import deque

import numpy as np

from common.classes import MARKINGS
from common.config import LocalizerConfig
from common.geometry import transform_points_2d
from services.localizer.map_cache import class_slots


def paint_overlap(points_v: np.ndarray, pose: np.ndarray, cache, tol_m: float) -> float:
    """Share of the (marking) points, vehicle frame, within tol_m of a map cell of any marking
    class at pose (0 without points)."""
    if not len(points_v):
        return 0.0
    world = transform_points_2d(pose, np.asarray(points_v, float))
    on_paint = np.zeros(len(world), bool)
    for cls in MARKINGS:
        nearest, valid = cache.nearest(world, class_slots(np.full(len(world), cls)))
        on_paint |= valid & (np.hypot(*(world - nearest).T) < tol_m)
    return float(on_paint.mean())


class PaintCheck:
    def __init__(
        self,
        min_fit: float = LocalizerConfig.integrity_min_paint_fit,
        tol_m: float = LocalizerConfig.integrity_paint_fit_tol_m,
        misses: int = LocalizerConfig.integrity_paint_misses,
        window: int = LocalizerConfig.settle_frames,
    ):
        """min_fit: the share of a frame's marking points that must lie within tol_m of the
        map's markings (0: off); misses: how many of the last `window` matches may fall short,
        the latest never."""
        self.min_fit, self.tol_m, self.misses = min_fit, tol_m, misses
        # whether each of the last matches fitted; before the first, as if they had
        self.fitted: deque = deque([True] * window, maxlen=window)

    def note(self, paint_v: np.ndarray, pose: np.ndarray, cache) -> None:
        """An accepted match at pose of a frame whose marking points are paint_v."""
        if self.min_fit > 0:
            self.fitted.append(paint_overlap(paint_v, pose, cache, self.tol_m) >= self.min_fit)

    @property
    def trusted(self) -> bool:
        return self.fitted[-1] and self.fitted.count(False) <= self.misses
