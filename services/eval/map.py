"""The merged map against the world's ground truth: the report's `map` section (per-class
precision and recall, codec fidelity, map size, the map digest), the area the mapping drives
observed, and the repaint check. Pure functions on arrays.

Rasters are world-aligned mosaics of tiles (0.1 m cells, row = north) whose south-west corner is
the south-west corner of the lowest tile; poses are (x, y, yaw) in the world frame."""

import hashlib
import struct

import cv2
import numpy as np

from common.classes import MARKINGS, NAMES, Cls
from common.evaluation import precision_recall
from common.grid import CELL_M, TILE_CELLS, tile_origin_m

# Repaint rule: the map follows when it shows >= 50 % of the new line and <= 20 % of the old one.
FOLLOW_NEW_MIN = 0.5
FOLLOW_OLD_MAX = 0.2


class Mosaic:
    """Tiles pasted into one raster; `origin_m` is its south-west corner, rows grow north."""

    def __init__(self, tiles: list[tuple[int, int]]):
        t = np.array(tiles, np.int64).reshape(-1, 2)
        self.tx0, self.ty0 = (int(v) for v in t.min(axis=0))
        self.ntx, self.nty = (int(v) for v in t.max(axis=0) - t.min(axis=0) + 1)
        self.origin_m = tile_origin_m((self.tx0, self.ty0))
        self.shape = (self.nty * TILE_CELLS, self.ntx * TILE_CELLS)

    def slot(self, tile) -> tuple[slice, slice]:
        r0 = (tile[1] - self.ty0) * TILE_CELLS
        c0 = (tile[0] - self.tx0) * TILE_CELLS
        return slice(r0, r0 + TILE_CELLS), slice(c0, c0 + TILE_CELLS)

    def paste(self, tiles, rasters) -> np.ndarray:
        out = np.zeros(self.shape, np.uint8)
        for tile, raster in zip(tiles, rasters, strict=True):
            out[self.slot(tile)] = raster
        return out

    def to_cells(self, xy_m: np.ndarray) -> np.ndarray:
        """World points (N, 2) -> float (col, row) in the mosaic."""
        return (np.asarray(xy_m, float) - self.origin_m) / CELL_M


def truth_mosaic(world, mosaic: Mosaic, tiles) -> np.ndarray:
    """Ground truth of the held tiles (other cells 0)."""
    return mosaic.paste(tiles, [world.rasterize(*tile_origin_m(t), TILE_CELLS, TILE_CELLS)
                                for t in tiles])


def visible_outline(camera, x_min_m: float, length_m: float, width_m: float) -> np.ndarray:
    """The part of the IPM region of interest the camera sees, as a vehicle-frame polygon (K, 2):
    the convex hull of the IPM table's ground points. Near the car the image is narrower than the
    ROI (the demo's camera: its image's bottom row meets the ground 4.9 m ahead, 2.3 m either
    side, and the full 4 m only from 7.3 m on), so a third of the ROI rectangle is never in view,
    and at a turn its inner corner sweeps paint no frame shows (the rectangle made a town's
    crosswalk recall 0.77 where the camera's view gives 0.97)."""
    from common.camera import build_ipm_lookup

    ipm = build_ipm_lookup(camera, x_min_m=x_min_m, length_m=length_m, width_m=width_m)
    if not len(ipm.ground_xy_m):
        return np.zeros((0, 2))
    hull = cv2.convexHull(np.asarray(ipm.ground_xy_m, np.float32))
    # the hull keeps every pixel along its straight edges: a few corners fill the same cells
    return cv2.approxPolyDP(hull, CELL_M / 4, closed=True)[:, 0, :].astype(float)


