"""Tile codecs: the contour codec ("contour/1", paper IV-D/E) and the raw raster codec ("raw/1").

Contour codec: per class, the label mask -> contours with holes (cv2.findContours RETR_CCOMP) ->
simplified polygons (approxPolyDP) in integer cell coordinates (x = col, y = row) -> delta +
zigzag varint -> zlib-9 or lzma, whichever is smaller (stdlib only). Decoding fills the polygons
(holes respected) class by class; later classes paint over earlier ones.

ROAD (class 1) is coded coarsely: the localizer matches paint only, so the road surface is the
smoothed union of all labelled cells (paint included, so no holes where paint lies) simplified
with a large tolerance; the paint classes drawn after it restore the exact marking cells. Each
8-connected piece of paint is closed with a 3x3 kernel on its own (fills the one-cell notches that
voting leaves on paint edges, every added cell touches a source cell, and neighbouring zebra
stripes are never bridged) and simplified to 1.5 cells. This keeps per-class
precision/recall at 0.1 m tolerance >= 0.97 against the source raster (measured >= 0.999 on
merged noisy maps: bench/bench_codec.py) at 7-8 KB per km of road.
"""

import lzma
import zlib

import cv2
import numpy as np

from common.classes import NUM_CLASSES, Cls
from common.errors import CodecError
from common.grid import TILE_CELLS

CODEC = "contour/1"
RAW_CODEC = "raw/1"

MAGIC = b"RMC1"
_ZLIB, _LZMA = 0, 1
ENCODED_CLASSES = (Cls.ROAD, Cls.LANE_LINE, Cls.STOP_LINE, Cls.CROSSWALK, Cls.GROUND_SIGN)

MARKING_EPSILON_CELLS = 1.5  # approxPolyDP tolerance for paint (cells)
CLOSE_MARKINGS = True  # 3x3 closing of paint masks before tracing
USE_LINES = True  # thin paint as centre polyline + thickness where that reproduces it
LINE_EPSILON_CELLS = 1.5  # centre line simplification (the per-piece check guards fidelity)
LINE_MAX_WIDTH_CELLS = 6.0
LINE_MAX_THICKNESS = 16
LINE_FIDELITY = 0.98  # per piece, at 1-cell tolerance, or the piece is traced as a polygon
MARKING_MIN_AREA_CELLS = 0  # paint specks below this many cells are dropped
ROAD_EPSILON_CELLS = 3.0  # road surface: coarse
ROAD_SMOOTH_CELLS = 7  # open/close kernel for the road surface before tracing
ROAD_MIN_AREA_CELLS = 50  # road specks below this are dropped

MAX_PAYLOAD_BYTES = 8 * 1024 * 1024  # decompression bound (no zip bombs)
MAX_POINTS = 4 * TILE_CELLS * TILE_CELLS


# -- varints -------------------------------------------------------------------------------------


def _zigzag(v: np.ndarray) -> np.ndarray:
    v = v.astype(np.int64)
    return ((v << 1) ^ (v >> 63)).astype(np.uint64)


def _unzigzag(u: np.ndarray) -> np.ndarray:
    u = u.astype(np.int64)
    return (u >> 1) ^ -(u & 1)


def varint_encode(values: np.ndarray) -> bytes:
    """Unsigned integers (< 2^35) -> LEB128 bytes, vectorised."""
    v = np.asarray(values, dtype=np.uint64).ravel()
    if v.size and int(v.max()) >= 1 << 35:
        raise CodecError("varint value out of range")
    nbytes = np.ones(v.shape, dtype=np.int64)
    for k in range(1, 5):
        nbytes += v >= np.uint64(1 << (7 * k))
    starts = np.cumsum(nbytes) - nbytes
    out = np.empty(int(nbytes.sum()), dtype=np.uint8)
    for k in range(5):
        m = nbytes > k
        byte = (v[m] >> np.uint64(7 * k)) & np.uint64(0x7F)
        more = np.where(nbytes[m] > k + 1, 0x80, 0).astype(np.uint8)
        out[starts[m] + k] = byte.astype(np.uint8) | more
    return out.tobytes()


