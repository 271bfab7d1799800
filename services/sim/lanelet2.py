"""Lanelet2 OSM importer: lat/lon -> local ENU metres about the map centre.

line_thin (0.12 m) / line_thick (0.25 m) solid, dashed (3 m / 6 m dashes), double and mixed lines;
stop lines 0.3 m; pedestrian/zebra markings (pairs of crossing edges) as 0.5 m / 0.5 m stripes;
road surface from lanelet boundaries; drives along chained lanelet centre lines."""

import logging
import math
from pathlib import Path

import numpy as np

from common.classes import Cls
from common.errors import WorldError
from common.geometry import latlon_to_local_m
from common.world import Marking, World
from services.sim import paint, routes
from services.sim.osm import read_osm

logger = logging.getLogger(__name__)

LINE_WIDTH_M = {"line_thin": paint.LINE_THIN_M, "line_thick": paint.LINE_THICK_M}
LINE_STYLES = {
    "solid": "solid",
    "dashed": "dashed",
    "solid_solid": "double",
    "solid_dashed": "solid_dashed",
    "dashed_solid": "dashed_solid",
}
DRIVABLE = ("road", "highway", "bicycle_lane")
DRIVEN = ("road", "highway")
CROSSING_TYPES = ("pedestrian_marking", "zebra_marking")


def load_lanelet2(path, seed: int = 0) -> World:
    osm = read_osm(path)
    latlon = np.array(list(osm.nodes.values()))
    lat0, lon0 = (latlon.min(axis=0) + latlon.max(axis=0)) / 2.0
    xy = _node_xy(osm, lat0, lon0)
    way_xy = {
        w: paint.dedupe(np.array([xy[n] for n in refs if n in xy]))
        for w, (refs, _) in osm.ways.items()
    }
    lanelets = _lanelets(osm, way_xy)
    markings = [
        Marking(Cls.ROAD, quad, "road")
        for left, right, tags in lanelets
        if tags.get("subtype") in DRIVABLE
        for quad in _surface(left, right)
    ]
    markings += _line_markings(osm, way_xy)
    markings += _crossings(osm, way_xy)
    lanes = _directed_centrelines(lanelets)
    drives = routes.chain_lanes(lanes, np.random.default_rng(seed))
    if not drives:
        raise WorldError(f"{path}: no drivable lanelets")
    km = routes.km_of_centrelines([c for c, _ in _centrelines(lanelets)])
    logger.info(
        "lanelet2 %s: %d markings, %.2f km of road, %d drives",
        Path(path).name,
        len(markings),
        km,
        len(drives),
    )
    return World(
        name=f"lanelet2:{Path(path).stem}",
        markings=markings,
        routes=drives,
        gnss_blocked=routes.blocked_zone_along(drives[0]),
        km_of_road=km,
        origin_latlon=(float(lat0), float(lon0)),
    )


def _node_xy(osm, lat0, lon0) -> dict[int, np.ndarray]:
    ids = list(osm.nodes)
    ll = np.array([osm.nodes[i] for i in ids])
    x, y = latlon_to_local_m(ll[:, 0], ll[:, 1], lat0, lon0)
    return {i: np.array([a, b]) for i, a, b in zip(ids, x, y, strict=False)}


def _lanelets(osm, way_xy):
    """(left, right, tags) per lanelet, both boundaries oriented along the driving direction."""
    out = []
    for members, tags in osm.relations.values():
        if tags.get("type") != "lanelet":
            continue
        roles = {role: ref for typ, ref, role in members if typ == "way"}
        if "left" not in roles or "right" not in roles:
            continue
        left, right = way_xy.get(roles["left"]), way_xy.get(roles["right"])
        if left is None or right is None or len(left) < 2 or len(right) < 2:
            continue
        if _reversed(left, right):
            right = right[::-1]
        d = left[-1] - left[0] + right[-1] - right[0]
        side = (left[0] + left[-1] - right[0] - right[-1]) / 2.0
        if d[0] * side[1] - d[1] * side[0] < 0:  # left must lie to the left of the direction
            left, right = right[::-1], left[::-1]
        out.append((left, right, tags))
    return out


def _surface(left, right, step_m: float = 2.0) -> list[np.ndarray]:
    """Road surface between two boundaries as a strip of quads (robust to odd lanelet shapes)."""
    n = max(
        2, int(math.ceil(max(paint.arc_length(left)[-1], paint.arc_length(right)[-1]) / step_m))
    )
    pl, pr = _param(left, n), _param(right, n)
    return [np.stack([pl[i], pl[i + 1], pr[i + 1], pr[i]]) for i in range(n - 1)]


