"""Camera renderer: the world's ground plane seen through a (vibrating) front camera.

Per camera a ray table is computed once (undistorted normalized coordinates of every pixel
centre, u + 0.5, v + 0.5 as in common.camera's IPM). Per frame: rotate the rays by the frame's
camera, intersect them with z = 0 (paper eq. 1 in reverse), move the ground points into the world
and cv2.remap the world-frame label window (0.1 m tiles) and world-anchored textures into the image.
Pixels above the horizon or beyond the window get label 0. The RGB image adds asphalt texture,
worn and faded paint, shadows, lighting, haze, sky and roadside, other vehicles (label 0), blur and
noise, all drawn from a seeded Appearance so that a drive renders the same every time."""

import math
from dataclasses import dataclass

import cv2
import numpy as np

from common.camera import CameraModel, undistort_normalized
from common.classes import Cls
from common.grid import TILE_CELLS
from common.world import World
from services.sim.raster import TileCache

SKY_BINS = 3600
LABEL_CELL_M = 0.05  # label window resolution: finer than the map, so edges are not stair-cased


class GroundRays:
    """Per-pixel rays of one camera model (intrinsics + distortion), built once."""

    def __init__(self, camera: CameraModel):
        self.width, self.height = camera.width, camera.height
        v, u = np.mgrid[0 : camera.height, 0 : camera.width]
        uv = np.stack([u.ravel() + 0.5, v.ravel() + 0.5], axis=1).astype(np.float64)
        norm = undistort_normalized(uv, camera.K, camera.dist)
        self.xc = norm[:, 0].reshape(camera.height, camera.width).astype(np.float32)
        self.yc = norm[:, 1].reshape(camera.height, camera.width).astype(np.float32)
        # per image row, the ranges of xc and yc: bound the rows a rotation turns downwards
        self._row_ranges = [f(c, axis=1).astype(np.float64) for c in (self.xc, self.yc)
                            for f in (np.min, np.max)]

    def ground(self, T_vehicle_camera: np.ndarray, max_range_m: float = 250.0):
        """(rows, gx, gy, dist, ok, R): the image rows that see the ground (a slice: every
        ground pixel is in them), their ground points (gx, gy) in the vehicle frame and
        distances, the ground mask (H, W) and the camera's rotation (float32). Only the rows
        that can look down (about the lower half) are intersected with the ground."""
        R, t = T_vehicle_camera[:3, :3].astype(np.float32), T_vehicle_camera[:3, 3]
        rows = self._rows_down(R)
        rx, ry, rz = self.rays(R, rows)
        down = rz < -1e-4
        lam = np.float32(-t[2]) / np.where(down, rz, np.float32(-1.0))
        dist = np.multiply(rx, rx)
        dist += np.square(ry)
        np.sqrt(dist, out=dist)
        dist *= lam  # lam * horiz
        ok_rows = down & (dist < max_range_m)
        np.copyto(lam, np.float32(0.0), where=~ok_rows)
        np.copyto(dist, np.float32(max_range_m), where=~ok_rows)
        gx = lam * rx
        gx += np.float32(t[0])
        gy = lam * ry
        gy += np.float32(t[1])
        ok = np.zeros((self.height, self.width), bool)
        ok[rows] = ok_rows
        return rows, gx, gy, dist, ok, R

    def rays(self, R: np.ndarray, rows: slice) -> tuple:
        """(rx, ry, rz) in the vehicle frame of the pixels of image `rows` (float32)."""
        xc, yc = self.xc[rows], self.yc[rows]
        tmp = np.empty_like(xc)  # one scratch plane: fresh temporaries cost more
        return tuple(_affine(xc, yc, R[i], tmp) for i in range(3))

    def _rows_down(self, R: np.ndarray) -> slice:
        """The rows from the first to the last with a ray that may point down (rz < -1e-4):
        a row's rz is at least the sum of its terms' minima over its ranges of xc and yc
        (float64; the 1e-3 slack covers float32 rounding many times over)."""
        x_lo, x_hi, y_lo, y_hi = self._row_ranges
        r20, r21, r22 = (float(r) for r in R[2])
        rz_lo = np.minimum(r20 * x_lo, r20 * x_hi) + np.minimum(r21 * y_lo, r21 * y_hi) + r22
        return _row_span(rz_lo < -1e-4 + 1e-3)


def _affine(xc: np.ndarray, yc: np.ndarray, r, tmp: np.ndarray) -> np.ndarray:
    """r[0] xc + r[1] yc + r[2] (float32, in this order of operations; `tmp`: scratch)."""
    out = np.multiply(xc, r[0])
    out += np.multiply(yc, r[1], out=tmp)
    out += r[2]
    return out


def _row_span(rows_down: np.ndarray) -> slice:
    """The rows from the first to the last True of `rows_down` (per row; the last row if none:
    the band is never empty)."""
    rows = np.flatnonzero(rows_down)
    if rows.size == 0:
        return slice(rows_down.shape[0] - 1, rows_down.shape[0])
    return slice(int(rows[0]), int(rows[-1]) + 1)


@dataclass
class FrameGeometry:
    rows: slice  # the image rows that see the ground; wx, wy and dist are theirs
    wx: np.ndarray  # world x of each pixel's ground point (rows, W) float32
    wy: np.ndarray
    dist: np.ndarray  # metres from the camera along the ground
    ground: np.ndarray  # bool (H, W): the ray hits the ground inside the range
    R_vehicle_camera: np.ndarray  # the camera's rotation (float32): GroundRays.rays

    @property
    def ground_rows(self) -> np.ndarray:
        """The ground mask of `rows`."""
        return self.ground[self.rows]


