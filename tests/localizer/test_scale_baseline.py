"""The odometry scale from along-road fixes a baseline apart (services/localizer/scale_baseline.py)."""

import math

import numpy as np
import pytest

from services.localizer.ekf import PoseFilter
from services.localizer.scale_baseline import ScaleBaselines, prior_free


def test_prior_free_takes_the_prediction_back_out_of_a_match():
    along = np.array([1.0, 0.0])
    prior, prior_cov = np.array([10.0, 0.0]), np.diag([0.2**2, 0.1**2])
    info = np.diag([1 / 0.1**2, 1 / 0.05**2])
    z_true = np.array([10.5, 0.0])  # what the match alone saw
    i_p, i_m = 1 / 0.2**2, 1 / 0.1**2
    post = prior + along * (i_m / (i_p + i_m)) * (z_true - prior)[0]  # the MAP along the road
    z, sigma = prior_free(post, prior, prior_cov, info, along)
    assert z == pytest.approx(z_true) and sigma == pytest.approx(0.1)


def test_a_baseline_measures_the_scale_and_a_short_one_nothing():
    b = ScaleBaselines(baseline_m=100.0, floor_m=0.05)
    assert b.fix(np.zeros(2), np.array([5.0, 5.0]), 0.1) is None
    assert b.fix(np.array([60.0, 0.0]), np.array([65.6, 5.0]), 0.1) is None  # 60 m: too short
    scale, sigma = b.fix(np.array([0.0, 120.0]), np.array([5.0, 5.0 + 121.2]), 0.1)
    assert scale == pytest.approx(1.01) and sigma == pytest.approx(math.hypot(0.1, 0.1) / 120)
    b.restart()
    assert b.fix(np.zeros(2), np.zeros(2), 0.1) is None  # a restart forgets the anchor


def test_the_filter_learns_the_scale_from_baselines_not_from_pulls():
    f = PoseFilter(scale_baseline_m=50.0)
    f.reset(np.zeros(3), np.diag([0.05**2, 0.05**2, 1e-5]))
    assert f.scale_frozen and not f.scale_from_pulls
    f.thaw_scale()
    assert f.scale_frozen  # a trusted pose does not thaw it
    true_scale = 1.02
    f.along_road_fix(np.zeros(2), 0.05)
    for _ in range(60):  # 60 m at 10 m/s, the wheels counting 2 % short
        f.predict(10.0 / true_scale, 0.0, 0.1)
    # a pull of 1.2 m along the road: the position moves, the scale does not
    f.update_posterior(np.array([60.0, 0.0, 0.0]), np.diag([1 / 0.05**2, 1 / 0.05**2, 1e4]))
    assert f.odometry_scale == pytest.approx(1.0)
    assert f.along_road_fix(np.array([60.0, 0.0]), 0.05)
    assert f.odometry_scale == pytest.approx(true_scale, abs=0.003)
