"""`roadmap trajectory --from DEMO_OUT --out DIR [--format tum|kitti]`: a demo's localized
trajectory and the production drive's ground truth as files evo (`evo_ape tum truth.tum
estimate.tum`) and other trajectory tools read. Evaluation side: the truth comes from the drive
log the simulator wrote, never from the localizer.

tum: DIR/estimate.tum (every frame the localizer estimated), DIR/truth.tum (every frame with a
true pose), stamps in seconds, the frames' own. kitti: DIR/estimate.kitti and DIR/truth.kitti
hold the same frames line by line (those with both), DIR/times.txt their stamps."""

import logging
import sys
from pathlib import Path

import numpy as np

from common.drivelog import DriveLog
from common.errors import ExportError
from common.trajectory import pair_by_stamp, read_tum, stamp_text, write_kitti, write_tum

logger = logging.getLogger(__name__)


def production_log(demo_out: Path) -> DriveLog:
    """The demo's production drive (drives/production/<id>): the one the localizer drove."""
    logs = sorted(p.parent for p in Path(demo_out).glob("drives/production/*/log.json"))
    if len(logs) != 1:
        raise ExportError(f"{demo_out}: expected one production drive log under "
                          f"drives/production, found {len(logs)}")
    return DriveLog(logs[0])


def true_frames(log: DriveLog) -> tuple[np.ndarray, np.ndarray]:
    """(frame_t_ns, true poses) of the frames whose true pose is known."""
    t, poses = log.streams["frame_t_ns"], log.streams["frame_pose_true"]
    known = np.all(np.isfinite(poses), axis=1)
    return t[known].astype(np.int64), poses[known]


def write_trajectories(demo_out: Path, out: Path, fmt: str = "tum",
                       localizer: str = "localizer") -> dict:
    """Write the estimate and the truth of a demo run in `fmt`; returns {name: path, rows}."""
    est_path = Path(demo_out) / localizer / "trajectory.tum"
    if not est_path.is_file():
        raise ExportError(f"{est_path}: no localizer trajectory (run roadmap demo first)")
    t_est, est = read_tum(est_path)
    log = production_log(Path(demo_out))
    t_true, true = true_frames(log)
    frames = log.streams["frame_t_ns"].astype(np.int64)
    ia, ib = pair_by_stamp(t_est, frames)  # stamps rounded through a float: the frames' own
    t_est = t_est.copy()
    t_est[ia] = frames[ib]
    out.mkdir(parents=True, exist_ok=True)
    if fmt == "tum":
        files = {"estimate": out / "estimate.tum", "truth": out / "truth.tum"}
        rows = {"estimate": write_tum(files["estimate"], t_est, est),
                "truth": write_tum(files["truth"], t_true, true)}
    elif fmt == "kitti":
        ia, ib = pair_by_stamp(t_est, t_true)
        files = {"estimate": out / "estimate.kitti", "truth": out / "truth.kitti",
                 "times": out / "times.txt"}
        rows = {"estimate": write_kitti(files["estimate"], est[ia]),
                "truth": write_kitti(files["truth"], true[ib])}
        files["times"].write_text("".join(f"{stamp_text(int(t))}\n" for t in t_est[ia]))
    else:
        raise ExportError(f"unknown trajectory format {fmt!r} (tum, kitti)")
    return {"files": {k: str(v) for k, v in files.items()}, "rows": rows}


def trajectory_command(args, cfg) -> int:
    res = write_trajectories(Path(args.from_dir), Path(args.out), args.format, args.localizer)
    for name, path in res["files"].items():
        rows = res["rows"].get(name)
        sys.stdout.write(f"{path}" + (f": {rows} poses" if rows is not None else "") + "\n")
    return 0