def varint_decode(data: bytes) -> np.ndarray:
    """LEB128 bytes -> uint64 array; truncated or over-long varints raise CodecError."""
    b = np.frombuffer(data, dtype=np.uint8)
    if b.size == 0:
        return np.zeros(0, dtype=np.uint64)
    if b[-1] & 0x80:
        raise CodecError("truncated varint stream")
    ends = np.flatnonzero(b < 0x80)
    vid = np.zeros(b.size, dtype=np.int64)
    vid[ends[:-1] + 1] = 1
    vid = np.cumsum(vid)
    starts = np.concatenate([[0], ends[:-1] + 1])
    pos = np.arange(b.size) - starts[vid]
    if pos.max() >= 5:
        raise CodecError("varint longer than 5 bytes")
    parts = (b & 0x7F).astype(np.uint64) << (7 * pos).astype(np.uint64)
    out = np.zeros(ends.size, dtype=np.uint64)
    np.add.at(out, vid, parts)
    return out


# -- contour codec -------------------------------------------------------------------------------


def _check_labels(labels: np.ndarray) -> np.ndarray:
    labels = np.asarray(labels)
    if labels.shape != (TILE_CELLS, TILE_CELLS) or labels.dtype != np.uint8:
        raise CodecError(f"expected a ({TILE_CELLS}, {TILE_CELLS}) uint8 label raster")
    return labels


def _road_mask(labels: np.ndarray) -> np.ndarray:
    mask = (labels > 0).astype(np.uint8)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (ROAD_SMOOTH_CELLS, ROAD_SMOOTH_CELLS))
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, k)
    return cv2.morphologyEx(mask, cv2.MORPH_OPEN, k)


def _components(mask: np.ndarray, epsilon: float, min_area: float) -> list[list[np.ndarray]]:
    """Mask -> [[outer, hole, ...], ...] simplified int rings, largest first (so islands inside
    holes are painted after the component whose hole contains them)."""
    comps = _traced(mask, epsilon, min_area)
    comps.sort(key=lambda ar: -ar[0])
    return [rings for _, rings in comps]


def _paint_components(mask: np.ndarray, epsilon: float, min_area: float):
    """Paint mask -> (polygon components, centre lines). Each 8-connected piece of paint becomes
    a centre polyline with a thickness where that reproduces it (a lane line or dash: one side
    instead of two), else it is closed (3x3) and traced on its own, so closing fills the notches
    of a stripe without bridging it to its neighbour."""
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    comps, lines = [], []
    kernel = np.ones((3, 3), np.uint8)
    for i in range(1, n):
        x, y, w, h = (int(v) for v in stats[i, :4])
        x0, y0 = max(x - 1, 0), max(y - 1, 0)
        sub = (lab[y0 : y + h + 1, x0 : x + w + 1] == i).astype(np.uint8)
        line = _centre_line(sub, LINE_EPSILON_CELLS) if USE_LINES else None
        if line is not None:
            lines.append((line[0] + [x0, y0], line[1]))
            continue
        if CLOSE_MARKINGS:
            sub = cv2.morphologyEx(sub, cv2.MORPH_CLOSE, kernel)
        comps += _traced(sub, epsilon, min_area, offset=(x0, y0))
    comps.sort(key=lambda ar: -ar[0])
    return [rings for _, rings in comps], lines


