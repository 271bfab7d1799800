"""TUM trajectory files: one pose a line, `timestamp x y z qx qy qz qw` (seconds, metres, unit
quaternion), as the TUM RGB-D benchmark and evo read them. Our poses are planar (x, y, yaw) in
the world ENU frame: z is 0 and the quaternion a rotation about z. Lines starting with # are
comments."""

from pathlib import Path

import numpy as np

from common.geometry import quat_wxyz_from_yaw


def write_tum(path: Path, t_ns: np.ndarray, poses: np.ndarray) -> None:
    """Poses (N, 3) at times t_ns (N,) -> a TUM file; poses that are not finite are left out."""
    with open(path, "w") as f:
        for t, (x, y, yaw) in zip(t_ns, poses, strict=True):
            if not np.all(np.isfinite([x, y, yaw])):
                continue
            w, qx, qy, qz = quat_wxyz_from_yaw(float(yaw))
            f.write(f"{int(t) / 1e9:.9f} {x:.4f} {y:.4f} 0.0 {qx:.8f} {qy:.8f} {qz:.8f} {w:.8f}\n")


def read_tum(text: str) -> np.ndarray:
    """TUM trajectory lines `t x y z qx qy qz qw` -> (N, 4) of (t_s, x, y, yaw)."""
    rows = []
    for line in text.splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        t, x, y, _z, qx, qy, qz, qw = (float(v) for v in line.split()[:8])
        yaw = np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
        rows.append((t, x, y, yaw))
    return np.array(rows, float).reshape(-1, 4)
