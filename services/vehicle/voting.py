"""Sparse 0.1 m voting grid (paper: per-cell statistics of semantic points) and its GridPatches.

Consumes labelled ground points in the world frame (metres); keeps, per global cell and class, a
saturating uint16 count; produces the argmax label raster and, per tile, sparse GridPatches of the
occupied cells. Cells and classes are packed into one int64 key, so every operation is a sort,
`np.unique` or `bincount` over arrays, never a Python loop over points."""

import numpy as np

from common.classes import NUM_CLASSES
from common.grid import CELL_M, global_cells, split_global_cells
from common.messages import GridPatch, patch_id

CLASS_BITS = 3
AXIS_BITS = 24
AXIS_OFFSET = 1 << (AXIS_BITS - 1)  # global cells in [-2^23, 2^23): +-838 km at 0.1 m
COUNT_MAX = np.iinfo(np.uint16).max
CONSOLIDATE_POINTS = 2_000_000  # pending points merged into the sorted store beyond this


def pack_keys(gxy: np.ndarray, classes: np.ndarray) -> np.ndarray:
    """Global cells (N, 2) + classes (N,) -> int64 keys, ordered by (gx, gy, class)."""
    gx = gxy[:, 0].astype(np.int64) + AXIS_OFFSET
    gy = gxy[:, 1].astype(np.int64) + AXIS_OFFSET
    return (((gx << AXIS_BITS) | gy) << CLASS_BITS) | classes.astype(np.int64)


def unpack_keys(keys: np.ndarray):
    """int64 keys -> (global cells (N, 2) int64, classes (N,) uint8)."""
    cls = (keys & ((1 << CLASS_BITS) - 1)).astype(np.uint8)
    cell = keys >> CLASS_BITS
    gy = (cell & ((1 << AXIS_BITS) - 1)) - AXIS_OFFSET
    gx = (cell >> AXIS_BITS) - AXIS_OFFSET
    return np.stack([gx, gy], axis=1), cls


