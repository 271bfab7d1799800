"""Seeded synthetic maps, drives and frames for the localizer tests and benchmark."""

import math

import numpy as np

from common.classes import Cls
from common.grid import TILE_CELLS, TILE_M, tile_origin_m
from common.world import Marking, World


def _rect(x0, x1, y0, y1):
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)


def straight_road(length_m=240.0, y_m=30.0, features=True, dashed=True) -> World:
    """Two-lane road along +x at y = y_m: solid edges, dashed centre, optional stop line,
    crosswalk and arrows. With features=False and dashed=False only parallel lines remain."""
    x0, x1 = 5.0, 5.0 + length_m
    m = [Marking(Cls.ROAD, _rect(x0, x1, y_m - 3.6, y_m + 3.6))]
    for yy in (y_m - 3.4, y_m + 3.4):
        m.append(Marking(Cls.LANE_LINE, _rect(x0, x1, yy - 0.075, yy + 0.075), "solid"))
    if dashed:
        for xs in np.arange(x0 + 2.0, x1 - 3.0, 9.0):
            m.append(
                Marking(Cls.LANE_LINE, _rect(xs, xs + 3.0, y_m - 0.075, y_m + 0.075), "dashed")
            )
    else:
        m.append(Marking(Cls.LANE_LINE, _rect(x0, x1, y_m - 0.075, y_m + 0.075), "solid"))
    if features:
        for xs in (60.0, 150.0):
            m.append(Marking(Cls.STOP_LINE, _rect(xs, xs + 0.4, y_m - 3.4, y_m), "stop"))
            for k in range(6):
                yy = y_m - 3.3 + k * 1.1
                m.append(Marking(Cls.CROSSWALK, _rect(xs + 2.0, xs + 5.0, yy, yy + 0.5), "zebra"))
        for xs in np.arange(x0 + 20.0, x1 - 10.0, 37.0):
            arrow = np.array(
                [
                    [0, -0.15],
                    [3.0, -0.15],
                    [3.0, -0.5],
                    [4.2, 0],
                    [3.0, 0.5],
                    [3.0, 0.15],
                    [0, 0.15],
                ]
            )
            m.append(Marking(Cls.GROUND_SIGN, arrow + [xs, y_m - 1.75], "arrow"))
            m.append(Marking(Cls.GROUND_SIGN, arrow * [-1, 1] + [xs + 20, y_m + 1.75], "arrow"))
    route = np.array([[x0, y_m - 1.75], [x1, y_m - 1.75]])
    return World("straight", m, routes=[route], km_of_road=length_m / 1000.0)


def world_tiles(world: World) -> dict:
    """Every tile the world touches -> its ground-truth label raster."""
    bx0, by0, bx1, by1 = world.bounds(1.0)
    out = {}
    for tx in range(math.floor(bx0 / TILE_M), math.floor(bx1 / TILE_M) + 1):
        for ty in range(math.floor(by0 / TILE_M), math.floor(by1 / TILE_M) + 1):
            x0, y0 = tile_origin_m((tx, ty))
            out[(tx, ty)] = world.rasterize(x0, y0, TILE_CELLS, TILE_CELLS)
    return out


def roi_grid(step_m=0.1, x_min=3.0, length=12.0, width=8.0):
    xs = np.arange(x_min, x_min + length, step_m) + step_m / 2
    ys = np.arange(-width / 2, width / 2, step_m) + step_m / 2
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def frame_points(cache, pose, rng, grid=None, noise_m=0.03, outliers=0.02, keep_road=0.1):
    """Semantic points of one frame seen at the true pose: ROI cells' classes from the map,
    jittered, with a few outliers; road points thinned to keep_road."""
    from common.geometry import transform_points_2d

    pts = roi_grid(0.1) if grid is None else grid
    cls = cache.class_at(transform_points_2d(np.asarray(pose), pts))
    keep = (cls >= Cls.LANE_LINE) | ((cls == Cls.ROAD) & (rng.random(len(cls)) < keep_road))
    pts, cls = pts[keep], cls[keep]
    pts = pts + rng.normal(0.0, noise_m, pts.shape)
    n_out = int(outliers * len(pts))
    if n_out:
        idx = rng.integers(0, len(pts), n_out)
        pts[idx] += rng.normal(0.0, 2.0, (n_out, 2))
    return pts, cls


