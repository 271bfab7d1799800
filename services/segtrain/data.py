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
    if rgb.shape[1::-1] == tuple(size):
        return rgb
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)


def resize_labels(labels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Class image -> (H, W) of `size` by per-class area coverage + argmax."""
    if labels.shape[::-1] == tuple(size):
        return labels
    cover = np.stack([cv2.resize((labels == c).astype(np.float32), size,
                                 interpolation=cv2.INTER_AREA) for c in range(NUM_CLASSES)])
    return cover.argmax(axis=0).astype(np.uint8)


def training_set(*, seed: int, input_size: tuple[int, int], budget_s: float,
                 max_frames: int = 6000, cache_dir: Path | None = None):
    """(frames (N, H, W, 3) uint8, labels (N, H, W) uint8) from procedural towns; cached by seed."""
    cache_dir = cache_dir or Path(tempfile.gettempdir()) / "roadmap-segtrain"
    cache = cache_dir / f"towns-v4-s{seed}-{input_size[0]}x{input_size[1]}.npz"
    if cache.is_file():
        logger.info("training frames from cache %s", cache)
        with np.load(cache) as z:
            return z["frames"], z["labels"]
    sim = _sim_available()
    share = 0.7 if sim else 0.0  # the simulator's renderer gets most of the budget
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

    rng = np.random.default_rng(seed + 7)
    t0 = time.perf_counter()
    frames, labels = [], []
    k = 0
    while time.perf_counter() - t0 < budget_s and len(frames) < max_frames:
        world = town_world(20_000 * (seed + 1) + k, rng)
        for _ in range(4):
            camera = random_camera(rng)
            renderer = FrameRenderer(world, camera, seed=int(rng.integers(2**31)))
            renderer.look.curb = rng.random() < 0.9  # curbs: light strips that are not paint
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

    p_line, p_other = rng.uniform(0.05, 0.35), rng.uniform(0.0, 0.3)
    keep = [m for m in world.markings
            if m.cls == Cls.ROAD or rng.random() >= (p_line if m.cls == Cls.LANE_LINE else p_other)]
    return dataclasses.replace(world, markings=keep)


def restyled(world, rng):
    """Town paint and road edges re-drawn the ways real maps draw them and towns never do:
    - edge lines dropped on many roads (curbstone edges: the curb is the only bright strip),
    - road shoulders narrowed down to none (edge line / curb right at the lane),
    - lane-line widths jittered, and thick (0.2-0.3 m) solid/dashed lines in patches (German
      'breite Strichmarkierung' near junctions; 0.25 m in Lanelet2 maps).
    Strip polygons (roads, lines, dashes) are re-stripped about their centre lines."""
    import dataclasses

    from common.classes import Cls

    p_no_edge = rng.uniform(0.4, 1.0)
    shoulder_cut = rng.uniform(0.0, 0.55) if rng.random() < 0.75 else 0.0
    p_thick = rng.uniform(0.1, 0.6) if rng.random() < 0.7 else 0.0
    thin_w = rng.uniform(0.10, 0.16)
    thick_cells: dict = {}
    out = []
    for m in world.markings:
        half = _strip_halves(m.polygon_xy_m)
        if m.cls == Cls.ROAD and m.kind == "road" and half is not None and shoulder_cut > 0:
            centre, off = half
            width = 2.0 * float(np.median(np.linalg.norm(off, axis=1)))
            scale = max(width - 2.0 * shoulder_cut, 0.5 * width) / width
            m = dataclasses.replace(m, polygon_xy_m=_strip_from(centre, off * scale))
        elif m.cls == Cls.LANE_LINE and m.kind in ("solid", "dashed") and half is not None:
            centre, off = half
            width = 2.0 * float(np.median(np.linalg.norm(off, axis=1)))
            if m.kind == "solid" and width > 0.14 and rng.random() < p_no_edge:
                continue  # an edge line (0.15 m; other solids are 0.12 m)
            cell = tuple(np.floor(centre.mean(axis=0) / 30.0).astype(int))
            if cell not in thick_cells:
                thick_cells[cell] = rng.random() < p_thick
            new_w = rng.uniform(0.2, 0.3) if thick_cells[cell] else thin_w
            m = dataclasses.replace(m, polygon_xy_m=_strip_from(centre, off * (new_w / width)))
        out.append(m)
    return dataclasses.replace(world, markings=out)


def _strip_halves(poly):
    """(centre line (N, 2), left offsets (N, 2)) of a polygon made by services.sim.paint.strip
    (left side forward, right side backward), or None for other shapes."""
    if len(poly) < 4 or len(poly) % 2:
        return None
    n = len(poly) // 2
    left, right = poly[:n], poly[n:][::-1]
    centre = 0.5 * (left + right)
    off = left - centre
    w = np.linalg.norm(off, axis=1)
    if w.min() < 0.02 or w.max() > 1.5 * w.min() + 1e-6:  # not a constant-width strip
        return None
    return centre, off


def _strip_from(centre, off):
    return np.concatenate([centre + off, (centre - off)[::-1]])


def town_world(seed: int, rng):
    """A training town (0.6-1.5 km) with thinned and restyled paint."""
    from services.sim.worlds import load_world

    world = load_world(f"town:{rng.uniform(0.6, 1.5):.2f}", seed)
    return thinned(restyled(world, rng), rng)


def _synth_towns(seed, input_size, budget_s, max_frames):
    from services.segtrain.synth import render_town_frames

    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    frames, labels = [], []
    k = 0
    while time.perf_counter() - t0 < budget_s and len(frames) < max_frames:
        world = town_world(10_000 * (seed + 1) + k, rng)
        for rgb, lab in render_town_frames(world, 5, 8, rng, supersample=2):
            frames.append(resize_image(rgb, input_size))
            labels.append(resize_labels(lab, input_size))
        logger.info("synth town %d: %d frames, %.0f s", k, len(frames), time.perf_counter() - t0)
        k += 1
    return np.stack(frames[:max_frames]), np.stack(labels[:max_frames])
