"""Seeded procedural town: a jittered street grid with straight and curved multi-lane roads,
intersections with stop lines, zebra crossings, turn arrows and road text, and a GNSS-blocked
stretch of at least 300 m. Local ENU metres; right-hand traffic.

By default every road has one lane each way except one arterial row with two. Segmentation
training asks for wide roads too (`lane_mix`, `median_prob`): up to four lanes each way, some
split by a raised median, as the arterials of real maps are (the Argoverse 2 worlds' far field
is many converging lines, which towns of one- and two-lane roads never show)."""

import math
from dataclasses import dataclass

import cv2
import numpy as np

from common.classes import Cls
from common.world import Marking, World
from services.sim import paint
from services.sim.routes import blocked_zone_along

LANE_W_M = 3.5
SHOULDER_M = 0.6
EDGE_LINE_M = 0.15
SPACING_M = 160.0
TEXTS = ("XING", "EXIT", "LEFT")


@dataclass
class Edge:
    a: int
    b: int
    lanes: int  # per direction
    center: np.ndarray  # (N, 2) road centre line from node a to node b, cut at the boxes
    lane_w: float = LANE_W_M
    median: float = 0.0  # width of a raised median between the directions (0: none, paint)

    @property
    def half_width(self) -> float:
        return 0.5 * self.median + self.lanes * self.lane_w + SHOULDER_M

    def lane_offset(self, lane: float) -> float:
        """Signed offset from the centre line of a point `lane` lane widths into the right-hand
        carriageway (0: its inner edge, beside the median or the centre line)."""
        return -(0.5 * self.median + self.lane_w * lane)


def _grid_shape(km: float) -> tuple[int, int]:
    target = km * 1000.0 / SPACING_M
    best = (2, 2)
    for nx in range(2, 12):
        for ny in (nx - 1, nx):
            if ny >= 2 and abs((nx - 1) * ny + nx * (ny - 1) - target) < abs(
                (best[0] - 1) * best[1] + best[0] * (best[1] - 1) - target
            ):
                best = (nx, ny)
    return best


def _nodes(nx: int, ny: int, rng) -> np.ndarray:
    ij = np.array([(i, j) for j in range(ny) for i in range(nx)], float)
    return ij * SPACING_M + rng.uniform(-12.0, 12.0, size=ij.shape)


def _bent(a: np.ndarray, b: np.ndarray, amp_m: float) -> np.ndarray:
    """Centre line from a to b bent sideways by amp * sin^2 (tangent = chord at both ends)."""
    t = np.linspace(0.0, 1.0, 81)
    d = b - a
    n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
    return a + t[:, None] * d + (amp_m * np.sin(np.pi * t) ** 2)[:, None] * n


def _edges(nodes, nx, ny, rng, lane_mix=None, median_prob=0.0) -> list[Edge]:
    """lane_mix: probabilities of 1, 2, ... lanes each way for every road (the arterial row
    draws at least two); None: one lane, two on the arterial row. A road of two or more lanes
    gets a raised median (1-4 m) with median_prob."""
    idx = lambda i, j: j * nx + i  # noqa: E731
    arterial_row = int(rng.integers(ny))
    pairs = [
        (idx(i, j), idx(i + 1, j), j == arterial_row) for j in range(ny) for i in range(nx - 1)
    ]
    pairs += [(idx(i, j), idx(i, j + 1), False) for j in range(ny - 1) for i in range(nx)]
    edges = []
    for a, b, arterial in pairs:
        amp = rng.uniform(-18.0, 18.0) if rng.random() < 0.4 else 0.0
        lane_w = rng.uniform(3.0, 3.75)  # lane widths vary from road to road
        lanes, median = (2 if arterial else 1), 0.0
        if lane_mix is not None:
            p = np.asarray(lane_mix, float)
            if arterial and len(p) > 1:
                p = np.concatenate([[0.0], p[1:]])
            lanes = 1 + int(rng.choice(len(p), p=p / p.sum()))
            if lanes >= 2 and rng.random() < median_prob:
                median = float(rng.uniform(1.0, 4.0))
        edges.append(Edge(a, b, lanes, _bent(nodes[a], nodes[b], amp), lane_w, median))
    return edges


def _box_half(edges, node) -> float:
    return max(e.half_width for e in edges if node in (e.a, e.b)) + 1.0


def _cut_edges(edges, nodes):
    """Cut each centre line where it enters the intersection boxes at its ends."""
    for e in edges:
        s = paint.arc_length(e.center)
        e.center = paint.sub_polyline(
            e.center, s, _box_half(edges, e.a), s[-1] - _box_half(edges, e.b)
        )


