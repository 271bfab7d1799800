"""Drive simulation with ground truth: vehicles drive a world's routes and write drive logs
(common/drivelog.py) with true poses, true label images, optionally rendered RGB frames,
wheel odometry, gyro and GNSS of the mapping or production noise profile (DESIGN.md).

Conventions of the simulated logs: frames 10 Hz, odometry 50 Hz, gyro 100 Hz, GNSS 10 Hz (RTK) or
5 Hz (consumer), dense truth 100 Hz. Inside a GNSS-blocked zone a fix has gnss_ok False, sigma 50 m
and a corrupted position: use only fixes with gnss_ok. The logged camera is the configured one; the
images are rendered with it rotated by the calibration error (notes.calibration_error_rad) and a
per-frame pitch/roll vibration. Label images are 0 above the horizon and on other vehicles.
Times start at 1.6e9 s + seed * 1e6 s + slot * 3600 s, so a later seed is a later traversal."""

import logging
import math
import signal
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.camera import CameraModel, camera_from_config
from common.config import CameraConfig
from common.drivelog import DriveLogMeta, DriveLogWriter
from common.errors import WorldError
from common.world import World
from services.sim import motion, paint, sensors
from services.sim.render import FrameRenderer, Vehicle

logger = logging.getLogger(__name__)

FRAME_HZ = 10.0
TRUTH_HZ = 100.0
BASE_TIME_S = 1_600_000_000
NS = sensors.NS
PREFIX = {"mapping": "map", "production": "prod"}


@dataclass
class DriveSummary:
    path: Path
    km: float
    frames: int
    gnss_outage_s: float


def simulate_drives(
    world: World,
    out_dir,
    *,
    vehicles: int = 1,
    drives: int = 1,
    profile: str = "mapping",
    seed: int = 0,
    images: bool = True,
    max_km: float | None = None,
    route=None,
    camera: CameraModel | None = None,
    noise: sensors.NoiseProfile | None = None,
    progress=None,
    first_vehicle: int = 0,
    workers: int = 1,
) -> list[Path]:
    """Write one drive log per (vehicle, drive) into out_dir/<vehicle>-d<drive>/.

    Vehicles of a world share its first route (other lanes of the same roads where the world has
    them), so their maps overlap; `route` (index or (N, 2) polyline) overrides it. Each drive
    differs in lane offset, speeds, sensor noise and looks. `noise` replaces the profile's
    noise model (e.g. a harder one in a test); `progress(done, total)` is called per frame.
    Vehicles are numbered from first_vehicle (more vehicles of the same fleet, their own ids,
    seeds and time slots). `workers` > 1 renders that many drives at once in forked processes
    (each drive has its own seed: the same logs as one at a time; progress is then called in
    the workers)."""
    return run_drives(drive_jobs(world, out_dir, vehicles=vehicles, drives=drives,
                                 profile=profile, seed=seed, images=images, max_km=max_km,
                                 route=route, camera=camera, noise=noise, progress=progress,
                                 first_vehicle=first_vehicle),
                      workers=workers)


def drive_jobs(world: World, out_dir, *, vehicles: int = 1, drives: int = 1,
               profile: str = "mapping", seed: int = 0, images: bool = True,
               max_km: float | None = None, route=None, camera: CameraModel | None = None,
               noise: sensors.NoiseProfile | None = None, progress=None,
               first_vehicle: int = 0) -> list[dict]:
    """simulate_drives' drives as jobs for run_drives (to render the drives of several calls
    together)."""
    if profile not in sensors.PROFILES:
        raise WorldError(f"unknown profile {profile!r} (mapping | production)")
    camera = camera or camera_from_config(CameraConfig())
    return [dict(world=world, out_dir=Path(out_dir), v=v, d=d, vehicles=vehicles,
                 profile=profile, seed=seed, images=images, max_km=max_km, route=route,
                 camera=camera, noise=noise or sensors.PROFILES[profile], progress=progress)
            for d in range(drives) for v in range(first_vehicle, first_vehicle + vehicles)]


_JOBS: list[dict] = []  # the drives of run_drives, inherited by its forked workers


def run_drives(jobs: list[dict], workers: int = 1) -> list[Path]:
    """The drive logs of drive_jobs' jobs, in order; `workers` > 1: that many at once in forked
    processes (the jobs reach them by fork, unpickled: a world's markings are large)."""
    if workers <= 1 or len(jobs) <= 1:
        return [_drive_one(**job) for job in jobs]
    import multiprocessing

    global _JOBS
    _JOBS = jobs
    try:
        with multiprocessing.get_context("fork").Pool(min(workers, len(jobs)),
                                                      initializer=die_with_parent) as pool:
            return pool.map(_job, range(len(jobs)), chunksize=1)
    finally:
        _JOBS = []


