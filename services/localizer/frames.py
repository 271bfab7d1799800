"""Frame -> semantic ground points for matching: IPM of the label image (paper eq. 1, shared with
the vehicle via common.camera) plus each point's derivative w.r.t. camera pitch and roll, so the
ICP can absorb vibration and calibration error. Vehicle frame, metres, radians."""

import math

import numpy as np

from common.camera import CameraModel, build_ipm_lookup


class FramePoints:
    """IPM lookup with its attitude jacobians (M, 2, 2) = d ground xy / d (pitch, roll)."""

    def __init__(
        self,
        camera: CameraModel,
        *,
        x_min_m: float,
        length_m: float,
        width_m: float,
        delta_rad: float = math.radians(0.25),
    ):
        self.ipm = build_ipm_lookup(camera, x_min_m=x_min_m, length_m=length_m, width_m=width_m)
        idx = self.ipm.pixel_index
        uv = np.stack([idx % camera.width + 0.5, idx // camera.width + 0.5], axis=1).astype(float)
        cols = []
        for d_pitch, d_roll in ((delta_rad, 0.0), (0.0, delta_rad)):
            plus = camera.perturbed(d_pitch, d_roll).ground_points(uv)
            minus = camera.perturbed(-d_pitch, -d_roll).ground_points(uv)
            cols.append((plus - minus) / (2.0 * delta_rad))
        jac = np.stack(cols, axis=2)
        self.jacobians = np.nan_to_num(jac, nan=0.0).astype(np.float32)

    def points(self, labels: np.ndarray, stride: int = 1):
        """Labels -> (points (K, 2), classes (K,), jacobians (K, 2, 2)) of labelled ROI pixels."""
        if stride > 1:
            sub = np.zeros_like(labels)
            sub[::stride, ::stride] = labels[::stride, ::stride]
            labels = sub
        flat = np.flatnonzero(labels)
        rows = self.ipm.index_of_pixel[flat]
        keep = rows >= 0
        rows = rows[keep]
        return (self.ipm.ground_xy_m[rows], labels.reshape(-1)[flat[keep]], self.jacobians[rows])
