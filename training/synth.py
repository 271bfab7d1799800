"""A small randomized ground-plane renderer for training data: World + camera + pose -> (RGB,
labels).

Every pixel's ray is intersected with the ground (paper eq. 1, `CameraModel.ground_points`), the
world's label raster is sampled there (2x2 supersampling, per-class coverage -> labels), and the
colour comes from randomized materials: asphalt with world-anchored texture and patches, worn paint
(white or yellow), verges, sky, soft shadows, vignetting. It complements the simulator's renderer
with more appearance variety (domain randomization) and stands in for it when it is absent."""

import functools

import cv2
import numpy as np

from common.camera import CameraModel
from common.classes import Cls
from common.geometry import rot_z
from services.sim.poses import _pose_on, _route_pose, random_pose  # noqa: F401 -- train-seg's
from training.looks import curb_face_gain

CELL_M = 0.05
SUPER = 2
CURB = 255  # raster values of curb top, curb face and sidewalk cells (rendered, labelled none)
FACE = 254
WALK = 253


TEXTURE = 1024  # world-anchored textures tile every 51.2 m (a power of two: a mask wraps)


class WorldRaster:
    """The world's label raster at CELL_M plus tiled world-anchored noise textures."""

    def __init__(self, world, rng):
        self.labels, self.x0, self.y0 = world.rasterize_all(4.0, CELL_M)
        # curbs: a 5-10 cm shaded band (the curb's vertical face as the camera sees it), the
        # curb top 0.1-0.2 m and, in some towns, a paved sidewalk 1-3 m wide behind it; all
        # labelled none (a curb is no marking, though a light one looks like an edge line)
        road = (self.labels >= Cls.ROAD).astype(np.uint8)
        d = cv2.distanceTransform((1 - road) * 255, cv2.DIST_L2, 3) * CELL_M
        face_end = rng.uniform(0.05, 0.1)
        curb_end = face_end + rng.uniform(0.1, 0.2)
        walk_end = curb_end + (rng.uniform(1.0, 3.0) if rng.random() < 0.6 else 0.0)
        out = road == 0
        for value, lo, hi in ((FACE, 0.0, face_end), (CURB, face_end, curb_end),
                              (WALK, curb_end, walk_end)):
            self.labels[out & (d > lo) & (d <= hi)] = value
        self.fine = _noise((TEXTURE, TEXTURE), rng, scale=1)  # grain
        self.coarse = _noise((TEXTURE, TEXTURE), rng, scale=64)  # patches, repairs, shadows
        self.wear = _noise((TEXTURE, TEXTURE), rng, scale=6)

    def sample(self, xy_world):
        """World points (N, 2) -> (labels, fine, coarse, wear) at the nearest cell; 0 outside."""
        lab, r, c = self._cells(xy_world)
        texel = (r & (TEXTURE - 1)) * TEXTURE + (c & (TEXTURE - 1))  # r % TEXTURE, c % ...
        return lab, *(t.ravel().take(texel) for t in (self.fine, self.coarse, self.wear))

    def labels_at(self, xy_world):
        """World points (N, 2) -> the label of the nearest cell; 0 outside."""
        return self._cells(xy_world)[0]

    def _cells(self, xy_world):
        """World points (N, 2) -> (label of the nearest cell, 0 outside; its row; its column)."""
        c = np.floor((xy_world[:, 0] - self.x0) / CELL_M).astype(np.int64)
        r = np.floor((xy_world[:, 1] - self.y0) / CELL_M).astype(np.int64)
        h, w = self.labels.shape
        ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        return np.where(ok, self.labels[np.where(ok, r, 0), np.where(ok, c, 0)], 0), r, c


