"""Local map for matching: decoded tile label rasters -> per-class nearest-map-point lookups.

Each cached tile (512 x 512 cells of 0.1 m, row north, col east) gets, per matched class, the
offset in cells from every cell to the nearest map cell of that class (cv2.distanceTransform
WithLabels), computed once on the tile plus a margin borrowed from cached neighbours so matches
cross tile borders. Offsets are int8 (|offset| <= 12.7 m; farther = no match), so a tile costs
about 0.5 MB per class. For the sub-cell refinement of a match, each class also gets a likelihood
field: its mask blurred by a Gaussian (float16, 0.5 MB per class), sampled bilinearly with its
gradient, whose ridge is the marking's centre. Tiles live in an LRU bounded by `capacity`."""

import logging
import math
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from common.classes import Cls
from common.config import LocalizerConfig
from common.grid import CELL_M, TILE_CELLS, TileId, global_cells, split_global_cells

logger = logging.getLogger(__name__)

MATCH_CLASSES = (Cls.ROAD, Cls.LANE_LINE, Cls.STOP_LINE, Cls.CROSSWALK, Cls.GROUND_SIGN)
NO_MATCH = -128  # int8 sentinel: no map cell of the class within reach
MAX_OFFSET_CELLS = 127


@dataclass
class TileFields:
    """Nearest same-class map cell for every cell of one tile: offsets (C, 2, 512, 512) int8."""

    tile: TileId
    version: int
    offsets: np.ndarray  # [class slot, (d_row, d_col), row, col]
    present: np.ndarray  # bool [class slot]: the class occurs in or near this tile
    smooth: np.ndarray | None = None  # float16 [class slot, row, col]: blurred class mask


def likelihood_field(mask_hw: np.ndarray, sigma_cells: float) -> np.ndarray:
    """Boolean mask -> float32 mask blurred by a Gaussian of sigma_cells (values in [0, 1])."""
    k = int(2 * math.ceil(3.0 * sigma_cells) + 1)
    return cv2.GaussianBlur(mask_hw.astype(np.float32), (k, k), sigma_cells)


def nearest_offsets(mask_hw: np.ndarray) -> np.ndarray:
    """Boolean mask (H, W) -> int8 (2, H, W) offsets (d_row, d_col) to the nearest True cell."""
    h, w = mask_hw.shape
    out = np.full((2, h, w), NO_MATCH, dtype=np.int8)
    if not mask_hw.any():
        return out
    src = np.where(mask_hw, 0, 1).astype(np.uint8)
    _, labels = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    zr, zc = np.nonzero(src == 0)  # label k (1-based) = k-th zero pixel in scan order
    idx = labels - 1
    d_row = zr[idx].astype(np.int32) - np.arange(h, dtype=np.int32)[:, None]
    d_col = zc[idx].astype(np.int32) - np.arange(w, dtype=np.int32)[None, :]
    far = (np.abs(d_row) > MAX_OFFSET_CELLS) | (np.abs(d_col) > MAX_OFFSET_CELLS)
    out[0] = np.where(far, NO_MATCH, d_row)
    out[1] = np.where(far, NO_MATCH, d_col)
    return out


