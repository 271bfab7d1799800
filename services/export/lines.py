"""Pieces of painted line (world metres) -> the lines a vector map draws: a strip polygon's centre
line, pieces cut at tile borders joined again, and dashes chained into one dashed line (Lanelet2
represents a dashed marking by one linestring through its dashes, not dash by dash)."""

from collections import defaultdict
from dataclasses import dataclass, field

import cv2
import numpy as np

JOIN_GAP_M = 0.35  # pieces whose ends are this close (a tile border's cut) are one line
JOIN_TURN_DEG = 35.0  # ... when the line turns no more than this there
DASH_MAX_M = 4.5  # a piece shorter than this is a dash candidate (dashes: 3 m, 6 m gaps)
DASH_GAP_M = (0.8, 12.0)  # gaps between neighbouring dashes of one line
DASH_TURN_DEG = 20.0  # dashes of one line point the same way, to this
DASH_CHORD_DEG = 15.0  # ... the gap between them runs their way, to this (a bend allows some)
DASH_OFFSET_M = 1.0  # ... and lies at most this far sideways (neighbour lines: 2.5 m and more)
SIMPLIFY_M = 0.04  # centre lines of strips are simplified to this


@dataclass
class Piece:
    """A painted line: polyline (n, 2) metres, painted width, and the tiles it came from with
    their versions; `dashes` > 0 once dashes are chained into it."""

    xy: np.ndarray
    width_m: float
    tiles: dict = field(default_factory=dict)  # (tx, ty) -> version
    dashes: int = 0

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.xy, axis=0), axis=1).sum())


def strip_centreline(ring: np.ndarray) -> tuple[np.ndarray, float]:
    """A thin strip's outline (n, 2) -> (centre polyline, width). The ends are the two vertices
    farthest apart; the two sides between them, resampled alike by arc length, average to the
    centre. Width = area / length, plus the cell the outline's cell centres leave off."""
    ring = np.asarray(ring, dtype=float)
    d = np.linalg.norm(ring[:, None] - ring[None], axis=2)
    i, j = sorted(np.unravel_index(int(np.argmax(d)), d.shape))
    if d[i, j] <= 0:
        return ring[:1].repeat(2, axis=0), 0.0
    side_a = ring[i : j + 1]
    side_b = np.concatenate([ring[j:], ring[: i + 1]])[::-1]
    n = max(len(side_a), len(side_b), 2)
    centre = 0.5 * (_resample(side_a, n) + _resample(side_b, n))
    centre = _simplify(centre, SIMPLIFY_M)
    length = max(float(np.linalg.norm(np.diff(centre, axis=0), axis=1).sum()), 1e-9)
    x, y = ring[:, 0], ring[:, 1]
    area = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
    return centre, area / length


def _resample(poly: np.ndarray, n: int) -> np.ndarray:
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    if s[-1] <= 0:
        return np.repeat(poly[:1], n, axis=0)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, poly[:, 0]), np.interp(t, s, poly[:, 1])], axis=1)


def _simplify(poly: np.ndarray, epsilon_m: float) -> np.ndarray:
    scale = 1000.0  # approxPolyDP on millimetres
    out = cv2.approxPolyDP((poly * scale).astype(np.float32).reshape(-1, 1, 2),
                           epsilon_m * scale, False)
    return out.reshape(-1, 2).astype(np.float64) / scale


def join_pieces(pieces: list[Piece]) -> list[Piece]:
    """Join pieces end to end where their ends meet (JOIN_GAP_M) and the line runs on
    (JOIN_TURN_DEG): a line the tile borders cut is one line again."""
    pieces = list(pieces)
    while True:
        best = _best_join(pieces)
        if best is None:
            return pieces
        a, end_a, b, end_b = best
        pieces[a] = _joined(pieces[a], end_a, pieces[b], end_b)
        del pieces[b]


def _best_join(pieces: list[Piece]):
    ends = _ends(pieces)
    best = None
    for u, v in _near_pairs(ends[:, :2], JOIN_GAP_M):
        a, b = int(ends[u, 2]), int(ends[v, 2])
        if a == b:
            continue
        gap = float(np.linalg.norm(ends[u, :2] - ends[v, :2]))
        out_a = _end_direction(pieces[a].xy, int(ends[u, 3]))
        out_b = _end_direction(pieces[b].xy, int(ends[v, 3]))
        if _angle_deg(out_a, -out_b) <= JOIN_TURN_DEG and (best is None or gap < best[0]):
            best = (gap, a, int(ends[u, 3]), b, int(ends[v, 3]))
    return None if best is None else best[1:]


def _ends(pieces: list[Piece]) -> np.ndarray:
    """(2n, 4): x, y, piece index, end (0 = first vertex, 1 = last)."""
    rows = []
    for k, p in enumerate(pieces):
        rows += [(*p.xy[0], k, 0), (*p.xy[-1], k, 1)]
    return np.array(rows, dtype=float).reshape(-1, 4)


def _end_direction(xy: np.ndarray, end: int) -> np.ndarray:
    """Unit vector pointing out of the polyline at an end."""
    d = xy[0] - xy[1] if end == 0 else xy[-1] - xy[-2]
    return d / max(float(np.linalg.norm(d)), 1e-9)


def _angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(u, v), -1.0, 1.0))))


