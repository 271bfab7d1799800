"""Synthetic, seeded drives for the vehicle tests: a curving road, its paint, noisy sensors.

Trajectory and sensor noise follow DESIGN.md's mapping profile (RTK 0.02 m, odometry scale error
0.5 %, gyro bias 0.02 deg/s) unless a test makes them harder. Labels are rendered by projecting
each pixel's ground point (common.camera) into a hand-built World raster."""

import math

import numpy as np

from common.camera import CameraModel, camera_from_config
from common.classes import Cls
from common.config import CameraConfig
from common.drivelog import DriveLogMeta, DriveLogWriter
from common.world import Marking, World

NS = 10**9


def centreline(length_m: float, step_m: float = 0.5) -> np.ndarray:
    """A gently curving road (N, 2): straight, left bend, straight, right bend, ..."""
    s = np.arange(0.0, length_m + step_m, step_m)
    curvature = 0.01 * np.sin(2 * np.pi * s / 400.0)  # 1/m, radius >= 100 m
    heading = np.concatenate([[0.0], np.cumsum(curvature[:-1] * step_m)])
    x = np.concatenate([[0.0], np.cumsum(np.cos(heading[:-1]) * step_m)])
    y = np.concatenate([[0.0], np.cumsum(np.sin(heading[:-1]) * step_m)])
    return np.stack([x, y], axis=1) + [1000.0, 2000.0]


def _offset(line: np.ndarray, d: float) -> np.ndarray:
    t = np.gradient(line, axis=0)
    n = np.stack([-t[:, 1], t[:, 0]], axis=1) / np.linalg.norm(t, axis=1, keepdims=True)
    return line + d * n


def _band(line: np.ndarray, d0: float, d1: float) -> np.ndarray:
    return np.concatenate([_offset(line, d0), _offset(line, d1)[::-1]])


def road_world(line: np.ndarray) -> World:
    """Two lanes of 3.5 m: road, solid edge lines, a dashed centre line (3 m dash / 6 m gap)."""
    markings = [Marking(Cls.ROAD, _band(line, -4.5, 4.5), "road")]
    for d in (-3.5, 3.5):
        for k in range(0, len(line) - 1, 40):  # pieces of 20 m keep polygons simple
            markings.append(
                Marking(Cls.LANE_LINE, _band(line[k : k + 41], d - 0.075, d + 0.075), "solid")
            )
    for k in range(0, len(line) - 7, 18):
        markings.append(Marking(Cls.LANE_LINE, _band(line[k : k + 7], -0.075, 0.075), "dashed"))
    for k in range(200, len(line) - 10, 400):
        markings.append(Marking(Cls.STOP_LINE, _band(line[k : k + 2], -3.4, -0.1), "stop"))
    return World(
        "synthetic-road",
        markings,
        routes=[_offset(line, -1.75)],
        km_of_road=len(line) * 0.5 / 1000.0,
    )


