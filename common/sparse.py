"""The "sparse/1" patch form (issue #68): a traversal's patch of one tile as its local map's
geometry plus the evidence the merger's rule weighs, instead of packed per-cell votes (~1 byte
per cell the camera saw: 680-910 KB per km driven on the demo drives).

What the shard's evidence rule (services/merger/shard.py) reads from a traversal's patch is, per
cell, a ballot (the class with the most votes) and the votes behind it (min_votes; and ties of
paint against ground, where the traversal that saw the cell with more pixels wins). Those votes
are the pixels that landed in the cell: the camera's ground-pixel density summed over the
frames (an observation-density field: near range, slow driving, the frame spacing) times the
share of them that showed the class (under 1 at a marking's edge, far under for stray paint).
So the form carries, per patch:

  footprint: the voted cells (road and paint), closed and opened with a FOOTPRINT_SMOOTH_CELLS
             square, traced to polygons with holes (FOOTPRINT_EPSILON_CELLS); every cell inside
             that is not paint is a road ballot ("road = footprint minus paint"); the shard
             closes the footprint for its "no paint" ballots exactly as for the cells form;
  paint:     per marking class its cells traced to polygons with holes (PAINT_EPSILON_CELLS),
             drawn over the footprint in class order;
  field:     the patch's frames as key poses every KEY_EVERY frames (5 cm, 1 mrad; the frames
             between interpolated) and the part of the ROI the camera sees (Roi): the shard
             sweeps a pinhole camera's ground density, (x - camera x)^-3 inside its horizontal
             field of view, normalised to the pixels per frame, along the frames;
  shares:    the paint cells of the decoded polygons (classes 2..5, raster order) whose votes
             are 2 or more octaves off the field, k = round(log2(votes / field)); the rest k = 0.
Expanded, a road cell votes max(2, round(field)) for road, a paint cell max(1, round(field *
2^k)) for its class; nothing else. Chosen on the stored patches of six demo drives (Karlsruhe
seeds 0-4, town seed 0), merged maps against the cells form's, per marking class: precision
and recall at worst 0.005 below it (means -0.001 to +0.004); a field per patch or per 0.8-3.2 m
block instead of the swept density, or one share per class instead of per cell, lost 0.01-0.02
of precision (stray paint then wins its ties); dropping the shares within an octave cost
nothing, dropping those beyond it 0.01 of recall or precision.

Payload: LEB128 varints (signed ones zigzag), in this order:
    roi x_min_dm, length_dm, width_dm, camera_x_dm, fov_slope_milli, pixels_per_frame,
    n_frames, key_every, n_keys,
    key poses (x, y in 5 cm, yaw in mrad, world frame: second differences, from zero),
    per layer (footprint, lane line, stop line, crosswalk, ground sign): n_components, per
    component n_rings, per ring n_points; the points (col, row cells: differences from the
    previous point, the first from (0, 0)); n_shares, the gaps between the shared paint
    cells' indices, their zigzag k.
A batch compresses its patches together (common.codec SparseBatch), so what the patches of one
seal share (ids, key poses) costs once. Everything here is pure and deterministic: the same
payload expands to the same cells and votes on every shard and on every replay."""

from dataclasses import dataclass

import cv2
import numpy as np

from common.classes import NUM_CLASSES, Cls
from common.contours import simplify_ring, varint_decode, varint_encode
from common.errors import CodecError
from common.grid import CELL_M, CELLS_PER_TILE, TILE_CELLS, tile_origin_m
from common.messages import GridPatch, SparsePatch

FORM = "sparse/1"
# closing then opening square of the voted cells before tracing: 5 spread the road 1-1.5 %
# into what the camera saw as nothing (labelled cells' precision against the truth 0.972 ->
# 0.963 on a demo drive; 3: 0.972, the same bytes)
FOOTPRINT_SMOOTH_CELLS = 3
FOOTPRINT_EPSILON_CELLS = 1.5  # approxPolyDP tolerance of the footprint
PAINT_EPSILON_CELLS = 0.8  # ... and of paint (1.0 lost lane-line recall on the demo drives)
KEY_EVERY = 10  # frames per key pose (every frame and every 10th gave the same maps)
POSE_UNIT_M = 0.05
YAW_UNIT_RAD = 0.001
LAYERS = (Cls.ROAD, Cls.LANE_LINE, Cls.STOP_LINE, Cls.CROSSWALK, Cls.GROUND_SIGN)
SHARE_MIN, SHARE_MAX = -12, 4  # octaves of votes / field
SHARE_EXCEPTION = 2  # octaves off the field a paint cell is sent at (the rest: k = 0)
ROAD_MIN_VOTES = 2  # a road ballot's votes at least (the shard's default min_votes)
DENSITY_EXPONENT = 3.0  # ground pixels per m^2 fall off as x^-3 (pinhole camera over a plane)