def _centre_line(sub: np.ndarray, epsilon: float):
    """A thin, elongated piece of paint -> (polyline vertices (k, 2) int, thickness) or None.

    The cells are binned along their principal axis; the bin means form the centre line, which is
    simplified (approxPolyDP, open) and drawn back with the mean width as thickness. Accepted only
    if the drawing matches the piece at 1-cell tolerance (precision and recall >= LINE_FIDELITY)."""
    ys, xs = np.nonzero(sub)
    if len(xs) < 8:
        return None
    pts = np.stack([xs, ys], axis=1).astype(np.float64)
    mean = pts.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((pts - mean).T))
    axis, normal = vecs[:, 1], vecs[:, 0]
    t, d = (pts - mean) @ axis, (pts - mean) @ normal
    length = t.max() - t.min() + 1.0
    width = len(pts) / length
    if width > LINE_MAX_WIDTH_CELLS or length < 3.0 * width:
        return None
    bins = np.floor(t - t.min()).astype(np.int64)
    counts = np.bincount(bins)
    used = counts > 0
    t_c = np.bincount(bins, weights=t)[used] / counts[used]
    d_c = np.bincount(bins, weights=d)[used] / counts[used]
    centre = mean + t_c[:, None] * axis + d_c[:, None] * normal
    verts = cv2.approxPolyDP(centre.astype(np.float32).reshape(-1, 1, 2), epsilon, False)
    verts = verts.reshape(-1, 2).astype(np.float64)
    if len(verts) < 2:
        verts = centre[[0, -1]]
    thickness = int(np.clip(np.round(width), 1, LINE_MAX_THICKNESS))
    _pull_ends(verts, (thickness - 1) / 2.0)  # round caps reach past the end vertices
    verts = np.round(verts).astype(np.int64)
    pad = LINE_MAX_THICKNESS
    target = cv2.copyMakeBorder(sub, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
    drawn = np.zeros_like(target)
    _draw_line(drawn, (verts + pad).astype(np.int32), thickness)
    return (verts, thickness) if _matches(drawn, target) else None


def _pull_ends(verts: np.ndarray, by: float) -> None:
    """Move the first and last vertex `by` cells inwards (never past half their segment)."""
    for end, nxt in ((0, 1), (-1, -2)):
        seg = verts[nxt] - verts[end]
        n = float(np.hypot(*seg))
        if n > 0:
            verts[end] += seg / n * min(by, n / 2.0)


def _draw_line(mask: np.ndarray, verts: np.ndarray, thickness: int) -> None:
    cv2.polylines(mask, [verts.reshape(-1, 1, 2)], False, 1, thickness=int(thickness))


def _matches(drawn: np.ndarray, sub: np.ndarray) -> bool:
    kernel = np.ones((3, 3), np.uint8)
    n_drawn, n_sub = int(drawn.sum()), int(sub.sum())
    if not n_drawn:
        return False
    precision = int((drawn & cv2.dilate(sub, kernel)).sum()) / n_drawn
    recall = int((sub & cv2.dilate(drawn, kernel)).sum()) / n_sub
    return min(precision, recall) >= LINE_FIDELITY


def _traced(mask, epsilon: float, min_area: float, offset=(0, 0)):
    """[(area, [outer, holes...])] of a mask, rings simplified and shifted by offset (x, y)."""
    contours, hierarchy = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE,
                                           offset=offset)
    if hierarchy is None:
        return []
    hierarchy = hierarchy[0]
    comps = []
    for i, c in enumerate(contours):
        if hierarchy[i][3] != -1:
            continue  # a hole; collected with its parent
        area = cv2.contourArea(c) + len(c)  # pixel area ~ polygon area + half the border
        if area < min_area:
            continue
        rings = [_simplify(c, epsilon)]
        j = hierarchy[i][2]
        while j != -1:
            rings.append(_simplify(contours[j], epsilon))
            j = hierarchy[j][0]
        comps.append((area, rings))
    return comps


def _simplify(contour: np.ndarray, epsilon: float) -> np.ndarray:
    """approxPolyDP, except where it would collapse a thin ring to a line (a 2-cell-wide dash
    becomes its diagonal): then the unsimplified ring is kept."""
    ring = cv2.approxPolyDP(contour, epsilon, True) if len(contour) > 4 else contour
    if len(ring) < 4 <= len(contour):
        ring = contour
    return ring.reshape(-1, 2).astype(np.int64)


def _class_plan(labels: np.ndarray, epsilon: float, min_area: float):
    """[(cls, polygon components, centre lines)] in ENCODED_CLASSES order."""
    road = _components(_road_mask(labels), ROAD_EPSILON_CELLS, ROAD_MIN_AREA_CELLS)
    plan = [(int(Cls.ROAD), road, [])]
    for cls in ENCODED_CLASSES[1:]:
        mask = (labels == cls).astype(np.uint8)
        comps, lines = _paint_components(mask, epsilon, min_area) if mask.any() else ([], [])
        plan.append((int(cls), comps, lines))
    return plan