def _road_markings(e: Edge, rng, crosswalk_ends: set) -> list[Marking]:
    """Surface, lane lines, and at both ends stop lines, crossings and arrows of one road."""
    c, n, hw = e.center, e.lanes, e.half_width
    s = paint.arc_length(c)
    if e.median > 0:  # two carriageways, the raised median between them off the road surface
        half = hw - 0.5 * e.median
        out = [Marking(Cls.ROAD, paint.strip(paint.offset(c, side * (hw - 0.5 * half)), half),
                       "road") for side in (-1, 1)]
    else:
        out = [Marking(Cls.ROAD, paint.strip(c, 2 * hw), "road")]
    zone = {end: (7.0 if end in crosswalk_ends else 1.5) for end in (e.a, e.b)}
    lo, hi = zone[e.a] + 0.5, s[-1] - zone[e.b] - 0.5
    body = paint.sub_polyline(c, s, lo, hi)
    # centre line: dashed (3/6) on two-lane roads, double solid on arterials; solid near stops
    if n == 1:
        sb = paint.arc_length(body)
        mid = paint.sub_polyline(body, sb, 20.0, sb[-1] - 20.0)
        out += paint.line_markings(mid, "dashed", paint.LINE_THIN_M, 3.0, 6.0)
        for a_, b_ in ((0.0, 20.0), (sb[-1] - 20.0, sb[-1])):
            out += paint.line_markings(paint.sub_polyline(body, sb, a_, b_), "solid")
    else:
        if e.median > 0:  # a solid line along each side of the median
            for side in (-1, 1):
                out += paint.line_markings(paint.offset(body, side * (0.5 * e.median + 0.1)),
                                           "solid", EDGE_LINE_M)
        else:
            out += paint.line_markings(body, "double")
        for k in range(1, n):
            for side in (-1, 1):
                out += paint.line_markings(paint.offset(body, -side * e.lane_offset(k)),
                                           "dashed", 0.15, 6.0, 12.0)
    for side in (-1, 1):
        out += paint.line_markings(paint.offset(body, -side * (e.lane_offset(n) - 0.1)),
                                   "solid", EDGE_LINE_M)
    out += _end_features(c, s, e, forward=True, crosswalk=e.b in crosswalk_ends, rng=rng)
    out += _end_features(c[::-1], paint.arc_length(c[::-1]), e, forward=False,
                         crosswalk=e.a in crosswalk_ends, rng=rng)
    if s[-1] > 100.0 and rng.random() < 0.5:  # road text in the right lane, mid-block
        x, y, yaw = _pose_at(c, s, 0.5 * s[-1], e.lane_offset(n - 0.5))
        out += paint.text_block(TEXTS[int(rng.integers(len(TEXTS)))], x, y, yaw)
    return out


def _pose_at(c, s, at, lateral):
    x = np.interp(at, s, c[:, 0])
    y = np.interp(at, s, c[:, 1])
    k = min(np.searchsorted(s, at), len(c) - 1)
    d = c[k] - c[max(k - 1, 0)]
    yaw = math.atan2(d[1], d[0])
    return x - math.sin(yaw) * lateral, y + math.cos(yaw) * lateral, yaw


def _end_features(c, s, e: Edge, *, forward, crosswalk, rng) -> list[Marking]:
    """Stop line over the incoming (right) lanes, optional zebra and turn arrows at c's far end."""
    n, hw = e.lanes, e.half_width
    out = []
    end = s[-1] - 1.0
    if crosswalk:
        a = _pose_at(c, s, end - 2.0, hw - 0.5)
        b = _pose_at(c, s, end - 2.0, -hw + 0.5)
        out += paint.zebra_across(np.array(a[:2]), np.array(b[:2]), depth_m=4.0)
        end -= 5.5
    p0, p1 = _pose_at(c, s, end, e.lane_offset(0) - 0.1), _pose_at(c, s, end, e.lane_offset(n))
    out.append(paint.stop_line(np.array(p0[:2]), np.array(p1[:2])))
    for lane in range(n):
        x, y, yaw = _pose_at(c, s, end - 14.0, e.lane_offset(lane + 0.5))
        if n == 2:
            kind = (
                "arrow_left"
                if lane == 0
                else ("arrow_straight" if rng.random() < 0.5 else "arrow_right")
            )
        else:
            kind = ("arrow_straight", "arrow_left", "arrow_right")[int(rng.integers(3))]
        out.append(paint.arrow(kind, x, y, yaw))
    return out


