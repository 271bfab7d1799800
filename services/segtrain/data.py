"""Training frames for the segmentation model, from seeded procedural towns only.

Two renderers: the simulator's (drive logs of simulated vehicles, when services.sim.simulate is
available) and services.segtrain.synth (random poses, jittered cameras, randomized materials).
Every kept frame is resized to the model's input size exactly as the runtime does (INTER_AREA)
and its true labels area-resized per class (argmax of the class coverage), so thin paint is
neither lost nor fattened."""

import logging
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from common.classes import NUM_CLASSES

logger = logging.getLogger(__name__)



def resize_image(rgb: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)


def resize_labels(labels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Class image -> (H, W) of `size` by per-class area coverage + argmax."""
    cover = np.stack([cv2.resize((labels == c).astype(np.float32), size,
                                 interpolation=cv2.INTER_AREA) for c in range(NUM_CLASSES)])
    return cover.argmax(axis=0).astype(np.uint8)


def training_set(*, seed: int, input_size: tuple[int, int], budget_s: float,
                 max_frames: int = 6000, cache_dir: Path | None = None):
    """(frames (N, H, W, 3) uint8, labels (N, H, W) uint8) from procedural towns; cached by seed."""
    cache_dir = cache_dir or Path(tempfile.gettempdir()) / "roadmap-segtrain"
    cache = cache_dir / f"towns-v2-s{seed}-{input_size[0]}x{input_size[1]}.npz"
    if cache.is_file():
        logger.info("training frames from cache %s", cache)
        with np.load(cache) as z:
            return z["frames"], z["labels"]
    sim = _sim_available()
    share = 0.6 if sim else 0.0  # the simulator's renderer gets most of the budget
    frames, labels = _synth_towns(seed, input_size, budget_s * (1 - share),
                                  int(max_frames * (1 - share)))
    if sim:
        f2, l2 = _sim_towns(seed, input_size, budget_s * share, max_frames - len(frames))
        frames, labels = np.concatenate([frames, f2]), np.concatenate([labels, l2])
    order = np.random.default_rng(seed).permutation(len(frames))
    frames, labels = frames[order], labels[order]
    cache.parent.mkdir(parents=True, exist_ok=True)
    np.savez(cache, frames=frames, labels=labels)
    return frames, labels


def _sim_available() -> bool:
    try:
        from services.sim.render import FrameRenderer  # noqa: F401
    except ImportError:
        logger.warning("simulator renderer not available: training on synth frames only")
        return False
    return True


def _sim_towns(seed, input_size, budget_s, max_frames):
    """The simulator's FrameRenderer (its own random looks per renderer seed) at random poses
    of procedural towns, with jittered cameras and random lead / parked cars."""
    from services.segtrain.synth import random_camera, random_pose
    from services.sim.render import FrameRenderer
    from services.sim.worlds import load_world

    rng = np.random.default_rng(seed + 7)
    t0 = time.perf_counter()
    frames, labels = [], []
    k = 0
    while time.perf_counter() - t0 < budget_s and len(frames) < max_frames:
        world = thinned(load_world(f"town:{rng.uniform(0.6, 1.5):.2f}", 20_000 * (seed + 1) + k),
                        rng)
        for _ in range(4):
            camera = random_camera(rng)
            renderer = FrameRenderer(world, camera, seed=int(rng.integers(2**31)))
            for _ in range(6):
                pose = random_pose(world, rng)
                rgb, lab = renderer.render(pose, camera.T_vehicle_camera,
                                           float(rng.uniform(0, 600)), random_cars(pose, rng))
                frames.append(resize_image(rgb, input_size))
                labels.append(resize_labels(lab, input_size))
        logger.info("sim town %d: %d frames, %.0f s", k, len(frames), time.perf_counter() - t0)
        k += 1
    return np.stack(frames[:max_frames]), np.stack(labels[:max_frames])


def random_cars(pose, rng) -> list:
    """A lead car (sometimes) and parked cars at the right (sometimes), as the simulator does."""
    from services.sim.render import Vehicle

    cars = []
    colour = lambda: tuple(rng.uniform(20, 220, 3))  # noqa: E731
    if rng.random() < 0.35:
        cars.append(Vehicle(rng.uniform(8, 30), rng.normal(0, 0.4), rng.normal(0, 0.05),
                            rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.7),
                            colour(), relative=True))
    for _ in range(int(rng.poisson(0.6))):
        cars.append(Vehicle(rng.uniform(5, 40), -rng.uniform(2.9, 3.8), rng.normal(0, 0.05),
                            rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.7),
                            colour(), relative=True))
    return cars


def thinned(world, rng):
    """The world with a random share of its paint removed (labels and looks alike), so that road
    edges without edge lines, and lanes without some markings, occur as in real maps."""
    import dataclasses

    from common.classes import Cls

    p_line, p_other = rng.uniform(0.15, 0.6), rng.uniform(0.0, 0.3)
    keep = [m for m in world.markings
            if m.cls == Cls.ROAD or rng.random() >= (p_line if m.cls == Cls.LANE_LINE else p_other)]
    return dataclasses.replace(world, markings=keep)


def _synth_towns(seed, input_size, budget_s, max_frames):
    from services.segtrain.synth import render_town_frames
    from services.sim.worlds import load_world

    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    frames, labels = [], []
    k = 0
    while time.perf_counter() - t0 < budget_s and len(frames) < max_frames:
        world = thinned(load_world(f"town:{rng.uniform(0.6, 1.5):.2f}", 10_000 * (seed + 1) + k),
                        rng)
        # supersample 1: the 2x area resize to the model's input size anti-aliases
        for rgb, lab in render_town_frames(world, 5, 8, rng, supersample=1):
            frames.append(resize_image(rgb, input_size))
            labels.append(resize_labels(lab, input_size))
        logger.info("synth town %d: %d frames, %.0f s", k, len(frames), time.perf_counter() - t0)
        k += 1
    return np.stack(frames[:max_frames]), np.stack(labels[:max_frames])
