"""Camera projection and IPM (paper eq. 1) against analytic ground points."""

import numpy as np

from common.camera import build_ipm_lookup, camera_from_config
from common.config import RoadmapConfig


def test_ipm_inverts_projection_of_ground_points(rng):
    cam = camera_from_config(RoadmapConfig().camera)
    pts = np.column_stack([rng.uniform(5, 15, 200), rng.uniform(-4, 4, 200), np.zeros(200)])
    uv, in_front = cam.project_vehicle_points(pts)
    assert in_front.all()
    back = cam.ground_points(uv)
    assert np.abs(back - pts[:, :2]).max() < 1e-6


def test_level_camera_horizon_has_no_ground_point():
    cam = camera_from_config(RoadmapConfig().camera)
    uv = np.array([[320.0, 10.0]])  # far above the horizon
    assert np.isnan(cam.ground_points(uv)).all()


def test_ipm_lookup_covers_only_the_roi():
    cam = camera_from_config(RoadmapConfig().camera)
    lut = build_ipm_lookup(cam, x_min_m=3.0, length_m=12.0, width_m=8.0)
    xy = lut.ground_xy_m
    assert xy[:, 0].min() >= 3.0 and xy[:, 0].max() <= 15.0 and np.abs(xy[:, 1]).max() <= 4.0
    labels = np.zeros((cam.height, cam.width), np.uint8)
    labels[-1, :] = 2  # bottom row: nearest ground
    labels[0, :] = 2  # top row: sky, outside the ROI
    pts, cls = lut.lookup(labels)
    assert len(pts) > 0 and (cls == 2).all() and pts[:, 0].max() < 6.0


def test_sky_rows_lie_above_the_rays_rising_the_margin_above_level():
    import dataclasses
    import math

    from common.camera import sky_rows

    cfg = dataclasses.replace(RoadmapConfig().camera, dist=[0.0, 0.0, 0.0, 0.0, 0.0])
    cam = camera_from_config(cfg)
    # no margin: the horizon's row, cy - fy tan(pitch), at the image's centre and sides
    horizon = cfg.cy - cfg.fy * math.tan(math.radians(cfg.pitch_deg))
    assert sky_rows(cam, 0.0) == math.floor(horizon)
    # rays rising 10 deg: higher in the image, and highest at its sides
    at_centre = cfg.cy - cfg.fy * math.tan(math.radians(cfg.pitch_deg + 10.0))
    assert sky_rows(cam, 10.0) < at_centre < horizon
    assert sky_rows(cam, 5.0) > sky_rows(cam, 10.0)
    # a camera looking steeply down sees no sky; one looking up sees mostly sky
    assert sky_rows(camera_from_config(dataclasses.replace(cfg, pitch_deg=40.0)), 10.0) == 0
    up = camera_from_config(dataclasses.replace(cfg, pitch_deg=-30.0))
    assert cfg.height * 0.8 < sky_rows(up, 10.0) <= cfg.height


def test_undistortion_inverts_opencvs_distortion_with_and_without_tangential_terms(rng):
    """undistort_normalized inverts OpenCV's model (k1, k2, p1, p2, k3), whether its tangential
    terms are zero (the shortcut: x = xd / radial) or not."""
    from common.camera import undistort_normalized

    K = np.array([[460.0, 0.0, 321.3], [0.0, 455.0, 179.2], [0.0, 0.0, 1.0]])
    xy = rng.uniform(-0.6, 0.6, (500, 2))
    for dist in ([-0.08, 0.01, 0.0, 0.0, 0.0], [-0.2, 0.05, 0.001, -0.002, 0.01]):
        k1, k2, p1, p2, k3 = dist
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        uv = np.column_stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]])
        np.testing.assert_allclose(undistort_normalized(uv, K, np.array(dist)), xy, atol=1e-9)