def die_with_parent() -> None:
    """Linux: SIGKILL this process when its parent dies, so that a demo killed mid-render (even
    by SIGKILL, which runs no cleanup) leaves no render worker behind. Elsewhere: nothing."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    PR_SET_PDEATHSIG = 1
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


def _job(i: int) -> Path:
    return _drive_one(**_JOBS[i])


def _drive_one(
    world,
    out_dir,
    *,
    v,
    d,
    vehicles,
    profile,
    seed,
    images,
    max_km,
    route,
    camera,
    progress,
    noise=None,
) -> Path:
    """Drive d of vehicle v: its own seed, time slot and log directory."""
    vehicle = f"{PREFIX[profile]}-{v}"
    slot = d * vehicles + v
    drive_seed = np.random.SeedSequence([seed, v, d, 0 if profile == "mapping" else 1])
    summary = simulate_drive(
        world,
        Path(out_dir) / f"{vehicle}-d{d}",
        vehicle=vehicle,
        traversal=f"{vehicle}-d{d}-s{seed}",
        profile=noise or sensors.PROFILES[profile],
        route=_route_for(world, v, route),
        camera=camera,
        rng=np.random.default_rng(drive_seed),
        images=images,
        max_km=max_km,
        t0_s=BASE_TIME_S + seed * 1_000_000 + slot * 3600,
        progress=progress,
    )
    return summary.path


def _route_for(world: World, vehicle: int, route) -> np.ndarray:
    """The route of a vehicle: explicit, or the first route and its parallel-lane variants."""
    if route is not None and not isinstance(route, (int, np.integer)):
        return np.asarray(route, float)
    if not world.routes:
        raise WorldError(f"world {world.name} has no routes")
    if route is not None:
        return world.routes[int(route) % len(world.routes)]
    first = paint.resample(world.routes[0], 2.0)[:200]
    variants = [r for r in world.routes if _follows(paint.resample(r, 2.0)[:200], first)]
    return variants[vehicle % len(variants)]


def _follows(a: np.ndarray, b: np.ndarray, tol_m: float = 8.0) -> bool:
    """Two routes run side by side (another lane of the same roads) over their first 400 m."""
    n = min(len(a), len(b))
    return n > 10 and float(np.median(np.linalg.norm(a[:n] - b[:n], axis=1))) < tol_m


def simulate_drive(
    world: World,
    root: Path,
    *,
    vehicle: str,
    traversal: str,
    profile: sensors.NoiseProfile,
    route: np.ndarray,
    camera: CameraModel,
    rng,
    images: bool,
    max_km: float | None,
    t0_s: int,
    progress=None,
) -> DriveSummary:
    """One drive: motion, sensors, camera errors, then frame by frame labels (and images)."""
    # 1. true motion along the route, with this drive's lane offset
    traj = motion.drive(
        route,
        rng,
        max_len_m=None if max_km is None else max_km * 1000.0,
        offset_m=float(np.clip(rng.normal(0.0, 0.25), -0.5, 0.5)),
        rate_hz=TRUTH_HZ,
    )
    t_frame = np.arange(0.0, traj.duration_s, 1.0 / FRAME_HZ)
    poses = traj.poses(t_frame)
    # 2. sensors at their own rates
    t_odom, v_odom, scale = sensors.odometry(traj, profile, rng)
    t_imu, w_imu, bias = sensors.gyro(traj, profile, rng)
    t_gnss, xy_gnss, sig_gnss, ok_gnss = sensors.gnss(traj, profile, world, rng)
    # 3. the camera: the logged calibration is off by the calibration error; frames vibrate
    calib = sensors.calibration_error(profile, rng)
    cam_true = camera.perturbed(*calib)
    shake = sensors.vibration(len(t_frame), profile, rng)
    others = _other_vehicles(traj, rng)
    # 4. frames
    renderer = FrameRenderer(world, cam_true, seed=int(rng.integers(2**31)))
    meta = _log_meta(world, vehicle, traversal, profile, camera, images,
                     odom_scale=scale, gyro_bias_rps=bias, calib=calib)
    writer = DriveLogWriter(root, meta)
    _write_frames(writer, renderer, cam_true, t_frame, poses, shake, others, images, progress)
    # 5. streams and meta (log.json last marks the log complete)
    t_truth = np.arange(0.0, traj.duration_s, 1.0 / TRUTH_HZ)
    ns = lambda t: (np.round(np.asarray(t) * NS) + t0_s * NS).astype(np.int64)  # noqa: E731
    writer.close({
        "frame_t_ns": ns(t_frame), "frame_pose_true": poses,
        "odom_t_ns": ns(t_odom), "odom_speed_mps": v_odom,
        "imu_t_ns": ns(t_imu), "imu_yaw_rate_rps": w_imu,
        "gnss_t_ns": ns(t_gnss), "gnss_xy_m": xy_gnss, "gnss_sigma_m": sig_gnss,
        "gnss_ok": ok_gnss,
        "truth_t_ns": ns(t_truth), "truth_pose": traj.poses(t_truth),
    })
    km = float(np.sum(np.linalg.norm(np.diff(traj.xy, axis=0), axis=1))) / 1000.0
    outage = float((~ok_gnss).sum()) / profile.gnss_hz
    logger.info("%s: %.2f km, %d frames, GNSS outage %.0f s", root.name, km, len(t_frame), outage)
    return DriveSummary(root, km, len(t_frame), outage)


def _log_meta(world: World, vehicle: str, traversal: str, profile: sensors.NoiseProfile,
              camera: CameraModel, images: bool, *, odom_scale: float, gyro_bias_rps: float,
              calib) -> DriveLogMeta:
    """The drive log's meta: who drove where with which camera, and the drive's true sensor
    errors (notes, for evaluation)."""
    return DriveLogMeta(
        vehicle=vehicle,
        traversal=traversal,
        profile=profile.name,
        world={
            "name": world.name,
            "origin_lat": world.origin_latlon[0],
            "origin_lon": world.origin_latlon[1],
        },
        camera=camera,
        notes={
            "source": "roadmap sim",
            "odom_scale": odom_scale,
            "gyro_bias_rps": gyro_bias_rps,
            "calibration_error_rad": [float(c) for c in calib],
            "vibration_deg": profile.vibration_deg,
            "images": images,
        },
    )


def _write_frames(writer: DriveLogWriter, renderer: FrameRenderer, cam_true: CameraModel,
                  t_frame, poses, shake, others, images: bool, progress=None) -> None:
    """Frame by frame: the vibrating camera's labels (and image) at the true pose."""
    for i, (t, pose) in enumerate(zip(t_frame, poses, strict=False)):
        T = cam_true.perturbed(d_pitch_rad=shake[i, 0], d_roll_rad=shake[i, 1]).T_vehicle_camera
        visible = others(t)
        if images:
            rgb, lab = renderer.render(pose, T, float(t), visible)
        else:
            rgb, lab = None, renderer.labels(pose, T, visible)
        writer.write_frame(i, rgb, lab)
        if progress:
            progress(i + 1, len(t_frame))