def _joined(a: Piece, end_a: int, b: Piece, end_b: int) -> Piece:
    """a's end_a meets b's end_b: one polyline, a first, running into b."""
    xa = a.xy if end_a == 1 else a.xy[::-1]
    xb = b.xy if end_b == 0 else b.xy[::-1]
    la, lb = a.length_m, b.length_m
    width = (a.width_m * la + b.width_m * lb) / max(la + lb, 1e-9)
    return Piece(np.concatenate([xa, xb]), width, {**a.tiles, **b.tiles}, a.dashes + b.dashes)


def _near_pairs(points: np.ndarray, radius: float):
    """Index pairs (i < j) of points at most radius apart (a bucket grid of radius cells)."""
    buckets = defaultdict(list)
    keys = np.floor(points / radius).astype(np.int64)
    for i, (kx, ky) in enumerate(keys):
        buckets[(int(kx), int(ky))].append(i)
    for i, (kx, ky) in enumerate(keys):
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for j in buckets.get((int(kx) + dx, int(ky) + dy), ()):
                    if j > i and np.linalg.norm(points[i] - points[j]) <= radius:
                        yield i, j


def chain_dashes(pieces: list[Piece]) -> list[Piece]:
    """Pieces shorter than DASH_MAX_M that follow each other along one line (gap within
    DASH_GAP_M, same direction and line to DASH_TURN_DEG, DASH_CHORD_DEG and DASH_OFFSET_M) ->
    one line through
    them, dashes = their number; longer pieces and lone short ones pass unchanged (a lone
    piece DASH_MAX_M or shorter keeps dashes = 1)."""
    short = [p for p in pieces if p.length_m < DASH_MAX_M]
    rest = [p for p in pieces if p.length_m >= DASH_MAX_M]
    links = _dash_links(short)
    chained, seen = [], set()
    for start in range(len(short)):
        if start in seen or len(links[start]) > 1:
            continue  # chains are walked from an end
        chained.append(_walk_chain(short, links, start, seen))
    for k in range(len(short)):  # closed loops (no end): walk from anywhere
        if k not in seen:
            chained.append(_walk_chain(short, links, k, seen))
    return rest + chained


def _dash_links(short: list[Piece]) -> list[list[int]]:
    """Each dash linked to its nearest follower ahead and behind, where both agree."""
    best = {}  # (dash, end) -> (gap, other dash, other end)
    if len(short) < 2:
        return [[] for _ in short]
    ends = _ends(short)
    for u, v in _near_pairs(ends[:, :2], DASH_GAP_M[1]):
        a, b = int(ends[u, 2]), int(ends[v, 2])
        if a == b:
            continue
        ea, eb = int(ends[u, 3]), int(ends[v, 3])
        gap = _dash_gap(short[a], ea, short[b], eb)
        if gap is None:
            continue
        for key, other in (((a, ea), (b, eb)), ((b, eb), (a, ea))):
            if key not in best or gap < best[key][0]:
                best[key] = (gap, *other)
    links = [[] for _ in short]
    for (a, ea), (_, b, eb) in best.items():
        if best.get((b, eb), (None, None, None))[1:] == (a, ea) and a < b:
            links[a].append(b)
            links[b].append(a)
    return links


def _dash_gap(a: Piece, ea: int, b: Piece, eb: int) -> float | None:
    """The gap from a's end ea to b's end eb if b continues a's line there, else None."""
    pa, pb = a.xy[0 if ea == 0 else -1], b.xy[0 if eb == 0 else -1]
    out_a = _end_direction(a.xy, ea)
    into_b = -_end_direction(b.xy, eb)
    gap_v = pb - pa
    gap = float(np.linalg.norm(gap_v))
    if not DASH_GAP_M[0] <= gap <= DASH_GAP_M[1]:
        return None
    if _angle_deg(out_a, into_b) > DASH_TURN_DEG:
        return None
    chord = gap_v / max(gap, 1e-9)
    if max(_angle_deg(out_a, chord), _angle_deg(into_b, chord)) > DASH_CHORD_DEG:
        return None
    sideways = abs(float(out_a[0] * gap_v[1] - out_a[1] * gap_v[0]))
    return gap if sideways <= DASH_OFFSET_M else None


def _walk_chain(short: list[Piece], links: list[list[int]], start: int, seen: set) -> Piece:
    """The dashes linked from `start` on, in order, as one piece through all of them."""
    order, prev, cur = [], None, start
    while cur is not None and cur not in seen:
        seen.add(cur)
        order.append(cur)
        nxt = [k for k in links[cur] if k != prev and k not in seen]
        prev, cur = cur, (nxt[0] if nxt else None)
    first = short[order[0]]
    xy = first.xy
    if len(order) > 1 and _dist_to(xy[0], short[order[1]].xy) < _dist_to(xy[-1],
                                                                          short[order[1]].xy):
        xy = xy[::-1]  # the first dash runs towards the second
    line = Piece(xy, first.width_m, dict(first.tiles), 1)
    for k in order[1:]:
        p = short[k]
        near_first = np.linalg.norm(line.xy[-1] - p.xy[0]) <= np.linalg.norm(line.xy[-1] - p.xy[-1])
        line = _joined(line, 1, Piece(p.xy if near_first else p.xy[::-1], p.width_m, p.tiles, 1), 0)
    return line


def _dist_to(point: np.ndarray, xy: np.ndarray) -> float:
    return float(min(np.linalg.norm(xy[0] - point), np.linalg.norm(xy[-1] - point)))