def encode_tile(
    labels: np.ndarray,
    *,
    epsilon_cells: float = MARKING_EPSILON_CELLS,
    min_area_cells: float = MARKING_MIN_AREA_CELLS,
) -> bytes:
    """(512, 512) uint8 label raster -> compressed contour bytes (codec "contour/1")."""
    labels = _check_labels(labels)
    structure, rings = [], []
    for _cls, comps, lines in _class_plan(labels, epsilon_cells, min_area_cells):
        structure.append(len(comps))
        for comp in comps:
            structure.append(len(comp))
            for ring in comp:
                structure.append(len(ring))
                rings.append(ring)
        structure.append(len(lines))
        for verts, thickness in lines:
            structure += [len(verts), thickness]
            rings.append(verts)
    points = np.concatenate(rings) if rings else np.zeros((0, 2), dtype=np.int64)
    deltas = np.diff(np.concatenate([[[0, 0]], points]), axis=0)
    head = varint_encode(np.asarray(structure, dtype=np.uint64))
    payload = varint_encode([len(head)]) + head + varint_encode(_zigzag(deltas.ravel()))
    return _compress(payload)


def _compress(payload: bytes) -> bytes:
    z = zlib.compress(payload, 9)
    # a 1 MiB dictionary: preset 9's 64 MiB one costs ~40 ms per call to set up, for nothing
    x = lzma.compress(payload, format=lzma.FORMAT_RAW,
                      filters=[{"id": lzma.FILTER_LZMA2, "preset": 9, "dict_size": 1 << 20}])
    return MAGIC + (bytes([_ZLIB]) + z if len(z) <= len(x) else bytes([_LZMA]) + x)


def _decompress(data: bytes) -> bytes:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise CodecError("contour tile: expected bytes")
    data = bytes(data)
    if len(data) < len(MAGIC) + 1 or data[: len(MAGIC)] != MAGIC:
        raise CodecError(f"contour tile: expected magic {MAGIC!r} ({CODEC})")
    method, body = data[len(MAGIC)], data[len(MAGIC) + 1 :]
    try:
        if method == _ZLIB:
            d = zlib.decompressobj()
            out = d.decompress(body, MAX_PAYLOAD_BYTES)
            if d.unconsumed_tail or not d.eof or d.unused_data:
                raise CodecError("contour tile: zlib stream truncated, oversize or trailing data")
            return out
        if method == _LZMA:
            d = lzma.LZMADecompressor(format=lzma.FORMAT_RAW, filters=[{"id": lzma.FILTER_LZMA2}])
            out = d.decompress(body, MAX_PAYLOAD_BYTES)
            if not d.eof or d.unused_data:
                raise CodecError("contour tile: lzma stream truncated, oversize or trailing data")
            return out
    except (zlib.error, lzma.LZMAError) as exc:
        raise CodecError(f"contour tile: corrupt compressed stream: {exc}") from exc
    raise CodecError(f"contour tile: unknown compressor id {method}")


def _parse(payload: bytes) -> tuple[list[int], np.ndarray]:
    """payload -> (structure ints, absolute points (n, 2))."""
    b = np.frombuffer(payload, dtype=np.uint8)
    ends = np.flatnonzero(b < 0x80)
    if ends.size == 0:
        raise CodecError("contour tile: empty payload")
    n_head = int(varint_decode(payload[: ends[0] + 1])[0])
    start = int(ends[0]) + 1
    if start + n_head > len(payload):
        raise CodecError("contour tile: structure longer than the payload")
    structure = [int(v) for v in varint_decode(payload[start : start + n_head])]
    deltas = _unzigzag(varint_decode(payload[start + n_head :]))
    if deltas.size % 2:
        raise CodecError("contour tile: odd number of coordinates")
    points = np.cumsum(deltas.reshape(-1, 2), axis=0)
    if points.size and (points.min() < 0 or points.max() >= TILE_CELLS):
        raise CodecError(f"contour tile: point outside [0, {TILE_CELLS})")
    return structure, points


