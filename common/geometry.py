"""Frames and rigid transforms: SE(2) poses (x, y, yaw) in metres/radians, SE(3) 4x4 matrices,
quaternions (w, x, y, z) and lat/lon to the local ENU frame of a world."""

import math

import numpy as np

EARTH_RADIUS_M = 6378137.0


def wrap_angle(angle_rad):
    """Wrap an angle (scalar or array) into [-pi, pi)."""
    return (np.asarray(angle_rad) + np.pi) % (2.0 * np.pi) - np.pi


def se2(x: float, y: float, yaw_rad: float) -> np.ndarray:
    """Pose (x, y, yaw) -> 3x3 homogeneous matrix T_parent_child."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def se2_params(T: np.ndarray) -> np.ndarray:
    """3x3 homogeneous matrix -> array (x, y, yaw)."""
    return np.array([T[0, 2], T[1, 2], math.atan2(T[1, 0], T[0, 0])])


def se2_inverse(T: np.ndarray) -> np.ndarray:
    R = T[:2, :2]
    out = np.eye(3)
    out[:2, :2] = R.T
    out[:2, 2] = -R.T @ T[:2, 2]
    return out


def se2_between(pose_a: np.ndarray, pose_b: np.ndarray) -> np.ndarray:
    """Relative pose of b seen from a, both (x, y, yaw): returns (dx, dy, dyaw) in a's frame."""
    dx, dy = pose_b[0] - pose_a[0], pose_b[1] - pose_a[1]
    c, s = math.cos(pose_a[2]), math.sin(pose_a[2])
    return np.array([c * dx + s * dy, -s * dx + c * dy, float(wrap_angle(pose_b[2] - pose_a[2]))])


def se2_compose(pose_a: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """pose_a (x, y, yaw) followed by delta (dx, dy, dyaw) expressed in a's frame."""
    c, s = math.cos(pose_a[2]), math.sin(pose_a[2])
    return np.array(
        [
            pose_a[0] + c * delta[0] - s * delta[1],
            pose_a[1] + s * delta[0] + c * delta[1],
            float(wrap_angle(pose_a[2] + delta[2])),
        ]
    )


def transform_points_2d(pose: np.ndarray, points_xy: np.ndarray) -> np.ndarray:
    """Points (N, 2) in the child frame of pose (x, y, yaw) -> parent frame."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    R = np.array([[c, -s], [s, c]])
    return points_xy @ R.T + np.asarray(pose[:2])


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=float)


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=float)


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=float)


def se3(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float)
    return T


def se3_inverse(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    return se3(R.T, -R.T @ t)


def quat_wxyz_from_yaw(yaw_rad: float) -> np.ndarray:
    return np.array([math.cos(yaw_rad / 2.0), 0.0, 0.0, math.sin(yaw_rad / 2.0)])


def quat_wxyz_to_rot(q) -> np.ndarray:
    w, x, y, z = (float(v) for v in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def latlon_to_local_m(lat_deg, lon_deg, origin_lat_deg: float, origin_lon_deg: float):
    """Lat/lon (degrees) -> local ENU metres (x east, y north) about an origin.

    Equirectangular about the origin: under 1 cm error across a few km, which is the size of a
    world here."""
    lat = np.radians(np.asarray(lat_deg, dtype=float))
    lon = np.radians(np.asarray(lon_deg, dtype=float))
    lat0, lon0 = math.radians(origin_lat_deg), math.radians(origin_lon_deg)
    x = (lon - lon0) * math.cos(lat0) * EARTH_RADIUS_M
    y = (lat - lat0) * EARTH_RADIUS_M
    return x, y


def local_m_to_latlon(x_m, y_m, origin_lat_deg: float, origin_lon_deg: float):
    lat0 = math.radians(origin_lat_deg)
    lat = origin_lat_deg + np.degrees(np.asarray(y_m, dtype=float) / EARTH_RADIUS_M)
    east = np.asarray(x_m, dtype=float)
    lon = origin_lon_deg + np.degrees(east / (EARTH_RADIUS_M * math.cos(lat0)))
    return lat, lon


WGS84_A = 6378137.0  # semi-major axis, metres
WGS84_E2 = 6.69437999014e-3  # first eccentricity squared


def geodetic_to_ecef(lat_deg, lon_deg, alt_m) -> np.ndarray:
    """WGS84 latitude, longitude (degrees), height (metres); scalars or arrays -> ECEF (..., 3)."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    n = WGS84_A / np.sqrt(1 - WGS84_E2 * np.sin(lat) ** 2)
    return np.stack(
        [
            (n + alt_m) * np.cos(lat) * np.cos(lon),
            (n + alt_m) * np.cos(lat) * np.sin(lon),
            (n * (1 - WGS84_E2) + alt_m) * np.sin(lat),
        ],
        axis=-1,
    )


def ecef_to_geodetic(p) -> tuple[float, float, float]:
    """ECEF (3,) metres -> (lat, lon, height) degrees/metres on WGS84 (Bowring iteration)."""
    x, y, z = (float(v) for v in p)
    lon = math.atan2(y, x)
    r = math.hypot(x, y)
    lat = math.atan2(z, r * (1 - WGS84_E2))
    for _ in range(6):
        n = WGS84_A / math.sqrt(1 - WGS84_E2 * math.sin(lat) ** 2)
        h = r / math.cos(lat) - n
        lat = math.atan2(z, r * (1 - WGS84_E2 * n / (n + h)))
    return math.degrees(lat), math.degrees(lon), h


def enu_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """R_enu_ecef at a geodetic point: ECEF directions -> (east, north, up)."""
    la, lo = math.radians(lat_deg), math.radians(lon_deg)
    return np.array(
        [
            [-math.sin(lo), math.cos(lo), 0.0],
            [-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)],
            [math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la)],
        ]
    )