MAX_FRAMES = 20_000  # a patch's frames (33 min at 10 Hz)
MAX_POINTS = 4 * CELLS_PER_TILE
MAX_RINGS = CELLS_PER_TILE
MAX_POSE_UNITS = 1 << 34  # |x|, |y| in 5 cm: beyond any world; |yaw| in mrad likewise


@dataclass(frozen=True)
class Roi:
    """The part of the IPM region of interest the camera sees, in the vehicle frame: x from
    x_min_dm over length_dm, |y| up to width_dm / 2 and up to fov_slope_milli / 1000 x (x -
    camera_x_dm), all decimetres; and the camera pixels that land in it per frame."""

    x_min_dm: int
    length_dm: int
    width_dm: int
    camera_x_dm: int
    fov_slope_milli: int
    pixels_per_frame: int


@dataclass
class Geometry:
    """A decoded sparse/1 payload (see the module docstring)."""

    roi: Roi
    n_frames: int
    key_every: int
    keys: np.ndarray  # int64 (n_keys, 3): x, y in POSE_UNIT_M, yaw in YAW_UNIT_RAD
    layers: list  # per LAYERS entry: [component: [ring: int32 (n, 2) (col, row)]]
    strong_at: np.ndarray  # int64 (m,): paint cells (decoded order) 2+ octaves off the field
    strong_k: np.ndarray  # int8 (m,): their octaves (|k| >= 2); every other paint cell k = 0


# -- vehicle side: cells + votes -> geometry ---------------------------------------------------


def roi_of_lookup(ground_xy_m: np.ndarray, *, camera_x_m: float, width_m: float,
                  stride: int = 1) -> Roi:
    """The Roi of a vehicle's IPM lookup (the ground points of its ROI pixels, vehicle frame):
    where they start and end ahead, the widest angle they reach off the camera's axis, and the
    pixels a frame votes with (every stride-th row and column)."""
    xy = np.asarray(ground_xy_m, dtype=np.float64).reshape(-1, 2)
    if not len(xy):
        return Roi(0, 1, max(int(round(width_m / CELL_M)), 1), 0, 0, 0)
    x_min = int(np.floor(xy[:, 0].min() / CELL_M))
    x_max = int(np.ceil(xy[:, 0].max() / CELL_M))
    camera_x = max(int(np.floor(camera_x_m / CELL_M)), 0)
    ahead = np.maximum(xy[:, 0] - camera_x * CELL_M, CELL_M)
    slope = int(np.ceil(1000.0 * float(np.max(np.abs(xy[:, 1]) / ahead))))
    return Roi(max(x_min, 0), max(x_max - x_min, 1), max(int(round(width_m / CELL_M)), 1),
               camera_x, slope, int(round(len(xy) / max(stride, 1) ** 2)))


def sparsify(cells: np.ndarray, votes: np.ndarray, tile, poses_xyyaw: np.ndarray, roi: Roi, *,
             footprint_smooth_cells: int = FOOTPRINT_SMOOTH_CELLS,
             footprint_epsilon_cells: float = FOOTPRINT_EPSILON_CELLS,
             paint_epsilon_cells: float = PAINT_EPSILON_CELLS,
             key_every: int = KEY_EVERY) -> Geometry:
    """A patch's cells (flat, sorted) and votes (n, NUM_CLASSES), voted from the frames at
    `poses_xyyaw` (world frame, metres and radians, in frame order) -> its sparse geometry."""
    cells = np.asarray(cells, dtype=np.int64)
    ballot, weight = _ballots(votes)
    voted = np.zeros(CELLS_PER_TILE, np.uint8)
    voted[cells] = 1
    layers = [_trace(_smoothed(voted, footprint_smooth_cells), footprint_epsilon_cells)]
    for cls in LAYERS[1:]:
        mask = np.zeros(CELLS_PER_TILE, np.uint8)
        mask[cells[ballot == cls]] = 1
        layers.append(_trace(mask.reshape(TILE_CELLS, TILE_CELLS), paint_epsilon_cells)
                      if mask.any() else [])
    geometry = Geometry(roi=roi, n_frames=len(poses_xyyaw), key_every=key_every,
                        keys=_key_poses(poses_xyyaw, key_every), layers=layers,
                        strong_at=np.zeros(0, np.int64), strong_k=np.zeros(0, np.int8))
    k = _shares(geometry, tile, cells, ballot, weight)
    geometry.strong_at = np.flatnonzero(np.abs(k) >= SHARE_EXCEPTION)
    geometry.strong_k = k[geometry.strong_at]
    return geometry