def _intersections(edges, nodes) -> list[Marking]:
    """Road surface of each intersection: hull of the incident roads' end caps."""
    out = []
    for k in range(len(nodes)):
        pts = []
        for e in edges:
            if k in (e.a, e.b):
                end = e.center[0] if k == e.a else e.center[-1]
                d = e.center[1] - e.center[0] if k == e.a else e.center[-1] - e.center[-2]
                nrm = np.array([-d[1], d[0]]) / np.linalg.norm(d)
                pts += [end + nrm * e.half_width, end - nrm * e.half_width]
        if len(pts) >= 3:
            hull = cv2.convexHull(np.array(pts, np.float32)).reshape(-1, 2).astype(float)
            out.append(Marking(Cls.ROAD, hull, "intersection"))
    return out


def _tour(edges, n_nodes, rng) -> list[int]:
    """Node sequence of a drive covering every road (no U-turns), least-visited roads first."""
    adj = {k: [] for k in range(n_nodes)}
    for i, e in enumerate(edges):
        adj[e.a].append((e.b, i))
        adj[e.b].append((e.a, i))
    visits = np.zeros(len(edges), int)
    path, prev = [edges[0].a], -1
    while (visits == 0).any() and len(path) < 20 * len(edges):
        here = path[-1]
        options = [(visits[i] + rng.random() * 0.5, nb, i) for nb, i in adj[here] if nb != prev]
        _, nb, i = min(options)
        visits[i] += 1
        prev = here
        path.append(nb)
    return path


def _lane_route(path, edges, nodes, lane: int) -> np.ndarray:
    """Lane centre polyline along a node path (right-hand lane `lane`), turns as Bezier curves."""
    legs = []
    for a, b in zip(path[:-1], path[1:], strict=False):
        e = next(e for e in edges if {e.a, e.b} == {a, b})
        c = e.center if e.a == a else e.center[::-1]
        legs.append(paint.offset(c, e.lane_offset(min(lane, e.lanes - 1) + 0.5)))
    pts = [legs[0]]
    for prev, nxt in zip(legs[:-1], legs[1:], strict=False):
        p0, p2 = prev[-1], nxt[0]
        d0 = (prev[-1] - prev[-2]) / np.linalg.norm(prev[-1] - prev[-2])
        d2 = (nxt[1] - nxt[0]) / np.linalg.norm(nxt[1] - nxt[0])
        # control point: where the two lane lines meet (straight on: the midpoint)
        A = np.stack([d0, -d2], axis=1)
        if abs(np.linalg.det(A)) > 0.2:
            t = np.linalg.solve(A, p2 - p0)
            p1 = p0 + t[0] * d0
        else:
            p1 = 0.5 * (p0 + p2)
        t = np.linspace(0.0, 1.0, 12)[1:-1, None]
        pts.append((1 - t) ** 2 * p0 + 2 * (1 - t) * t * p1 + t**2 * p2)
        pts.append(nxt)
    return paint.dedupe(np.concatenate(pts))


def build_town(km: float = 2.0, seed: int = 0, lane_mix=None, median_prob: float = 0.0) -> World:
    """lane_mix, median_prob: wide roads (`_edges`); the default town has none."""
    rng = np.random.default_rng(seed)
    nx, ny = _grid_shape(km)
    nodes = _nodes(nx, ny, rng)
    edges = _edges(nodes, nx, ny, rng, lane_mix, median_prob)
    _cut_edges(edges, nodes)
    crosswalk_ends = {int(k) for k in np.flatnonzero(rng.random(len(nodes)) < 0.5)}
    markings = _intersections(edges, nodes)
    for e in edges:
        markings += _road_markings(e, rng, crosswalk_ends)
    path = _tour(edges, len(nodes), rng)
    routes = [
        _lane_route(path, edges, nodes, 0),
        _lane_route(path[::-1], edges, nodes, 0),
        _lane_route(path, edges, nodes, 1),
    ]
    most = max(e.lanes for e in edges)
    routes += [_lane_route(path[::-1] if lane % 2 else path, edges, nodes, lane)
               for lane in range(2, most)]  # wide roads: their outer lanes too
    km_road = sum(float(np.linalg.norm(nodes[e.b] - nodes[e.a])) for e in edges) / 1000.0
    return World(
        name=f"town-{km:g}km-s{seed}",
        markings=markings,
        routes=routes,
        gnss_blocked=blocked_zone_along(routes[0]),
        km_of_road=km_road,
        origin_latlon=(49.0, 8.4),
    )