def _noise(shape, rng, scale):
    """Smooth noise in [-1, 1] of feature size ~scale cells (bilinear upsampled random grid)."""
    h, w = shape
    g = rng.standard_normal((max(h // scale, 2) + 1, max(w // scale, 2) + 1)).astype(np.float32)
    n = cv2.resize(g, (w, h), interpolation=cv2.INTER_LINEAR if scale > 1 else cv2.INTER_NEAREST)
    return np.clip(n / 2.0, -1.0, 1.0).astype(np.float32)


def random_camera(rng, width=640, height=360) -> CameraModel:
    """The default front camera with height, pitch, roll, yaw and focal-length jitter."""
    f = 460.0 * rng.uniform(0.85, 1.15)
    return CameraModel.from_mount(
        width=width, height=height, fx=f, fy=f, cx=width / 2 + rng.normal(0, 6),
        cy=height / 2 + rng.normal(0, 6), dist=[rng.uniform(-0.08, 0.0), 0.01, 0, 0, 0],
        x_m=1.8, y_m=0.0, height_m=rng.uniform(1.25, 1.75), pitch_deg=rng.uniform(1.5, 7.0),
        roll_deg=rng.normal(0, 0.8), yaw_deg=rng.normal(0, 1.0))


MAX_RANGE_M = 120.0


class GroundMap:
    """Per camera, once: every supersampled pixel's ground point in the vehicle frame (for
    the colours) and every pixel centre's (for the labels)."""

    def __init__(self, camera: CameraModel, supersample: int = SUPER):
        self.camera, self.ss = camera, supersample
        w, h, k = camera.width, camera.height, supersample
        self.uv, ground_v, self.hit, dist = _ground_at(camera, w, h, k)
        # the sub-pixels that see the ground: the only ones whose world cells are sampled
        self.on = np.flatnonzero(self.hit)
        self.ground_on, self.dist_on = ground_v[self.on], dist[self.on]
        # Labels are the class at each pixel's centre, as the simulator's renderer labels its
        # frames (services/sim/render.py) and as the benchmark scores them. (Until 2026-11-26
        # they were the majority of the 2x2 sub-samples with ties to the lower class: road over
        # paint, so every line was labelled half a pixel thinner than drawn.)
        if k > 1:
            _, centre_v, centre_hit, _ = _ground_at(camera, w, h, 1)
            self.centre_on = np.flatnonzero(centre_hit)
            self.centre_ground_on = centre_v[self.centre_on]
        else:
            self.centre_on, self.centre_ground_on = self.on, self.ground_on
        # the sky's sub-pixels and their brightness, lighter towards the horizon (the sky's
        # colour multiplies it per frame)
        self.sky = np.flatnonzero(~self.hit)
        self.sky_gain = 0.8 + 0.2 * np.clip(self.uv[self.sky, 1] / h, 0.0, 1.0)[:, None]


def _ground_at(camera: CameraModel, w: int, h: int, k: int):
    """(uv, ground points, hit, distance) of the centres of a k x k sub-pixel grid (k = 1: the
    pixels' centres), in row-major order of the (h k, w k) grid; ground points beyond
    MAX_RANGE_M or above the horizon are not hit (and 0)."""
    v, u = np.mgrid[0:h * k, 0:w * k]
    uv = np.stack([(u.ravel() + 0.5) / k, (v.ravel() + 0.5) / k], axis=1)
    ground_v = camera.ground_points(uv)
    hit = np.isfinite(ground_v).all(axis=1)
    dist = np.where(hit, np.hypot(ground_v[:, 0], ground_v[:, 1]), np.inf)
    hit &= dist < MAX_RANGE_M
    return uv, np.where(hit[:, None], ground_v, 0.0), hit, dist


def render(raster: WorldRaster, ground: GroundMap, pose, rng, curb_label=None):
    """-> (rgb (H, W, 3) uint8, labels (H, W) uint8) of the camera at vehicle pose (x, y, yaw).
    With `curb_label` (an auxiliary training class), curb face and top cells get that label
    (else 0, none, like sidewalks). Only the pixels that see the ground sample the world."""
    w, h = ground.camera.width, ground.camera.height
    R, at = rot_z(pose[2])[:2, :2], [pose[0], pose[1]]
    lab, fine, coarse, wear = raster.sample(ground.ground_on @ R.T + at)
    style = _style(rng)
    rgb = _shade(lab, fine, coarse, wear, ground, style, rng)
    k = ground.ss
    rgb = rgb.reshape(h * k, w * k, 3)
    if k > 1:  # the colours' sub-pixels are not the pixel centres the labels are taken at
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
        lab = raster.labels_at(ground.centre_ground_on @ R.T + at)
    centre = np.zeros(w * h, raster.labels.dtype)
    centre[ground.centre_on] = lab
    curb = 0 if curb_label is None or style["curb"] is None else curb_label  # else: verge
    labels = np.where(centre == WALK, 0, np.where(centre > WALK, curb, centre))
    return _camera_effects(rgb, style, rng), labels.reshape(h, w).astype(np.uint8)


def _style(rng) -> dict:
    asphalt = rng.uniform(45, 140)
    return {
        "asphalt": np.array([asphalt, asphalt, asphalt]) * rng.uniform(0.92, 1.08, 3),
        "verge": rng.choice([[70, 110, 50], [120, 115, 105], [150, 140, 120], [90, 80, 65]])
        * rng.uniform(0.7, 1.2, 3),
        "sky": np.array([rng.uniform(150, 230), rng.uniform(170, 235), rng.uniform(190, 255)]),
        "paint": rng.uniform(170, 250),
        "yellow": rng.random() < 0.25,
        "wear": rng.uniform(0.0, 0.45),
        "shadow": rng.uniform(0.0, 0.6),
        "light": rng.uniform(0.55, 1.35),
        "fog_m": rng.uniform(60, 400),
        "curb": rng.uniform(140, 215) * rng.uniform(0.95, 1.05, 3) if rng.random() < 0.7 else None,
        "face": curb_face_gain(rng),
        "walk": rng.uniform(105, 185) * rng.uniform(0.95, 1.05, 3),
    }


# the ground's materials: their texture gains (grain, patches), and which raster values are
# each: 0 verge, 1-3 curb top, curb face, sidewalk (verge where a town draws no curbs), 4 road
# surface and 5 paint (both asphalt)
_VERGE, _CURB_TOP, _CURB_FACE, _WALK, _ROAD, _PAINT = range(6)
_GRAIN = np.array([0.25, 0.08, 0.08, 0.08, 0.10, 0.10], np.float32)
_PATCHES = np.array([0.2, 0.08, 0.08, 0.08, 0.12, 0.12], np.float32)
_MATERIAL = np.full(256, _VERGE, np.uint8)
_MATERIAL[Cls.ROAD] = _ROAD
_MATERIAL[Cls.LANE_LINE:WALK] = _PAINT
_MATERIAL_CURBED = _MATERIAL.copy()
_MATERIAL_CURBED[[CURB, FACE, WALK]] = _CURB_TOP, _CURB_FACE, _WALK


def _shade(lab, fine, coarse, wear, ground, s, rng):
    """The colours (H k * W k, 3) uint8 of the sub-pixels: those that see the ground from their
    world cells' labels and textures (`lab`... sampled at `ground.on`), the rest sky. Each
    pixel's material looked up from its label, its colour scaled by its textures (paint worn
    through to the asphalt under it), lit, shadowed and fogged."""
    curbed = s["curb"] is not None
    material = (_MATERIAL_CURBED if curbed else _MATERIAL)[lab]
    gain = 1.0 + _GRAIN[material] * fine + _PATCHES[material] * coarse
    colours = np.array([s["verge"], s["curb"] if curbed else s["verge"],
                        s["curb"] * s["face"] if curbed else s["verge"], s["walk"],
                        s["asphalt"], s["asphalt"]], np.float64).T
    rgb, gain64 = np.empty((len(lab), 3), np.float32), gain.astype(np.float64)
    for channel, rgb_c in zip(colours, rgb.T, strict=True):  # a channel at a time: 2x faster
        np.multiply(channel[material], gain64, out=rgb_c, casting="unsafe")
    paint = np.flatnonzero(material == _PAINT)
    base = s["asphalt"] * gain[paint, None]
    colour = np.array([s["paint"], s["paint"], s["paint"]])
    tint = np.array([s["paint"], s["paint"] * 0.8, 60.0]) if s["yellow"] else colour
    pc = np.where((lab[paint] == Cls.LANE_LINE)[:, None], tint, colour)
    worn = np.clip(1.0 - s["wear"] * (1.0 + wear[paint]), 0.25, 1.0)[:, None]
    rgb[paint] = worn * pc + (1 - worn) * base
    shadow = 1.0 - s["shadow"] * np.clip(coarse * 3.0 - 0.6, 0.0, 1.0)
    rgb *= (shadow * s["light"])[:, None]
    fog = np.exp(-ground.dist_on / s["fog_m"])[:, None]
    ground_rgb = fog * rgb
    haze = (1 - fog) * s["sky"]
    haze *= 0.9
    ground_rgb += haze
    out = np.empty((len(ground.uv), 3), np.uint8)
    out[ground.on] = np.clip(ground_rgb, 0, 255, out=ground_rgb)
    sky = rng.normal(0, 3, (len(ground.sky), 3))
    sky += s["sky"] * ground.sky_gain
    out[ground.sky] = np.clip(sky, 0, 255, out=sky)
    return out


def _camera_effects(rgb, s, rng):
    img = rgb.astype(np.float32)
    if rng.random() < 0.5:
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.4, 1.0))
    img *= (1.0 - rng.uniform(0, 0.5) * _radius2(*img.shape[:2]))[..., None]
    img += rng.normal(0, rng.uniform(1, 6), img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


@functools.lru_cache(maxsize=4)
def _radius2(h: int, w: int) -> np.ndarray:
    """Each pixel's squared distance from the image centre, in image widths and heights (the
    vignette's falloff; read-only, shared by the frames of one size)."""
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - w / 2) / w) ** 2 + ((yy - h / 2) / h) ** 2
    r2.flags.writeable = False
    return r2


def render_town_frames(world, n_cameras: int, poses_per_camera: int, rng, supersample=SUPER,
                       curb_label=None, turn_prob=0.0):
    """Yield (rgb, labels) of random poses in a world, a few poses per jittered camera."""
    raster = WorldRaster(world, rng)
    for _ in range(n_cameras):
        ground = GroundMap(random_camera(rng), supersample)
        for _ in range(poses_per_camera):
            yield render(raster, ground, random_pose(world, rng, turn_prob=turn_prob), rng,
                         curb_label)
