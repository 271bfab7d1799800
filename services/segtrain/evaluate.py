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
    def __init__(self):
        self.inter = {c: 0 for c in CLASSES}
        self.union = {c: 0 for c in CLASSES}
        self.true_px = {c: 0 for c in CLASSES}

    def add(self, pred, truth, mask=None):
        if mask is not None:
            pred, truth = pred[mask], truth[mask]
        for c in CLASSES:
            p, t = pred == c, truth == c
            self.inter[c] += int((p & t).sum())
            self.union[c] += int((p | t).sum())
            self.true_px[c] += int(t.sum())

    def result(self) -> dict:
        """{class name: IoU, or None where the class never occurs in the truth}."""
        return {NAMES[c]: (round(self.inter[c] / self.union[c], 4) if self.true_px[c] else None)
                for c in CLASSES}
