"""One drive scored against the simulator's truth, from what the services wrote: the car's
per-frame poses and integrity flags (localizer/diagnostics.jsonl) against the production drive
log's true poses, and which frames had a marking in the camera's view (the log's true labels
inside the IPM ROI), as the paper evaluates over frames with markings."""

import json
from pathlib import Path

import numpy as np

from common.camera import build_ipm_lookup
from common.classes import Cls
from common.drivelog import DriveLog
from services.eval.localization import convergence_index, pose_errors

THRESHOLD_M = 0.5  # availability and integrity: an error above this is a wrong pose
HOLD_S = 1.0  # convergence: the error stays below THRESHOLD_M this long
MIN_MARKING_PIXELS = 20  # true marking pixels inside the ROI for "a marking in view"
STATS = ("x_m", "y_m", "lateral_m", "longitudinal_m", "yaw_deg")


def car_estimates(diagnostics: Path, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Per frame: the pose the car reported (NaN where none) and whether it said ok."""
    est = np.full((frames, 3), np.nan)
    ok = np.zeros(frames, bool)
    for line in diagnostics.read_text().splitlines():
        row = json.loads(line)
        i = int(row["i"])
        if 0 <= i < frames and row.get("pose") is not None:
            est[i] = row["pose"]
            ok[i] = bool(row.get("ok"))
    return est, ok


def markings_in_view(log: DriveLog, roi) -> np.ndarray:
    """Per frame: whether at least MIN_MARKING_PIXELS true marking pixels lie in the ROI."""
    ipm = build_ipm_lookup(log.meta.camera, x_min_m=roi.x_min_m, length_m=roi.length_m,
                           width_m=roi.width_m)
    seen = np.zeros(len(log), bool)
    for i in range(len(log)):
        labels = log.labels(i)
        if labels is not None:
            roi_labels = labels.reshape(-1)[ipm.pixel_index]
            seen[i] = int(np.count_nonzero(roi_labels >= Cls.LANE_LINE)) >= MIN_MARKING_PIXELS
    return seen


def frame_errors(est: np.ndarray, truth: np.ndarray) -> dict[str, np.ndarray]:
    """Absolute per-frame errors (NaN where the car had no pose) and the position error."""
    err = pose_errors(est, truth)
    return {k: np.abs(v) for k, v in err.items()}


def _stats(values: np.ndarray) -> dict:
    v = values[np.isfinite(values)]
    if not len(v):
        return {"mean": None, "p90": None, "max": None}
    return {"mean": float(v.mean()), "p90": float(np.percentile(v, 90)), "max": float(v.max())}


def _over(err: dict, use: np.ndarray, ok: np.ndarray) -> dict:
    """Statistics over the frames `use`: their count, availability, the share the car said
    ok (what a user may act on; the integrity checks' price), and each error's mean / p90 /
    max."""
    pos = np.where(np.isfinite(err["position_m"]), err["position_m"], np.inf)
    out = {"frames": int(use.sum()),
           "availability_0_5m": float(np.mean(pos[use] < THRESHOLD_M)) if use.any() else None,
           "ok_share": float(np.mean(ok[use])) if use.any() else None}
    out.update({k: _stats(err[k][use]) for k in STATS})
    return out


def score_frames(t_ns: np.ndarray, est: np.ndarray, ok: np.ndarray, truth: np.ndarray,
                 in_view: np.ndarray) -> dict:
    """The drive's figures: error statistics and availability after convergence (as the
    demo's report counts them) over frames with markings in view and over all frames, and over
    the frames with markings in view from the first one on, converged or not (a frame without
    a pose is unavailable and has no error); the
    integrity violations over every frame (error > THRESHOLD_M while the car said ok); and
    convergence counted from the first frame with a marking in view. A drive that never
    converges is scored over all its frames: left without figures, it dropped out of the
    suite's medians and worst cases, the worst drive of all."""
    t_s = (np.asarray(t_ns, np.int64) - int(t_ns[0])) * 1e-9
    err = frame_errors(est, truth)
    pos = err["position_m"]
    first_view = int(np.argmax(in_view)) if in_view.any() else None
    k = convergence_index(np.where(np.isfinite(pos), pos, np.inf), t_s, THRESHOLD_M, HOLD_S)
    convergence = (None if k is None or first_view is None
                   else max(0.0, float(t_s[k] - t_s[first_view])))
    ok = np.asarray(ok, bool)
    violations = ok & np.isfinite(pos) & (pos > THRESHOLD_M)
    after = np.ones(len(pos), bool)
    if k is not None:
        after[:k] = False
    since_view = np.zeros(len(pos), bool)
    if first_view is not None:
        since_view[first_view:] = True
    return {
        "markings_in_view": _over(err, in_view & after, ok),
        "all_frames": _over(err, after, ok),
        # converged or not: a late convergence leaves a start metres off out of the figures
        # above, and one found sooner counts its settling in (docs/RESULTS.md, 2026-12-07)
        "from_first_marking": _over(err, in_view & since_view, ok),
        "frames": int(len(pos)),
        "frames_without_markings": int((~in_view).sum()),
        "integrity_violations": int(violations.sum()),
        "convergence_s": convergence,
        "errors_m": [round(float(e), 4) for e in pos[in_view & after & np.isfinite(pos)]],
    }


def score_drive(out_dir: Path, roi) -> dict:
    """Score the demo run in `out_dir` (its production drive log and the car's outputs)."""
    (prod,) = sorted((out_dir / "drives" / "production").iterdir())
    log = DriveLog(prod)
    est, ok = car_estimates(out_dir / "localizer" / "diagnostics.jsonl", len(log))
    return score_frames(log.streams["frame_t_ns"], est, ok, log.streams["frame_pose_true"],
                        markings_in_view(log, roi))
