"""The frame's paint as an integrity monitor of the map-matched pose.

ICP matches road-surface points too, and those fit anywhere along a road: a match they made can
be metres off with a covariance of centimetres (held-out Karlsruhe s433: ok 1.7-6.6 m off, none
of a frame's 133-3372 marking points within 0.3 m of the map's markings of their class; 50-98 %
of them at the true pose). So every accepted match is asked whether its frame's marking points
lie on the map's markings.

Two relaxations are options, off by default: asking only where the paint lies, not which class
the model gave it (`any_class`), and letting some of the last matches miss (`misses`). Each
gave 4-5 % more ok frames on three sets of drives and more wrong ones on a fourth (held-out
seeds 441-443: 88 -> 109 and -> 114 violation frames; docs/RESULTS.md).

Lane lines run along the road and fit at any along-road offset; a frame's stop lines, crosswalks
and ground signs do not. A match whose frame sees one of those where the map has one nearby,
but not under it, is misplaced along the road whatever its lane lines say (held-out town:3
s461: 0.9-2.7 m behind for 150 frames, its lane points fitting 0.7-1.0, a stop line's 1764
points 0.00, a sign's 2362 points 0.00; 1.00 and 0.96 at the true pose)."""

from collections import deque

import numpy as np

from common.classes import MARKINGS, Cls
from common.config import LocalizerConfig
from common.geometry import transform_points_2d
from services.localizer.init import class_distances, fine_overlap
from services.localizer.map_cache import class_slots

# markings that pin the position along the road (lane lines fit anywhere along it)
ALONG_ROAD_CLASSES = (Cls.STOP_LINE, Cls.CROSSWALK, Cls.GROUND_SIGN)


def paint_overlap(points_v: np.ndarray, classes: np.ndarray, pose: np.ndarray, cache,
                  tol_m: float, any_class: bool = False) -> float:
    """Share of the marking points (vehicle frame) within tol_m of a map cell of their class
    (init.fine_overlap), or with any_class of any marking class, at pose (0 without points)."""
    if not any_class:
        return fine_overlap(points_v, class_slots(classes), pose, cache, tol_m=tol_m)
    if not len(points_v):
        return 0.0
    world = transform_points_2d(pose, np.asarray(points_v, float))
    on_paint = np.zeros(len(world), bool)
    for cls in MARKINGS:
        nearest, valid = cache.nearest(world, class_slots(np.full(len(world), cls)))
        on_paint |= valid & (np.hypot(*(world - nearest).T) < tol_m)
    return float(on_paint.mean())


def misplaced_classes(points_v: np.ndarray, classes: np.ndarray, pose: np.ndarray, cache,
                      tol_m: float, min_fit: float, min_points: int, reach_m: float) -> list:
    """The along-road classes (ALONG_ROAD_CLASSES) of which the frame has min_points or more,
    the map has a marking within reach_m of most of them, and fewer than min_fit lie within
    tol_m of it at pose. Paint the map lacks (unmapped, or imagined by the model) is no
    evidence either way: it has nothing of its class within reach."""
    classes = np.asarray(classes)
    out = []
    for cls in ALONG_ROAD_CLASSES:
        sel = classes == cls
        if min_points <= 0 or sel.sum() < min_points:
            continue
        d = class_distances(np.asarray(points_v, float)[sel], class_slots(classes[sel]), pose,
                            cache)
        if np.mean(d < reach_m) >= 0.5 and np.mean(d < tol_m) < min_fit:
            out.append(Cls(cls).name.lower())
    return out


def balanced_overlap(points_v: np.ndarray, classes: np.ndarray, pose: np.ndarray, cache,
                     tol_m: float, min_points: int) -> float:
    """The mean over the marking classes with min_points or more points (else over all of
    them) of each class's share within tol_m of the map's: a stop line weighs as much as the
    lane lines that outnumber it ten to one."""
    classes = np.asarray(classes)
    present = [c for c in MARKINGS if (classes == c).sum() >= max(min_points, 1)]
    if not present:
        return paint_overlap(points_v, classes, pose, cache, tol_m)
    return float(np.mean([paint_overlap(points_v[classes == c], classes[classes == c], pose,
                                        cache, tol_m) for c in present]))