def roi_footprint(mosaic: Mosaic, drives) -> np.ndarray:
    """Cells that a vehicle-frame outline (visible_outline) swept along true poses: what could
    be mapped. drives: (poses (N, 3) x, y, yaw; outline (K, 2)) per drive."""
    polys = []
    for poses_xyyaw, outline_v in drives:
        outline_v = np.asarray(outline_v, float)
        if len(outline_v) < 3:
            continue
        poses = np.asarray(poses_xyyaw, float)
        for x, y, yaw in poses[np.all(np.isfinite(poses), axis=1)]:
            c, s = np.cos(yaw), np.sin(yaw)
            world = outline_v @ np.array([[c, s], [-s, c]]) + (x, y)
            polys.append(np.round(mosaic.to_cells(world) * 16).astype(np.int32))
    mask = np.zeros(mosaic.shape, np.uint8)
    if polys:
        cv2.fillPoly(mask, polys, 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


def map_quality(pred: np.ndarray, truth: np.ndarray, observed: np.ndarray) -> dict:
    """Per marking class: precision of the map's cells against the truth, recall of the true
    cells inside the observed area (roi_footprint; 0.1 m tolerance)."""
    truth_seen = np.where(observed, truth, 0)
    out = {}
    for c in MARKINGS:
        precision, _, n_pred, _ = precision_recall(pred, truth, int(c))
        _, recall, _, n_true = precision_recall(pred, truth_seen, int(c))
        out[NAMES[c]] = {"precision": _num(precision), "recall": _num(recall),
                         "cells_map": n_pred, "cells_true_observed": n_true}
    return out


def codec_fidelity(decoded: np.ndarray, raw: np.ndarray) -> dict:
    """Per marking class: precision/recall of the decoded map against the merged (raw) map."""
    out = {}
    for c in MARKINGS:
        p, r, _, _ = precision_recall(decoded, raw, int(c))
        out[NAMES[c]] = {"codec_precision": _num(p), "codec_recall": _num(r)}
    return out


def map_sizes(compressed: list[bytes], raw_tiles: np.ndarray) -> dict:
    """Bytes of the map as contours (ours), as a sparse grid (uint32 cell + uint8 class per
    labelled cell) and as one PNG per tile."""
    png = sum(len(cv2.imencode(".png", r)[1]) for r in raw_tiles)
    return {"compressed_bytes": int(sum(len(b) for b in compressed)),
            "raw_sparse_bytes": int(np.count_nonzero(raw_tiles)) * 5,
            "png_bytes": int(png)}


def map_digest(tiles, raw_tiles) -> str:
    """sha256 over the tiles sorted by id: (tx, ty) as two int64 + the 512x512 label bytes."""
    h = hashlib.sha256()
    for i in sorted(range(len(tiles)), key=lambda k: tuple(tiles[k])):
        h.update(struct.pack("<qq", *tiles[i]))
        h.update(np.ascontiguousarray(raw_tiles[i], np.uint8).tobytes())
    return h.hexdigest()


def km_mapped(drives_xy_m: list[np.ndarray]) -> float:
    """km of road the mapping drives covered, each road counted once (neighbouring lanes and the
    other direction of a road merge), as the simulator counts world.km_of_road."""
    from services.sim.routes import km_of_centrelines

    return float(km_of_centrelines([np.asarray(d, float) for d in drives_xy_m if len(d) > 1]))


# -- repaint ----------------------------------------------------------------------------------


def repaint_masks(old_truth: np.ndarray, new_truth: np.ndarray, observed: np.ndarray):
    """Lane-line cells only the old paint has, and only the new paint has (observed area)."""
    old = (old_truth == Cls.LANE_LINE) & (new_truth != Cls.LANE_LINE) & observed
    new = (new_truth == Cls.LANE_LINE) & (old_truth != Cls.LANE_LINE) & observed
    return old, new


def follow_state(pred: np.ndarray, old_only: np.ndarray, new_only: np.ndarray) -> dict:
    """How much of the new line the map shows (0.1 m tolerance) and how much of the old one."""
    lane = pred == Cls.LANE_LINE
    near = cv2.dilate(lane.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    new_shown = float((near & new_only).sum() / max(1, new_only.sum()))
    old_shown = float((lane & old_only).sum() / max(1, old_only.sum()))
    return {"new_shown": new_shown, "old_shown": old_shown,
            "followed": bool(new_shown >= FOLLOW_NEW_MIN and old_shown <= FOLLOW_OLD_MAX)}


def _num(v):
    return None if v is None or not np.isfinite(v) else float(v)
