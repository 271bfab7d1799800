"""The files `roadmap vehicle` writes in its STATE (besides the outbox), and their readers.
Nothing in them comes from truth; the evaluation harness (services/eval/mapping.py) reads them
with the drive log.

    summary.json    counters of the run: frames committed, patches sent / acked / accepted,
                    duplicates, pending, errors, bytes sent, calibration, per-stage timings
    poses.npz       the committed frames (VehicleMapper.trajectory): t_ns (N,) int64, pose
                    (N, 3) optimized x, y, yaw (world ENU, m / rad), gnss_covered (N,) bool,
                    odom_delta (N, 3) raw odometry since the previous frame
    trajectory.tum  the same poses as a TUM trajectory (`t x y z qx qy qz qw`,
                    common/trajectory.py)
    local_map.npz   labels (H, W) uint8 (0.1 m cells, row north), origin_m: its south-west
                    corner (x0, y0)
    config.toml     the effective config"""

import json
import math
from pathlib import Path

import numpy as np

from common.trajectory import write_tum

POSE_KEYS = ("t_ns", "pose", "gnss_covered", "odom_delta")


def write_poses(state: Path, trajectory: dict[str, np.ndarray]) -> None:
    """poses.npz and trajectory.tum of the committed frames."""
    np.savez(state / "poses.npz", **{k: trajectory[k] for k in POSE_KEYS})
    write_tum(state / "trajectory.tum", trajectory["t_ns"], trajectory["pose"])


def read_poses(state: Path) -> dict[str, np.ndarray]:
    with np.load(Path(state) / "poses.npz") as z:
        return {k: z[k] for k in POSE_KEYS}


def write_local_map(state: Path, labels: np.ndarray, x0_m: float, y0_m: float) -> None:
    np.savez_compressed(state / "local_map.npz", labels=labels, origin_m=np.array([x0_m, y0_m]))


def write_summary(state: Path, summary: dict) -> None:
    (state / "summary.json").write_text(
        json.dumps(_clean(summary), indent=1, default=lambda o: None, allow_nan=False)
    )


def read_summary(state: Path) -> dict:
    return json.loads((Path(state) / "summary.json").read_text())


def _clean(obj):
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    return obj
