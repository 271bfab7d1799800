"""Sensor noise has the configured statistics (DESIGN.md noise profiles)."""

import math

import numpy as np
import pytest

from common.world import World
from services.sim import motion, sensors
from services.sim.sensors import PROFILES


@pytest.fixture(scope="module")
def traj():
    t = np.linspace(0, 2 * np.pi, 400)
    route = np.stack([400 * np.cos(t), 250 * np.sin(t)], axis=1)  # a 2 km oval
    return motion.drive(route, np.random.default_rng(0))


def test_motion_is_realistic(traj):
    assert 8.0 <= np.percentile(traj.speed, 90) <= 15.0
    acc = np.gradient(traj.speed, traj.t_s)
    assert np.abs(acc).max() < 2.5
    assert np.max(np.abs(traj.speed * traj.yaw_rate)) < 2.5  # lateral acceleration, m/s^2


@pytest.mark.parametrize("name", ["mapping", "production"])
def test_odometry_scale_error_and_noise(traj, name, rng):
    p = PROFILES[name]
    t, v, scale = sensors.odometry(traj, p, rng)
    assert np.median(np.diff(t)) == pytest.approx(1 / p.odom_hz)
    assert abs(scale - 1) == pytest.approx(p.odom_scale_error)
    true = traj.at(t, "speed")
    moving = true > 3
    assert np.median(v[moving] / true[moving]) == pytest.approx(scale, abs=0.002)
    assert np.std(v - true * scale) == pytest.approx(p.odom_noise_mps, rel=0.15)


@pytest.mark.parametrize("name", ["mapping", "production"])
def test_gyro_bias_and_noise(traj, name, rng):
    p = PROFILES[name]
    t, w, bias = sensors.gyro(traj, p, rng)
    err = w - traj.at(t, "yaw_rate")
    assert abs(math.degrees(bias)) == pytest.approx(p.gyro_bias_dps)
    assert np.mean(err) == pytest.approx(bias, abs=math.radians(0.005))
    assert np.std(err) == pytest.approx(math.radians(p.gyro_noise_dps), rel=0.1)


def test_rtk_gnss_noise_and_outages(traj, rng):
    p = PROFILES["mapping"]
    zone = np.array([[-500.0, 0.0], [500.0, 0.0], [500.0, 300.0], [-500.0, 300.0]])
    world = World("w", [], gnss_blocked=[zone])
    t, xy, sigma, ok = sensors.gnss(traj, p, world, rng)
    true = traj.poses(t)[:, :2]
    assert np.median(np.diff(t)) == pytest.approx(0.1)
    assert np.array_equal(ok, true[:, 1] < 0)  # lost exactly inside the zone
    err = xy[ok] - true[ok]
    assert np.std(err) == pytest.approx(0.02, rel=0.15)
    assert np.all(sigma[ok] == 0.02) and np.all(np.isfinite(xy))


def test_consumer_gnss_has_metres_of_slowly_varying_bias(traj, rng):
    p = PROFILES["production"]
    errs = []
    for seed in range(8):
        t, xy, _, ok = sensors.gnss(traj, p, World("w", []), np.random.default_rng(seed))
        errs.append(np.linalg.norm(xy - traj.poses(t)[:, :2], axis=1))
        assert ok.all() and 1.0 <= 1 / np.median(np.diff(t)) <= 10.0
    e = np.concatenate(errs)
    assert 1.5 <= np.sqrt(np.mean(e**2)) <= 3.0
    # slowly varying: consecutive fixes share most of their error
    d = np.diff(xy - traj.poses(t)[:, :2], axis=0)
    assert np.std(d) < 0.7


def test_vibration_and_calibration_error(rng):
    p = PROFILES["production"]
    shake = sensors.vibration(20000, p, rng)
    assert np.degrees(np.std(shake, axis=0)) == pytest.approx([0.3, 0.3], rel=0.1)
    cal = sensors.calibration_error(p, rng)
    assert math.degrees(np.linalg.norm(cal)) == pytest.approx(0.2)
