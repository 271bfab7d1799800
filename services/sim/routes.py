"""Helpers shared by the map importers: chaining lane centre lines into long drives, km of road
from centre lines (each road once), and GNSS-blocked zones along a route. Metres, local ENU."""

import math

import numpy as np

from services.sim import paint


def chain_lanes(
    lanes: list[np.ndarray],
    rng,
    *,
    join_m: float = 1.5,
    max_turn_deg: float = 70.0,
    uturn_m: float = 30.0,
    min_len_m: float = 200.0,
    max_routes: int = 6,
    max_len_m: float = 4000.0,
) -> list[np.ndarray]:
    """Directed lane centre lines -> long drives. A walk goes from a lane to a successor (end meets
    start within join_m, heading change below max_turn_deg), least-visited first; at a dead end it
    U-turns onto an opposite lane starting within uturn_m. Joins are smooth Bezier curves."""
    starts = np.array([lane[0] for lane in lanes])
    heads = np.array([_heading(lane, start=True) for lane in lanes])
    succ = []
    for lane in lanes:
        d = np.linalg.norm(starts - lane[-1], axis=1)
        turn = np.abs(paint_wrap(heads - _heading(lane, start=False)))
        ahead = np.flatnonzero((d < join_m) & (turn < math.radians(max_turn_deg)))
        back = np.flatnonzero((d < uturn_m) & (d > 10.0) & (turn > math.radians(150)))
        succ.append((ahead, back))
    visits = np.zeros(len(lanes), int)
    routes = []
    for _ in range(4 * max_routes):
        if len(routes) >= max_routes or visits.min() > 0:
            break
        unvisited = np.flatnonzero(visits == 0)
        k = int(unvisited[np.argmax([paint.arc_length(lanes[i])[-1] for i in unvisited])])
        seq, length = [k], paint.arc_length(lanes[k])[-1]
        visits[k] += 1
        while length < max_len_m:
            ahead, back = succ[seq[-1]]
            options = ahead if len(ahead) else back
            if len(options) == 0:
                break
            k = int(min(options, key=lambda i: (visits[i], rng.random())))
            if visits[k] >= 3:
                break
            visits[k] += 1
            seq.append(k)
            length += paint.arc_length(lanes[k])[-1]
        route = _join([lanes[i] for i in seq])
        if paint.arc_length(route)[-1] >= min_len_m or not routes:
            routes.append(route)
    routes.sort(key=lambda r: -paint.arc_length(r)[-1])
    return routes


def _join(lanes: list[np.ndarray]) -> np.ndarray:
    """Concatenate lanes; gaps are bridged by a cubic Bezier along both headings."""
    pts = [lanes[0]]
    for prev, nxt in zip(lanes[:-1], lanes[1:], strict=False):
        p0, p3 = prev[-1], nxt[0]
        gap = float(np.linalg.norm(p3 - p0))
        if gap > 0.3:
            d0 = prev[-1] - prev[max(-3, -len(prev))]
            d3 = nxt[min(2, len(nxt) - 1)] - nxt[0]
            d0, d3 = d0 / np.linalg.norm(d0), d3 / np.linalg.norm(d3)
            r = 0.6 * gap + 2.0
            t = np.linspace(0.0, 1.0, max(4, int(gap * 2)))[1:-1, None]
            p1, p2 = p0 + r * d0, p3 - r * d3
            pts.append(
                (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * p1 + 3 * (1 - t) * t**2 * p2 + t**3 * p3
            )
        pts.append(nxt)
    return paint.dedupe(np.concatenate(pts), eps=0.05)


def paint_wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _heading(lane: np.ndarray, start: bool) -> float:
    d = lane[min(2, len(lane) - 1)] - lane[0] if start else lane[-1] - lane[max(-3, -len(lane))]
    return math.atan2(d[1], d[0])


def km_of_centrelines(lanes: list[np.ndarray], *, merge_m: float = 4.5, step_m: float = 1.0):
    """Length of road (km) under lane centre lines, each road counted once: a sample counts unless
    an already counted sample lies within merge_m with a parallel or opposite heading
    (a neighbouring lane or the other direction of the same road)."""
    cell = merge_m
    buckets: dict[tuple[int, int], list[tuple[float, float, float]]] = {}
    total = 0.0
    for lane in sorted(lanes, key=lambda c: -paint.arc_length(c)[-1]):
        pts = paint.resample(lane, step_m)
        if len(pts) < 2:
            continue
        d = np.gradient(pts, axis=0)
        yaws = np.arctan2(d[:, 1], d[:, 0])
        new = []
        for (x, y), yaw in zip(pts[:-1], yaws[:-1], strict=False):
            cx, cy = int(x // cell), int(y // cell)
            dup = False
            for i in (cx - 1, cx, cx + 1):
                for j in (cy - 1, cy, cy + 1):
                    for px, py, pyaw in buckets.get((i, j), ()):
                        if (px - x) ** 2 + (py - y) ** 2 < merge_m**2 and abs(
                            math.cos(pyaw - yaw)
                        ) > 0.8:
                            dup = True
                            break
                    if dup:
                        break
                if dup:
                    break
            new.append((x, y, yaw))  # duplicates stay: they block the next neighbouring lane
            total += 0.0 if dup else step_m
        for x, y, yaw in new:
            buckets.setdefault((int(x // cell), int(y // cell)), []).append((x, y, yaw))
    return total / 1000.0


def blocked_zone_along(
    route: np.ndarray,
    *,
    start_m: float = 250.0,
    length_m: float = 300.0,
    width_m: float = 30.0,
    piece_m: float = 25.0,
) -> list[np.ndarray]:
    """GNSS-blocked zone: buffers (short pieces, so curves stay simple) around length_m of route,
    starting at or after start_m (drives start with a fix), where the route passes only once
    (a route that comes back along the same road would otherwise lose GNSS twice)."""
    s = paint.arc_length(route)
    step = 5.0
    samples = paint.resample(route, step)
    best = None
    for a in np.arange(
        min(start_m, max(s[-1] - length_m, 0.0)), max(s[-1] - length_m, 0.0) + 1, 50.0
    ):
        axis = paint.resample(paint.sub_polyline(route, s, a, min(a + length_m, s[-1])), step)
        d2 = np.min(np.sum((samples[:, None] - axis[None]) ** 2, axis=2), axis=1)
        inside_m = step * np.count_nonzero(d2 < (width_m / 2) ** 2)
        if best is None or inside_m < best[0] - 20.0:
            best = (inside_m, a)
        if inside_m <= 1.5 * length_m:
            break
    a = best[1]
    b = min(a + length_m, s[-1])
    out = []
    while a < b - 1e-6:
        piece = paint.sub_polyline(route, s, a, min(a + piece_m, b))
        d = piece[-1] - piece[0]
        ext = d / max(np.linalg.norm(d), 1e-9) * 2.0
        out.append(paint.strip(np.stack([piece[0] - ext, piece[-1] + ext]), width_m))
        a += piece_m
    return out
