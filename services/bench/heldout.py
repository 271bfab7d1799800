"""Held-out evaluation of a segmenter: frames of benchmark worlds rendered by the simulator, and
per-class IoU accumulated over frames (sum of intersections / sum of unions)."""

import numpy as np

from common.classes import MARKINGS, NAMES, Cls

CLASSES = (Cls.ROAD, Cls.LANE_LINE, Cls.STOP_LINE, Cls.CROSSWALK, Cls.GROUND_SIGN)
# Words of the road text added to held-out worlds: none of them is painted in the training towns
# (services/sim/town.py TEXTS).
HELDOUT_TEXTS = ("BUS", "SLOW", "STOP", "ONLY")
# Arrows added to held-out worlds, each drawn as the union of the towns' arrow glyphs: the
# straight-and-turn arrows are shapes no training town paints.
HELDOUT_ARROWS = (("arrow_straight",), ("arrow_left",), ("arrow_right",),
                  ("arrow_straight", "arrow_left"), ("arrow_straight", "arrow_right"))


def render_heldout(spec: str, *, frames: int, seed: int, rare_prob: float = 0.3,
                   facing: Cls | None = None):
    """`frames` (rgb, labels) of a held-out world rendered by the simulator's FrameRenderer at
    seeded random poses on its routes (a share of them facing stop lines, crosswalks or signs),
    through the default camera with vibration (0.3 deg), with random lead / parked cars;
    -> (pairs, nominal camera). With `facing`, every pose faces a marking of that class instead
    (`FacingPoses`: the world's routes pass few of its stop lines); facing Cls.GROUND_SIGN, the
    world first gets signs painted in its lanes (`with_ground_signs`: the benchmark worlds have
    none)."""
    from common.camera import camera_from_config
    from common.config import CameraConfig
    from services.sim.poses import random_cars, random_pose
    from services.sim.render import FrameRenderer
    from services.sim.worlds import load_world

    rng = np.random.default_rng(seed)
    world = load_world(spec, seed)
    camera = camera_from_config(CameraConfig())
    facing_poses = None
    if facing == Cls.GROUND_SIGN:
        world, anchors = with_ground_signs(world, seed)
        facing_poses = FacingPoses(world, facing, anchors=anchors)
    elif facing is not None:
        facing_poses = FacingPoses(world, facing)
    pairs = []
    for start in range(0, frames, 10):  # a new look (renderer seed) every 10 frames
        renderer = FrameRenderer(world, camera, seed=int(rng.integers(2**31)), jumps=True)
        for _ in range(min(10, frames - start)):
            shake = np.radians(rng.normal(0.0, 0.3, 2))
            T = camera.perturbed(d_pitch_rad=shake[0], d_roll_rad=shake[1]).T_vehicle_camera
            if facing_poses is not None:
                pose = facing_poses.draw(rng)
            else:
                pose = random_pose(world, rng, rare_prob=rare_prob)
            cars = random_cars(pose, rng)
            pairs.append(renderer.render(pose, T, float(rng.uniform(0, 600)), cars))
    return pairs, camera


