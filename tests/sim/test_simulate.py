"""Drive simulation end to end: drive logs round-trip through common.drivelog, with ground truth
consistent across streams, seeded, and overlapping routes for mapping vehicles."""

import json
import math

import numpy as np
import pytest

from common.drivelog import DriveLog
from common.geometry import wrap_angle
from services.sim.simulate import simulate_drives
from services.sim.worlds import load_world
from tests.conftest import roadmap


@pytest.fixture(scope="module")
def world():
    return load_world("town:1", seed=1)


@pytest.fixture(scope="module")
def logs(world, tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    return simulate_drives(
        world, out, vehicles=2, drives=1, profile="mapping", seed=3, images=True, max_km=0.05
    )


def test_drive_log_round_trip(logs):
    assert [p.name for p in logs] == ["map-0-d0", "map-1-d0"]
    log = DriveLog(logs[0])
    s = log.streams
    n = len(log)
    assert n > 50 and s["frame_pose_true"].shape == (n, 3)
    for k in ("frame_t_ns", "odom_t_ns", "imu_t_ns", "gnss_t_ns", "truth_t_ns"):
        assert s[k].dtype == np.int64 and np.all(np.diff(s[k]) > 0)
    assert np.median(np.diff(s["frame_t_ns"])) == pytest.approx(1e8)
    assert log.image(0).shape == (log.meta.camera.height, log.meta.camera.width, 3)
    assert log.labels(n - 1).shape == (log.meta.camera.height, log.meta.camera.width)
    assert log.meta.vehicle == "map-0" and log.meta.profile == "mapping"
    cal = json.loads((logs[0] / "log.json").read_text())["notes"]["calibration_error_rad"]
    assert math.degrees(np.linalg.norm(cal)) == pytest.approx(0.1)


def test_frame_poses_match_dense_truth(logs):
    s = DriveLog(logs[0]).streams
    x = np.interp(s["frame_t_ns"], s["truth_t_ns"], s["truth_pose"][:, 0])
    assert np.abs(x - s["frame_pose_true"][:, 0]).max() < 0.05
    # the yaw integrates to the heading change (gyro minus its bias)
    w = s["imu_yaw_rate_rps"]
    dyaw = np.sum(w[:-1] * np.diff(s["imu_t_ns"]) / 1e9)
    true = np.unwrap(s["truth_pose"][:, 2])
    assert abs(wrap_angle(dyaw - (true[-1] - true[0]))) < math.radians(3)


def test_labels_show_the_road_ahead(logs):
    log = DriveLog(logs[0])
    lab = log.labels(len(log) // 2)
    h = lab.shape[0]
    assert (lab[int(0.8 * h) :] > 0).mean() > 0.5  # road right in front
    assert (lab[: int(0.3 * h)] == 0).all()  # sky


def test_mapping_vehicles_drive_the_same_roads(logs):
    a, b = (DriveLog(p).streams["frame_pose_true"][:, :2] for p in logs)
    d = np.min(np.linalg.norm(a[:, None] - b[None], axis=2), axis=1)
    assert np.median(d) < 4.0


def test_simulation_is_seeded(world, tmp_path):
    a = simulate_drives(world, tmp_path / "a", seed=5, images=False, max_km=0.05)[0]
    b = simulate_drives(world, tmp_path / "b", seed=5, images=False, max_km=0.05)[0]
    c = simulate_drives(world, tmp_path / "c", seed=6, images=False, max_km=0.05)[0]
    sa, sb, sc = (DriveLog(p).streams for p in (a, b, c))
    assert all(np.array_equal(sa[k], sb[k]) for k in sa)
    assert not np.array_equal(sa["gnss_xy_m"], sc["gnss_xy_m"])
    assert np.array_equal(DriveLog(a).labels(10), DriveLog(b).labels(10))


def test_production_profile_and_later_seeds_are_later_in_time(world, tmp_path):
    m = simulate_drives(world, tmp_path / "m", seed=0, images=False, max_km=0.05)[0]
    p = simulate_drives(
        world, tmp_path / "p", seed=1000, images=False, max_km=0.05, profile="production"
    )[0]
    lp = DriveLog(p)
    assert lp.meta.vehicle == "prod-0" and lp.meta.profile == "production"
    assert lp.streams["frame_t_ns"][0] > DriveLog(m).streams["frame_t_ns"][-1]


def test_cli_sim_prints_a_summary(tmp_path):
    out = roadmap("sim", "--world", "town:1", "--out", tmp_path, "--no-images", "--max-km",
                  0.05, "--vehicles", 2, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "2 drive logs" in out.stdout and "km" in out.stdout and "frames" in out.stdout
    assert (tmp_path / "map-1-d0" / "log.json").exists()


def test_cli_world_render_writes_a_png(tmp_path):
    out = roadmap("world", "render", "--world", "town:1", "--out", tmp_path / "map.png",
                  timeout=120)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "map.png").stat().st_size > 1000


def test_comma2k19_converts_to_a_drive_log(shared_data, tmp_path):
    from services.sim.comma2k19 import convert

    log = DriveLog(convert(shared_data / "comma2k19" / "segment40", tmp_path / "comma"))
    s = log.streams
    assert len(log) == 1200 and log.image(0).shape == (874, 1164, 3) and log.image(1) is None
    steps = np.linalg.norm(np.diff(s["frame_pose_true"][:, :2], axis=0), axis=1)
    assert 0.9 < steps.sum() / 1000 < 1.1  # about 1 km
    # heading agrees with the direction of motion; gyro sign agrees with the heading change
    heading = np.arctan2(*np.diff(s["frame_pose_true"][:, :2], axis=0).T[::-1])
    assert np.degrees(np.abs(wrap_angle(heading - s["frame_pose_true"][:-1, 2]))).mean() < 3
    t = s["frame_t_ns"] / 1e9
    ref = np.gradient(np.unwrap(s["frame_pose_true"][:, 2]), t)
    gyro = np.interp(t, s["imu_t_ns"] / 1e9, s["imu_yaw_rate_rps"])
    assert np.corrcoef(ref, gyro)[0, 1] > 0.5
    # consumer GNSS within a few metres of the reference
    gx = np.interp(s["gnss_t_ns"], s["frame_t_ns"], s["frame_pose_true"][:, 0])
    gy = np.interp(s["gnss_t_ns"], s["frame_t_ns"], s["frame_pose_true"][:, 1])
    assert np.median(np.hypot(s["gnss_xy_m"][:, 0] - gx, s["gnss_xy_m"][:, 1] - gy)) < 3.0


def test_labels_map_back_onto_the_world_through_the_logged_camera(world, tmp_path):
    """IPM of the true label images with the logged (miscalibrated by 0.1 deg) camera at the true
    poses lands on the world's own markings: the chain the vehicle mapper relies on."""
    import cv2

    from common.camera import build_ipm_lookup
    from common.classes import Cls
    from common.geometry import transform_points_2d

    log = DriveLog(simulate_drives(world, tmp_path, images=False, max_km=0.1, seed=2)[0])
    ipm = build_ipm_lookup(log.meta.camera, x_min_m=3.0, length_m=12.0, width_m=8.0)
    pts, cls = [], []
    for i in range(0, len(log), 4):
        xy, c = ipm.lookup(log.labels(i))
        pts.append(transform_points_2d(log.streams["frame_pose_true"][i], xy))
        cls.append(c)
    pts, cls = np.concatenate(pts), np.concatenate(cls)
    x0, y0 = pts.min(axis=0) - 2.0
    x1, y1 = pts.max(axis=0) + 2.0
    truth = world.rasterize(x0, y0, int((y1 - y0) / 0.1), int((x1 - x0) / 0.1))
    for c in (Cls.ROAD, Cls.LANE_LINE):
        ij = ((pts[cls == c] - [x0, y0]) / 0.1).astype(int)
        near = cv2.dilate((truth == c).astype(np.uint8), np.ones((3, 3), np.uint8))
        assert len(ij) > 1000 and near[ij[:, 1], ij[:, 0]].mean() > 0.97


def test_more_vehicles_of_a_fleet_get_their_own_ids_and_drives(world, tmp_path):
    """first_vehicle (the demo's extra vehicles): ids after the fleet's, on the given route, each
    vehicle's drive as that vehicle would have driven it in a larger fleet."""
    (extra,) = simulate_drives(world, tmp_path / "x", vehicles=1, seed=5, images=False,
                               max_km=0.05, route=0, first_vehicle=3)
    assert extra.name == "map-3-d0"
    (fleet_v3,) = [p for p in simulate_drives(world, tmp_path / "f", vehicles=4, seed=5,
                                              images=False, max_km=0.05, route=0)
                   if p.name == "map-3-d0"]
    a, b = DriveLog(extra).streams, DriveLog(fleet_v3).streams
    assert all(np.array_equal(a[k], b[k]) for k in a)  # same seed and time slot per vehicle
