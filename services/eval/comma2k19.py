"""The pose graph on the real comma2k19 drive: consumer GNSS + CAN speed + gyro vs the reference.

Reads a comma2k19 segment in place (arrays without the .npy suffix, /work/shared/data/README.md),
converts ECEF and lat/lon into a local ENU frame at the first reference position (metres), and
reports position errors of the pose graph, of GNSS alone and of odometry alone against the
drive's fused reference poses (`global_pose`)."""

from pathlib import Path

import numpy as np

from common.geometry import ecef_to_geodetic, enu_rotation, geodetic_to_ecef, quat_wxyz_to_rot
from services.vehicle.estimator import PoseEstimator, dead_reckon

CONSUMER_GNSS_SIGMA_M = 2.0  # u-blox without RTK (README: about 1.5 m off the reference)


def load_segment(root: str | Path) -> dict:
    """Streams in the drive-log layout (ns times, ENU metres) plus the reference poses."""
    root = Path(root)
    ld = lambda p: np.load(root / p)  # noqa: E731
    ref_ecef = ld("global_pose/frame_positions")
    lat0, lon0, _ = ecef_to_geodetic(ref_ecef[0])
    R = enu_rotation(lat0, lon0)
    ref_xy = ((ref_ecef - ref_ecef[0]) @ R.T)[:, :2]
    forward_ecef = np.array(
        [quat_wxyz_to_rot(q)[:, 0] for q in ld("global_pose/frame_orientations")]
    )
    forward_enu = forward_ecef @ R.T
    ref_yaw = np.unwrap(np.arctan2(forward_enu[:, 1], forward_enu[:, 0]))
    g = ld("processed_log/GNSS/live_gnss_ublox/value")
    gnss_xy = ((geodetic_to_ecef(g[:, 0], g[:, 1], g[:, 4]) - ref_ecef[0]) @ R.T)[:, :2]
    ns = lambda t: np.round(np.asarray(t) * 1e9).astype(np.int64)  # noqa: E731
    gyro = ld("processed_log/IMU/gyro/value")
    return {
        "frame_t_ns": ns(ld("global_pose/frame_times")),
        "frame_pose_true": np.column_stack([ref_xy, ref_yaw]),
        "odom_t_ns": ns(ld("processed_log/CAN/speed/t")),
        "odom_speed_mps": ld("processed_log/CAN/speed/value")[:, 0],
        "imu_t_ns": ns(ld("processed_log/IMU/gyro/t")),
        "imu_yaw_rate_rps": -gyro[:, 2],  # device frame is (forward, right, down): yaw up = -down
        "gnss_t_ns": ns(ld("processed_log/GNSS/live_gnss_ublox/t")),
        "gnss_xy_m": gnss_xy,
        "gnss_sigma_m": np.full(len(gnss_xy), CONSUMER_GNSS_SIGMA_M),
        "gnss_ok": np.ones(len(gnss_xy), bool),
        "origin_latlon": (lat0, lon0),
    }


def run_estimator(streams: dict, estimator: PoseEstimator) -> np.ndarray:
    """Replay streams through the estimator -> optimized poses (F, 3) in frame order."""
    s, poses = streams, {}
    o = i = g = 0
    for t in s["frame_t_ns"]:
        o2, i2, g2 = (
            int(np.searchsorted(s[k], t, "right")) for k in ("odom_t_ns", "imu_t_ns", "gnss_t_ns")
        )
        estimator.add_odometry(s["odom_t_ns"][o:o2], s["odom_speed_mps"][o:o2])
        estimator.add_imu(s["imu_t_ns"][i:i2], s["imu_yaw_rate_rps"][i:i2])
        for k in range(g, g2):
            estimator.add_gnss(
                int(s["gnss_t_ns"][k]),
                s["gnss_xy_m"][k],
                float(s["gnss_sigma_m"][k]),
                bool(s["gnss_ok"][k]),
            )
        o, i, g = o2, i2, g2
        estimator.add_frame(int(t))
        poses.update(estimator.settled())
    poses.update(estimator.settled(flush=True))
    return np.array([poses[k] for k in range(len(s["frame_t_ns"]))])


def _stats(err) -> dict:
    return {
        "mean": float(np.mean(err)),
        "p90": float(np.percentile(err, 90)),
        "max": float(np.max(err)),
    }


def evaluate(root: str | Path) -> dict:
    """Position errors (metres: mean, p90, max) of the pose graph, GNSS alone, odometry alone."""
    s = load_segment(root)
    truth = s["frame_pose_true"]
    est = PoseEstimator(settle_lag_s=1.0)
    poses = run_estimator(s, est)
    final = est.graph.estimates()
    smoothed = np.array([final[k] for k in range(len(truth))])
    t = s["frame_t_ns"].astype(float)
    gnss_at_frames = np.column_stack(
        [np.interp(t, s["gnss_t_ns"].astype(float), s["gnss_xy_m"][:, k]) for k in range(2)]
    )
    odo = dead_reckon(truth[0], est.raw_deltas()[1:])
    err = lambda xy: np.linalg.norm(xy - truth[:, :2], axis=1)  # noqa: E731
    yaw_err = np.degrees(np.abs(np.angle(np.exp(1j * (poses[:, 2] - truth[:, 2])))))
    length = float(np.sum(np.linalg.norm(np.diff(truth[:, :2], axis=0), axis=1)))
    return {
        "frames": int(len(truth)),
        "length_m": length,
        "pose_graph_committed_m": _stats(err(poses[:, :2])),
        "pose_graph_smoothed_m": _stats(err(smoothed[:, :2])),
        "gnss_only_m": _stats(err(gnss_at_frames)),
        "odometry_only_m": _stats(err(odo[:, :2])),
        "pose_graph_yaw_deg": _stats(yaw_err),
        "notes": "reference = comma2k19 global_pose (fused INS/GNSS/vision); committed = poses as "
        "the mapper commits them (1 s settle lag), smoothed = the whole graph at the end; "
        "gnss-only = fixes interpolated to frame times; odometry-only = CAN speed + gyro "
        "dead reckoning from the true first pose; GNSS is u-blox without RTK, with a bias "
        "and about 0.1 s timestamp latency that no factor models",
    }