class FacingPoses:
    """Vehicle poses (x, y, yaw) on the road facing a marking of one class across its long side,
    `near_m`..`far_m` before its centre (the 4-20 m of the route poses that face a rare marking),
    from either side (a stop line is also passed from behind), shifted along the marking and
    turned by a few degrees. The Karlsruhe world's routes face only 4 of its 28 stop lines, and
    61 of 300 route frames show one (55 % of their pixels in 2 frames): too few to measure. These
    poses reach every marking with road before it (13 of the 28). With `anchors` ((x, y, yaw) of
    markings read along the driving direction: ground signs), the poses stand behind each anchor
    on its lane instead, shifted sideways by up to 0.3 m."""

    CELL_M = 0.1  # road lookup raster

    def __init__(self, world, cls: Cls, near_m: float = 4.0, far_m: float = 20.0,
                 anchors: list[tuple[float, float, float]] | None = None):
        self.near_m, self.far_m = near_m, far_m
        self._road, self._x0, self._y0 = world.rasterize_all(2.0, self.CELL_M)
        self.options = []  # (centre, long axis, normal towards the camera, half length)
        for x, y, yaw in anchors or ():
            ahead = np.array([np.cos(yaw), np.sin(yaw)])
            self.options.append((np.array([x, y]), np.array([-ahead[1], ahead[0]]), -ahead, 0.5))
        for m in world.markings if anchors is None else ():
            if m.cls != cls:
                continue
            centre, along, normal, length = long_axis(m.polygon_xy_m)
            half = length / 2
            for side in (normal, -normal):
                ray = centre + np.outer(np.linspace(near_m, far_m, 5), side)
                if self.on_road(ray).all():
                    self.options.append((centre, along, side, half))
        if not self.options:
            raise ValueError(f"no {cls.name} marking with road before it")

    def on_road(self, xy) -> np.ndarray:
        """(N,) bool: world points (N, 2) on the road surface or its paint."""
        c = np.floor((xy[:, 0] - self._x0) / self.CELL_M).astype(np.int64)
        r = np.floor((xy[:, 1] - self._y0) / self.CELL_M).astype(np.int64)
        h, w = self._road.shape
        ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        return ok & (self._road[np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)] >= Cls.ROAD)

    def draw(self, rng) -> tuple[float, float, float]:
        for _ in range(100):
            centre, along, side, half = self.options[int(rng.integers(len(self.options)))]
            shift = rng.uniform(-1.0, 1.0) * min(0.6 * half, 3.0)
            xy = centre + along * shift + side * rng.uniform(self.near_m, self.far_m)
            if self.on_road(xy[None])[0]:
                yaw = float(np.arctan2(-side[1], -side[0]) + rng.normal(0.0, np.radians(5.0)))
                return float(xy[0]), float(xy[1]), yaw
        raise RuntimeError("no road pose found before the markings")


def long_axis(polygon: np.ndarray):
    """A marking's (centre, unit long axis, unit normal, length along the axis): the principal
    axes of its vertices."""
    centre = polygon.mean(axis=0)
    axes = np.linalg.eigh(np.cov((polygon - centre).T))[1]
    along = axes[:, 1]
    return centre, along, axes[:, 0], float(np.ptp((polygon - centre) @ along))


def with_ground_signs(world, seed: int, spacing_m: float = 30.0, margin_m: float = 0.3):
    """The world with turn arrows and road text painted in its lanes, and each sign's (x, y,
    yaw: the way its arrow points) -> (world, anchors).

    Neither the Karlsruhe nor the Argoverse 2 maps have ground signs, so the benchmark paints
    some to measure that class on held-out scenes. Candidate places: the routes (lane centre
    lines) every 10 m, then beside each lane-line piece at least 2 m long, 1.6-1.9 m to either
    side (mid-lane), pointing either way along it; in a seeded random order. A glyph (70 % one
    of HELDOUT_ARROWS scaled 0.85-1.15, 30 % a word of HELDOUT_TEXTS) goes where it and
    `margin_m` around it lie on bare road (no paint, no sign placed before), at least
    `spacing_m` from every other sign. Words no town paints and straight-and-turn arrows no town
    paints, but the towns' font and single arrows (services/sim/paint.py): this measures the
    model mostly on scenes, looks and surroundings it never saw, less on glyphs it never saw."""
    import dataclasses

    rng = np.random.default_rng([seed, 0x516E])
    candidates = _sign_candidates(world, rng)
    placer = _SignPlacer(world, margin_m)
    signs, anchors = [], []
    for i in rng.permutation(len(candidates)):
        x, y, yaw = candidates[i]
        if anchors and np.hypot(*(np.array(anchors)[:, :2] - [x, y]).T).min() < spacing_m:
            continue
        glyph = _random_glyph(rng, x, y, yaw)
        if placer.place(glyph):
            signs += glyph
            anchors.append((float(x), float(y), float(yaw)))
    if not anchors:
        raise ValueError(f"{world.name}: no bare road for a ground sign")
    return dataclasses.replace(world, markings=list(world.markings) + signs), anchors


