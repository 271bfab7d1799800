"""Localization accuracy against ground truth: the report's `localization` section.

Consumes what `roadmap localize` wrote in its OUT (services/localizer/outputs.py: per-frame
estimates in diagnostics.jsonl, the tiles it received in tiles.npz, summary.json, config.toml)
and the drive log's true poses (`frame_pose_true`).

x/y errors are in the world frame, lateral/longitudinal in the true vehicle frame (x forward,
y left), yaw in degrees; statistics (mean, p90, max of absolute errors) are taken over the frames
after convergence. Convergence: the first frame from which the position error stays under the
availability threshold for `hold_s`; availability: share of frames after it with error < 0.5 m
(a frame without an estimate counts as unavailable).

With `on_map` (per frame: the map covers the camera's view at the true pose), the statistics and
the availability are those of the on-map frames after convergence, as in the paper's evaluation
(a car off the mapped area has nothing to match); `all_frames` keeps them over every frame. The
map of a frame is every tile the car had received by then, in its latest version (tiles.npz);
the car's own LRU evictions are not replayed (with the default cache it evicts only tiles it no
longer wants around its estimate)."""

import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.config import RoiConfig
from common.drivelog import DriveLog
from common.geometry import transform_points_2d, wrap_angle
from services.localizer.map_cache import TileCache
from services.localizer.outputs import read_diagnostics, read_summary, read_tiles
from services.localizer.tiles import decode_tile_message


def _stats(values: np.ndarray) -> dict:
    if len(values) == 0:
        return {"mean": None, "p90": None, "max": None}
    a = np.abs(values)
    return {"mean": float(a.mean()), "p90": float(np.percentile(a, 90)), "max": float(a.max())}


def pose_errors(est: np.ndarray, true: np.ndarray) -> dict:
    """Per-frame errors (arrays) of estimates (N, 3) against truth (N, 3)."""
    dx, dy = est[:, 0] - true[:, 0], est[:, 1] - true[:, 1]
    c, s = np.cos(true[:, 2]), np.sin(true[:, 2])
    return {
        "x_m": dx,
        "y_m": dy,
        "longitudinal_m": c * dx + s * dy,
        "lateral_m": -s * dx + c * dy,
        "yaw_deg": np.degrees(wrap_angle(est[:, 2] - true[:, 2])),
        "position_m": np.hypot(dx, dy),
    }


