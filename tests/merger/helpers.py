"""Synthetic grid patches for merger tests: traversals that see a tile's label raster."""

import numpy as np

from common.classes import NUM_CLASSES
from common.messages import GridPatch


def patches_from_labels(
    labels: np.ndarray,
    *,
    tile=(0, 0),
    traversal: str,
    t_ns: int,
    vehicle: str = "map-0",
    rng=None,
    votes_per_cell: int = 6,
    flip_rate: float = 0.0,
    n_patches: int = 2,
    seen_nothing: np.ndarray | None = None,
) -> list[GridPatch]:
    """One traversal of a tile: every labelled cell gets `votes_per_cell` votes for its class
    (a fraction `flip_rate` of the votes go to a random other class), split into patches. Cells
    labelled 0 get no votes (as vehicles send them), except where the mask `seen_nothing` is
    set: those get explicit class-0 votes (ground seen as nothing)."""
    rng = rng or np.random.default_rng(0)
    flat = labels.ravel()
    nothing = np.zeros(flat.shape, bool) if seen_nothing is None else seen_nothing.ravel()
    cells = np.flatnonzero((flat > 0) | nothing).astype(np.uint32)
    votes = np.zeros((len(cells), NUM_CLASSES), np.uint16)
    votes[np.arange(len(cells)), flat[cells]] = votes_per_cell
    if flip_rate:
        noisy = rng.random(len(cells)) < flip_rate
        other = rng.integers(1, NUM_CLASSES, noisy.sum())
        votes[np.flatnonzero(noisy), other] += votes_per_cell
        votes[np.flatnonzero(noisy), flat[cells[noisy]]] = votes_per_cell // 2
    out = []
    for k, part in enumerate(np.array_split(np.arange(len(cells)), n_patches)):
        out.append(
            GridPatch(
                patch_id=f"{vehicle}/{traversal}/{tile[0]}/{tile[1]}/{k}",
                vehicle=vehicle,
                tile=tuple(tile),
                cells=cells[part],
                votes=votes[part],
                t_first_ns=t_ns + k,
                t_last_ns=t_ns + k + 1,
                traversal=traversal,
            )
        )
    return out


def lane_tile(offset_cells: int = 0) -> np.ndarray:
    """A road with a lane line at column 200 + offset, a stop line and a crosswalk."""
    labels = np.zeros((512, 512), np.uint8)
    labels[:, 150:300] = 1
    labels[:, 200 + offset_cells : 202 + offset_cells] = 2
    labels[300:303, 160:240] = 3
    for k in range(6):
        labels[350:390, 240 + 9 * k : 245 + 9 * k] = 4
    return labels


def island_tile(offset_cells: int = 0, island=(196, 206)) -> np.ndarray:
    """lane_tile whose lane line (at column 200 + offset) may sit beside a narrow strip of
    ground that is nothing (class 0, columns island[0]:island[1], e.g. a painted-over island)."""
    labels = lane_tile(offset_cells)
    labels[:, island[0] : island[1]] = 0
    labels[:, 200 + offset_cells : 202 + offset_cells] = 2
    return labels