def _sign_candidates(world, rng) -> list[tuple[float, float, float]]:
    """(x, y, yaw) places for signs: every 10 m along the routes, then beside lane lines."""
    candidates = []
    for route in world.routes:
        # not paint.arc_length (norm, not hypot): the two differ in the last bits, which moves
        # one of Karlsruhe's signs away from the placements the benchmark's figures come from
        s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(route, axis=0).T))])
        for at in np.arange(5.0, s[-1] - 5.0, 10.0):
            k = int(np.clip(np.searchsorted(s, at), 1, len(route) - 1))
            d = route[k] - route[k - 1]
            candidates.append((np.interp(at, s, route[:, 0]), np.interp(at, s, route[:, 1]),
                               float(np.arctan2(d[1], d[0]))))
    for m in world.markings:
        if m.cls != Cls.LANE_LINE or len(m.polygon_xy_m) < 3:
            continue
        centre, along, _, length = long_axis(m.polygon_xy_m)
        if length < 2.0:
            continue
        yaw = float(np.arctan2(along[1], along[0]))
        for side in (-1.0, 1.0):
            xy = centre + side * rng.uniform(1.6, 1.9) * np.array([-along[1], along[0]])
            candidates.append((xy[0], xy[1], yaw + (np.pi if rng.random() < 0.5 else 0.0)))
    return candidates


def _random_glyph(rng, x: float, y: float, yaw: float) -> list:
    """70 %: one of HELDOUT_ARROWS scaled 0.85-1.15; else a word of HELDOUT_TEXTS."""
    from services.sim import paint

    if rng.random() < 0.7:
        kinds = HELDOUT_ARROWS[int(rng.integers(len(HELDOUT_ARROWS)))]
        scale = float(rng.uniform(0.85, 1.15))
        return [paint.arrow(kind, x, y, yaw, scale=scale) for kind in kinds]
    word = HELDOUT_TEXTS[int(rng.integers(len(HELDOUT_TEXTS)))]
    return paint.text_block(word, x, y, yaw)


class _SignPlacer:
    """The world's label raster, where each placed sign (with `margin_m` around it) claims
    bare road; a glyph that would touch paint or another sign is refused."""

    def __init__(self, world, margin_m: float):
        import cv2

        self.cell = FacingPoses.CELL_M
        self.labels, self.x0, self.y0 = world.rasterize_all(4.0, self.cell)
        self.grow = int(np.ceil(margin_m / self.cell))
        self.kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE,
                                                (2 * self.grow + 1, 2 * self.grow + 1))

    def place(self, glyph: list) -> bool:
        import cv2

        from common.world import World

        cell, grow, x0, y0 = self.cell, self.grow, self.x0, self.y0
        pts = np.concatenate([g.polygon_xy_m for g in glyph])
        c0 = int(np.floor((pts[:, 0].min() - x0) / cell)) - grow - 1
        r0 = int(np.floor((pts[:, 1].min() - y0) / cell)) - grow - 1
        c1 = int(np.ceil((pts[:, 0].max() - x0) / cell)) + grow + 1
        r1 = int(np.ceil((pts[:, 1].max() - y0) / cell)) + grow + 1
        if r0 < 0 or c0 < 0 or r1 > self.labels.shape[0] or c1 > self.labels.shape[1]:
            return False
        mask = World("sign", glyph).rasterize(x0 + c0 * cell, y0 + r0 * cell, r1 - r0, c1 - c0,
                                              cell) > 0
        footprint = cv2.dilate(mask.astype(np.uint8), self.kernel) > 0
        window = self.labels[r0:r1, c0:c1]
        if not mask.any() or (window[footprint] != Cls.ROAD).any():
            return False
        window[footprint] = Cls.GROUND_SIGN
        return True


def mean_paint_iou(ious: dict) -> float:
    """Mean IoU of the marking classes present in `ious` (IouAccumulator.result()); 0 when
    none is."""
    paint = {NAMES[c] for c in MARKINGS}
    marks = [v for name, v in ious.items() if v is not None and name in paint]
    return float(np.mean(marks)) if marks else 0.0