class VotingGrid:
    """Per global cell and class, a saturating uint16 vote count; sparse (occupied cells only)."""

    def __init__(self):
        self._keys = np.zeros(0, np.int64)  # sorted, unique
        self._counts = np.zeros(0, np.uint16)
        self._pending: list[np.ndarray] = []
        self._pending_weights: list[np.ndarray] = []
        self._pending_n = 0
        self.t_first_ns: int | None = None
        self.t_last_ns: int | None = None

    def __len__(self) -> int:
        self._consolidate()
        return len(self._keys)

    def add_points(self, points_xy_m: np.ndarray, classes: np.ndarray, t_ns: int = 0) -> None:
        """One vote per labelled ground point (world frame, metres) for its cell and class."""
        if len(points_xy_m) == 0:
            return
        self._add_keys(pack_keys(global_cells(points_xy_m), classes), None, t_ns)

    def add_presence(self, points_xy_m: np.ndarray, classes: np.ndarray, t_ns: int = 0) -> None:
        """One vote per distinct (cell, class) among the points: counts the calls (frames)
        that saw a class in a cell, however many of their points fell there."""
        if len(points_xy_m) == 0:
            return
        self._add_keys(np.unique(pack_keys(global_cells(points_xy_m), classes)), None, t_ns)

    def drop_unconfirmed(self, seen: "VotingGrid", min_count, first_class: int) -> int:
        """Remove the votes of every (cell, class >= first_class) that `seen` counts fewer than
        `min_count` times (e.g. paint seen in fewer frames than that; one value, or an array of
        one per class); -> keys removed."""
        keys, _ = self.items()
        classes = keys & ((1 << CLASS_BITS) - 1)
        target = classes >= first_class
        if not target.any():
            return 0
        seen_keys, seen_counts = seen.items()
        wanted = keys[target]
        count = np.zeros(len(wanted), np.int64)
        if len(seen_keys):
            at = np.minimum(np.searchsorted(seen_keys, wanted), len(seen_keys) - 1)
            hit = seen_keys[at] == wanted
            count[hit] = seen_counts[at[hit]]
        need = np.asarray(min_count)
        need = need[classes[target]] if need.ndim else need
        drop = np.zeros(len(keys), bool)
        drop[np.flatnonzero(target)[count < need]] = True
        self._keys, self._counts = self._keys[~drop], self._counts[~drop]
        return int(drop.sum())

    def drop_class_where(self, cls: int, seen: "VotingGrid", other: int, min_count: int) -> int:
        """Remove the votes for class `cls` of every cell that `seen` counts `other` at least
        `min_count` times in (e.g. a ground sign on a cell that frames saw as lane line);
        -> keys removed."""
        keys, _ = self.items()
        hit = np.flatnonzero((keys & ((1 << CLASS_BITS) - 1)) == cls)
        seen_keys, seen_counts = seen.items()
        if not len(hit) or not len(seen_keys):
            return 0
        wanted = (keys[hit] >> CLASS_BITS << CLASS_BITS) | other
        at = np.minimum(np.searchsorted(seen_keys, wanted), len(seen_keys) - 1)
        drop = hit[(seen_keys[at] == wanted) & (seen_counts[at] >= min_count)]
        keep = np.ones(len(keys), bool)
        keep[drop] = False
        self._keys, self._counts = self._keys[keep], self._counts[keep]
        return len(drop)

    def merge(self, other: "VotingGrid") -> None:
        """Add another grid's votes to this one (e.g. a sealed delta into the whole local map)."""
        keys, counts = other.items()
        if len(keys):
            self._add_keys(keys, counts.astype(np.int64), other.t_first_ns, other.t_last_ns)

    def items(self) -> tuple[np.ndarray, np.ndarray]:
        """(sorted int64 keys, uint16 counts) of every non-zero (cell, class)."""
        self._consolidate()
        return self._keys, self._counts

    def clear(self) -> None:
        self.__init__()

    def label_raster(self, x0_m: float, y0_m: float, rows: int, cols: int) -> np.ndarray:
        """Argmax label per cell of the window with south-west corner (x0, y0); 0 where empty."""
        gxy, cls, votes = self._cell_votes()
        col = gxy[:, 0] - int(round(x0_m / CELL_M))
        row = gxy[:, 1] - int(round(y0_m / CELL_M))
        inside = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
        raster = np.zeros((rows, cols), np.uint8)
        raster[row[inside], col[inside]] = np.argmax(votes[inside], axis=1).astype(np.uint8)
        return raster

    def bounds_m(self) -> tuple[float, float, float, float] | None:
        keys, _ = self.items()
        if not len(keys):
            return None
        gxy, _ = unpack_keys(keys)
        lo, hi = gxy.min(axis=0), gxy.max(axis=0) + 1
        return lo[0] * CELL_M, lo[1] * CELL_M, hi[0] * CELL_M, hi[1] * CELL_M

    def patches(self, vehicle: str, traversal: str, seq: int) -> list[GridPatch]:
        """One GridPatch per tile: occupied cells (sorted unique flat index) and their votes."""
        gxy, _, votes = self._cell_votes()
        if not len(gxy):
            return []
        tiles, flat = split_global_cells(gxy)
        order = np.lexsort((flat, tiles[:, 1], tiles[:, 0]))
        tiles, flat, votes = tiles[order], flat[order], votes[order]
        starts = np.flatnonzero(np.any(np.diff(tiles, axis=0) != 0, axis=1)) + 1
        out = []
        for a, b in zip(np.r_[0, starts], np.r_[starts, len(flat)], strict=True):
            tile = (int(tiles[a, 0]), int(tiles[a, 1]))
            out.append(
                GridPatch(
                    patch_id=patch_id(vehicle, traversal, tile, seq),
                    vehicle=vehicle,
                    tile=tile,
                    cells=flat[a:b].astype(np.uint32),
                    votes=votes[a:b],
                    traversal=traversal,
                    t_first_ns=int(self.t_first_ns or 0),
                    t_last_ns=int(self.t_last_ns or 0),
                )
            )
        return out

    # -- internals ---------------------------------------------------------------------------

    def _add_keys(self, keys, weights, t_first_ns, t_last_ns=None) -> None:
        self._pending.append(keys)
        self._pending_weights.append(np.ones(len(keys), np.int64) if weights is None else weights)
        self._pending_n += len(keys)
        t_last_ns = t_first_ns if t_last_ns is None else t_last_ns
        if t_first_ns is not None:
            self.t_first_ns = (
                t_first_ns if self.t_first_ns is None else min(self.t_first_ns, t_first_ns)
            )
            self.t_last_ns = t_last_ns if self.t_last_ns is None else max(self.t_last_ns, t_last_ns)
        if self._pending_n > CONSOLIDATE_POINTS:
            self._consolidate()

    def _consolidate(self) -> None:
        if not self._pending:
            return
        keys = np.concatenate([self._keys, *self._pending])
        weights = np.concatenate([self._counts.astype(np.int64), *self._pending_weights])
        self._keys, inverse = np.unique(keys, return_inverse=True)
        sums = np.bincount(inverse, weights=weights, minlength=len(self._keys))
        self._counts = np.minimum(sums, COUNT_MAX).astype(np.uint16)
        self._pending, self._pending_weights, self._pending_n = [], [], 0

    def _cell_votes(self):
        """(unique global cells (M, 2), argmax class (M,), votes (M, NUM_CLASSES) uint16)."""
        keys, counts = self.items()
        cells = keys >> CLASS_BITS
        ucells, inverse = np.unique(cells, return_inverse=True)
        votes = np.zeros((len(ucells), NUM_CLASSES), np.uint16)
        votes[inverse, (keys & ((1 << CLASS_BITS) - 1)).astype(np.int64)] = counts
        gxy, _ = unpack_keys(ucells << CLASS_BITS)
        return gxy, np.argmax(votes, axis=1).astype(np.uint8), votes


def raster_window(grid: VotingGrid, margin_m: float = 2.0):
    """The whole local map as (labels, x0_m, y0_m), aligned to the 0.1 m global cells."""
    b = grid.bounds_m()
    if b is None:
        return np.zeros((0, 0), np.uint8), 0.0, 0.0
    x0 = np.floor((b[0] - margin_m) / CELL_M) * CELL_M
    y0 = np.floor((b[1] - margin_m) / CELL_M) * CELL_M
    cols = int(round((b[2] + margin_m - x0) / CELL_M))
    rows = int(round((b[3] + margin_m - y0) / CELL_M))
    return grid.label_raster(x0, y0, rows, cols), float(x0), float(y0)
