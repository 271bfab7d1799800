"""Road-paint geometry: polylines (N, 2) in metres -> filled marking polygons.

Lane lines as strips (solid, dashed with a real dash/gap, double), stop lines, zebra crosswalks
(stripes along the walking direction), arrow glyphs and text blocks. Left of a polyline: +normal."""

import math

import cv2
import numpy as np

from common.classes import Cls
from common.world import Marking

LINE_THIN_M = 0.12
LINE_THICK_M = 0.25
DOUBLE_GAP_M = 0.12  # clear paint gap between the two lines of a double line
STOP_LINE_M = 0.3
ZEBRA_STRIPE_M = 0.5
ZEBRA_GAP_M = 0.5


def arc_length(poly: np.ndarray) -> np.ndarray:
    """Cumulative length (N,) along a polyline."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def dedupe(poly: np.ndarray, eps: float = 1e-3) -> np.ndarray:
    """Drop consecutive duplicate vertices."""
    poly = np.asarray(poly, float)
    if len(poly) < 2:
        return poly
    keep = np.concatenate([[True], np.linalg.norm(np.diff(poly, axis=0), axis=1) > eps])
    return poly[keep]


def remove_cusps(poly: np.ndarray, max_turn_deg: float = 100.0) -> np.ndarray:
    """Drop vertices where the polyline doubles back (e.g. overlapping lane pieces at a join)."""
    poly = dedupe(poly)
    cos_max = math.cos(math.radians(max_turn_deg))
    for _ in range(50):
        if len(poly) < 3:
            return poly
        d = np.diff(poly, axis=0)
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
        bad = np.flatnonzero(np.sum(d[1:] * d[:-1], axis=1) < cos_max) + 1
        if len(bad) == 0:
            return poly
        poly = np.delete(poly, bad[::2], axis=0)
    return poly


def resample(poly: np.ndarray, step_m: float) -> np.ndarray:
    """Points every step_m along the polyline (end point included)."""
    poly = dedupe(poly)
    s = arc_length(poly)
    if s[-1] <= 0:
        return poly
    n = max(2, int(math.ceil(s[-1] / step_m)) + 1)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, poly[:, 0]), np.interp(t, s, poly[:, 1])], axis=1)


def sub_polyline(poly: np.ndarray, s: np.ndarray, a: float, b: float) -> np.ndarray:
    """The piece of a polyline between arc lengths a < b (s = arc_length(poly))."""
    inner = (s > a) & (s < b)
    ts = np.concatenate([[a], s[inner], [b]])
    return np.stack([np.interp(ts, s, poly[:, 0]), np.interp(ts, s, poly[:, 1])], axis=1)


def normals(poly: np.ndarray) -> np.ndarray:
    """Unit left normals (N, 2) at the vertices (averaged over the adjacent segments)."""
    d = np.diff(poly, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    t = np.concatenate([d[:1], d[:-1] + d[1:], d[-1:]])
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-9)
    return np.stack([-t[:, 1], t[:, 0]], axis=1)


def offset(poly: np.ndarray, d_m: float) -> np.ndarray:
    """Polyline shifted d_m to its left (negative: right)."""
    poly = dedupe(poly)
    return poly + d_m * normals(poly)


def strip(poly: np.ndarray, width_m: float) -> np.ndarray:
    """A polygon of constant width centred on the polyline."""
    poly = dedupe(poly)
    n = normals(poly) * (width_m / 2.0)
    return np.concatenate([poly + n, (poly - n)[::-1]])


def dashes(poly: np.ndarray, width_m: float, dash_m: float, gap_m: float, phase_m: float = 0.0):
    """One polygon per dash along the polyline."""
    poly = dedupe(poly)
    if len(poly) < 2:
        return []
    s = arc_length(poly)
    out, a = [], -phase_m
    while a < s[-1]:
        lo, hi = max(a, 0.0), min(a + dash_m, s[-1])
        if hi - lo > 0.2 * dash_m:
            out.append(strip(sub_polyline(poly, s, lo, hi), width_m))
        a += dash_m + gap_m
    return out


def line_polygons(
    poly: np.ndarray,
    style: str,
    width_m: float = LINE_THIN_M,
    dash_m: float = 3.0,
    gap_m: float = 6.0,
    phase_m: float = 0.0,
) -> list:
    """Lane line of a style: solid | dashed | double (two solids) | solid_dashed | dashed_solid."""
    half = (width_m + DOUBLE_GAP_M) / 2.0
    if style == "solid":
        return [strip(poly, width_m)]
    if style == "dashed":
        return dashes(poly, width_m, dash_m, gap_m, phase_m)
    if style == "double":
        return [strip(offset(poly, half), width_m), strip(offset(poly, -half), width_m)]
    if style in ("solid_dashed", "dashed_solid"):
        left, right = offset(poly, half), offset(poly, -half)
        solid, dashed = (left, right) if style == "solid_dashed" else (right, left)
        return [strip(solid, width_m)] + dashes(dashed, width_m, dash_m, gap_m, phase_m)
    raise ValueError(f"unknown line style {style!r}")


def line_markings(poly, style, width_m=LINE_THIN_M, dash_m=3.0, gap_m=6.0, phase_m=0.0):
    polys = line_polygons(poly, style, width_m, dash_m, gap_m, phase_m)
    return [Marking(Cls.LANE_LINE, p, style) for p in polys]


def zebra(
    left: np.ndarray,
    right: np.ndarray,
    stripe_m: float = ZEBRA_STRIPE_M,
    gap_m: float = ZEBRA_GAP_M,
) -> list[Marking]:
    """Zebra stripes between two boundaries that run along the walking direction.

    Each stripe spans from the left to the right boundary and is stripe_m long in the walking
    direction (parallel to the traffic), separated by gap_m."""
    left, right = dedupe(left), dedupe(right)
    sl, sr = arc_length(left), arc_length(right)
    length = 0.5 * (sl[-1] + sr[-1])
    if length < stripe_m:
        return []
    n = int((length + gap_m) // (stripe_m + gap_m))
    start = 0.5 * (length - (n * (stripe_m + gap_m) - gap_m))
    out = []
    for k in range(n):
        a = (start + k * (stripe_m + gap_m)) / length
        b = a + stripe_m / length
        pl = sub_polyline(left, sl, a * sl[-1], b * sl[-1])
        pr = sub_polyline(right, sr, a * sr[-1], b * sr[-1])
        out.append(Marking(Cls.CROSSWALK, np.concatenate([pl, pr[::-1]]), "zebra"))
    return out


def zebra_across(center_a: np.ndarray, center_b: np.ndarray, depth_m: float = 4.0) -> list:
    """Zebra crossing walked from center_a to center_b, depth_m deep along the traffic."""
    a, b = np.asarray(center_a, float), np.asarray(center_b, float)
    d = (b - a) / max(np.linalg.norm(b - a), 1e-9)
    n = np.array([-d[1], d[0]]) * depth_m / 2.0
    return zebra(np.stack([a + n, b + n]), np.stack([a - n, b - n]))


def stop_line(a: np.ndarray, b: np.ndarray, width_m: float = STOP_LINE_M) -> Marking:
    return Marking(Cls.STOP_LINE, strip(np.stack([a, b]).astype(float), width_m), "stop")


def place(local_xy: np.ndarray, x: float, y: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return local_xy @ np.array([[c, s], [-s, c]]) + [x, y]


# Arrow glyphs in a local frame: x along the driving direction (tip at +x), y left; metres.
ARROWS = {
    "arrow_straight": np.array(
        [
            (-2.5, -0.08),
            (1.0, -0.08),
            (1.0, -0.35),
            (2.5, 0.0),
            (1.0, 0.35),
            (1.0, 0.08),
            (-2.5, 0.08),
        ]
    ),
    "arrow_left": np.array(
        [
            (-2.5, -0.08),
            (1.08, -0.08),
            (1.08, 0.5),
            (1.35, 0.5),
            (1.0, 1.2),
            (0.65, 0.5),
            (0.92, 0.5),
            (0.92, 0.08),
            (-2.5, 0.08),
        ]
    ),
}
ARROWS["arrow_right"] = ARROWS["arrow_left"][::-1] * [1.0, -1.0]


def arrow(kind: str, x: float, y: float, yaw: float, scale: float = 1.0) -> Marking:
    return Marking(Cls.GROUND_SIGN, place(ARROWS[kind] * scale, x, y, yaw), kind)


def text_block(
    text: str, x: float, y: float, yaw: float, height_m: float = 2.4, width_m: float = 2.6
) -> list[Marking]:
    """Road text read by an approaching driver: letters elongated along the driving direction.

    Glyph outlines come from a Hershey font, rasterized and traced (outer contours)."""
    font, thick = cv2.FONT_HERSHEY_SIMPLEX, 9
    scale = 4.0
    (w, h), base = cv2.getTextSize(text, font, scale, thick)
    img = np.zeros((h + base + 20, w + 20), np.uint8)
    cv2.putText(img, text, (10, h + 10), font, scale, 255, thick, cv2.LINE_8)
    contours, _ = cv2.findContours(img, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    along, across = height_m / h, width_m / w  # metres per glyph pixel (elongated along the road)
    out = []
    for c in contours:
        c = c.reshape(-1, 2).astype(float)
        if len(c) < 3:
            continue
        # image u (text direction) -> local -y (left to right as seen by the driver),
        # image v (down) -> local -x (letters' tops point away from the driver)
        lx = -(c[:, 1] - (h + 10) / 2.0) * along
        ly = -(c[:, 0] - img.shape[1] / 2.0) * across
        out.append(Marking(Cls.GROUND_SIGN, place(np.stack([lx, ly], axis=1), x, y, yaw), "text"))
    return out