def _rings_by_class(structure: list[int], n_points: int):
    """Walk the structure ints -> [(cls, [[n_outer, n_hole...], ...], [(n_verts, thickness)])]
    and check every count."""
    it, used, out = iter(structure), 0, []
    try:
        for cls in ENCODED_CLASSES:
            comps = []
            for _ in range(_bounded(next(it), "components")):
                n_rings = _bounded(next(it), "rings")
                if n_rings < 1:
                    raise CodecError("contour tile: a component needs an outer ring")
                sizes = [_bounded(next(it), "points") for _ in range(n_rings)]
                if min(sizes) < 1:
                    raise CodecError("contour tile: empty ring")
                used += sum(sizes)
                comps.append(sizes)
            lines = []
            for _ in range(_bounded(next(it), "lines")):
                n_verts, thickness = _bounded(next(it), "vertices"), next(it)
                if n_verts < 2 or not 1 <= thickness <= LINE_MAX_THICKNESS:
                    raise CodecError("contour tile: a line needs >= 2 vertices and a thickness "
                                     f"in [1, {LINE_MAX_THICKNESS}]")
                used += n_verts
                lines.append((n_verts, thickness))
            out.append((int(cls), comps, lines))
    except StopIteration as exc:
        raise CodecError("contour tile: structure ends early") from exc
    if next(it, None) is not None:
        raise CodecError("contour tile: trailing structure data")
    if used != n_points:
        raise CodecError(f"contour tile: structure names {used} points, stream has {n_points}")
    return out


def _bounded(v: int, what: str) -> int:
    if v > MAX_POINTS:
        raise CodecError(f"contour tile: implausible number of {what}: {v}")
    return v


def decode_tile(data: bytes) -> np.ndarray:
    """Contour bytes -> (512, 512) uint8 labels; any malformed input raises CodecError."""
    structure, points = _parse(_decompress(data))
    labels = np.zeros((TILE_CELLS, TILE_CELLS), dtype=np.uint8)
    pts = points.astype(np.int32)
    offset = 0
    for cls, comps, lines in _rings_by_class(structure, len(points)):
        mask = np.zeros_like(labels)
        for sizes in comps:
            rings = []
            for n in sizes:
                rings.append(pts[offset : offset + n].reshape(-1, 1, 2))
                offset += n
            _paint_component(mask, rings)
        for n, thickness in lines:
            _draw_line(mask, pts[offset : offset + n], thickness)
            offset += n
        labels[mask > 0] = cls
    return labels


def _paint_component(mask: np.ndarray, rings: list[np.ndarray]) -> None:
    """Fill the outer ring, clear hole interiors; hole rings are traced on foreground cells, so
    they are drawn back after clearing."""
    cv2.fillPoly(mask, [rings[0]], 1)
    if len(rings) > 1:
        cv2.fillPoly(mask, rings[1:], 0)
        cv2.polylines(mask, rings[1:], True, 1)


# -- raw codec -----------------------------------------------------------------------------------


def encode_raw(labels: np.ndarray) -> bytes:
    """(512, 512) uint8 labels -> zlib of the raster (codec "raw/1", the uncompressed map)."""
    return zlib.compress(_check_labels(labels).tobytes(), 6)


def decode_raw(data: bytes) -> np.ndarray:
    n = TILE_CELLS * TILE_CELLS
    try:
        d = zlib.decompressobj()
        raw = d.decompress(bytes(data), n + 1)
    except (zlib.error, TypeError) as exc:
        raise CodecError(f"raw tile: expected zlib of a {TILE_CELLS}^2 uint8 raster") from exc
    if len(raw) != n or not d.eof or d.unused_data:
        raise CodecError(f"raw tile: expected zlib of exactly {n} bytes")
    labels = np.frombuffer(raw, dtype=np.uint8).reshape(TILE_CELLS, TILE_CELLS).copy()
    if labels.max() >= NUM_CLASSES:
        raise CodecError(f"raw tile: class value >= {NUM_CLASSES}")
    return labels
