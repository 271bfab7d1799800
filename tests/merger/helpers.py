"""Synthetic grid patches for merger tests: traversals that see a tile's label raster."""

import cv2
import numpy as np

from common import sparse
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


# the demo camera's visible ROI (common.sparse.roi_of_lookup of services.vehicle.synthetic's
# mapping camera is close to this): what the observation model below and the sparse form share
DEMO_ROI = dict(x_min_dm=48, length_dm=62, width_dm=80, camera_x_dm=18, fov_slope_milli=738,
                pixels_per_frame=82530)


def observed_traversal(
    labels: np.ndarray,
    *,
    traversal: str,
    t_ns: int,
    x_m: float = 22.5,
    tile=(0, 0),
    vehicle: str = "map-0",
    rng=None,
    step_m: float = 0.66,
    frames_per_patch: int = 40,
    stray_rate: float = 0.0,
):
    """A vehicle driving north through a tile along x = x_m (metres from the tile's west
    edge), its camera seeing `labels` (a (512, 512) raster): per frame the ground pixels of
    common.sparse's density model, so a cell's votes are the pixels that landed in it, split
    0.6 / 0.4 between paint and road at a marking's edge; `stray_rate` of the road cells show
    stray paint with a twentieth of their pixels. Returns [(GridPatch, poses (n, 3))] of
    `frames_per_patch` frames each, ids as a vehicle makes them."""
    rng = rng or np.random.default_rng(0)
    roi = sparse.Roi(**DEMO_ROI)
    y = np.arange(-12.0, 51.2, step_m)
    poses = np.stack([np.full(len(y), x_m), y, np.full(len(y), np.pi / 2)], axis=1)
    x0, y0 = tile[0] * 51.2, tile[1] * 51.2
    poses[:, 0] += x0
    poses[:, 1] += y0
    flat = labels.ravel()
    paint = (labels >= 2).astype(np.uint8)
    inner = cv2.erode(paint, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT)
    edge = (paint - inner).ravel() > 0
    stray = (flat == 1) & (rng.random(flat.shape) < stray_rate)
    out = []
    for k, start in enumerate(range(0, len(poses), frames_per_patch)):
        part = poses[start:start + frames_per_patch]
        geometry = sparse.Geometry(roi=roi, n_frames=len(part), key_every=1,
                                   keys=np.round(part / (sparse.POSE_UNIT_M, sparse.POSE_UNIT_M,
                                                         sparse.YAW_UNIT_RAD)).astype(np.int64),
                                   layers=[[] for _ in sparse.LAYERS],
                                   strong_at=np.zeros(0, np.int64), strong_k=np.zeros(0, np.int8))
        field = sparse.evidence_field(geometry, tile)
        cells = np.flatnonzero((field >= 1.0) & (flat > 0)).astype(np.uint32)
        if not len(cells):
            continue
        f = field[cells].astype(np.float64)
        votes = np.zeros((len(cells), NUM_CLASSES), np.uint16)
        cls = flat[cells]
        share = np.where(edge[cells], 0.6, 1.0)
        votes[np.arange(len(cells)), cls] = np.maximum(np.round(f * share), 1)
        votes[edge[cells], 1] = np.round(f[edge[cells]] * 0.4)
        s = stray[cells]
        votes[s, 2] = np.maximum(np.round(f[s] * 0.05), 1)
        votes[s, 1] = 0
        out.append((GridPatch(patch_id=f"{vehicle}.{traversal}.{tile[0]}_{tile[1]}.{k:06d}",
                              vehicle=vehicle, tile=tuple(tile), cells=cells, votes=votes,
                              t_first_ns=t_ns + k, t_last_ns=t_ns + k + 1, traversal=traversal),
                    part))
    return out