def _ballots(votes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per cell the class with the most votes (ties to the higher class, as the shard's
    ballots) and its votes."""
    v = np.asarray(votes, dtype=np.int64)
    ballot = NUM_CLASSES - 1 - np.argmax(v[:, ::-1], axis=1)
    return ballot, v[np.arange(len(v)), ballot]


def _smoothed(mask: np.ndarray, size: int) -> np.ndarray:
    mask = mask.reshape(TILE_CELLS, TILE_CELLS)
    if size <= 1:
        return mask
    kernel = np.ones((size, size), np.uint8)
    closed = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel, borderType=cv2.BORDER_REPLICATE)
    return cv2.morphologyEx(closed, cv2.MORPH_OPEN, kernel, borderType=cv2.BORDER_REPLICATE)


def _trace(mask: np.ndarray, epsilon: float) -> list:
    """Mask -> components [outer ring, hole rings...] of int32 (n, 2) (col, row), largest first
    (islands inside a hole are drawn after the component whose hole holds them)."""
    contours, hierarchy = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    if hierarchy is None:
        return []
    hierarchy = hierarchy[0]
    comps = []
    for i, c in enumerate(contours):
        if hierarchy[i][3] != -1:
            continue
        rings = [simplify_ring(c, epsilon).astype(np.int32)]
        j = hierarchy[i][2]
        while j != -1:
            rings.append(simplify_ring(contours[j], epsilon).astype(np.int32))
            j = hierarchy[j][0]
        comps.append((cv2.contourArea(c) + len(c), rings))
    comps.sort(key=lambda ar: -ar[0])
    return [rings for _, rings in comps]


def _key_poses(poses_xyyaw: np.ndarray, key_every: int) -> np.ndarray:
    """Every key_every-th frame's pose and the last one's, quantized; yaw unwrapped first so the
    differences (and the interpolation between keys) never jump by 2 pi."""
    poses = np.asarray(poses_xyyaw, dtype=np.float64).reshape(-1, 3)
    if not len(poses):
        return np.zeros((0, 3), np.int64)
    idx = _key_index(len(poses), key_every)
    key = poses[idx]
    yaw = np.unwrap(poses[:, 2])[idx]
    return np.stack([np.round(key[:, 0] / POSE_UNIT_M), np.round(key[:, 1] / POSE_UNIT_M),
                     np.round(yaw / YAW_UNIT_RAD)], axis=1).astype(np.int64)


def _key_index(n_frames: int, key_every: int) -> np.ndarray:
    return np.unique(np.r_[np.arange(0, n_frames, key_every), n_frames - 1]) if n_frames else (
        np.zeros(0, np.int64))


def _shares(geometry: Geometry, tile, cells, ballot, weight) -> np.ndarray:
    """Per decoded paint cell: the octave of its votes over the field (0 for a cell the
    polygons added: no votes of its class)."""
    labels = rasterize(geometry.layers)
    field = np.maximum(evidence_field(geometry, tile), 1.0)
    votes_of = np.zeros(CELLS_PER_TILE, np.int64)
    votes_of[cells] = np.where(ballot >= 2, weight, 0)
    class_of = np.zeros(CELLS_PER_TILE, np.int64)
    class_of[cells] = ballot
    out = []
    for cls in LAYERS[1:]:
        at = np.flatnonzero(labels == cls)
        if not len(at):
            continue
        own = (class_of[at] == cls) & (votes_of[at] > 0)
        k = np.zeros(len(at), np.int64)
        k[own] = np.round(np.log2(votes_of[at][own] / field[at][own]))
        out.append(k)
    k = np.concatenate(out) if out else np.zeros(0, np.int64)
    return np.clip(k, SHARE_MIN, SHARE_MAX).astype(np.int8)


# -- both sides: geometry -> labels, field ------------------------------------------------------


def rasterize(layers: list) -> np.ndarray:
    """Layers -> flat (512 * 512) uint8 labels: the footprint as road, paint over it in class
    order. Holes are cut, their boundary cells (traced on the cells themselves) kept."""
    labels = np.zeros((TILE_CELLS, TILE_CELLS), np.uint8)
    for cls, comps in zip(LAYERS, layers, strict=True):
        if not comps:
            continue
        mask = np.zeros((TILE_CELLS, TILE_CELLS), np.uint8)
        for rings in comps:
            cv2.fillPoly(mask, [rings[0].reshape(-1, 1, 2)], 1)
            for hole in rings[1:]:
                cv2.fillPoly(mask, [hole.reshape(-1, 1, 2)], 0)
                cv2.polylines(mask, [hole.reshape(-1, 1, 2)], True, 1)
        labels[mask > 0] = int(cls)
    return labels.reshape(-1)


def frame_poses(geometry: Geometry) -> np.ndarray:
    """(n_frames, 3) poses (metres, radians) interpolated between the key poses."""
    idx = _key_index(geometry.n_frames, geometry.key_every)
    keys = geometry.keys.astype(np.float64) * (POSE_UNIT_M, POSE_UNIT_M, YAW_UNIT_RAD)
    frames = np.arange(geometry.n_frames)
    return np.stack([np.interp(frames, idx, keys[:, k]) for k in range(3)], axis=1)


def density_image(roi: Roi) -> np.ndarray:
    """Camera pixels per 0.1 m cell of the ROI in one frame, float32 (lateral, forward): a
    pinhole camera over the ground plane, (x - camera x)^-3 inside its horizontal field of
    view, normalised to the ROI's pixels per frame."""
    n_x, n_y = max(roi.length_dm, 1), max(roi.width_dm, 1)
    ahead = np.maximum((roi.x_min_dm - roi.camera_x_dm + np.arange(n_x) + 0.5) * CELL_M, CELL_M)
    y_m = (np.arange(n_y) + 0.5) * CELL_M - n_y * CELL_M / 2.0
    seen = np.abs(y_m)[:, None] <= roi.fov_slope_milli / 1000.0 * ahead[None, :]
    image = np.where(seen, ahead[None, :] ** -DENSITY_EXPONENT, 0.0)
    total = image.sum()
    return (image * (roi.pixels_per_frame / total if total > 0 else 0.0)).astype(np.float32)


def evidence_field(geometry: Geometry, tile) -> np.ndarray:
    """Flat (512 * 512) float32: camera pixels expected per cell of the tile over the patch's
    frames (density_image swept along frame_poses; a frame whose ROI misses the tile adds
    nothing)."""
    field = np.zeros((TILE_CELLS, TILE_CELLS), np.float32)
    if not geometry.n_frames or geometry.roi.pixels_per_frame <= 0:
        return field.reshape(-1)
    image = density_image(geometry.roi)
    h, w = image.shape
    affine = _image_to_tile(geometry.roi, frame_poses(geometry), tile)  # (F, 2, 3)
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64) - 0.5
    dst = corners @ affine[:, :, :2].transpose(0, 2, 1) + affine[:, None, :, 2]  # (F, 4, 2)
    lo = np.maximum(np.floor(dst.min(axis=1)).astype(int) - 1, 0)
    hi = np.minimum(np.ceil(dst.max(axis=1)).astype(int) + 2, TILE_CELLS)
    for k in np.flatnonzero(np.all(lo < hi, axis=1)):
        (c0, r0), (c1, r1) = lo[k], hi[k]
        m = affine[k].copy()
        m[:, 2] -= (c0, r0)
        field[r0:r1, c0:c1] += cv2.warpAffine(image, m, (int(c1 - c0), int(r1 - r0)),
                                              flags=cv2.INTER_LINEAR,
                                              borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return field.reshape(-1)


def _image_to_tile(roi: Roi, poses_xyyaw: np.ndarray, tile) -> np.ndarray:
    """(F, 2, 3) affines: density_image pixel (i forward, j lateral; centres at integers) ->
    tile cell (col, row; centres at integers), one per frame pose (world frame)."""
    x0, y0 = tile_origin_m(tile)
    c, s = np.cos(poses_xyyaw[:, 2]), np.sin(poses_xyyaw[:, 2])
    # vehicle frame of pixel (i, j): x = (x_min_dm + i + 0.5) / 10, y = (j + 0.5) / 10 - w / 2
    vx0 = (roi.x_min_dm + 0.5) * CELL_M
    vy0 = 0.5 * CELL_M - roi.width_dm * CELL_M / 2.0
    col = (poses_xyyaw[:, 0] - x0 + c * vx0 - s * vy0) / CELL_M - 0.5
    row = (poses_xyyaw[:, 1] - y0 + s * vx0 + c * vy0) / CELL_M - 0.5
    return np.stack([np.stack([c, -s, col], axis=1), np.stack([s, c, row], axis=1)], axis=1)


# -- shard side: geometry -> cells + votes -----------------------------------------------------


def expand(geometry: Geometry, tile) -> tuple[np.ndarray, np.ndarray]:
    """Cells (uint32, sorted) and votes (uint16 [n, NUM_CLASSES], one class per cell): road
    cells max(2, round(field)) for road, paint cells max(1, round(field * 2^k)) for their
    class. Raises CodecError when the shares do not match the decoded paint cells."""
    labels = rasterize(geometry.layers)
    cells = np.flatnonzero(labels)
    paint = np.concatenate([np.flatnonzero(labels == cls) for cls in LAYERS[1:]])
    if len(geometry.strong_at) and int(geometry.strong_at[-1]) >= len(paint):
        raise CodecError(f"{FORM}: a share for paint cell {int(geometry.strong_at[-1])} of "
                         f"{len(paint)}")
    k = np.zeros(len(paint))
    k[geometry.strong_at] = geometry.strong_k
    field = np.maximum(evidence_field(geometry, tile).astype(np.float64), 1.0)
    weight = np.maximum(np.round(field), ROAD_MIN_VOTES)
    weight[paint] = np.maximum(np.round(field[paint] * np.exp2(k)), 1)
    votes = np.zeros((len(cells), NUM_CLASSES), np.uint16)
    votes[np.arange(len(cells)), labels[cells]] = np.minimum(weight[cells], 65535)
    return cells.astype(np.uint32), votes


# -- payload bytes -------------------------------------------------------------------------------


def pack(geometry: Geometry) -> bytes:
    """Geometry -> payload bytes (module docstring; uncompressed: the batch compresses)."""
    r, keys = geometry.roi, geometry.keys
    head = [r.x_min_dm, r.length_dm, r.width_dm, r.camera_x_dm, r.fov_slope_milli,
            r.pixels_per_frame, geometry.n_frames,
            geometry.key_every, len(keys)]
    structure, rings = [], []
    for comps in geometry.layers:
        structure.append(len(comps))
        for comp in comps:
            structure.append(len(comp))
            structure += [len(ring) for ring in comp]
            rings += comp
    points = np.concatenate(rings) if rings else np.zeros((0, 2), np.int64)
    deltas = np.diff(points.astype(np.int64), axis=0, prepend=0).reshape(-1)
    key_deltas = np.diff(keys, n=2, axis=0, prepend=np.zeros((2, 3), np.int64)).reshape(-1)
    gaps = np.diff(geometry.strong_at, prepend=-1) - 1
    return b"".join([
        varint_encode(np.asarray(head, np.uint64)),
        varint_encode(_zigzag(key_deltas)),
        varint_encode(np.asarray(structure, np.uint64)),
        varint_encode(_zigzag(deltas)),
        varint_encode(np.asarray([len(gaps)], np.uint64)),
        varint_encode(gaps.astype(np.uint64)),
        varint_encode(_zigzag(geometry.strong_k.astype(np.int64))),
    ])


def unpack(data: bytes, what: str = FORM) -> Geometry:
    """Payload bytes -> Geometry, strictly: CodecError naming what was expected."""
    values = _Reader(data, what)
    x_min, length, width, cam_x, slope, ppf, n_frames, key_every, n_keys = values.take(9)
    if not (0 < length <= 1000 and 0 < width <= 1000 and x_min <= 1000 and cam_x <= 1000
            and slope <= 100_000 and ppf < 1 << 32):
        raise CodecError(f"{what}: ROI out of range (length, width in (0, 100] m)")
    if n_frames > MAX_FRAMES or key_every < 1 or n_keys != len(_key_index(n_frames, key_every)):
        raise CodecError(f"{what}: expected n_keys = key poses of {n_frames} frames every "
                         f"{key_every}")
    steps = np.cumsum(_unzigzag(values.take(3 * n_keys)).reshape(-1, 3), axis=0)
    keys = np.cumsum(steps, axis=0) if np.abs(steps).max(initial=0) < MAX_POSE_UNITS else steps
    if keys.size and int(np.abs(keys).max()) >= MAX_POSE_UNITS:
        raise CodecError(f"{what}: key pose out of range")
    layers, n_points = _structure(values, what)
    points = np.cumsum(_unzigzag(values.take(2 * n_points)).reshape(-1, 2), axis=0)
    if points.size and (int(points.min()) < 0 or int(points.max()) >= TILE_CELLS):
        raise CodecError(f"{what}: polygon point outside the tile [0, {TILE_CELLS})")
    layers = _fill_rings(layers, points.astype(np.int32))
    (n_strong,) = values.take(1)
    if n_strong > CELLS_PER_TILE:
        raise CodecError(f"{what}: more shares than cells in a tile")
    strong_at = np.cumsum(values.take(n_strong) + 1) - 1
    strong_k = _unzigzag(values.take(n_strong))
    if strong_k.size and (int(strong_k.min()) < SHARE_MIN or int(strong_k.max()) > SHARE_MAX
                          or int(np.abs(strong_k).min()) < SHARE_EXCEPTION):
        raise CodecError(f"{what}: shares must be octaves in [{SHARE_MIN}, {SHARE_MAX}], at "
                         f"least {SHARE_EXCEPTION} off 0")
    values.end()
    return Geometry(roi=Roi(x_min, length, width, cam_x, slope, ppf), n_frames=n_frames,
                    key_every=key_every, keys=keys, layers=layers, strong_at=strong_at,
                    strong_k=strong_k.astype(np.int8))


def _structure(values: "_Reader", what: str) -> tuple[list, int]:
    """Per layer: [component: [ring sizes]], and the total of points."""
    layers, total, n_rings = [], 0, 0
    for _ in LAYERS:
        (n_comps,) = values.take(1)
        comps = []
        for _ in range(min(n_comps, MAX_RINGS + 1)):
            (n,) = values.take(1)
            sizes = [int(s) for s in values.take(n)] if n <= MAX_RINGS else None
            if sizes is None or n < 1 or any(s < 1 for s in sizes):
                raise CodecError(f"{what}: a component needs rings of at least one point")
            n_rings += n
            total += sum(sizes)
            comps.append(sizes)
        if n_comps > MAX_RINGS or n_rings > MAX_RINGS or total > MAX_POINTS:
            raise CodecError(f"{what}: more than {MAX_RINGS} rings or {MAX_POINTS} points")
        layers.append(comps)
    return layers, total


def _fill_rings(layers: list, points: np.ndarray) -> list:
    out, at = [], 0
    for comps in layers:
        filled = []
        for sizes in comps:
            rings = []
            for n in sizes:
                rings.append(points[at:at + n])
                at += n
            filled.append(rings)
        out.append(filled)
    return out


class _Reader:
    """The payload's varints, taken in order; running short or left over is a CodecError."""

    def __init__(self, data: bytes, what: str):
        self.what = what
        try:
            self.values = varint_decode(data)
        except CodecError as exc:
            raise CodecError(f"{what}: {exc}") from exc
        self.at = 0

    def take(self, n: int) -> np.ndarray:
        n = int(n)
        if n < 0 or self.at + n > len(self.values):
            raise CodecError(f"{self.what}: payload ends early (expected {n} more values)")
        out = self.values[self.at:self.at + n].astype(np.int64)
        self.at += n
        return out

    def end(self) -> None:
        if self.at != len(self.values):
            raise CodecError(f"{self.what}: {len(self.values) - self.at} values after the end")


def _zigzag(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.int64)
    return ((v << 1) ^ (v >> 63)).astype(np.uint64)


def _unzigzag(u: np.ndarray) -> np.ndarray:
    u = np.asarray(u, dtype=np.int64)
    return (u >> 1) ^ -(u & 1)


# -- messages ------------------------------------------------------------------------------------


def expand_patch(patch: SparsePatch) -> GridPatch:
    """The GridPatch a SparsePatch stands for (cells and votes by `expand`), carrying the
    payload (`sparse`) so a store keeps the patch as it came. CodecError on a bad payload."""
    what = f"SparsePatch {patch.patch_id!r}"
    if patch.form != FORM:
        raise CodecError(f"{what}: unknown form {patch.form!r}, expected {FORM}")
    cells, votes = expand(unpack(patch.data, what), patch.tile)
    return GridPatch(patch_id=patch.patch_id, vehicle=patch.vehicle, tile=tuple(patch.tile),
                     cells=cells, votes=votes, t_first_ns=patch.t_first_ns,
                     t_last_ns=patch.t_last_ns, traversal=patch.traversal,
                     sparse=bytes(patch.data))
