"""Camera model and inverse perspective mapping (paper eq. 1).

Frames: vehicle (x forward, y left, z up, origin on the ground under the rear axle), camera
(OpenCV: x right, y down, z forward). `T_vehicle_camera` maps camera coordinates to the vehicle.
The IPM lookup from pixel to ground point is computed once per calibration; per frame only the
labelled pixels are looked up."""

import math
from dataclasses import dataclass

import cv2
import numpy as np

from common.geometry import rot_x, rot_y, rot_z, se3, se3_inverse

# Camera axes expressed in the vehicle frame for a level camera looking forward.
R_VEHICLE_CAMERA_LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def mount_rotation(pitch_rad: float, roll_rad: float, yaw_rad: float) -> np.ndarray:
    """R_vehicle_camera for a camera pitched down by pitch_rad (positive = looking down)."""
    return rot_z(yaw_rad) @ rot_y(pitch_rad) @ rot_x(roll_rad) @ R_VEHICLE_CAMERA_LEVEL


def undistort_normalized(uv: np.ndarray, K: np.ndarray, dist: np.ndarray, iters: int = 20):
    """Pixels (N, 2) -> undistorted normalized coordinates (N, 2) by fixed-point iteration.

    Inverts OpenCV's radial-tangential model (k1, k2, p1, p2, k3); numpy only, so it behaves the
    same on every OpenCV version."""
    d = np.zeros(5)
    d[: min(5, len(dist))] = np.asarray(dist, float)[:5]
    k1, k2, p1, p2, k3 = d
    xd = (uv[:, 0] - K[0, 2]) / K[0, 0]
    yd = (uv[:, 1] - K[1, 2]) / K[1, 1]
    x, y = xd.copy(), yd.copy()
    tangential = p1 != 0.0 or p2 != 0.0  # without, dx and dy are +0.0: x = xd / radial exactly
    for _ in range(iters):
        r2 = x * x
        r2 += y * y
        radial = r2 * k3  # 1 + r2 (k1 + r2 (k2 + r2 k3)), in place, in the same order
        radial += k2
        radial *= r2
        radial += k1
        radial *= r2
        radial += 1.0
        if tangential:
            dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            x = (xd - dx) / radial
            y = (yd - dy) / radial
        else:
            x = xd / radial
            y = yd / radial
    return np.stack([x, y], axis=1)


