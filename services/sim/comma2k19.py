"""Converter of a real comma2k19 segment into a drive log (proves the format fits real data).

Reference poses (ECEF positions, orientations ECEF <- device [forward, right, down], 20 Hz) become
local ENU (x east, y north) about the first position, yaw from the device's forward axis; consumer
GNSS (u-blox lat/lon) goes through the same local frame; the IMU gyro about the down axis gives the
yaw rate (z up: minus gyro z); CAN speed is the wheel odometry; the single preview.png is frame 0.
The reference positions are those of the device (camera), not the rear axle: good to ~1 m."""

import logging
from pathlib import Path

import cv2
import numpy as np

from common.camera import CameraModel
from common.drivelog import DriveLogMeta, DriveLogWriter
from common.errors import DriveLogError
from common.geometry import ecef_to_geodetic, enu_rotation, latlon_to_local_m, quat_wxyz_to_rot

logger = logging.getLogger(__name__)

GNSS_SIGMA_M = 2.0  # u-blox consumer receiver, no per-fix accuracy in processed_log


def comma_camera() -> CameraModel:
    """The comma2k19 road camera: fx = fy = 910, cx 582, cy 437, 1164 x 874, ~1.2 m high, level."""
    return CameraModel.from_mount(
        width=1164,
        height=874,
        fx=910.0,
        fy=910.0,
        cx=582.0,
        cy=437.0,
        dist=[0.0, 0.0, 0.0, 0.0, 0.0],
        x_m=1.5,
        y_m=0.0,
        height_m=1.22,
        pitch_deg=0.0,
    )


def _load(seg: Path, rel: str) -> np.ndarray:
    path = seg / rel
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise DriveLogError(f"{path}: cannot read ({exc})") from exc


def read_segment(seg) -> dict:
    """The segment's streams in the local ENU frame (seconds on the segment's clock)."""
    seg = Path(seg)
    pos = _load(seg, "global_pose/frame_positions")
    quat = _load(seg, "global_pose/frame_orientations")
    t_frame = _load(seg, "global_pose/frame_times")
    lat0, lon0, _ = ecef_to_geodetic(pos[0])
    R = enu_rotation(lat0, lon0)
    enu = (pos - pos[0]) @ R.T
    fwd = np.array([R @ quat_wxyz_to_rot(q)[:, 0] for q in quat])  # device forward axis in ENU
    yaw = np.arctan2(fwd[:, 1], fwd[:, 0])
    gnss = _load(seg, "processed_log/GNSS/live_gnss_ublox/value")
    gx, gy = latlon_to_local_m(gnss[:, 0], gnss[:, 1], lat0, lon0)
    gyro = _load(seg, "processed_log/IMU/gyro/value")
    return {
        "origin": (lat0, lon0),
        "t_frame": t_frame,
        "pose": np.stack([enu[:, 0], enu[:, 1], yaw], axis=1),
        "t_gnss": _load(seg, "processed_log/GNSS/live_gnss_ublox/t"),
        "gnss_xy": np.stack([gx, gy], 1),
        "t_imu": _load(seg, "processed_log/IMU/gyro/t"),
        "yaw_rate": -gyro[:, 2],
        "t_odom": _load(seg, "processed_log/CAN/speed/t"),
        "speed": _load(seg, "processed_log/CAN/speed/value").reshape(-1),
    }


def convert(seg, out) -> Path:
    """Write the segment as a drive log at `out`; returns its path."""
    seg, out = Path(seg), Path(out)
    d = read_segment(seg)
    ns = lambda t: np.round(np.asarray(t) * 1e9).astype(np.int64)  # noqa: E731
    camera = comma_camera()
    meta = DriveLogMeta(
        vehicle="comma2k19",
        traversal=f"comma2k19-{seg.name}",
        profile="production",
        world={
            "name": f"comma2k19:{seg.name}",
            "origin_lat": d["origin"][0],
            "origin_lon": d["origin"][1],
        },
        camera=camera,
        notes={
            "source": "comma2k19",
            "segment": str(seg.name),
            "poses": "fused INS/GNSS/vision reference of the device (camera), 20 Hz",
            "gnss": "u-blox live fixes, sigma assumed",
            "images": "frame 0 only (preview.png)",
        },
    )
    writer = DriveLogWriter(out, meta)
    preview = cv2.imread(str(seg / "preview.png"), cv2.IMREAD_COLOR)
    if preview is not None and preview.shape[:2] == (camera.height, camera.width):
        writer.write_frame(0, cv2.cvtColor(preview, cv2.COLOR_BGR2RGB), None)
    n = len(d["t_gnss"])
    writer.close(
        {
            "frame_t_ns": ns(d["t_frame"]),
            "frame_pose_true": d["pose"],
            "odom_t_ns": ns(d["t_odom"]),
            "odom_speed_mps": d["speed"],
            "imu_t_ns": ns(d["t_imu"]),
            "imu_yaw_rate_rps": d["yaw_rate"],
            "gnss_t_ns": ns(d["t_gnss"]),
            "gnss_xy_m": d["gnss_xy"],
            "gnss_sigma_m": np.full(n, GNSS_SIGMA_M),
            "gnss_ok": np.ones(n, bool),
            "truth_t_ns": ns(d["t_frame"]),
            "truth_pose": d["pose"],
        }
    )
    logger.info("comma2k19 %s -> %s: %d frames", seg.name, out, len(d["t_frame"]))
    return out
