"""The vector world model of road-surface paint, with ground truth for every claim.

A World is a list of filled polygons in the local ENU frame (metres), each with a class: road
surface first, paint on top (dashes, zebra stripes and arrow glyphs are individual polygons).
It also carries lane centre lines for routing, GNSS-blocked zones, and its km of road (each road's
centre line counted once). Sources (procedural town, Lanelet2, Argoverse 2) build Worlds;
everything downstream only sees this model."""

from dataclasses import dataclass, field

import cv2
import numpy as np

from common.classes import Cls, colorize
from common.grid import CELL_M

SUBPIXEL_BITS = 4  # cv2.fillPoly fixed-point: 1/16 cell


@dataclass
class Marking:
    cls: Cls
    polygon_xy_m: np.ndarray  # (N, 2) closed implicitly
    kind: str = ""  # e.g. "solid", "dashed", "double", "zebra", "arrow_left", "text"


@dataclass
class World:
    name: str
    markings: list[Marking]  # includes Cls.ROAD polygons
    routes: list[np.ndarray] = field(default_factory=list)  # lane centre polylines (N, 2)
    gnss_blocked: list[np.ndarray] = field(default_factory=list)  # polygons where GNSS is lost
    km_of_road: float = 0.0
    origin_latlon: tuple[float, float] = (0.0, 0.0)

    def bounds(self, margin_m: float = 0.0) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of all markings."""
        pts = np.concatenate([m.polygon_xy_m for m in self.markings])
        lo, hi = pts.min(axis=0) - margin_m, pts.max(axis=0) + margin_m
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    def rasterize(
        self, x0_m: float, y0_m: float, rows: int, cols: int, cell_m: float = CELL_M
    ) -> np.ndarray:
        """Ground-truth labels of the window whose south-west corner is (x0, y0).

        raster[r, c] is the class at the cell centre (x0 + (c + .5) cell, y0 + (r + .5) cell);
        row grows north. Road is drawn first, then paint in class order."""
        raster = np.zeros((rows, cols), dtype=np.uint8)
        scale = (1 << SUBPIXEL_BITS) / cell_m
        x1, y1 = x0_m + cols * cell_m, y0_m + rows * cell_m
        for cls in (Cls.ROAD, Cls.LANE_LINE, Cls.STOP_LINE, Cls.CROSSWALK, Cls.GROUND_SIGN):
            polys = []
            for m in self.markings:
                if m.cls != cls:
                    continue
                p = m.polygon_xy_m
                lo, hi = p.min(axis=0), p.max(axis=0)
                if hi[0] < x0_m or lo[0] > x1 or hi[1] < y0_m or lo[1] > y1:
                    continue
                # cell centres sample the polygon: shift by half a cell
                q = (p - [x0_m, y0_m]) * scale - (1 << SUBPIXEL_BITS) * 0.5
                polys.append(np.round(q).astype(np.int32))
            # one call per polygon: a single fillPoly call fills overlaps even-odd (holes)
            for poly in polys:
                cv2.fillPoly(raster, [poly], int(cls), lineType=cv2.LINE_8, shift=SUBPIXEL_BITS)
        return raster

    def rasterize_all(self, margin_m: float = 2.0, cell_m: float = CELL_M):
        """Whole world -> (raster, x0, y0)."""
        x0, y0, x1, y1 = self.bounds(margin_m)
        x0, y0 = np.floor(x0 / cell_m) * cell_m, np.floor(y0 / cell_m) * cell_m
        rows, cols = int(np.ceil((y1 - y0) / cell_m)), int(np.ceil((x1 - x0) / cell_m))
        return self.rasterize(x0, y0, rows, cols, cell_m), x0, y0

    def gnss_blocked_at(self, points_xy_m: np.ndarray) -> np.ndarray:
        """Boolean (N,) for points inside any GNSS-blocked zone."""
        out = np.zeros(len(points_xy_m), dtype=bool)
        for zone in self.gnss_blocked:
            contour = zone.astype(np.float32).reshape(-1, 1, 2)
            for i, (x, y) in enumerate(points_xy_m):
                if not out[i] and cv2.pointPolygonTest(contour, (float(x), float(y)), False) >= 0:
                    out[i] = True
        return out


def render_png(labels: np.ndarray, path: str, max_side_px: int = 4000) -> None:
    """Save a label raster (row = north) in the paper's colours, north up."""
    rgb = colorize(labels[::-1])
    scale = min(1.0, max_side_px / max(rgb.shape[:2]))
    if scale < 1.0:
        # keep thin paint visible when shrinking: max-pool markings over road
        k = int(np.ceil(1.0 / scale))
        h, w = labels.shape[0] // k * k, labels.shape[1] // k * k
        pooled = labels[::-1][:h, :w].reshape(h // k, k, w // k, k).max(axis=(1, 3))
        rgb = colorize(pooled)
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
