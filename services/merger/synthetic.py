"""A small synthetic road network as a common.world.World, for merger tests and benchmarks when no
simulator world is at hand: straight and curved two-lane roads with solid edge lines, dashed
centre lines, stop lines, zebra crossings and arrows. Metres, local ENU frame."""

import numpy as np

from common.classes import Cls
from common.world import Marking, World

LANE_W_M = 3.5
LINE_W_M = 0.15


def strip(polyline_xy_m: np.ndarray, width_m: float) -> np.ndarray:
    """Polygon of a polyline swept with a width (mitre-free: normals per vertex)."""
    p = np.asarray(polyline_xy_m, dtype=np.float64)
    d = np.gradient(p, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    n = np.stack([-d[:, 1], d[:, 0]], axis=1) * (width_m / 2)
    return np.concatenate([p + n, (p - n)[::-1]])


def _offset(p: np.ndarray, off_m: float) -> np.ndarray:
    d = np.gradient(p, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return p + np.stack([-d[:, 1], d[:, 0]], axis=1) * off_m


def _arc_length(p: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])


def _dashes(p: np.ndarray, dash_m: float, gap_m: float) -> list[np.ndarray]:
    s = _arc_length(p)
    out, start = [], 0.0
    while start + dash_m <= s[-1]:
        t = np.linspace(start, start + dash_m, 4)
        seg = np.stack([np.interp(t, s, p[:, 0]), np.interp(t, s, p[:, 1])], axis=1)
        out.append(strip(seg, LINE_W_M))
        start += dash_m + gap_m
    return out


def _road_markings(centre: np.ndarray) -> list[Marking]:
    half = LANE_W_M
    ms = [Marking(Cls.ROAD, strip(centre, 2 * half + 1.0), "road")]
    for side in (-1, 1):
        edge = _offset(centre, side * (half - 0.1))
        ms.append(Marking(Cls.LANE_LINE, strip(edge, LINE_W_M), "solid"))
    ms += [Marking(Cls.LANE_LINE, q, "dashed") for q in _dashes(centre, 3.0, 6.0)]
    return ms


def _crossing(at_xy: np.ndarray, heading_rad: float) -> list[Marking]:
    """Stop line, a zebra crossing and a straight/left arrow, across a road heading `heading`."""
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    R = np.array([[c, -s], [s, c]])

    def place(poly):
        return np.asarray(poly, dtype=np.float64) @ R.T + at_xy

    ms = [Marking(Cls.STOP_LINE, place([[0, -3.4], [0.3, -3.4], [0.3, -0.1], [0, -0.1]]), "stop")]
    for k in range(8):
        y0 = -3.4 + k * 0.9
        stripe = [[1.5, y0], [5.5, y0], [5.5, y0 + 0.45], [1.5, y0 + 0.45]]
        ms.append(Marking(Cls.CROSSWALK, place(stripe), "zebra"))
    arrow = [[-8, -1.9], [-4, -1.9], [-4, -1.4], [-2.5, -1.75], [-4, -2.1], [-4, -1.6], [-8, -1.6]]
    ms.append(Marking(Cls.GROUND_SIGN, place(arrow), "arrow_straight"))
    # an "O" glyph: four bars around a hole
    for x0, y0, x1, y1 in ((-14, -2.6, -11, -2.2), (-14, -1.3, -11, -0.9),
                           (-14, -2.6, -13.6, -0.9), (-11.4, -2.6, -11, -0.9)):
        ms.append(Marking(Cls.GROUND_SIGN, place([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]), "text"))
    return ms


def synthetic_world(km: float = 1.0, seed: int = 0) -> World:
    """Roads of about `km` total centre line: alternating straight and curved 200 m roads placed on
    a grid, each with a crossing at its end."""
    rng = np.random.default_rng(seed)
    markings, routes, total_m = [], [], 0.0
    n_roads = max(1, int(round(km * 1000 / 200)))
    for i in range(n_roads):
        x0, y0 = (i % 3) * 260.0, (i // 3) * 60.0
        t = np.linspace(0, 200, 201)
        bend = rng.uniform(-15, 15) if i % 2 else 0.0
        centre = np.stack([x0 + t, y0 + bend * np.sin(np.pi * t / 200)], axis=1)
        markings += _road_markings(centre)
        heading = np.arctan2(*(centre[-1] - centre[-2])[::-1])
        markings += _crossing(centre[-12], heading)
        routes.append(centre)
        total_m += float(_arc_length(centre)[-1])
    return World("synthetic", markings, routes=routes, km_of_road=total_m / 1000)