def _reversed(a: np.ndarray, b: np.ndarray) -> bool:
    """True when polyline b runs against a (its ends pair up crosswise)."""
    same = np.linalg.norm(a[0] - b[0]) + np.linalg.norm(a[-1] - b[-1])
    cross = np.linalg.norm(a[0] - b[-1]) + np.linalg.norm(a[-1] - b[0])
    return cross < same


def _centreline(left, right, step_m: float = 1.0) -> np.ndarray:
    n = max(
        2, int(math.ceil(max(paint.arc_length(left)[-1], paint.arc_length(right)[-1]) / step_m))
    )
    return 0.5 * (_param(left, n) + _param(right, n))


def _param(poly, n):
    s = paint.arc_length(poly)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, poly[:, 0]), np.interp(t, s, poly[:, 1])], axis=1)


def _centrelines(lanelets):
    return [(_centreline(lb, rb), t) for lb, rb, t in lanelets if t.get("subtype") in DRIVEN]


def _directed_centrelines(lanelets) -> list[np.ndarray]:
    out = []
    for c, tags in _centrelines(lanelets):
        out.append(c)
        if tags.get("one_way", "yes") in ("no", "false"):
            out.append(c[::-1])
    return out


def _line_markings(osm, way_xy) -> list[Marking]:
    out = []
    for w, (_, tags) in osm.ways.items():
        poly, typ = way_xy[w], tags.get("type")
        if len(poly) < 2:
            continue
        if typ in LINE_WIDTH_M:
            style = LINE_STYLES.get(tags.get("subtype", "solid"), "solid")
            out += paint.line_markings(poly, style, LINE_WIDTH_M[typ], 3.0, 6.0)
        elif typ == "stop_line":
            out.append(Marking(Cls.STOP_LINE, paint.strip(poly, paint.STOP_LINE_M), "stop"))
    return out


def _crossings(osm, way_xy) -> list[Marking]:
    """Pair crossing edges (parallel, 1.5-8 m apart, overlapping) and stripe between them;
    an edge without a partner becomes a 3 m deep crossing on the side its nearest road is not."""
    ways = [
        w
        for w, (_, t) in osm.ways.items()
        if t.get("type") in CROSSING_TYPES and len(way_xy[w]) >= 2
    ]
    partner = {}
    for a in ways:
        best = None
        for b in ways:
            if b == a:
                continue
            gap = _parallel_gap(way_xy[a], way_xy[b])
            if gap is not None and (best is None or gap < best[0]):
                best = (gap, b)
        if best:
            partner[a] = best[1]
    out, done = [], set()
    for a in ways:
        b = partner.get(a)
        if a in done:
            continue
        if b is not None and partner.get(b) == a:
            left, right = way_xy[a], way_xy[b]
            if _reversed(left, right):
                right = right[::-1]
            out += paint.zebra(left, right)
            done |= {a, b}
        else:
            out += _single_edge_crossing(way_xy[a])
            done.add(a)
    return out


def _parallel_gap(a, b):
    """Perpendicular distance between two roughly parallel, overlapping segments, else None."""
    da = a[-1] - a[0]
    la = np.linalg.norm(da)
    db = b[-1] - b[0]
    lb = np.linalg.norm(db)
    if la < 1.0 or lb < 1.0 or abs(np.dot(da, db)) / (la * lb) < 0.9:
        return None
    u = da / la
    n = np.array([-u[1], u[0]])
    gap = abs(np.dot((b[0] + b[-1]) / 2.0 - a[0], n))
    ta = sorted([0.0, la])
    tb = sorted([np.dot(b[0] - a[0], u), np.dot(b[-1] - a[0], u)])
    overlap = min(ta[1], tb[1]) - max(ta[0], tb[0])
    if 1.5 <= gap <= 8.0 and overlap > 0.5 * min(la, lb):
        return gap
    return None


def _single_edge_crossing(edge, depth_m: float = 3.0) -> list[Marking]:
    """A crossing known by one edge only: stripes over depth_m centred on the edge."""
    return paint.zebra(paint.offset(edge, depth_m / 2.0), paint.offset(edge, -depth_m / 2.0))