class TileCache:
    """LRU of decoded tiles (labels + version) and their lazily built matching fields."""

    def __init__(
        self,
        capacity: int = LocalizerConfig.cache_tiles,
        margin_cells: int = 30,
        field_sigma_cells: float = 1.5,
        line_grow_cells: int = LocalizerConfig.field_line_grow_cells,
    ):
        """line_grow_cells: the lane-line mask is dilated by this square kernel before it is
        blurred into the likelihood field (the nearest-cell offsets keep the exact mask). A
        0.15 m line blurred by 0.15 m is a sharp ridge the refinement overshoots and that
        rewards points on the line's crest only; widened to 0.55 m it is a plateau with soft
        flanks, still centred on the line. 1: not widened."""
        self.capacity = int(capacity)
        self.margin = int(margin_cells)
        self.field_sigma_cells = float(field_sigma_cells)
        self.line_grow_cells = int(line_grow_cells)
        self._labels: OrderedDict[TileId, tuple[int, np.ndarray]] = OrderedDict()
        self._fields: dict[TileId, TileFields] = {}
        self.fields_built = 0

    # -- tiles ------------------------------------------------------------------------------

    def put(self, tile: TileId, version: int, labels: np.ndarray) -> None:
        """Insert or replace a decoded tile; fields of it and its neighbours are rebuilt lazily."""
        tile = (int(tile[0]), int(tile[1]))
        self._labels[tile] = (int(version), np.asarray(labels, dtype=np.uint8))
        self._labels.move_to_end(tile)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                self._fields.pop((tile[0] + dx, tile[1] + dy), None)
        while len(self._labels) > self.capacity:
            old, _ = self._labels.popitem(last=False)
            self._fields.pop(old, None)

    def version(self, tile: TileId) -> int | None:
        entry = self._labels.get((int(tile[0]), int(tile[1])))
        return None if entry is None else entry[0]

    def labels(self, tile: TileId) -> np.ndarray | None:
        entry = self._labels.get((int(tile[0]), int(tile[1])))
        return None if entry is None else entry[1]

    def tiles(self) -> list[TileId]:
        return list(self._labels)

    def __contains__(self, tile) -> bool:
        return (int(tile[0]), int(tile[1])) in self._labels

    def touch(self, tile: TileId) -> None:
        if tile in self._labels:
            self._labels.move_to_end(tile)

    # -- fields -----------------------------------------------------------------------------

    def fields(self, tile: TileId) -> TileFields | None:
        """Matching fields of a cached tile (built on first use), or None if it is not cached."""
        if tile not in self._labels:
            return None
        f = self._fields.get(tile)
        if f is None:
            f = self._build_fields(tile)
            self._fields[tile] = f
            self.fields_built += 1
        return f

    def _window(self, tile: TileId) -> np.ndarray:
        """The tile's labels with a margin of neighbour cells (zeros where not cached)."""
        m, n = self.margin, TILE_CELLS
        win = np.zeros((n + 2 * m, n + 2 * m), dtype=np.uint8)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                lab = self.labels((tile[0] + dx, tile[1] + dy))
                if lab is None:
                    continue
                # destination window rows/cols for this neighbour, clipped to the margin
                r0, c0 = m + dy * n, m + dx * n
                rs, re = max(r0, 0), min(r0 + n, n + 2 * m)
                cs, ce = max(c0, 0), min(c0 + n, n + 2 * m)
                win[rs:re, cs:ce] = lab[rs - r0 : re - r0, cs - c0 : ce - c0]
        return win

    def _build_fields(self, tile: TileId) -> TileFields:
        win = self._window(tile)
        m, n = self.margin, TILE_CELLS
        offsets = np.full((len(MATCH_CLASSES), 2, n, n), NO_MATCH, dtype=np.int8)
        smooth = np.zeros((len(MATCH_CLASSES), n, n), dtype=np.float16)
        present = np.zeros(len(MATCH_CLASSES), dtype=bool)
        for slot, cls in enumerate(MATCH_CLASSES):
            mask = win == cls
            if not mask.any():
                continue
            present[slot] = True
            offsets[slot] = nearest_offsets(mask)[:, m : m + n, m : m + n]
            if cls == Cls.LANE_LINE and self.line_grow_cells > 1:
                k = np.ones((self.line_grow_cells, self.line_grow_cells), np.uint8)
                mask = cv2.dilate(mask.astype(np.uint8), k) > 0  # the field only: see __init__
            smooth[slot] = likelihood_field(mask, self.field_sigma_cells)[m : m + n, m : m + n]
        return TileFields(tile, self.version(tile), offsets, present, smooth)

    # -- queries ----------------------------------------------------------------------------

    def nearest(self, points_xy_m: np.ndarray, slots: np.ndarray):
        """World points (N, 2), class slots (N,) -> (nearest map cell centres (N, 2), valid (N,)).

        `slots` index MATCH_CLASSES (see `class_slots`); invalid where no tile or no such class."""
        pts = np.asarray(points_xy_m, dtype=np.float64)
        nearest = np.zeros_like(pts)
        valid = np.zeros(len(pts), dtype=bool)
        if len(pts) == 0:
            return nearest, valid
        gxy = global_cells(pts)
        for tile, sel, rows, cols in _by_tile(gxy):
            f = self.fields(tile)
            if f is None:
                continue
            s = slots[sel]
            d_row = f.offsets[s, 0, rows, cols].astype(np.int64)
            d_col = f.offsets[s, 1, rows, cols].astype(np.int64)
            ok = (d_row != NO_MATCH) & (s >= 0)
            nearest[sel, 0] = (gxy[sel, 0] + d_col + 0.5) * CELL_M
            nearest[sel, 1] = (gxy[sel, 1] + d_row + 0.5) * CELL_M
            valid[sel] = ok
        return nearest, valid

    def field(self, points_xy_m: np.ndarray, slots: np.ndarray):
        """Likelihood field of each point's class at world points: (value (N,), gradient (N, 2)
        per metre, valid (N,)), bilinear between cell centres; invalid where a corner's tile is
        not cached or the slot is -1."""
        pts = np.asarray(points_xy_m, dtype=np.float64)
        slots = np.asarray(slots, dtype=np.int64)
        u = pts / CELL_M - 0.5  # cell-centre coordinates
        base = np.floor(u).astype(np.int64)
        a, b = (u - base).T
        corner = {}
        valid = slots >= 0
        for dx in (0, 1):
            for dy in (0, 1):
                v, ok = self._sample(base + (dx, dy), slots)
                corner[dx, dy] = v
                valid &= ok
        f00, f10, f01, f11 = corner[0, 0], corner[1, 0], corner[0, 1], corner[1, 1]
        value = (1 - a) * (1 - b) * f00 + a * (1 - b) * f10 + (1 - a) * b * f01 + a * b * f11
        grad = (
            np.stack(
                [(1 - b) * (f10 - f00) + b * (f11 - f01), (1 - a) * (f01 - f00) + a * (f11 - f10)],
                axis=1,
            )
            / CELL_M
        )
        return np.where(valid, value, 0.0), np.where(valid[:, None], grad, 0.0), valid

    def _sample(self, gxy: np.ndarray, slots: np.ndarray):
        """Smooth field values at global cells (N, 2) for class slots (N,); (values, cached)."""
        out = np.zeros(len(gxy))
        ok = np.zeros(len(gxy), dtype=bool)
        for tile, sel, rows, cols in _by_tile(gxy):
            f = self.fields(tile)
            if f is None:
                continue
            s = np.maximum(slots[sel], 0)
            out[sel] = f.smooth[s, rows, cols]
            ok[sel] = True
        return out, ok

    def class_at(self, points_xy_m: np.ndarray) -> np.ndarray:
        """Map class at world points (N,) uint8; 0 where no tile is cached."""
        pts = np.asarray(points_xy_m, dtype=np.float64)
        out = np.zeros(len(pts), dtype=np.uint8)
        if len(pts) == 0:
            return out
        for tile, sel, rows, cols in _by_tile(global_cells(pts)):
            lab = self.labels(tile)
            if lab is not None:
                out[sel] = lab[rows, cols]
        return out


def get_tile_cache(lc) -> TileCache:
    """LocalizerConfig -> the car's TileCache (capacity, lane-line field widening)."""
    return TileCache(capacity=lc.cache_tiles, line_grow_cells=lc.field_line_grow_cells)


def _by_tile(gxy: np.ndarray):
    """Global cells (N, 2) grouped by tile: (tile, indices into gxy, rows, cols in the tile)."""
    tiles, flat = split_global_cells(gxy)
    key = tiles[:, 0] * 1_000_003 + tiles[:, 1]
    for k in np.unique(key):
        sel = np.flatnonzero(key == k)
        rows, cols = np.divmod(flat[sel], TILE_CELLS)
        yield (int(tiles[sel[0], 0]), int(tiles[sel[0], 1])), sel, rows, cols


_SLOT_OF_CLASS = np.full(256, -1, dtype=np.int64)
for _slot, _cls in enumerate(MATCH_CLASSES):
    _SLOT_OF_CLASS[int(_cls)] = _slot


def class_slots(classes: np.ndarray) -> np.ndarray:
    """Class ids (N,) -> slots in MATCH_CLASSES (N,), -1 for classes not matched."""
    return _SLOT_OF_CLASS[np.asarray(classes, dtype=np.int64)]