def _other_vehicles(traj: motion.Trajectory, rng):
    """Parked cars along the right side of the driven path and an intermittent lead car.

    Returns f(t) -> list of Vehicle visible around time t."""
    parked = []
    step = 10.0
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(traj.xy, axis=0), axis=1))])
    for at in np.arange(20.0, s[-1], step):
        if rng.random() < 0.12:
            k = int(np.searchsorted(s, at))
            x, y = traj.xy[min(k, len(s) - 1)]
            yaw = traj.yaw[min(k, len(s) - 1)]
            side = rng.uniform(2.9, 3.6)
            parked.append(
                Vehicle(
                    x + math.sin(yaw) * side,
                    y - math.cos(yaw) * side,
                    yaw,
                    rng.uniform(3.8, 4.8),
                    rng.uniform(1.7, 1.9),
                    rng.uniform(1.4, 1.7),
                    _car_colour(rng),
                )
            )
    xy_parked = np.array([[p.x, p.y] for p in parked]).reshape(-1, 2)
    lead_on = rng.random(int(traj.duration_s / 10.0) + 2) < 0.35  # lead car present per 10 s
    lead_gap = rng.uniform(10.0, 30.0, len(lead_on))
    lead_col = _car_colour(rng)
    oncoming_on = rng.random(len(lead_on)) < 0.3  # a car passes the other way per 10 s
    oncoming_col = [_car_colour(rng) for _ in range(len(lead_on))]

    def visible(t: float) -> list:
        x, y = np.interp(t, traj.t_s, traj.xy[:, 0]), np.interp(t, traj.t_s, traj.xy[:, 1])
        out = [
            parked[i]
            for i in np.flatnonzero(np.hypot(xy_parked[:, 0] - x, xy_parked[:, 1] - y) < 60.0)
        ]
        k = int(t / 10.0)
        if lead_on[k]:  # the lead car drives our path, gap metres ahead
            at = np.interp(t, traj.t_s, s) + lead_gap[k] + 3.0 * math.sin(0.5 * t)
            if at < s[-1]:
                lx, ly = np.interp(at, s, traj.xy[:, 0]), np.interp(at, s, traj.xy[:, 1])
                out.append(
                    Vehicle(lx, ly, float(np.interp(at, s, traj.yaw)), 4.4, 1.8, 1.5, lead_col)
                )
        if oncoming_on[k]:  # in the lane to our left, coming towards us
            now = np.interp(t, traj.t_s, s)
            at = np.interp(10.0 * k, traj.t_s, s) + 90.0 - 14.0 * (t - 10.0 * k)
            if now + 4.0 < at < s[-1]:
                yaw = float(np.interp(at, s, traj.yaw))
                ox = np.interp(at, s, traj.xy[:, 0]) - 3.3 * math.sin(yaw)
                oy = np.interp(at, s, traj.xy[:, 1]) + 3.3 * math.cos(yaw)
                out.append(Vehicle(ox, oy, yaw + math.pi, 4.5, 1.8, 1.5, oncoming_col[k]))
        return out

    return visible


CAR_COLOURS = (
    (235, 235, 235),
    (25, 25, 28),
    (160, 162, 165),
    (95, 98, 102),
    (30, 45, 95),
    (150, 25, 25),
    (200, 200, 190),
    (60, 70, 60),
)


def _car_colour(rng) -> tuple:
    base = np.array(CAR_COLOURS[int(rng.integers(len(CAR_COLOURS)))], float)
    return tuple(np.clip(base * rng.uniform(0.85, 1.1), 0, 255))
