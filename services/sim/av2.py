"""Argoverse 2 log importer: lane boundaries by mark type (solid, dashed, double), pedestrian
crossings (edge1/edge2) as zebra stripes, drivable areas as road surface, and the real ego pose
sequence (city_SE3_egovehicle.csv) as the route. City frame metres, used as the local frame."""

import json
from pathlib import Path

import numpy as np

from common.camera import CameraModel
from common.classes import Cls
from common.errors import WorldError
from common.geometry import quat_wxyz_to_rot, se3
from common.world import Marking, World
from services.sim import paint, routes

WIDTH_M = 0.15
STYLES = {
    "SOLID": "solid",
    "DASHED": "dashed",
    "DOUBLE_SOLID": "double",
    "DOUBLE_DASH": "double",
    "SOLID_DASH": "solid_dashed",
    "DASH_SOLID": "dashed_solid",
}
PITTSBURGH_LATLON = (40.44, -80.0)


def _xy(points) -> np.ndarray:
    return np.array([[p["x"], p["y"]] for p in points], float)


def _style(mark_type: str) -> str | None:
    if not mark_type or mark_type in ("NONE", "UNKNOWN"):
        return None
    stem = mark_type.rsplit("_", 1)[0]  # drop the colour
    return STYLES.get(stem, "solid")


def load_ego_poses(log_dir) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps_ns (N,), poses (N, 3) x, y, yaw) from city_SE3_egovehicle.csv."""
    path = Path(log_dir) / "city_SE3_egovehicle.csv"
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1)
    except (OSError, ValueError) as exc:
        raise WorldError(f"{path}: cannot read ego poses ({exc})") from exc
    t = np.loadtxt(path, delimiter=",", skiprows=1, usecols=0, dtype=np.int64)
    order = np.argsort(t)
    yaw = np.array([np.arctan2(R[1, 0], R[0, 0]) for R in map(quat_wxyz_to_rot, data[:, 1:5])])
    return t[order], np.stack([data[:, 5], data[:, 6], yaw], axis=1)[order]


def av2_camera(log_dir, sensor: str = "ring_front_center", scale: float = 1.0) -> CameraModel:
    """A real Argoverse 2 camera (intrinsics, k1 k2 k3 radial distortion, extrinsics) from a log's
    calibration/ folder; `scale` resizes the image (e.g. 0.25 for a quarter-size camera)."""
    cal = Path(log_dir) / "calibration"
    try:
        intr = _csv_row(cal / "intrinsics.csv", sensor)
        extr = _csv_row(cal / "egovehicle_SE3_sensor.csv", sensor)
    except (OSError, KeyError, ValueError) as exc:
        raise WorldError(f"{cal}: no calibration for {sensor} ({exc})") from exc
    K = np.array(
        [
            [float(intr["fx_px"]) * scale, 0.0, float(intr["cx_px"]) * scale],
            [0.0, float(intr["fy_px"]) * scale, float(intr["cy_px"]) * scale],
            [0.0, 0.0, 1.0],
        ]
    )
    dist = np.array([float(intr["k1"]), float(intr["k2"]), 0.0, 0.0, float(intr["k3"])])
    q = [float(extr[k]) for k in ("qw", "qx", "qy", "qz")]
    T = se3(quat_wxyz_to_rot(q), [float(extr[k]) for k in ("tx_m", "ty_m", "tz_m")])
    return CameraModel(
        int(round(int(intr["width_px"]) * scale)),
        int(round(int(intr["height_px"]) * scale)),
        K,
        dist,
        T,
    )


def _csv_row(path: Path, sensor: str) -> dict:
    lines = [line.strip().split(",") for line in path.read_text().splitlines() if line.strip()]
    rows = {r[0]: dict(zip(lines[0], r, strict=False)) for r in lines[1:]}
    return rows[sensor]


def load_av2(log_dir, seed: int = 0) -> World:
    log_dir = Path(log_dir)
    maps = sorted(log_dir.glob("log_map_archive_*.json"))
    if not maps:
        raise WorldError(f"{log_dir}: no log_map_archive_*.json")
    vector = json.loads(maps[0].read_text())
    markings = [
        Marking(Cls.ROAD, _xy(a["area_boundary"]), "road")
        for a in vector.get("drivable_areas", {}).values()
    ]
    seen = set()
    centre = []
    for lane in vector.get("lane_segments", {}).values():
        for side in ("left", "right"):
            poly = _xy(lane[f"{side}_lane_boundary"])
            key = tuple(np.round(poly[[0, -1]].ravel(), 1))
            style = _style(lane.get(f"{side}_lane_mark_type", "NONE"))
            if style is None or key in seen or tuple(np.round(poly[[-1, 0]].ravel(), 1)) in seen:
                continue
            seen.add(key)
            markings += paint.line_markings(poly, style, WIDTH_M, 3.0, 9.0)
        if lane.get("lane_type") == "VEHICLE":
            centre.append(
                0.5
                * (
                    _param(_xy(lane["left_lane_boundary"]))
                    + _param(_xy(lane["right_lane_boundary"]))
                )
            )
    for pc in vector.get("pedestrian_crossings", {}).values():
        e1, e2 = _xy(pc["edge1"]), _xy(pc["edge2"])
        if np.linalg.norm(e1[0] - e2[-1]) < np.linalg.norm(e1[0] - e2[0]):
            e2 = e2[::-1]
        markings += paint.zebra(e1, e2)
    _, poses = load_ego_poses(log_dir)
    route = paint.dedupe(poses[:, :2], eps=0.05)
    return World(
        name=f"av2:{log_dir.name[:8]}",
        markings=markings,
        routes=[route],
        gnss_blocked=[],
        km_of_road=routes.km_of_centrelines(centre),
        origin_latlon=PITTSBURGH_LATLON,
    )


def _param(poly, n: int = 20) -> np.ndarray:
    s = paint.arc_length(paint.dedupe(poly))
    poly = paint.dedupe(poly)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, poly[:, 0]), np.interp(t, s, poly[:, 1])], axis=1)