def segmenter_iou(seg, frames, labels) -> dict:
    """Per-class IoU of an OnnxSegmenter as the runtime segments frames (N, H, W, 3) at its
    model's input size, against their labels."""
    acc = IouAccumulator()
    for frame, truth in zip(frames, labels, strict=True):
        acc.add(seg.segment_model_size(frame), truth)
    return acc.result()


class IouAccumulator:
    """Per-class IoU pooled over frames. Each frame's counts are kept, so that how much the
    pooled IoU owes to which frames were drawn can be bootstrapped (`interval`): on 100 frames
    of the Karlsruhe world, a second draw of frames moved lane-line IoU by 0.09."""

    def __init__(self):
        self._frames: list[np.ndarray] = []  # per frame: (3, classes) intersection, union, truth

    def add(self, pred, truth, mask=None):
        if mask is not None:
            pred, truth = pred[mask], truth[mask]
        counts = np.zeros((3, len(CLASSES)), np.int64)
        for k, c in enumerate(CLASSES):
            p, t = pred == c, truth == c
            counts[:, k] = (p & t).sum(), (p | t).sum(), t.sum()
        self._frames.append(counts)

    def _totals(self) -> np.ndarray:
        return sum(self._frames, np.zeros((3, len(CLASSES)), np.int64))

    @property
    def true_px(self) -> dict:
        return {c: int(n) for c, n in zip(CLASSES, self._totals()[2], strict=True)}

    def result(self) -> dict:
        """{class name: IoU, or None where the class never occurs in the truth}."""
        return _iou(self._totals())

    def precision_recall(self) -> dict:
        """{class name: {"precision", "recall"}} pooled over the frames (None where undefined)."""
        inter, union, true = self._totals()
        pred = union - true + inter
        ratio = lambda a, b: round(float(a / b), 4) if b else None  # noqa: E731
        return {NAMES[c]: {"precision": ratio(i, p), "recall": ratio(i, t)}
                for c, i, p, t in zip(CLASSES, inter, pred, true, strict=True)}

    def draws(self, n: int, rng, minus: "IouAccumulator | None" = None) -> list[dict]:
        """`n` bootstrap results: the pooled IoU of as many frames drawn with replacement. With
        `minus` (a second model on the same frames), its IoU on the same draw is subtracted: the
        paired difference, much narrower than the two intervals apart, since the frames that
        are hard for one model are hard for the other ({name: difference or None})."""
        counts, m = np.stack(self._frames), len(self._frames)
        other = None if minus is None else np.stack(minus._frames)
        if other is not None and other.shape != counts.shape:
            raise ValueError(f"paired accumulators hold {m} and {len(other)} frames")
        out = []
        for _ in range(n):
            pick = rng.integers(0, m, m)
            iou = _iou(counts[pick].sum(axis=0))
            if other is not None:
                base = _iou(other[pick].sum(axis=0))
                iou = {k: None if v is None else v - base[k] for k, v in iou.items()}
            out.append(iou)
        return out

    def interval(self, n: int = 1000, seed: int = 0, q=(5, 95)) -> dict:
        """{class name: [low, high] percentiles of the bootstrapped IoU, or None}."""
        return bootstrap_interval(self.draws(n, np.random.default_rng(seed)), q)


def bootstrap_interval(draws: list[dict], q=(5, 95)) -> dict:
    """Percentiles per class of bootstrap results ({name: IoU or None} each); None where the
    class is absent from every draw."""
    out = {}
    for name in draws[0]:
        vals = [d[name] for d in draws if d[name] is not None]
        out[name] = [round(float(v), 4) for v in np.percentile(vals, q)] if vals else None
    return out


def _iou(totals: np.ndarray) -> dict:
    inter, union, true = totals
    return {NAMES[c]: (round(float(inter[k] / union[k]), 4) if true[k] else None)
            for k, c in enumerate(CLASSES)}
