"""Held-out evaluation of a segmenter: frames of benchmark worlds rendered by the simulator, and
per-class IoU accumulated over frames (sum of intersections / sum of unions)."""

import numpy as np

from common.classes import NAMES, Cls

CLASSES = (Cls.ROAD, Cls.LANE_LINE, Cls.STOP_LINE, Cls.CROSSWALK, Cls.GROUND_SIGN)


def render_heldout(spec: str, *, frames: int, seed: int, rare_prob: float = 0.3):
    """`frames` (rgb, labels) of a held-out world rendered by the simulator's FrameRenderer at
    seeded random poses on its routes (a share of them facing stop lines, crosswalks or signs),
    through the default camera with vibration (0.3 deg), with random lead / parked cars;
    -> (pairs, nominal camera)."""
    from common.camera import camera_from_config
    from common.config import CameraConfig
    from services.segtrain.data import random_cars
    from services.segtrain.synth import random_pose
    from services.sim.render import FrameRenderer
    from services.sim.worlds import load_world

    rng = np.random.default_rng(seed)
    world = load_world(spec, seed)
    camera = camera_from_config(CameraConfig())
    pairs = []
    for start in range(0, frames, 10):  # a new look (renderer seed) every 10 frames
        renderer = FrameRenderer(world, camera, seed=int(rng.integers(2**31)))
        for _ in range(min(10, frames - start)):
            shake = np.radians(rng.normal(0.0, 0.3, 2))
            T = camera.perturbed(d_pitch_rad=shake[0], d_roll_rad=shake[1]).T_vehicle_camera
            pose = random_pose(world, rng, rare_prob=rare_prob)
            cars = random_cars(pose, rng)
            pairs.append(renderer.render(pose, T, float(rng.uniform(0, 600)), cars))
    return pairs, camera


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

    def draws(self, n: int, rng) -> list[dict]:
        """`n` bootstrap results: the pooled IoU of as many frames drawn with replacement."""
        counts, m = np.stack(self._frames), len(self._frames)
        return [_iou(counts[rng.integers(0, m, m)].sum(axis=0)) for _ in range(n)]

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
