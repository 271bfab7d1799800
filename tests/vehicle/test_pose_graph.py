"""Pose graph and estimator: perturb-then-recover, outage bridging, odometry integration."""

import math

import numpy as np
import pytest

from common.geometry import se2_between
from services.vehicle.estimator import PoseEstimator, integrate_odometry
from services.vehicle.pose_graph import PoseGraph
from services.vehicle.synthetic import drive


def _run_estimator(streams, **kw):
    est = PoseEstimator(**kw)
    s = streams
    o = i = g = 0
    poses = {}
    for t in s["frame_t_ns"]:
        o2, i2, g2 = (
            int(np.searchsorted(s[k], t, "right")) for k in ("odom_t_ns", "imu_t_ns", "gnss_t_ns")
        )
        est.add_odometry(s["odom_t_ns"][o:o2], s["odom_speed_mps"][o:o2])
        est.add_imu(s["imu_t_ns"][i:i2], s["imu_yaw_rate_rps"][i:i2])
        for k in range(g, g2):
            est.add_gnss(
                s["gnss_t_ns"][k], s["gnss_xy_m"][k], s["gnss_sigma_m"][k], s["gnss_ok"][k]
            )
        o, i, g = o2, i2, g2
        est.add_frame(int(t))
        poses.update(est.settled())
    poses.update(est.settled(flush=True))
    return est, np.array([poses[k] for k in range(len(s["frame_t_ns"]))])


def test_pose_graph_recovers_from_perturbed_start(rng):
    truth = np.array([[k * 1.0, 0.02 * k**1.5, 0.03 * math.sqrt(k)] for k in range(60)])
    g = PoseGraph()
    g.add_node(0, truth[0] + [1.5, -1.0, 0.2])
    g.add_prior(0, truth[0] + [1.5, -1.0, 0.2], sigmas=[5.0, 5.0, 1.0])
    for k in range(1, len(truth)):
        g.add_node(k, truth[k] + rng.normal(0, [0.5, 0.5, 0.05]))
        g.add_odometry(k - 1, k, se2_between(truth[k - 1], truth[k]))
    for k in range(0, len(truth), 3):
        g.add_gnss(k, truth[k, :2] + rng.normal(0, 0.02, 2), 0.02)
    g.optimize(iterations=6)
    est = g.estimates()
    err = np.array([np.linalg.norm(est[k][:2] - truth[k, :2]) for k in range(len(truth))])
    yaw_err = np.array([abs(est[k][2] - truth[k, 2]) for k in range(len(truth))])
    assert err.max() < 0.03
    assert yaw_err.max() < 0.003


@pytest.fixture(scope="module")
def outage_run():
    s = drive(np.random.default_rng(0), length_m=1100.0, outage_m=(600.0, 900.0))
    est, poses = _run_estimator(s)
    return s, est, poses


def test_estimator_bridges_300m_gnss_outage(outage_run):
    s, est, poses = outage_run
    truth = s["frame_pose_true"]
    err = np.linalg.norm(poses[:, :2] - truth[:, :2], axis=1)
    outage = np.array([not est.covered(k) for k in range(len(err))])
    assert outage.sum() * 0.05 * 10.0 > 290.0  # about 300 m of frames had no fix
    assert err[outage].mean() <= 0.10
    assert err.mean() <= 0.05
    # calibration found the simulated 0.5 % scale error and 0.02 deg/s gyro bias
    assert abs(est.calibration.scale - 1 / 1.005) < 1e-3
    assert abs(math.degrees(est.calibration.gyro_bias_rps) - 0.02) < 0.006


def test_uncalibrated_odometry_drifts_through_the_outage(outage_run):
    s, est, _ = outage_run
    raw = est.raw_deltas()
    outage = np.flatnonzero([not est.covered(k) for k in range(len(raw))])
    a, b = outage[0] - 1, outage[-1]
    pose = s["frame_pose_true"][a].copy()
    from services.vehicle.estimator import dead_reckon

    dr = dead_reckon(pose, raw[a + 1 : b + 1])
    end_err = np.linalg.norm(dr[-1, :2] - s["frame_pose_true"][b, :2])
    assert end_err > 0.5  # what the pose graph corrects


def test_integrate_odometry_on_a_circle():
    t = np.arange(0, 2.01, 0.01)
    t_ns = (t * 1e9).astype(np.int64)
    v, w = np.full(len(t), 5.0), np.full(len(t), 0.5)
    delta, dist = integrate_odometry(0, int(2e9), t_ns, v, t_ns, w)
    r, th = 10.0, 1.0
    assert abs(dist - 10.0) < 1e-9
    np.testing.assert_allclose(delta, [r * math.sin(th), r * (1 - math.cos(th)), th], atol=1e-4)
    scaled, _ = integrate_odometry(0, int(2e9), t_ns, v, t_ns, w, scale=2.0, gyro_bias_rps=0.5)
    np.testing.assert_allclose(scaled, [20.0, 0.0, 0.0], atol=1e-9)


def test_bad_gnss_fixes_are_ignored(rng):
    s = drive(rng, length_m=200.0, outage_m=None)
    s["gnss_ok"][::2] = False
    s["gnss_xy_m"][::2] += 50.0  # garbage when not ok
    _, poses = _run_estimator(s)
    err = np.linalg.norm(poses[:, :2] - s["frame_pose_true"][:, :2], axis=1)
    assert err.max() < 0.1