def fill_cache(cache, world: World):
    for tile, labels in world_tiles(world).items():
        cache.put(tile, 1, labels)
    return cache


def synthetic_drive(
    rng,
    *,
    duration_s=20.0,
    speed_mps=10.0,
    start=(12.0, 28.25, 0.0),
    frame_hz=10.0,
    imu_hz=100.0,
    gnss_hz=5.0,
    odom_scale=1.01,
    gyro_bias_rps=0.000873,  # 0.05 deg/s
    gnss_bias_m=(2.0, -1.5),
    gnss_sigma_m=1.5,
    gnss_reported_sigma_m=None,
    weave_m=0.6,
):
    """A production drive along the straight road with a gentle lane weave: dict of streams
    (times in ns) as in a drive log, with the true pose at frames. The receiver reports
    gnss_reported_sigma_m (default: its white noise's sigma) whatever its bias."""
    dt = 1.0 / imu_hz
    n = int(duration_s * imu_hz)
    t = np.arange(n) * dt
    # lateral weave: y(t) = y0 + weave * sin(2 pi t / 10)
    x = start[0] + speed_mps * t
    y = start[1] + weave_m * np.sin(2 * np.pi * t / 10.0)
    vy = weave_m * 2 * np.pi / 10.0 * np.cos(2 * np.pi * t / 10.0)
    yaw = np.arctan2(vy, speed_mps) + start[2]
    speed = np.hypot(speed_mps, vy)
    yaw_rate = np.gradient(np.unwrap(yaw), dt)
    t_ns = (t * 1e9).astype(np.int64)
    truth = np.stack([x, y, yaw], axis=1)
    fidx = np.arange(0, n, int(imu_hz / frame_hz))
    gidx = np.arange(0, n, int(imu_hz / gnss_hz))
    bias = np.asarray(gnss_bias_m) + np.cumsum(rng.normal(0, 0.02, (len(gidx), 2)), axis=0)
    return {
        "frame_t_ns": t_ns[fidx],
        "frame_pose_true": truth[fidx],
        "odom_t_ns": t_ns,
        "odom_speed_mps": speed * odom_scale + rng.normal(0, 0.02, n),
        "imu_t_ns": t_ns,
        "imu_yaw_rate_rps": yaw_rate + gyro_bias_rps + rng.normal(0, 0.002, n),
        "gnss_t_ns": t_ns[gidx],
        "gnss_xy_m": truth[gidx, :2] + bias + rng.normal(0, gnss_sigma_m, (len(gidx), 2)),
        "gnss_sigma_m": np.full(len(gidx), gnss_reported_sigma_m or gnss_sigma_m),
        "gnss_ok": np.ones(len(gidx), bool),
        "truth_t_ns": t_ns,
        "truth_pose": truth,
    }


def render_labels(cache, ipm, pose) -> np.ndarray:
    """Label image of a frame: every ROI pixel takes the map class at its ground point."""
    from common.geometry import transform_points_2d

    labels = np.zeros(ipm.width * ipm.height, dtype=np.uint8)
    labels[ipm.pixel_index] = cache.class_at(transform_points_2d(np.asarray(pose), ipm.ground_xy_m))
    return labels.reshape(ipm.height, ipm.width)


def write_log(root, cache, streams, camera, vehicle="prod-0"):
    """A label-only production drive log whose frames are rendered from the map."""
    from common.camera import build_ipm_lookup
    from common.drivelog import DriveLogMeta, DriveLogWriter

    ipm = build_ipm_lookup(camera, x_min_m=3.0, length_m=12.0, width_m=8.0)
    meta = DriveLogMeta(
        vehicle,
        f"{vehicle}-d0",
        "production",
        {"name": "straight", "origin_lat": 0.0, "origin_lon": 0.0},
        camera,
    )
    w = DriveLogWriter(root, meta)
    for i, pose in enumerate(streams["frame_pose_true"]):
        w.write_frame(i, None, render_labels(cache, ipm, pose))
    w.close(streams)
    return root
