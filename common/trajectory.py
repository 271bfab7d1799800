"""Planar trajectories in the standard files trajectory tools read (evo, the TUM and KITTI
benchmarks): poses (x, y, yaw) in the world frame (metres, radians) lifted to SE(3) with z = 0.

TUM: one line per pose, `t x y z qx qy qz qw` (t in seconds). KITTI: one line per pose, the 3x4
matrix [R | t] row by row, no times (a KITTI pair of files must hold the same poses' stamps, line
by line; times.txt beside them lists those stamps in seconds)."""

import math
from pathlib import Path

import numpy as np

from common.errors import ExportError
from common.geometry import quat_wxyz_from_yaw


def write_tum(path: str | Path, t_ns: np.ndarray, poses: np.ndarray) -> int:
    """Poses (N, 3) at times t_ns (N,) -> a TUM file; rows with a non-finite pose are left out.
    Returns the number of rows written."""
    n = 0
    with open(path, "w") as f:
        for t, (x, y, yaw) in zip(np.asarray(t_ns), np.asarray(poses, float), strict=True):
            if not np.all(np.isfinite([x, y, yaw])):
                continue
            w, qx, qy, qz = quat_wxyz_from_yaw(float(yaw))
            f.write(f"{stamp_text(int(t))} {x:.4f} {y:.4f} 0.0 {qx:.8f} {qy:.8f} {qz:.8f} "
                    f"{w:.8f}\n")
            n += 1
    return n


def stamp_text(t_ns: int) -> str:
    """Nanoseconds -> seconds with 9 decimals, exactly (a float64 holds ~0.5 us at 2.6e9 s)."""
    sign, t_ns = ("-", -t_ns) if t_ns < 0 else ("", t_ns)
    return f"{sign}{t_ns // 1_000_000_000}.{t_ns % 1_000_000_000:09d}"


def stamp_ns(text: str) -> int:
    """Seconds as written in a file -> nanoseconds, exactly to 9 decimals."""
    whole, _, frac = text.strip().partition(".")
    sign = -1 if whole.startswith("-") else 1
    return sign * (abs(int(whole or "0")) * 1_000_000_000 + int((frac + "000000000")[:9] or 0))


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM file -> (t_ns (N,) int64, poses (N, 3) of x, y, yaw); ExportError on a bad line."""
    t_ns, poses = [], []
    for k, line in enumerate(Path(path).read_text().splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            t, *rest = line.split()
            x, y, _z, qx, qy, qz, qw = (float(v) for v in rest)
            t_ns.append(stamp_ns(t))
        except ValueError as exc:
            raise ExportError(f"{path}:{k}: expected 8 numbers (t x y z qx qy qz qw)") from exc
        poses.append((x, y, math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))))
    return np.array(t_ns, np.int64), np.array(poses, float).reshape(-1, 3)


def write_kitti(path: str | Path, poses: np.ndarray) -> int:
    """Poses (N, 3) -> a KITTI file (every row must be finite: KITTI has no stamps to skip by)."""
    poses = np.asarray(poses, float).reshape(-1, 3)
    if not np.all(np.isfinite(poses)):
        raise ExportError("KITTI rows carry no stamps: pair the poses before writing them")
    with open(path, "w") as f:
        for x, y, yaw in poses:
            c, s = math.cos(yaw), math.sin(yaw)
            m = [c, -s, 0.0, x, s, c, 0.0, y, 0.0, 0.0, 1.0, 0.0]
            f.write(" ".join(f"{v:.9g}" for v in m) + "\n")
    return len(poses)


def read_kitti(path: str | Path) -> np.ndarray:
    """A KITTI file -> poses (N, 3) of x, y, yaw (the rotation's yaw; roll and pitch dropped)."""
    rows = []
    for k, line in enumerate(Path(path).read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            m = [float(v) for v in line.split()]
        except ValueError:
            m = []
        if len(m) != 12:
            raise ExportError(f"{path}:{k}: expected 12 numbers (a 3x4 pose matrix)")
        rows.append((m[3], m[7], math.atan2(m[4], m[0])))
    return np.array(rows, float).reshape(-1, 3)


def pair_by_stamp(t_a: np.ndarray, t_b: np.ndarray, max_diff_ns: int = 1_000_000):
    """Indices (ia, ib) pairing each stamp of a with the nearest stamp of b within max_diff_ns,
    each b used once, in a's order."""
    t_a, t_b = np.asarray(t_a, np.int64), np.asarray(t_b, np.int64)
    if len(t_a) == 0 or len(t_b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.argsort(t_b, kind="stable")
    sb = t_b[order]
    right = np.clip(np.searchsorted(sb, t_a), 0, len(sb) - 1)
    left = np.clip(right - 1, 0, len(sb) - 1)
    nearest = np.where(np.abs(sb[left] - t_a) <= np.abs(sb[right] - t_a), left, right)
    ok = np.abs(sb[nearest] - t_a) <= max_diff_ns
    ia, ib = np.flatnonzero(ok), order[nearest[ok]]
    _, first = np.unique(ib, return_index=True)
    keep = np.sort(first)
    return ia[keep], ib[keep]
