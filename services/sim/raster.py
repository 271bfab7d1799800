"""Fast label rasters of a World: a bounding-box index over its polygons and a cache of
0.1 m tiles, stitched into a world-frame window around the car. Row = north, as World.rasterize."""

import cv2
import numpy as np

from common.classes import Cls
from common.grid import CELL_M, TILE_CELLS
from common.world import SUBPIXEL_BITS, World

DRAW_ORDER = (Cls.ROAD, Cls.LANE_LINE, Cls.STOP_LINE, Cls.CROSSWALK, Cls.GROUND_SIGN)


class MarkingIndex:
    """World polygons with their bounding boxes, rasterized per window in class order.

    Same result as World.rasterize, but the polygons of a window are found with one vectorized
    bounding-box test instead of a Python scan of every marking."""

    def __init__(self, world: World):
        self.polys = [m.polygon_xy_m for m in world.markings]
        self.cls = np.array([int(m.cls) for m in world.markings], np.uint8)
        self.lo = np.array([p.min(axis=0) for p in self.polys]).reshape(-1, 2)
        self.hi = np.array([p.max(axis=0) for p in self.polys]).reshape(-1, 2)
        rank = {int(c): k for k, c in enumerate(DRAW_ORDER)}
        self.order = np.array([rank.get(int(c), 0) for c in self.cls])

    def rasterize(self, x0_m: float, y0_m: float, rows: int, cols: int, cell_m: float = CELL_M):
        raster = np.zeros((rows, cols), np.uint8)
        x1, y1 = x0_m + cols * cell_m, y0_m + rows * cell_m
        hit = np.flatnonzero(
            (self.hi[:, 0] >= x0_m)
            & (self.lo[:, 0] <= x1)
            & (self.hi[:, 1] >= y0_m)
            & (self.lo[:, 1] <= y1)
        )
        scale = (1 << SUBPIXEL_BITS) / cell_m
        half = (1 << SUBPIXEL_BITS) * 0.5
        for i in hit[np.argsort(self.order[hit], kind="stable")]:
            q = np.round((self.polys[i] - [x0_m, y0_m]) * scale - half).astype(np.int32)
            cv2.fillPoly(raster, [q], int(self.cls[i]), lineType=cv2.LINE_8, shift=SUBPIXEL_BITS)
        return raster


class TileCache:
    """Label tiles (TILE_CELLS square at cell_m) on a global tile grid, rasterized on demand,
    and stitched windows of (2k+1)^2 tiles around a point."""

    def __init__(
        self, world: World, radius_tiles: int = 2, max_tiles: int = 400, cell_m: float = CELL_M
    ):
        self.index = MarkingIndex(world)
        self.cell_m = cell_m
        self.k = radius_tiles
        self.max_tiles = max_tiles
        self.tiles: dict[tuple[int, int], np.ndarray] = {}
        self._window_key = None
        self._window = None

    def tile(self, tx: int, ty: int) -> np.ndarray:
        key = (tx, ty)
        if key not in self.tiles:
            if len(self.tiles) >= self.max_tiles:
                self.tiles.pop(next(iter(self.tiles)))
            size = TILE_CELLS * self.cell_m
            self.tiles[key] = self.index.rasterize(
                tx * size, ty * size, TILE_CELLS, TILE_CELLS, self.cell_m
            )
        return self.tiles[key]

    def window(self, x_m: float, y_m: float):
        """(raster, x0, y0): the tiles around the tile holding (x, y); cached while in that tile."""
        size = TILE_CELLS * self.cell_m
        tx, ty = int(np.floor(x_m / size)), int(np.floor(y_m / size))
        if self._window_key != (tx, ty):
            n = 2 * self.k + 1
            out = np.empty((n * TILE_CELLS, n * TILE_CELLS), np.uint8)
            for j in range(n):
                for i in range(n):
                    out[
                        j * TILE_CELLS : (j + 1) * TILE_CELLS, i * TILE_CELLS : (i + 1) * TILE_CELLS
                    ] = self.tile(tx - self.k + i, ty - self.k + j)
            self._window_key = (tx, ty)
            self._window = (out, (tx - self.k) * size, (ty - self.k) * size)
        return self._window