def interp_poses(t_query_s: np.ndarray, t_s: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Linear interpolation of (x, y, yaw) at query times (yaw unwrapped first)."""
    yaw = np.unwrap(poses[:, 2])
    return np.stack([np.interp(t_query_s, t_s, poses[:, 0]), np.interp(t_query_s, t_s, poses[:, 1]),
                     wrap_angle(np.interp(t_query_s, t_s, yaw))], axis=1)


def convergence_index(
    position_err_m: np.ndarray, t_s: np.ndarray, threshold_m: float, hold_s: float
) -> int | None:
    """First frame from which the error stays below threshold for hold_s (None: never)."""
    good = np.isfinite(position_err_m) & (position_err_m < threshold_m)
    n = len(good)
    # end of the current run of good frames, scanning from the back
    run_end = np.empty(n, dtype=np.int64)
    nxt = n
    for i in range(n - 1, -1, -1):
        if not good[i]:
            nxt = i
        run_end[i] = nxt
    for i in np.flatnonzero(good):
        last = run_end[i] - 1
        if t_s[last] - t_s[i] >= hold_s or run_end[i] == n:
            return int(i)
    return None


def localization_metrics(
    t_ns: np.ndarray,
    est: np.ndarray,
    true: np.ndarray,
    *,
    threshold_m: float = 0.5,
    hold_s: float = 1.0,
    on_map: np.ndarray | None = None,
) -> dict:
    """The report's localization section from per-frame estimates (NaN = none) and truth."""
    t_s = (np.asarray(t_ns, dtype=np.int64) - int(t_ns[0])) * 1e-9 if len(t_ns) else np.zeros(0)
    est = np.asarray(est, dtype=float)
    true = np.asarray(true, dtype=float)
    valid_truth = np.all(np.isfinite(true), axis=1)
    est, true, t_s = est[valid_truth], true[valid_truth], t_s[valid_truth]
    err = pose_errors(est, true)
    pos = np.where(np.isfinite(err["position_m"]), err["position_m"], np.inf)
    k = convergence_index(pos, t_s, threshold_m, hold_s) if len(pos) else None
    after = np.zeros(len(pos), dtype=bool)
    if k is not None:
        after[k:] = True
    out = {
        "frames": int(len(t_s)),
        "convergence_s": None if k is None else float(t_s[k]),
        **_over(err, pos, after, threshold_m),
        "frames_after_convergence": int(after.sum()),
    }
    if on_map is None:
        return out
    mapped = np.asarray(on_map, dtype=bool)[valid_truth]
    return {
        **out,
        **_over(err, pos, after & mapped, threshold_m),
        "frames_on_map": int(mapped.sum()),
        "all_frames": {key: out[key] for key in _STATS + ("availability_0_5m",)},
    }


_STATS = ("lateral_m", "longitudinal_m", "x_m", "y_m", "yaw_deg")


def _over(err: dict, pos: np.ndarray, use: np.ndarray, threshold_m: float) -> dict:
    """Availability and error statistics over the frames in `use` (a frame without an estimate
    counts as unavailable and is left out of the statistics)."""
    out = {"availability_0_5m": float(np.mean(pos[use] < threshold_m)) if use.any() else 0.0}
    fin = use & np.isfinite(pos)
    for name in _STATS:
        out[name] = _stats(err[name][fin])
    return out


def summary_line(m: dict) -> str:
    """One line for logs: x/y/yaw mean and p90, availability, convergence."""

    def f(key, unit_scale=1.0):
        s = m[key]
        return (
            "n/a"
            if s["mean"] is None
            else f"{s['mean'] * unit_scale:.3f}/{s['p90'] * unit_scale:.3f}"
        )

    conv = m["convergence_s"]
    return (
        f"x {f('x_m')} m, y {f('y_m')} m, yaw {f('yaw_deg')} deg (mean/p90), "
        f"availability {m['availability_0_5m'] * 100:.2f} %, convergence "
        f"{'never' if conv is None else f'{conv:.1f} s'}, frames {m['frames']}"
    )


# -- from the localizer's outputs ----------------------------------------------------------------


@dataclass
class LocalizedFrames:
    """Per localized frame (in frame order): the localizer's estimate and the truth."""

    frame: np.ndarray  # (N,) index in the drive log
    t_ns: np.ndarray  # (N,) the estimate's stamp (diagnostics.jsonl)
    frame_t_ns: np.ndarray  # (N,) the frame's time in the drive log
    est: np.ndarray  # (N, 3) x, y, yaw; NaN without an estimate
    truth: np.ndarray  # (N, 3) true pose of the frame; NaN if unknown
    on_map: np.ndarray  # (N,) bool: the tiles received by then cover the view at the true pose


def localized_frames(out: Path, log: DriveLog) -> LocalizedFrames:
    """The estimates of `roadmap localize --out OUT` on `log`, with the log's truth."""
    out = Path(out)
    rows = read_diagnostics(out / "diagnostics.jsonl")
    frame = np.array([r["i"] for r in rows], dtype=np.int64)
    est = np.array([r["pose"] if r["pose"] is not None else [np.nan] * 3 for r in rows],
                   dtype=float).reshape(-1, 3)
    truth = log.streams["frame_pose_true"][frame].reshape(-1, 3)
    roi = _roi(out / "config.toml")
    return LocalizedFrames(
        frame=frame,
        t_ns=np.array([r["t_ns"] for r in rows], dtype=np.int64),
        frame_t_ns=log.streams["frame_t_ns"][frame],
        est=est,
        truth=truth,
        on_map=map_coverage(read_tiles(out / "tiles.npz"), frame, truth, roi),
    )


def _roi(config_toml: Path) -> RoiConfig:
    """The ROI the car ran with (the [roi] of its effective config)."""
    with open(config_toml, "rb") as f:
        return RoiConfig(**tomllib.load(f).get("roi", {}))


def map_coverage(received, frame: np.ndarray, truth: np.ndarray, roi) -> np.ndarray:
    """Per frame: whether the tiles the car had received by then (received: [(frame, Tile)] in
    the order applied) cover its view at the true pose (map_covers_view)."""
    cache = TileCache(capacity=max(1, len(received)))  # every tile received, latest version
    k, out = 0, np.zeros(len(frame), dtype=bool)
    for n, (i, pose) in enumerate(zip(frame, truth, strict=True)):
        while k < len(received) and received[k][0] <= i:
            msg = received[k][1]
            cache.put(msg.tile, msg.version, decode_tile_message(msg))
            k += 1
        out[n] = map_covers_view(cache, pose, roi)
    return out


def map_covers_view(cache: TileCache, true_pose, roi, min_fraction: float = 0.25) -> bool:
    """Whether the map has road or paint under at least min_fraction of the ROI seen from the
    true pose (a 1 m grid); False without a true pose."""
    if not np.all(np.isfinite(true_pose)):
        return False
    xs = roi.x_min_m + 0.5 + np.arange(int(roi.length_m))
    ys = -roi.width_m / 2 + 0.5 + np.arange(int(roi.width_m))
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    world = transform_points_2d(np.asarray(true_pose, dtype=float), grid)
    return bool(np.mean(cache.class_at(world) != 0) >= min_fraction)


def localization_section(frames: LocalizedFrames, summary: dict) -> dict:
    """The report's localization section: accuracy, then the localizer's own summary."""
    return {
        **localization_metrics(frames.frame_t_ns, frames.est, frames.truth,
                               on_map=frames.on_map),
        **summary,
    }


def evaluate_localizer(out: Path, log: DriveLog) -> dict:
    """The localization section of `roadmap localize --out OUT` on `log`."""
    return localization_section(localized_frames(out, log), read_summary(out))