def drive(
    rng,
    *,
    length_m=1200.0,
    speed_mps=10.0,
    frame_hz=20.0,
    outage_m=(500.0, 800.0),
    scale_error=0.005,
    gyro_bias_dps=0.02,
    gnss_sigma_m=0.02,
    gnss_hz=10.0,
    lane_offset_m=-1.75,
):
    """Streams of a drive along centreline(length_m) in the right lane (drive log layout)."""
    line = _offset(centreline(length_m), lane_offset_m)
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    s_line = np.concatenate([[0.0], np.cumsum(seg)])
    total_s = (s_line[-1] - 1.0) / speed_mps

    def truth_at(t_s):
        s = np.clip(t_s * speed_mps, 0, s_line[-1])
        x, y = np.interp(s, s_line, line[:, 0]), np.interp(s, s_line, line[:, 1])
        hx, hy = np.gradient(line[:, 0]), np.gradient(line[:, 1])
        yaw = np.unwrap(np.arctan2(hy, hx))
        return np.stack([x, y, np.interp(s, s_line, yaw)], axis=-1)

    t_frame = np.arange(0.0, total_s, 1.0 / frame_hz)
    t_odom = np.arange(0.0, total_s, 1.0 / 83.0)
    t_imu = np.arange(0.0, total_s, 1.0 / 100.0)
    t_gnss = np.arange(0.0, total_s, 1.0 / gnss_hz)
    truth_imu = truth_at(t_imu)
    yaw_rate = np.gradient(truth_imu[:, 2], t_imu)
    gnss_true = truth_at(t_gnss)
    s_gnss = t_gnss * speed_mps
    ok = (
        ~((s_gnss >= outage_m[0]) & (s_gnss < outage_m[1]))
        if outage_m
        else np.ones(len(t_gnss), bool)
    )
    t_truth = np.arange(0.0, total_s, 0.01)
    return {
        "frame_t_ns": (t_frame * NS).astype(np.int64),
        "frame_pose_true": truth_at(t_frame),
        "odom_t_ns": (t_odom * NS).astype(np.int64),
        "odom_speed_mps": speed_mps * (1 + scale_error) + rng.normal(0, 0.02, len(t_odom)),
        "imu_t_ns": (t_imu * NS).astype(np.int64),
        "imu_yaw_rate_rps": yaw_rate
        + math.radians(gyro_bias_dps)
        + rng.normal(0, math.radians(0.1), len(t_imu)),
        "gnss_t_ns": (t_gnss * NS).astype(np.int64),
        "gnss_xy_m": gnss_true[:, :2] + rng.normal(0, gnss_sigma_m, (len(t_gnss), 2)),
        "gnss_sigma_m": np.full(len(t_gnss), gnss_sigma_m),
        "gnss_ok": ok,
        "truth_t_ns": (t_truth * NS).astype(np.int64),
        "truth_pose": truth_at(t_truth),
    }


def mapping_camera() -> CameraModel:
    return camera_from_config(CameraConfig())


class LabelRenderer:
    """True label image of a frame: every pixel's ground point looked up in the world raster."""

    def __init__(self, world: World, camera: CameraModel, max_range_m: float = 30.0):
        self.camera = camera
        v, u = np.mgrid[0 : camera.height, 0 : camera.width]
        uv = np.stack([u.ravel() + 0.5, v.ravel() + 0.5], axis=1).astype(float)
        g = camera.ground_points(uv)
        self.valid = np.isfinite(g[:, 0]) & (np.hypot(g[:, 0], g[:, 1]) < max_range_m)
        self.ground_v = g[self.valid]
        self.raster, self.x0, self.y0 = world.rasterize_all(margin_m=5.0)

    def render(self, pose) -> np.ndarray:
        x, y, yaw = pose
        c, s = math.cos(yaw), math.sin(yaw)
        gx = x + c * self.ground_v[:, 0] - s * self.ground_v[:, 1]
        gy = y + s * self.ground_v[:, 0] + c * self.ground_v[:, 1]
        col = np.floor((gx - self.x0) / 0.1).astype(np.int64)
        row = np.floor((gy - self.y0) / 0.1).astype(np.int64)
        h, w = self.raster.shape
        inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        values = np.zeros(len(gx), np.uint8)
        values[inside] = self.raster[row[inside], col[inside]]
        out = np.zeros(self.camera.height * self.camera.width, np.uint8)
        out[self.valid] = values
        return out.reshape(self.camera.height, self.camera.width)


def write_drive_log(root, rng, *, vehicle="map-0", traversal="t0", frame_stride=1, **drive_kw):
    """A label-only drive log (no RGB) of a synthetic drive; returns (root, world, streams)."""
    length_m = drive_kw.get("length_m", 1200.0)
    world = road_world(centreline(length_m))
    streams = drive(rng, **drive_kw)
    camera = mapping_camera()
    meta = DriveLogMeta(
        vehicle=vehicle,
        traversal=traversal,
        profile="mapping",
        world={"name": world.name, "origin_lat": 0.0, "origin_lon": 0.0},
        camera=camera,
        notes={"source": "services/vehicle/synthetic.py"},
    )
    writer = DriveLogWriter(root, meta)
    renderer = LabelRenderer(world, camera)
    if frame_stride > 1:
        for k in ("frame_t_ns", "frame_pose_true"):
            streams[k] = streams[k][::frame_stride]
    for i, pose in enumerate(streams["frame_pose_true"]):
        writer.write_frame(i, None, renderer.render(pose))
    writer.close(streams)
    return root, world, streams