class PaintCheck:
    def __init__(
        self,
        min_fit: float = LocalizerConfig.integrity_min_paint_fit,
        tol_m: float = LocalizerConfig.integrity_paint_fit_tol_m,
        misses: int = LocalizerConfig.integrity_paint_misses,
        window: int = LocalizerConfig.settle_frames,
        any_class: bool = LocalizerConfig.integrity_paint_any_class,
        lost_matches: int = LocalizerConfig.paint_lost_matches,
        lost_fit: float = LocalizerConfig.paint_lost_fit,
        relocate_margin: float = LocalizerConfig.paint_relocate_margin,
        misplaced_min_points: int = LocalizerConfig.paint_misplaced_min_points,
        misplaced_reach_m: float = LocalizerConfig.paint_misplaced_reach_m,
        fuse_min_fit: float = LocalizerConfig.paint_fuse_min_fit,
    ):
        """min_fit: the share of a frame's marking points that must lie within tol_m of the
        map's markings (0: off); misses: how many of the last `window` matches may fall short,
        the latest never; any_class: a marking of any class will do; lost_matches, lost_fit:
        the filter is lost when fewer than lost_fit of the last lost_matches fitted (0: never);
        relocate_margin: by how much more of its paint a pose found then must fit the map's;
        misplaced_min_points, misplaced_reach_m: misplaced_classes (0 points: off), a miss,
        and a search along the road (`misplaced`); fuse_min_fit: the share of its frame's paint
        a match must leave on the map's to be fused at all (0: off; the Localizer asks)."""
        self.min_fit, self.tol_m, self.misses, self.any_class = min_fit, tol_m, misses, any_class
        # whether each of the last matches fitted; before the first, as if they had
        self.fitted: deque = deque([True] * window, maxlen=window)
        self.lost_fit, self.relocate_margin = lost_fit, relocate_margin
        self.since_start: deque = deque(maxlen=max(lost_matches, 1))  # ... since the (re)start
        self.misplaced_min_points, self.misplaced_reach_m = misplaced_min_points, misplaced_reach_m
        self.misplaced: list = []  # the latest match's misplaced_classes
        self.fuse_min_fit = fuse_min_fit

    @classmethod
    def from_config(cls, lc: LocalizerConfig) -> "PaintCheck":
        return cls(lc.integrity_min_paint_fit, lc.integrity_paint_fit_tol_m,
                   lc.integrity_paint_misses, lc.settle_frames, lc.integrity_paint_any_class,
                   lc.paint_lost_matches, lc.paint_lost_fit, lc.paint_relocate_margin,
                   lc.paint_misplaced_min_points, lc.paint_misplaced_reach_m,
                   lc.paint_fuse_min_fit)

    def share(self, paint_v: np.ndarray, classes: np.ndarray, pose: np.ndarray, cache) -> float:
        """How much of the paint fits the map's at pose, as this check measures it."""
        return paint_overlap(paint_v, classes, pose, cache, self.tol_m, self.any_class)

    def balanced_share(self, paint_v: np.ndarray, classes: np.ndarray, pose: np.ndarray,
                       cache) -> float:
        """... class by class (balanced_overlap): where a misplaced stop line is the evidence."""
        return balanced_overlap(paint_v, classes, pose, cache, self.tol_m,
                                self.misplaced_min_points)

    def note(self, paint_v: np.ndarray, classes: np.ndarray, pose: np.ndarray, cache,
             share: float | None = None) -> None:
        """A match at pose of a frame whose marking points are paint_v (classes); `share`:
        their share on the map's, if already measured (self.share)."""
        if self.min_fit > 0:
            self.misplaced = misplaced_classes(paint_v, classes, pose, cache, self.tol_m,
                                               self.min_fit, self.misplaced_min_points,
                                               self.misplaced_reach_m)
            if share is None:
                share = self.share(paint_v, classes, pose, cache)
            fitted = share >= self.min_fit and not self.misplaced
            self.fitted.append(fitted)
            self.since_start.append(fitted)

    def restart(self) -> None:
        """The filter starts again: what the lost test counts begins anew."""
        self.since_start.clear()

    @property
    def lost(self) -> bool:
        """A run of matches whose paint mostly misses the map's: not a frame of imagined paint
        now and then (4-12 % of a healthy drive's matches) but a pose off the paint, which the
        flag alone would leave there (held-out town s443: 3-6 m off for 100 s, ok now and then
        when a frame's paint happened to fit)."""
        full = len(self.since_start) == self.since_start.maxlen
        return full and self.lost_fit > 0 and np.mean(self.since_start) < self.lost_fit

    @property
    def trusted(self) -> bool:
        return self.fitted[-1] and self.fitted.count(False) <= self.misses