@dataclass(frozen=True)
class CameraModel:
    width: int
    height: int
    K: np.ndarray  # 3x3 intrinsics
    dist: np.ndarray  # OpenCV (k1, k2, p1, p2[, k3...])
    T_vehicle_camera: np.ndarray  # 4x4

    @classmethod
    def from_mount(
        cls, *, width, height, fx, fy, cx, cy, dist, x_m, y_m, height_m, pitch_deg, roll_deg=0.0,
        yaw_deg=0.0,
    ) -> "CameraModel":
        R = mount_rotation(math.radians(pitch_deg), math.radians(roll_deg), math.radians(yaw_deg))
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        T = se3(R, [x_m, y_m, height_m])
        return cls(int(width), int(height), K, np.asarray(dist, float), T)

    def to_dict(self) -> dict:
        return {
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "T_vehicle_camera": self.T_vehicle_camera.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "CameraModel":
        return cls(
            int(d["width"]), int(d["height"]), np.array(d["K"], float), np.array(d["dist"], float),
            np.array(d["T_vehicle_camera"], float),
        )

    def perturbed(self, d_pitch_rad: float = 0.0, d_roll_rad: float = 0.0, d_yaw_rad: float = 0.0):
        """The same camera after a small extra rotation (vibration, calibration error)."""
        dR = rot_z(d_yaw_rad) @ rot_y(d_pitch_rad) @ rot_x(d_roll_rad)
        T = self.T_vehicle_camera.copy()
        T[:3, :3] = dR @ T[:3, :3]
        return CameraModel(self.width, self.height, self.K, self.dist, T)

    def project_vehicle_points(self, points_v: np.ndarray):
        """Points (N, 3) in the vehicle frame -> pixels (N, 2) and mask of points in front."""
        T_cv = se3_inverse(self.T_vehicle_camera)
        pc = points_v @ T_cv[:3, :3].T + T_cv[:3, 3]
        in_front = pc[:, 2] > 0.05
        uv = np.full((len(pc), 2), np.nan)
        if in_front.any():
            img, _ = cv2.projectPoints(pc[in_front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                       self.K, self.dist)
            uv[in_front] = img.reshape(-1, 2)
        return uv, in_front

    def pixel_rays_vehicle(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> unit-free ray directions (N, 3) in the vehicle frame (pi_c^-1)."""
        norm = undistort_normalized(uv, self.K, self.dist)
        rays_c = np.concatenate([norm, np.ones((len(norm), 1))], axis=1)
        return rays_c @ self.T_vehicle_camera[:3, :3].T

    def ground_points(self, uv: np.ndarray) -> np.ndarray:
        """Paper eq. 1: pixels (N, 2) -> ground points (N, 2) on z = 0 of the vehicle frame.

        NaN where the ray does not hit the ground in front of the camera."""
        rays = self.pixel_rays_vehicle(uv)
        origin = self.T_vehicle_camera[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = -origin[2] / rays[:, 2]
        lam[~(lam > 0)] = np.nan
        return origin[:2] + lam[:, None] * rays[:, :2]


def sky_rows(camera: CameraModel, margin_deg: float) -> int:
    """How many top rows of the image lie above every ray that rises `margin_deg` above level
    (across the camera's view): ground seen there would have to climb more than `margin_deg`
    towards the horizon, so no road marking is there to segment. 0 when such rays leave the
    image through its top (a camera pitched far up or a negative margin)."""
    theta = np.radians(np.linspace(-89.0, 89.0, 357))  # directions across the view
    rise = math.radians(margin_deg)
    far = 1e4  # metres: the horizon
    dirs = np.stack([np.cos(rise) * np.cos(theta), np.cos(rise) * np.sin(theta),
                     np.full_like(theta, np.sin(rise))], axis=1)
    origin = camera.T_vehicle_camera[:3, 3]
    uv, in_front = camera.project_vehicle_points(origin + far * dirs)
    inside = in_front & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width)
    if not inside.any():
        return 0
    return int(np.clip(math.floor(np.nanmin(uv[inside, 1])), 0, camera.height))


def sky_fraction(camera: CameraModel, margin_deg: float) -> float:
    """sky_rows as a share of the image height, for OnnxSegmenter's `sky_fraction`: 0 for a
    negative margin (every row segmented), at most 0.95 (a camera that sees almost only sky
    still has its bottom rows segmented)."""
    if margin_deg < 0:
        return 0.0
    return min(sky_rows(camera, margin_deg) / camera.height, 0.95)


@dataclass(frozen=True)
class IpmLookup:
    """Pixel -> ground point table for the pixels inside the ROI, built once per calibration.

    `pixel_index` is flat v * width + u of every ROI pixel, `ground_xy_m` its ground point in the
    vehicle frame; `index_of_pixel` maps a flat pixel to its row in the table (-1 outside)."""

    width: int
    height: int
    pixel_index: np.ndarray  # int64 [M]
    ground_xy_m: np.ndarray  # float32 [M, 2]
    index_of_pixel: np.ndarray  # int32 [H * W]

    def lookup(self, labels: np.ndarray, stride: int = 1):
        """Label image (H, W) -> (ground points (K, 2) in the vehicle frame, classes (K,)).

        Only pixels in the ROI with a non-zero label are returned; cost grows with those pixels."""
        if stride > 1:
            sub = np.zeros_like(labels)
            sub[::stride, ::stride] = labels[::stride, ::stride]
            labels = sub
        flat = np.flatnonzero(labels)
        rows = self.index_of_pixel[flat]
        keep = rows >= 0
        rows = rows[keep]
        return self.ground_xy_m[rows], labels.reshape(-1)[flat[keep]]


def build_ipm_lookup(
    camera: CameraModel, *, x_min_m: float, length_m: float, width_m: float
) -> IpmLookup:
    """Precompute the IPM table for the ROI [x_min, x_min + length] x [-width/2, width/2]."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    uv = np.stack([u.ravel() + 0.5, v.ravel() + 0.5], axis=1).astype(np.float64)
    below = uv[:, 1] > camera.K[1, 2] - 0.25 * camera.height  # rays above this never hit the ROI
    xy = np.full((len(uv), 2), np.nan)
    xy[below] = camera.ground_points(uv[below])
    inside = (
        (xy[:, 0] >= x_min_m)
        & (xy[:, 0] <= x_min_m + length_m)
        & (np.abs(xy[:, 1]) <= width_m / 2.0)
    )
    pixel_index = np.flatnonzero(inside)
    index_of_pixel = np.full(camera.width * camera.height, -1, dtype=np.int32)
    index_of_pixel[pixel_index] = np.arange(len(pixel_index), dtype=np.int32)
    return IpmLookup(camera.width, camera.height, pixel_index, xy[inside].astype(np.float32),
                     index_of_pixel)


def camera_from_config(cam) -> CameraModel:
    """CameraConfig -> CameraModel."""
    return CameraModel.from_mount(
        width=cam.width, height=cam.height, fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy,
        dist=cam.dist, x_m=cam.x_m, y_m=cam.y_m, height_m=cam.height_m, pitch_deg=cam.pitch_deg,
        roll_deg=cam.roll_deg, yaw_deg=cam.yaw_deg,
    )
