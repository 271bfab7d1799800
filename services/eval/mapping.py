"""Mapping accuracy against ground truth: a mapping vehicle's poses and local map, and the
report's `mapping` section over the fleet.

Consumes what `roadmap vehicle` wrote in its STATE (services/vehicle/outputs.py: poses.npz, the
optimized pose of every committed frame with its GNSS coverage and raw odometry; local_map.npz)
and the drive log's true poses (`frame_pose_true`) or the world's truth raster. Positions in the
world ENU frame, metres; map quality per class at 0.1 m tolerance."""

import cv2
import numpy as np

from common.evaluation import per_class_precision_recall
from common.world import World
from services.vehicle.estimator import dead_reckon

POSE_ERRORS = ("pose_error_m", "outage_pose_error_m", "odometry_only_error_m")


def _stats(err: np.ndarray):
    err = err[np.isfinite(err)]
    if not len(err):
        return {"mean": None, "max": None}
    return {"mean": float(err.mean()), "max": float(err.max())}


def pose_errors(poses: dict, truth: np.ndarray) -> dict:
    """Position errors vs truth: all frames, GNSS-outage frames, and raw odometry in outages.

    poses: a vehicle's committed frames (services.vehicle.outputs: pose (N, 3), gnss_covered
    (N,), odom_delta (N, 3)); truth: the drive's true poses by frame (F >= N, 3).
    Odometry-only: uncalibrated wheel + gyro dead reckoning from the optimized pose of the last
    GNSS-covered frame before each outage, through the outage (what the map would get without
    the pose graph)."""
    n = len(poses["pose"])
    if n == 0:
        return {k: {"mean": None, "max": None} for k in POSE_ERRORS}
    est = poses["pose"]
    err = np.linalg.norm(est[:, :2] - truth[:n, :2], axis=1)
    outage = ~np.asarray(poses["gnss_covered"], dtype=bool)
    odo = _odometry_only_errors(est, outage, poses["odom_delta"], truth)
    return {
        "pose_error_m": _stats(err),
        "outage_pose_error_m": _stats(err[outage]),
        "odometry_only_error_m": _stats(odo),
    }


def _odometry_only_errors(est, outage, raw, truth) -> np.ndarray:
    """Errors of raw odometry chained from the pose before each outage, over the outage."""
    n, odo_err, i = len(est), [], 0
    while i < n:
        if not outage[i] or i == 0:
            i += 1
            continue
        j = i
        while j < n and outage[j]:
            j += 1
        dr = dead_reckon(est[i - 1], raw[i:j])[1:]
        odo_err.append(np.linalg.norm(dr[:, :2] - truth[i:j, :2], axis=1))
        i = j
    return np.concatenate(odo_err) if odo_err else np.zeros(0)


def mapping_section(vehicles: list[tuple[dict, dict]], segmenter: str) -> dict:
    """The report's mapping section: per vehicle (its summary.json, its pose_errors) the errors
    weighted by committed frames, their max, and the frame count."""
    frames = [int(s.get("frames", 0)) for s, _ in vehicles]

    def agg(key):
        rows = [(e.get(key) or {}, f) for (_, e), f in zip(vehicles, frames, strict=True)]
        rows = [(r, f) for r, f in rows if r.get("mean") is not None]
        if not rows:
            return {"mean": None, "max": None}
        w = sum(f for _, f in rows) or 1
        return {"mean": sum(r["mean"] * f for r, f in rows) / w,
                "max": max(r.get("max") or 0.0 for r, _ in rows)}

    return {**{key: agg(key) for key in POSE_ERRORS}, "frames": sum(frames),
            "vehicles": len(vehicles), "segmenter": segmenter}


def local_map_quality(
    labels: np.ndarray, x0_m: float, y0_m: float, world: World, tol_cells: int = 1
) -> dict:
    """Per marking class precision/recall of a vehicle's local label raster (0.1 m cells, world
    ENU, south-west corner x0/y0) vs `world`: {class: {precision, recall, cells_pred,
    cells_true}}. Truth is only counted where the vehicle saw the ground (cells with any vote,
    dilated by the tolerance), since one traversal cannot recall paint outside its camera's ROI."""
    truth = world.rasterize(x0_m, y0_m, labels.shape[0], labels.shape[1])
    seen = labels > 0
    if tol_cells > 0:
        k = np.ones((2 * tol_cells + 1, 2 * tol_cells + 1), np.uint8)
        seen = cv2.dilate(seen.astype(np.uint8), k).astype(bool)
    truth[~seen] = 0
    return per_class_precision_recall(labels, truth, tol_cells=tol_cells)