class LabelRenderer:
    """True label images: the world's labels seen through the camera (0 above the horizon)."""

    def __init__(
        self,
        world: World,
        camera: CameraModel,
        cell_m: float = LABEL_CELL_M,
        range_m: float = 100.0,
    ):
        self.rays = GroundRays(camera)
        radius = int(np.ceil(range_m / (TILE_CELLS * cell_m)))
        self.tiles = TileCache(world, radius_tiles=radius, cell_m=cell_m)
        self.cell_m = cell_m

    def geometry(self, pose, T_vehicle_camera) -> FrameGeometry:
        rows, gx, gy, dist, ok, R = self.rays.ground(T_vehicle_camera)
        c, s = np.float32(math.cos(pose[2])), np.float32(math.sin(pose[2]))
        wx = c * gx
        wx += np.float32(pose[0])
        wx -= s * gy
        wy = s * gx
        wy += np.float32(pose[1])
        wy += c * gy
        return FrameGeometry(rows, wx, wy, dist, ok, R)

    def labels(self, pose, T_vehicle_camera, geo: FrameGeometry | None = None):
        """(labels (H, W) uint8, geometry, (window, mx, my)) for a vehicle pose (x, y, yaw):
        mx, my (H, W) are the pixels' label window coordinates (-10 off the ground)."""
        geo = geo or self.geometry(pose, T_vehicle_camera)
        window, x0, y0 = self.tiles.window(pose[0], pose[1])
        inv = np.float32(1.0 / self.cell_m)
        off_ground = ~geo.ground_rows
        mx, my = (np.full(geo.ground.shape, -10.0, np.float32) for _ in range(2))
        for m, w, origin in ((mx, geo.wx, x0), (my, geo.wy, y0)):
            band = m[geo.rows]
            np.subtract(w, np.float32(origin), out=band)
            band *= inv
            band -= 0.5
            np.copyto(band, np.float32(-10.0), where=off_ground)
        lab = np.zeros(geo.ground.shape, np.uint8)
        cv2.remap(window, mx[geo.rows], my[geo.rows], cv2.INTER_NEAREST, dst=lab[geo.rows],
                  borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return lab, geo, (window, mx, my)


# -- appearance --------------------------------------------------------------------------------


def _noise_texture(rng, size: int, blur_px: float, lo: float, hi: float) -> np.ndarray:
    """Tileable smooth noise in [lo, hi] (float32), wrapped so remap can use BORDER_WRAP."""
    n = rng.normal(size=(size, size)).astype(np.float32)
    if blur_px > 0:
        n = cv2.GaussianBlur(np.tile(n, (3, 3)), (0, 0), blur_px)[size : 2 * size, size : 2 * size]
    n = (n - n.min()) / max(float(n.max() - n.min()), 1e-6)
    return (lo + (hi - lo) * n).astype(np.float32)


def _shadow_texture(rng, size: int, res_m: float, density: float) -> np.ndarray:
    """Tree and building shadows: blurred random ellipses and long bands (1 = full shadow)."""
    img = np.zeros((size, size), np.float32)
    for _ in range(int(density * 60)):
        c = (int(rng.integers(size)), int(rng.integers(size)))
        axes = (int(rng.uniform(1.0, 5.0) / res_m), int(rng.uniform(1.0, 4.0) / res_m))
        cv2.ellipse(img, c, axes, float(rng.uniform(0, 180)), 0, 360, 1.0, -1)
    for _ in range(int(density * 6)):
        x, y = int(rng.integers(size)), int(rng.integers(size))
        w, h = int(rng.uniform(8, 40) / res_m), int(rng.uniform(4, 20) / res_m)
        cv2.rectangle(img, (x, y), (x + w, y + h), 1.0, -1)
    img = cv2.GaussianBlur(np.tile(img, (3, 3)), (0, 0), 0.4 / res_m)[
        size : 2 * size, size : 2 * size
    ]
    return np.clip(img, 0.0, 1.0)


@dataclass
class Vehicle:
    """Another car: a box on the ground, pose in the world or relative to the ego vehicle."""

    x: float
    y: float
    yaw: float
    length: float
    width: float
    height: float
    color: tuple
    relative: bool = False  # pose in the ego vehicle frame (a lead car)


class Appearance:
    """Everything random about how a drive looks, drawn once from a seed."""

    def __init__(self, rng: np.random.Generator):
        # the draws' order is the looks' seed contract: a drive's seed gives the same looks
        self._surfaces(rng)
        self._light(rng)
        self._textures(rng)
        self._skyline_colours(rng)
        self._tint()
        self._curbs(rng)

    def _surfaces(self, rng) -> None:
        """Asphalt, off-road ground and paint, and how worn the paint is."""
        g = rng.uniform(75, 125)
        tint = rng.uniform(-6, 6, 3)
        self.asphalt_rgb = np.array([g, g, g + rng.uniform(0, 6)]) + tint
        grounds = [
            np.array([70, 105, 55]),
            np.array([150, 148, 140]),
            np.array([120, 100, 75]),
            np.array([95, 95, 90]),
            np.array([60, 85, 45]),
        ]
        pick = rng.choice(len(grounds), 2, replace=False)
        self.offroad_rgb = grounds[pick[0]] * rng.uniform(0.8, 1.15)
        self.offroad2_rgb = grounds[pick[1]] * rng.uniform(0.8, 1.15)
        self.paint_rgb = (
            np.array([235, 235, 228]) if rng.random() < 0.8 else np.array([230, 222, 175])
        ) * rng.uniform(0.85, 1.0)  # aged: yellowish
        self.fade = rng.uniform(0.45, 1.0)  # how much of the paint is left
        self.wear_level = rng.uniform(0.0, 0.3)  # worn fraction of paint

    def _light(self, rng) -> None:
        """Exposure, colour cast, shadows, sky, haze, blur and sensor noise."""
        self.gain = rng.uniform(0.65, 1.3)
        self.gain_wobble = rng.uniform(0.0, 0.15)  # clouds
        self.colour_cast = rng.uniform(0.92, 1.08, 3)
        self.shadow_strength = rng.uniform(0.0, 0.6) if rng.random() < 0.8 else 0.0
        self.sky_top = (
            np.array([70, 120, 200]) * rng.uniform(0.7, 1.2)
            if rng.random() < 0.6
            else np.array([170, 175, 180]) * rng.uniform(0.8, 1.1)
        )
        self.haze_rgb = np.clip(self.sky_top * 0.5 + 110, 0, 255)
        self.fog_m = rng.uniform(60.0, 250.0)
        self.blur_prob = rng.uniform(0.0, 0.4)
        self.noise_sigma = rng.uniform(1.5, 7.0)

    def _textures(self, rng) -> None:
        """World-anchored textures, the curb's colour and the skyline's shape."""
        # two-channel world-anchored textures: (grain, paint wear) at 4 cm, (blotches, roadside
        # mix) at 0.5 m
        self.fine = cv2.merge(
            [_noise_texture(rng, 256, 0.7, 0.82, 1.18), _noise_texture(rng, 256, 1.5, 0.0, 1.0)]
        )
        self.coarse = cv2.merge(
            [_noise_texture(rng, 256, 6.0, 0.8, 1.2), _noise_texture(rng, 256, 12.0, 0.0, 1.0)]
        )
        self.curb_rgb = np.array([185, 183, 178]) * rng.uniform(0.8, 1.1)
        self.curb = rng.random() < 0.7
        self.shadow = _shadow_texture(rng, 512, 0.25, rng.uniform(0.3, 1.5))
        self.skyline_elev = self._skyline(rng)

    def _skyline_colours(self, rng) -> None:
        palette = np.array(
            [
                [120, 118, 115],
                [150, 140, 125],
                [140, 95, 80],
                [95, 100, 105],
                [175, 170, 160],
                [60, 80, 55],
                [45, 65, 45],
                [110, 105, 95],
            ],
            float,
        )
        self.skyline_rgb = palette[rng.integers(len(palette), size=64)] * rng.uniform(
            0.75, 1.2, (64, 1)
        )

    def _tint(self) -> None:
        """The colour cast applied to every surface colour drawn so far."""
        for name in (
            "asphalt_rgb",
            "offroad_rgb",
            "offroad2_rgb",
            "paint_rgb",
            "sky_top",
            "haze_rgb",
            "skyline_rgb",
            "curb_rgb",
        ):
            setattr(self, name, (getattr(self, name) * self.colour_cast).astype(np.float32))

    def _curbs(self, rng) -> None:
        # raised curbs (drawn last so that the draws above keep their values): a curb stone
        # 0.1-0.2 m wide and 8-16 cm high along every road edge, its vertical face usually in
        # shade (sometimes sunlit), often a paved sidewalk behind it at the curb's height
        self.curb_w_m = rng.uniform(0.1, 0.2)
        self.curb_h_m = rng.uniform(0.08, 0.16)
        self.curb_face = rng.uniform(0.35, 0.75) if rng.random() < 0.8 else rng.uniform(1.0, 1.2)
        self.sidewalk_m = rng.uniform(1.0, 3.0) if rng.random() < 0.6 else 0.0
        self.sidewalk_rgb = (
            np.array([165, 160, 150]) * rng.uniform(0.65, 1.1) * self.colour_cast
        ).astype(np.float32)

    @staticmethod
    def _skyline(rng) -> np.ndarray:
        """Elevation (rad) of buildings/trees over azimuth bins of the world frame."""
        elev = np.zeros(SKY_BINS, np.float32)
        i = 0
        while i < SKY_BINS:
            w = int(rng.integers(20, 160))
            kind = rng.random()
            h = math.radians(rng.uniform(1.0, 14.0)) if kind < 0.7 else 0.0
            if kind > 0.85:  # trees: rounded
                h = math.radians(rng.uniform(3, 10)) * np.sin(np.linspace(0, np.pi, w)) ** 0.5
            elev[i : i + w] = h if np.isscalar(h) else h[: len(elev[i : i + w])]
            i += w
        return elev


class FrameRenderer:
    """RGB and label images of a drive: geometry from LabelRenderer, looks from Appearance."""

    def __init__(self, world: World, camera: CameraModel, seed: int = 0, jumps: bool = False):
        """`jumps`: the frames' poses are unrelated (training frames at random poses), so
        each frame computes the surface masks of only its own box of the label window (a
        third to a half of the time a frame takes at a random pose); else (a drive) those of
        the whole window, kept while the frames stay in it. The frames are the same bytes."""
        self.jumps = jumps
        self.rng = np.random.default_rng(seed)
        self.look = Appearance(self.rng)
        self.labeler = LabelRenderer(world, camera)
        self.camera = camera
        self.h, self.w = camera.height, camera.width
        yy, xx = np.mgrid[0 : self.h, 0 : self.w].astype(np.float32)
        r2 = ((xx - self.w / 2) / self.w) ** 2 + ((yy - self.h / 2) / self.h) ** 2
        self.vignette = cv2.merge([(1.0 - 0.35 * r2).astype(np.float32)] * 3)
        self._surface_cache = None  # (window, origin, its masks): kept while frames stay in it
        self._spare_masks = None  # the masks before those: the next window's buffer
        self._skyline = None  # (gain, _skyline_bins()): the skyline's colours at that gain
        gamma = self.rng.uniform(0.8, 1.25)
        self.tone = np.clip(255.0 * (np.arange(256) / 255.0) ** gamma, 0, 255).astype(np.uint8)
        self.noise = [
            self.rng.normal(0, self.look.noise_sigma, (self.h, self.w, 3)).astype(np.float32)
            for _ in range(4)
        ]

    def _surface(self, window, mx, my, ground, camera_xy, origin_m=None):
        """(surface, x0, y0): the (road, paint, curb, sidewalk) masks (`_surface_masks`) of the
        label window, or with `jumps` of the box of it from cell (x0, y0) on that this frame's
        remaps read: the ground points (mx, my) and the points between them and the camera's
        ground point (`camera_xy`, window coordinates: `_raised`), which lie in the same box.
        A frame at a random pose sees about a quarter of its window. The box's masks are the
        whole window's where the frame reads them: the box has a margin wider than the blur
        and the rings reach, and starts on the rings' 4-cell grid. `origin_m`: the window's
        world origin (x0, y0), to carry the last window's masks over (`_window_masks`)."""
        if not self.jumps:
            if self._surface_cache is None or self._surface_cache[0] is not window:
                masks = self._window_masks(window, origin_m)
                self._surface_cache = (window, origin_m, masks)
            return self._surface_cache[2], 0, 0
        box = _read_box(mx[ground], my[ground], camera_xy, self._surface_margin_cells(),
                        window.shape)
        if box is None:  # every read is off the window
            return _NO_SURFACE, 0, 0
        (x0, x1), (y0, y1) = box
        return self._surface_masks(window[y0:y1, x0:x1]), x0, y0

    def _window_masks(self, window, origin_m):
        """_surface_masks of a drive's next label window, which overlaps the last one: the
        last window's masks where the two agree (the overlap, but for a margin along the
        sides it does not share with both windows: there either window's edge is near), the
        masks of boxes of the new window (`_box_masks`) in the strips around that. A window
        moves by whole tiles, on the rings' 4-cell grid. Same bytes as the whole window's."""
        last = self._surface_cache
        if origin_m is None or last is None or last[1] is None or last[0].shape != window.shape:
            return self._surface_masks(window)
        shift = [round((o - p) / self.labeler.cell_m) for o, p in zip(origin_m, last[1],
                                                                      strict=True)]
        margin = self._surface_margin_cells()
        keep = []  # per axis (rows, cols): the new window's span the last masks hold
        for d, n in ((shift[1], window.shape[0]), (shift[0], window.shape[1])):
            lo, hi = max(0, -d) + margin * (d != 0), min(n, n - d) - margin * (d != 0)
            if hi - lo < 4 or d % 4:
                return self._surface_masks(window)
            keep.append((lo, hi))
        (y0, y1), (x0, x1) = keep
        dx, dy = shift
        masks = self._spare_masks  # written over: filling fresh pages costs more than copying
        if masks is None or masks.shape[:2] != window.shape:
            masks = np.empty(window.shape + (4,), np.uint8)
        self._spare_masks = last[2]
        masks[y0:y1, x0:x1] = last[2][y0 + dy : y1 + dy, x0 + dx : x1 + dx]
        rows, cols = window.shape
        strips = (((0, y0), (0, cols)), ((y1, rows), (0, cols)),
                  ((y0, y1), (0, x0)), ((y0, y1), (x1, cols)))
        for (ya, yb), (xa, xb) in strips:
            if ya < yb and xa < xb:
                masks[ya:yb, xa:xb] = self._box_masks(window, (ya, yb), (xa, xb), margin)
        return masks

    def _box_masks(self, window, rows, cols, margin: int):
        """The whole window's _surface_masks of the cells rows x cols (spans), from a box of
        the window `margin` cells wider on the 4-cell grid (see _surface)."""
        box = []
        for (lo, hi), n in ((rows, window.shape[0]), (cols, window.shape[1])):
            box.append((max(lo - margin, 0) // 4 * 4, min(-(-(hi + margin) // 4) * 4, n)))
        (ya, yb), (xa, xb) = box
        masks = self._surface_masks(window[ya:yb, xa:xb])
        return masks[rows[0] - ya : rows[1] - ya, cols[0] - xa : cols[1] - xa]

    def _ring_cells(self) -> tuple:
        """(curb, sidewalk) band widths in label cells (the sidewalk's from the road, through
        the curb; None without a sidewalk)."""
        cell = self.labeler.cell_m
        walk = (self.look.curb_w_m + self.look.sidewalk_m) / cell if self.look.sidewalk_m else None
        return self.look.curb_w_m / cell, walk

    def _surface_margin_cells(self) -> int:
        """Cells around a box of the window whose masks a computation on the box alone gets
        wrong: the paint blur's 2 and the curb and sidewalk rings' reach."""
        reach = 2
        if self.look.curb:
            curb_cells, walk_cells = self._ring_cells()
            reach = max(reach, _ring_reach(curb_cells))
            if walk_cells is not None:
                reach = max(reach, _ring_reach(walk_cells, coarse=4))
        return reach + 8

    def _surface_masks(self, window):
        """(road, paint, curb, sidewalk) masks of a label window (or a box of it whose origin
        is on the 4-cell grid) as one 4-channel uint8 image, so that a single linear remap
        samples all four. Paint is softened to hide the cell steps; curb and sidewalk are
        bands at a distance from the road (label: none)."""
        road = cv2.compare(window, int(Cls.ROAD), cv2.CMP_GE)  # 255 / 0, 10x numpy's time
        paint = cv2.GaussianBlur(cv2.compare(window, int(Cls.LANE_LINE), cv2.CMP_GE), (0, 0), 0.6)
        if self.look.curb:
            curb_cells, walk_cells = self._ring_cells()
            curb = _ring(road, curb_cells)
            walk = (_ring(road, walk_cells, coarse=4) if walk_cells is not None
                    else np.zeros_like(road))
            walk = cv2.subtract(walk, curb)
        else:
            curb = walk = np.zeros_like(road)
        return cv2.merge([road, paint, curb, walk])

    def _camera_cell(self, pose, T_vehicle_camera) -> tuple:
        """The camera's ground point in the label window's coordinates, as mx, my (float32)."""
        _, x0, y0 = self.labeler.tiles.window(pose[0], pose[1])  # cached: the same window
        cam_x, cam_y = _camera_ground_point(pose, T_vehicle_camera)
        cell = self.labeler.cell_m
        return np.float32((cam_x - x0) / cell - 0.5), np.float32((cam_y - y0) / cell - 0.5)

    def _raised(self, T_vehicle_camera, geo, surface, camera_xy, mx, my):
        """Where the camera sees a raised curb (looks with curbs): everything off the road
        stands curb_h_m high. A ray meets that height at t = c + (g - c) (H - h) / H (c the
        camera's ground point `camera_xy`, g the ray's ground point, H the camera height): off
        the road at t, the ray ends on the curb top / sidewalk / verge there; on the road at t
        but off the road at g, it ends on the curb's vertical face. Returns (surface sampled at
        t, top mask, face mask) of the ground rows (mx, my: theirs), or None without curbs."""
        if not self.look.curb:
            return None
        height = float(T_vehicle_camera[2, 3])
        k = np.float32(max(height - self.look.curb_h_m, 0.05) / height)
        ground = geo.ground_rows
        tx, ty = (_toward(m, c, k, ground) for m, c in zip((mx, my), camera_xy, strict=True))
        surf_t = _remap_surface(surface, tx, ty)
        road_t = surf_t[:, :, 0] >= 128
        top = ground & ~road_t
        return surf_t, top, ground & road_t

    def _ground_labels(self, pose, T_vehicle_camera, rgb: bool = True):
        """(labels, geometry, (surface, mx, my), raised) of the ground: the road hidden behind
        a raised island gets label 0. mx, my and raised are of the ground rows (geo.rows).
        Without `rgb`, the surface masks are computed only for raised curbs (else None)."""
        lab, geo, (window, mx, my) = self.labeler.labels(pose, T_vehicle_camera)
        if not (rgb or self.look.curb):
            return lab, geo, (None, mx[geo.rows], my[geo.rows]), None
        camera_xy = self._camera_cell(pose, T_vehicle_camera)
        _, x0, y0 = self.labeler.tiles.window(pose[0], pose[1])  # cached: the same window
        surface = self._surface(window, mx, my, geo.ground, camera_xy, origin_m=(x0, y0))
        mx, my = mx[geo.rows], my[geo.rows]
        raised = self._raised(T_vehicle_camera, geo, surface, camera_xy, mx, my)
        if raised is not None:
            lab[geo.rows][raised[1]] = 0
        return lab, geo, (surface, mx, my), raised

    def labels(self, pose, T_vehicle_camera, vehicles=()) -> np.ndarray:
        lab, *_ = self._ground_labels(pose, T_vehicle_camera, rgb=False)
        for hull, _, _ in self._vehicle_items(pose, T_vehicle_camera, vehicles):
            cv2.fillPoly(lab, [hull], 0)
        return lab

    def render(self, pose, T_vehicle_camera, t_s: float, vehicles=(), curb_label=None):
        """(rgb uint8 (H, W, 3), labels uint8 (H, W)) of one frame. With `curb_label` (training
        only: an auxiliary class beyond ours), the pixels of raised curbs (vertical face and
        top band) get that label instead of 0 (none)."""
        lab, geo, (surface, mx, my), raised = self._ground_labels(pose, T_vehicle_camera)
        if curb_label is not None and raised is not None:
            surf_t, top, on_face = raised
            band = lab[geo.rows]
            band[(on_face & (band == 0)) | (top & (surf_t[:, :, 2] >= 128))] = curb_label
        rgb = self._ground(geo, surface, mx, my, t_s, raised)
        rgb = self._sky(rgb, geo, pose)
        rgb = self._vehicles(rgb, lab, pose, T_vehicle_camera, vehicles)
        return self._sensor(rgb), lab

    # -- layers --------------------------------------------------------------------------------
    # The ground layers work on the ground rows only, in place on float32 planes: (H, W)
    # temporaries cost more than the arithmetic. Each in-place sequence keeps its formula's
    # order of operations (a + b == b + a and a * b == b * a are exact, a regrouping is not):
    # the images are the same bytes as the formulas written out, which the model trained on.

    def _ground(self, geo, surface, mx, my, t_s, raised=None):
        """Asphalt / roadside with texture, raised curbs and sidewalks, worn paint, shadows,
        lighting and haze of the ground rows, as one (rows, W, 3) float32 image (`surface`:
        _surface's; mx, my: the rows' window coordinates)."""
        look = self.look
        # 1. how much of each pixel is road, paint, curb top, sidewalk and curb face
        cover = self._cover(surface, mx, my, raised)
        # 2. world-anchored textures: asphalt grain and blotches, paint wear, roadside mix
        textures = _TextureMaps(geo.wx, geo.wy)
        grain, wear = cv2.split(textures.remap(look.fine, 0.04))  # contiguous planes: numpy
        blotch, mix = cv2.split(textures.remap(look.coarse, 0.5))  # on a channel takes 5x
        tex = self._texture(geo.dist, grain, blotch)
        cover["paint"] *= self._paint_left(wear)
        _ramp(mix, 0.5, 4.0)  # patches of the second roadside
        # 3. light: shadows and exposure, haze with distance
        fog = geo.dist * np.float32(1.0 / look.fog_m)
        np.clip(fog, 0.0, 1.0, out=fog)
        np.power(fog, 1.5, out=fog)
        keep = self._shade(textures, t_s)
        keep *= np.subtract(1.0, fog)
        # 4. the colour planes: surfaces under texture and paint, in light, through haze
        a = tex
        a *= keep
        a *= np.subtract(1.0, cover["paint"])
        b = cover["paint"]
        b *= keep
        return self._colours(cover, mix, a, b, fog)

    def _cover(self, surface, mx, my, raised) -> dict:
        """Per-pixel weights (float32 planes) of the surfaces: road and paint at the ground
        point; with raised curbs (`raised`), the curb top, sidewalk and curb face, which hide
        the road and paint behind them (None without curbs)."""
        surf = _remap_surface(surface, mx, my)
        road, paint = _unit_channel(surf, 0), _unit_channel(surf, 1)
        curb = walk = face = None
        if raised is not None:
            surf_t, top, on_face = raised
            face = np.subtract(1.0, road)  # off the road at g, on it at t
            np.clip(face, 0.0, 1.0, out=face)
            face *= on_face
            topf = top.astype(np.float32)
            curb, walk = _unit_channel(surf_t, 2), _unit_channel(surf_t, 3)
            curb *= topf
            walk *= topf
            np.subtract(1.0, topf, out=topf)
            road *= topf  # hidden behind a raised island
            paint *= topf
        paint -= 0.27  # re-sharpen
        paint *= np.float32(1 / 0.45)
        np.clip(paint, 0.0, 1.0, out=paint)
        return {"road": road, "paint": paint, "curb": curb, "walk": walk, "face": face}

    def _colours(self, cover, mix, a, b, fog) -> np.ndarray:
        """(rows, W, 3): the surfaces' colours weighted by `cover` (roadside: its two colours
        by `mix`), times `a` (texture and light, without paint), plus paint times `b` and haze
        times `fog`."""
        look = self.look
        off = np.subtract(1.0, cover["road"])
        raised = [cover[k] for k in ("curb", "walk", "face") if cover[k] is not None]
        for m in raised:
            off -= m
        np.clip(off, 0.0, 1.0, out=off)
        planes, tmp = [], np.empty_like(off)
        for c in range(3):
            # per colour plane: (rows, W) x scalar ops are far cheaper than x (3,) broadcasts
            ground = np.multiply(mix, look.offroad2_rgb[c] - look.offroad_rgb[c])
            ground += look.offroad_rgb[c]
            ground *= off
            layers = [(cover["road"], look.asphalt_rgb[c])]
            if raised:  # without curbs their weights are 0: adding 0 changes nothing
                curb_face_rgb = look.curb_rgb[c] * np.float32(look.curb_face)
                layers += [(cover["curb"], look.curb_rgb[c]), (cover["face"], curb_face_rgb),
                           (cover["walk"], look.sidewalk_rgb[c])]
            for m, colour in layers:
                ground += np.multiply(m, colour, out=tmp)
            ground *= a
            ground += np.multiply(b, look.paint_rgb[c], out=tmp)
            ground += np.multiply(fog, look.haze_rgb[c], out=tmp)
            planes.append(ground)
        return cv2.merge(planes)

    def _texture(self, dist, grain, blotch):
        """Asphalt grain (fading out with distance) times large blotches."""
        near = dist * np.float32(1 / 40.0)
        np.subtract(1.0, near, out=near)
        np.clip(near, 0.0, 1.0, out=near)
        tex = np.subtract(grain, 1.0)
        tex *= near
        tex += 1.0
        tex *= blotch
        return tex

    def _paint_left(self, wear):
        """How much of the paint is left (in place on the `wear` texture)."""
        wear -= self.look.wear_level
        wear *= 4.0
        np.clip(wear, 0.0, 1.0, out=wear)
        wear *= np.float32(self.look.fade)
        return wear

    def _shade(self, textures, t_s):
        """Exposure (with clouds) times the world-anchored shadows."""
        look = self.look
        gain = np.float32(look.gain * (1.0 + look.gain_wobble * math.sin(0.07 * t_s)))
        shade = textures.remap(look.shadow, 0.25)
        shade *= look.shadow_strength
        np.subtract(1.0, shade, out=shade)
        shade *= gain
        return shade

    def _sky(self, ground_rgb, geo, pose):
        """Sky gradient and a world-fixed skyline (buildings, trees) where no ground is seen,
        the ground rows' `ground_rgb` where it is; returns the (H, W, 3) float32 image. The sky
        is drawn at a quarter of the resolution and scaled up; only the quarter rows that the
        image rows with sky read are drawn (the rest stay 0, under the ground)."""
        look = self.look
        rows = self._sky_rows(geo.ground)
        small = np.zeros((self.h // 4, self.w // 4, 3), np.float32)
        full = slice(0, 4 * rows if rows < self.h // 4 else self.h)
        rays = self.labeler.rays.rays(geo.R_vehicle_camera, full)
        rx, ry, rz = (cv2.resize(r, (self.w // 4, rows), interpolation=cv2.INTER_AREA)
                      for r in rays)
        elev = np.arctan2(rz, np.sqrt(rx * rx + ry * ry))
        az = (np.arctan2(ry, rx) + pose[2]) % (2 * np.pi)
        b = (az * (SKY_BINS / (2 * np.pi))).astype(np.int32) % SKY_BINS
        t = np.clip(elev / 0.5, 0.0, 1.0)
        building = (elev < look.skyline_elev[b]) & (elev > -0.03)
        if self._skyline is None or self._skyline[0] != look.gain:
            self._skyline = (look.gain, self._skyline_bins())
        lit, lit_rgb, unlit_rgb = self._skyline[1]
        windows = lit[b] & ((elev * 150.0) % 3.0 < 1.4)
        for c in range(3):  # per plane: (rows, W / 4, 3) broadcasts take 5x the time
            sky = look.haze_rgb[c] + (look.sky_top[c] - look.haze_rgb[c]) * t
            bcol = np.where(windows, lit_rgb[c][b], unlit_rgb[c][b])
            small[:rows, :, c] = np.where(building, bcol, sky)
        rgb = self._upscale_sky(small, rows)
        cv2.copyTo(ground_rgb, geo.ground_rows.view(np.uint8), rgb[geo.rows])
        return rgb

    def _upscale_sky(self, small, rows: int) -> np.ndarray:
        """The (H, W, 3) image of the quarter-resolution sky, the image rows that read only its
        first `rows` rows scaled up from those alone (a linear upscale by 4 from fewer rows
        reads the same rows with the same weights; the rows below are ground)."""
        if 4 * rows + 8 > self.h or self.h % 4 or self.w % 4:
            return cv2.resize(small, (self.w, self.h), interpolation=cv2.INTER_LINEAR)
        rgb = np.empty((self.h, self.w, 3), np.float32)
        cv2.resize(small[: rows + 1], (self.w, 4 * (rows + 1)), dst=rgb[: 4 * (rows + 1)],
                   interpolation=cv2.INTER_LINEAR)
        return rgb

    def _skyline_bins(self):
        """Per azimuth bin of the skyline: whether its building has lit windows (the rows of
        them are per pixel), and its colour planes with and without them (float64)."""
        look = self.look
        bins = np.arange(SKY_BINS)
        lit = ((bins % 7) < 3) & (look.skyline_elev > 0.05)
        base = look.skyline_rgb[(bins // 37) % len(look.skyline_rgb)].astype(np.float64)
        return lit, (base * 0.6 * look.gain).T.copy(), (base * 1.0 * look.gain).T.copy()

    def _sky_rows(self, ground) -> int:
        """How many rows of the quarter-resolution sky the image rows with sky read: a linear
        upscale by 4 reads quarter rows floor((v + 0.5) / 4 - 0.5) and the one below."""
        sky = np.flatnonzero(~ground.all(axis=1))
        if self.h % 4:  # the quarter image is not a 4 x 4 block average of whole rows
            return self.h // 4
        if sky.size == 0:
            return 1
        return min(self.h // 4, int(sky[-1]) // 4 + 2)

    def _vehicle_items(self, pose, T_vehicle_camera, vehicles):
        """(image hull int32, vehicle, corner pixels) of other vehicles, far to near; vehicles
        partly behind the camera are skipped."""
        cam = CameraModel(
            self.camera.width, self.camera.height, self.camera.K, self.camera.dist, T_vehicle_camera
        )
        out = []
        for v in sorted(vehicles, key=lambda v: -_ego_dist(v, pose)):
            corners = _box_corners(v, pose)
            uv, front = cam.project_vehicle_points(corners)
            if not front.all() or np.abs(uv).max() > 1e5:
                continue
            hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2)
            out.append((np.round(hull).astype(np.int32), v, uv))
        return out

    def _vehicles(self, rgb, lab, pose, T_vehicle_camera, vehicles):
        """Other vehicles as boxes: the two faces nearest the camera with glass and bumper bands;
        their pixels get label 0."""
        cam_pos = T_vehicle_camera[:3, 3]
        for hull, v, uv in self._vehicle_items(pose, T_vehicle_camera, vehicles):
            body = np.array(v.color, np.float32) * self.look.gain
            cv2.fillPoly(rgb, [hull], (body * 0.8).tolist())
            corners = _box_corners(v, pose)
            faces = [(i, (i + 1) % 4) for i in range(4)]
            dist = [np.linalg.norm((corners[i] + corners[j]) / 2 - cam_pos) for i, j in faces]
            for k in np.argsort(dist)[1::-1]:  # the two nearest faces, farther first
                i, j = faces[k]
                shade = 0.75 + 0.25 * k % 2
                for lo, hi, col in (
                    (0.0, 1.0, body * shade),
                    (0.62, 0.95, body * 0.2 + 25),
                    (0.05, 0.25, body * 0.25 + 10),
                ):
                    quad = _band(uv, i, j, lo, hi)
                    cv2.fillPoly(rgb, [np.round(quad).astype(np.int32)], col.tolist())
            cv2.fillPoly(lab, [hull], 0)
        return rgb

    def _sensor(self, rgb):
        """Vignetting, optional defocus or motion blur, pixel noise, 8-bit with a tone curve."""
        cv2.multiply(rgb, self.vignette, dst=rgb)  # in place: rgb is this frame's own
        if self.rng.random() < self.look.blur_prob:
            if self.rng.random() < 0.5:
                rgb = cv2.GaussianBlur(rgb, (0, 0), float(self.rng.uniform(0.6, 1.6)))
            else:
                rgb = cv2.filter2D(rgb, -1, motion_kernel(self.rng))
        cv2.add(rgb, self.noise[int(self.rng.integers(len(self.noise)))], dst=rgb)
        return cv2.LUT(np.clip(rgb, 0, 255, out=rgb).astype(np.uint8), self.tone)


def motion_kernel(rng) -> np.ndarray:
    """A motion blur: a line kernel of 3, 5 or 7 taps, horizontal or vertical (pitching). Odd
    lengths only: cv2.filter2D anchors a kernel at its middle tap, so an even one (until
    2026-11-26: 4 or 6 taps) moved the image half a pixel against its labels."""
    n = 2 * int(rng.integers(1, 4)) + 1
    k = np.zeros((n, n), np.float32)
    k[n // 2, :] = 1.0 / n
    return k.T.copy() if rng.random() < 0.5 else k


def _remap_surface(surface, mx, my) -> np.ndarray:
    """FrameRenderer._surface's masks (surface, x0, y0) at window coordinates (mx, my),
    linearly interpolated, 0 off the masks. Moving the maps to the box's origin is exact in
    float32 (an integer off a coordinate below 2^13), so the samples are the whole window's."""
    masks, x0, y0 = surface
    if x0 or y0:
        mx, my = mx - np.float32(x0), my - np.float32(y0)
    return cv2.remap(masks, mx, my, cv2.INTER_LINEAR)


def _unit_channel(image: np.ndarray, c: int) -> np.ndarray:
    """Channel c of a uint8 image as float32 in [0, 1]."""
    out = cv2.extractChannel(image, c).astype(np.float32)  # a strided astype: 2.5x the time
    out *= np.float32(1 / 255)
    return out


def _ramp(x: np.ndarray, mid: float, gain: float) -> np.ndarray:
    """clip((x - mid) gain + mid, 0, 1), in place (float32)."""
    x -= mid
    x *= gain
    x += mid
    return np.clip(x, 0.0, 1.0, out=x)


def _toward(m: np.ndarray, c, k, ground: np.ndarray) -> np.ndarray:
    """c + (m - c) k (float32) on the ground, -10 (off every window) elsewhere."""
    out = np.subtract(m, c)
    out *= k
    out += c
    np.copyto(out, np.float32(-10.0), where=~ground)
    return out


class _TextureMaps:
    """World-anchored tileable textures at a frame's ground points (wx, wy). A texture of n
    texels at res_m repeats every n res_m metres; the points are wrapped into its period
    explicitly (keeps float32 precision far from 0). Textures of one period whose n and 1 /
    res_m are powers of two share the wrap (scaling by a power of two is exact: the maps are
    the same bytes as wrapping each texture's own)."""

    def __init__(self, wx: np.ndarray, wy: np.ndarray):
        self.wx, self.wy = wx, wy
        self._wrapped = {}  # period (m) -> the points wrapped into it

    def remap(self, tex: np.ndarray, res_m: float) -> np.ndarray:
        n, scale = tex.shape[0], 1.0 / res_m
        if _power_of_two(n) and _power_of_two(scale):
            period = n * res_m
            if period not in self._wrapped:
                self._wrapped[period] = [_wrap(w, period) for w in (self.wx, self.wy)]
            maps = [w * np.float32(scale) for w in self._wrapped[period]]
        else:
            maps = [_wrap(w * np.float32(scale), n) for w in (self.wx, self.wy)]
        return cv2.remap(tex, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def _wrap(m: np.ndarray, n: float) -> np.ndarray:
    """m - floor(m / n) n (float32): m wrapped into [0, n)."""
    q = m * (np.float32(1.0) / np.float32(n)) if _power_of_two(n) else m / np.float32(n)
    np.floor(q, out=q)  # / n is exactly * (1 / n) for a power of two
    q *= np.float32(n)
    return np.subtract(m, q, out=q)


def _power_of_two(x: float) -> bool:
    return x > 0 and math.frexp(x)[0] == 0.5


_NO_SURFACE = np.zeros((1, 1, 4), np.uint8)  # a frame that reads nothing of its window


def _read_box(xs, ys, camera_xy, margin: int, shape) -> tuple | None:
    """((x0, x1), (y0, y1)): the cells of a label window of `shape` that remaps at points
    (xs, ys) and between them and `camera_xy` read, `margin` cells wider, on the 4-cell grid
    of `_ring`'s coarse bands; None if that is no cell of the window."""
    if xs.size == 0:
        return None
    spans = []
    for v, c, size in ((xs, camera_xy[0], shape[1]), (ys, camera_xy[1], shape[0])):
        lo = max(int(np.floor(min(v.min(), c))) - margin, 0) // 4 * 4
        hi = min(-(-(int(np.floor(max(v.max(), c))) + 2 + margin) // 4) * 4, size)
        if lo >= hi:
            return None
        spans.append((lo, hi))
    return tuple(spans)


def _ring_radius(width_cells: float, coarse: int = 1) -> int:
    """The dilation radius of `_ring`'s band, in cells of its `coarse`-times smaller grid."""
    return max(int(round(width_cells / coarse)), 1)


def _ring_reach(width_cells: float, coarse: int = 1) -> int:
    """How many cells of the mask away `_ring`'s band can reach: its radius, and on a coarse
    grid the coarse cell around each cell too."""
    return coarse * (_ring_radius(width_cells, coarse) + (coarse > 1))


def _ring(mask: np.ndarray, width_cells: float, coarse: int = 1) -> np.ndarray:
    """255 where a uint8 mask (0 / 255) is 0 but within width_cells of it (a band around it);
    computed on a `coarse`-times smaller grid for wide bands (a dilation is cheap only with
    small kernels)."""
    small = mask if coarse == 1 else cv2.resize(mask, None, fx=1 / coarse, fy=1 / coarse,
                                                 interpolation=cv2.INTER_AREA)
    r = _ring_radius(width_cells, coarse)
    grown = cv2.dilate(small, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    if coarse > 1:
        grown = cv2.resize(grown, mask.shape[::-1], interpolation=cv2.INTER_NEAREST)
    return cv2.subtract(grown, mask)


def _camera_ground_point(pose, T_vehicle_camera) -> tuple[float, float]:
    """World (x, y) of the point on the ground below the camera."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    tx, ty = float(T_vehicle_camera[0, 3]), float(T_vehicle_camera[1, 3])
    return pose[0] + c * tx - s * ty, pose[1] + s * tx + c * ty


def _ego_dist(v: Vehicle, pose) -> float:
    if v.relative:
        return math.hypot(v.x, v.y)
    return math.hypot(v.x - pose[0], v.y - pose[1])


def _band(uv: np.ndarray, i: int, j: int, lo: float, hi: float) -> np.ndarray:
    """Image quad of a horizontal band (fractions lo..hi of the height) of the face i-j."""
    bi, bj, ti, tj = uv[i], uv[j], uv[i + 4], uv[j + 4]
    return np.stack(
        [bi + lo * (ti - bi), bj + lo * (tj - bj), bj + hi * (tj - bj), bi + hi * (ti - bi)]
    )


def _box_corners(v: Vehicle, pose) -> np.ndarray:
    """8 corners (bottom 4, then top 4) of a vehicle box in the ego vehicle frame."""
    hl, hw = v.length / 2, v.width / 2
    base = np.array([[hl, hw], [hl, -hw], [-hl, -hw], [-hl, hw]])
    c, s = math.cos(v.yaw), math.sin(v.yaw)
    pts = base @ np.array([[c, s], [-s, c]]) + [v.x, v.y]
    if not v.relative:
        dx, dy = pts[:, 0] - pose[0], pts[:, 1] - pose[1]
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pts = np.stack([c * dx + s * dy, -s * dx + c * dy], axis=1)
    bottom = np.concatenate([pts, np.zeros((4, 1))], axis=1)
    top = np.concatenate([pts, np.full((4, 1), v.height)], axis=1)
    return np.concatenate([bottom, top])
