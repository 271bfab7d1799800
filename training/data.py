"""Training frames for the segmentation model, from seeded procedural towns only.

Two renderers: the simulator's (drive logs of simulated vehicles, when services.sim.simulate is
available) and training.synth (random poses, jittered cameras, randomized materials).
Every kept frame is resized to the model's input size exactly as the runtime does (INTER_AREA)
and its true labels area-resized per class (argmax of the class coverage), so thin paint is
neither lost nor fattened."""

import contextlib
import dataclasses
import logging
import os
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from common.classes import NUM_CLASSES, Cls
from common.errors import ConfigError
from services.sim.poses import random_cars  # noqa: F401 -- read as seg_data's
from training.looks import SUNLIT_CURB, curb_face_gain  # noqa: F401 -- read as seg_data's

logger = logging.getLogger(__name__)

# Training labels have one class beyond ours: raised curbs (face and top band). A light curb
# looks like an edge line; labelled none, it was where 85 % of the lane-line false positives on
# the Karlsruhe frames lay. Taught as its own class, it is folded back into none at export.
CURB_AUX = NUM_CLASSES
TRAIN_CLASSES = NUM_CLASSES + 1
# A share of training poses turned off the route (synth.random_pose): on Karlsruhe frames, thin
# lane lines crossing the view at junctions were the largest share of missed lane line (called
# stop line, 0.3 m wide to their 0.12 m); towns' route poses almost never show them.
TURN_PROB = 0.2
# Lanes each way of the training towns' roads (1, 2, 3, 4) and the share of roads of two or more
# lanes split by a raised median (services.sim.town): real maps' arterials are wide, and the
# Argoverse 2 frames' far field, many converging lines, is where their lane line was lost.
LANE_MIX = (0.45, 0.3, 0.17, 0.08)
# junction lines (junction_lines): "light" in 80 % of the towns at 30-90 % of their junctions,
# drawn after `restyled`; "heavy" in every town at 50-100 %, 1-4 turn guides, drawn before it
# (the straight lines then also cross the mouths of roads whose edge lines it later drops)
JUNCTIONS = ("light", "heavy")
MEDIAN_PROB = 0.35




def resize_image(rgb: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    if rgb.shape[1::-1] == tuple(size):
        return rgb
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)


def resize_labels(labels: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Class image -> (H, W) of `size` by per-class area coverage + argmax."""
    if labels.shape[::-1] == tuple(size):
        return labels
    cover = np.stack([cv2.resize((labels == c).astype(np.float32), size,
                                 interpolation=cv2.INTER_AREA) for c in range(TRAIN_CLASSES)])
    return cover.argmax(axis=0).astype(np.uint8)


CHUNK_FRAMES = 24  # frames per town chunk: the unit of work, of seeding and of parallelism
SYNTH_SHARE = 0.3  # chunks 0-2 of every 10 come from synth.py, the rest from the simulator


def check_synth_share(share: float) -> None:
    """--synth-share is a share of every 10 chunks: 0, 0.1, ..., 1."""
    if not (0.0 <= share <= 1.0 and abs(10 * share - round(10 * share)) < 1e-9):
        raise ConfigError(f"--synth-share {share}: must be one of 0, 0.1, ..., 1 (a share of "
                          "every ten chunks)")


def is_synth_chunk(k: int, synth_share: float = SYNTH_SHARE) -> bool:
    """Whether chunk k of a run renders with synth.py (else the simulator): the first
    10 * synth_share chunks of every 10."""
    return k % 10 < round(10 * synth_share)


def _share_key(synth_share: float) -> str:
    """The cache key's part for the synth share: empty for the default (older caches stay)."""
    return "" if synth_share == SYNTH_SHARE else f"-y{round(10 * synth_share)}"


def check_junctions(junctions: str) -> None:
    if junctions not in JUNCTIONS:
        raise ConfigError(f"junction lines {junctions!r}: one of {', '.join(JUNCTIONS)}")


def training_set(*, seed: int, input_size: tuple[int, int], budget_s: float,
                 max_frames: int = 6000, workers: int = 1, cache_dir: Path | None = None,
                 cache: bool = True, turn_prob: float = TURN_PROB,
                 synth_share: float = SYNTH_SHARE, junctions: str = "light"):
    """(frames (N, H, W, 3) uint8, labels (N, H, W) uint8) from procedural towns (their
    junction lines as `junctions` says: town_world); cached.

    The set is a sequence of chunks (one town, CHUNK_FRAMES frames each), chunk k rendered from
    its own seed (seed, k) alone, so the first n chunks are the same whatever `workers` renders
    them; rendering stops at max_frames or when budget_s is spent (whichever comes first)."""
    cache_dir = cache_dir or Path(tempfile.gettempdir()) / "roadmap-segtrain"
    # the budget is in the key: a set cut short by a smaller budget is not reused for a larger
    path = cache_dir / (f"towns-v13-s{seed}-{input_size[0]}x{input_size[1]}-n{max_frames}"
                        f"-b{round(budget_s)}-t{round(100 * turn_prob)}"
                        f"{_share_key(synth_share)}"
                        f"{'' if junctions == 'light' else '-j' + junctions}.npz")
    if cache and path.is_file():
        logger.info("training frames from cache %s", path)
        with np.load(path) as z:
            return z["frames"], z["labels"]
    sim = _sim_available()
    n_chunks = -(-max_frames // CHUNK_FRAMES)
    jobs = [(seed, k, tuple(input_size), sim, turn_prob, synth_share, junctions)
            for k in range(n_chunks)]
    t0 = time.perf_counter()
    w, h = input_size
    # filled chunk by chunk and permuted in place: 12000 frames are 11 GB, and a list of chunks
    # concatenated, then permuted by fancy indexing, held three copies (OOM at 24 GB)
    frames = np.empty((n_chunks * CHUNK_FRAMES, h, w, 3), np.uint8)
    labels = np.empty((n_chunks * CHUNK_FRAMES, h, w), np.uint8)
    n = 0
    if workers > 1:
        import multiprocessing

        pool = multiprocessing.get_context("spawn").Pool(workers, initializer=cv2.setNumThreads,
                                                          initargs=(1,))
        results = pool.imap(_render_chunk, jobs)
    else:
        pool, results = None, map(_render_chunk, jobs)
    try:
        for k, (f, lab) in enumerate(results):
            frames[n:n + len(f)], labels[n:n + len(f)] = f, lab
            n += len(f)
            if k % 10 == 9:
                logger.info("chunk %d: %d frames, %.0f s", k + 1, n, time.perf_counter() - t0)
            if time.perf_counter() - t0 > budget_s:
                logger.info("render budget %.0f s spent after %d chunks", budget_s, k + 1)
                break
    finally:
        if pool is not None:
            pool.terminate()
    frames, labels = frames[:min(n, max_frames)], labels[:min(n, max_frames)]
    order = np.random.default_rng(seed).permutation(len(frames))
    permute_rows(frames, order)
    permute_rows(labels, order)
    if cache:
        _save_cache(path, frames, labels)
    return frames, labels


def _save_cache(path: Path, frames: np.ndarray, labels: np.ndarray) -> None:
    """Write the rendered set to `path` whole or not at all: a full disk (a set is 5-6 GB)
    costs the next run its cache, never this run its frames or a truncated file at `path`."""
    tmp = path.with_name(path.name + ".part")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            np.savez(f, frames=frames, labels=labels)
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        logger.warning("training frames not cached (%s); going on without the cache", exc)


def permute_rows(a: np.ndarray, order: np.ndarray) -> None:
    """a[:] = a[order] in place, one row of extra memory (follows the permutation's cycles)."""
    done = np.zeros(len(order), bool)
    for start in range(len(order)):
        if done[start]:
            continue
        held, i = a[start].copy(), start
        while True:
            done[i] = True
            j = int(order[i])
            if j == start:
                a[i] = held
                break
            a[i] = a[j]
            i = j


class FrameStream:
    """Training frames rendered by `workers` processes while the model trains (a GPU would
    otherwise wait minutes for its frames, and train on fewer). Worker i renders chunks
    k = i, i + workers, ... ((seed, k) as in training_set) into files of a private folder;
    `take()` hands over the chunks that arrived since the last call, in k order. Files, not
    pipes: stopping the workers (SIGKILL) can never hang on a half-sent chunk, and the workers
    run single-threaded at low priority so the training process keeps its core. What a run has
    seen when it stops depends on the render speed, so a streamed run is reproducible in its
    recipe, not bit for bit."""

    def __init__(self, *, seed: int, input_size: tuple[int, int], max_frames: int, workers: int,
                 turn_prob: float = TURN_PROB, synth_share: float = SYNTH_SHARE,
                 junctions: tuple[str, ...] = ("light",)):
        """junctions: the towns' junction-line doses (JUNCTIONS), chunk k drawn with dose
        k mod their number (training_set's chunks for one dose)."""
        import multiprocessing

        for dose in junctions:
            check_junctions(dose)

        self._dir = Path(tempfile.mkdtemp(prefix="roadmap-stream-"))
        self._n_chunks = -(-max_frames // CHUNK_FRAMES)
        self._next = 0
        self.frames = 0
        ctx = multiprocessing.get_context("spawn")
        sim = _sim_available()
        self._procs = [ctx.Process(target=_stream_worker, daemon=True,
                                   args=(self._dir, seed, i, workers, self._n_chunks,
                                         tuple(input_size), sim, turn_prob, synth_share,
                                         tuple(junctions)))
                       for i in range(workers)]
        for proc in self._procs:
            proc.start()

    def wait(self, n_frames: int, timeout_s: float):
        """Block until n_frames have arrived (or all chunks, or timeout_s) -> take()."""
        deadline = time.monotonic() + timeout_s
        chunks = []
        while True:
            chunks += self._arrived()
            if (self.frames >= n_frames or self._next >= self._n_chunks
                    or time.monotonic() > deadline):
                break
            if not any(proc.is_alive() for proc in self._procs):
                if not (landed := self._arrived()):  # (a chunk may have landed since)
                    codes = [proc.exitcode for proc in self._procs]
                    raise RuntimeError(f"the render workers exited (codes {codes}) after "
                                       f"{self.frames} frames")
                chunks += landed
                continue
            time.sleep(0.2)
        if not chunks:
            raise RuntimeError(f"no training frames rendered in {timeout_s:.0f} s")
        return _stack(chunks)

    def take(self):
        """(frames, labels) of the chunks arrived since the last call, or None."""
        chunks = self._arrived()
        return _stack(chunks) if chunks else None

    def _arrived(self) -> list:
        """[(frames, labels)] of the chunks that landed since the last call, in k order."""
        chunks = []
        while self._next < self._n_chunks:
            path = self._dir / f"{self._next}.npz"
            if not path.is_file():
                if (self._dir / f"{self._next}.err").is_file():
                    raise RuntimeError(f"rendering chunk {self._next} failed: "
                                       + (self._dir / f"{self._next}.err").read_text())
                break
            with np.load(path) as z:
                chunks.append((z["frames"], z["labels"]))
            path.unlink()
            self._next += 1
        self.frames += sum(len(f) for f, _ in chunks)
        return chunks

    def close(self):
        import shutil

        for proc in self._procs:
            proc.kill()
        for proc in self._procs:
            proc.join(timeout=10)
        shutil.rmtree(self._dir, ignore_errors=True)


def _stack(chunks: list):
    return np.concatenate([f for f, _ in chunks]), np.concatenate([lab for _, lab in chunks])


def _stream_worker(folder: Path, seed: int, index: int, workers: int, n_chunks: int,
                   input_size, sim: bool, turn_prob: float, synth_share: float,
                   junctions: tuple[str, ...]):
    import os
    import traceback

    os.nice(10)
    cv2.setNumThreads(1)
    for k in range(index, n_chunks, workers):
        while len(list(folder.glob("*.npz"))) > 4 * workers:  # the trainer is behind: wait
            time.sleep(0.5)
        try:
            frames, labels = _render_chunk((seed, k, input_size, sim, turn_prob, synth_share,
                                            junctions[k % len(junctions)]))
        except Exception:
            (folder / f"{k}.err").write_text(traceback.format_exc())
            return
        tmp = folder / f"{k}.tmp.npz"
        np.savez(tmp, frames=frames, labels=labels)
        tmp.rename(folder / f"{k}.npz")


def _render_chunk(job):
    """CHUNK_FRAMES (frames, labels) of chunk k: one town, synth.py or the simulator."""
    seed, k, input_size, sim, turn_prob, synth_share, junctions = job
    rng = np.random.default_rng([seed, k])
    world = town_world(10_000 * (seed + 1) + k, rng, junctions)
    if sim and not is_synth_chunk(k, synth_share):
        pairs = _sim_frames(world, rng, turn_prob)
    else:
        from training.synth import render_town_frames

        pairs = render_town_frames(world, 3, CHUNK_FRAMES // 3, rng, supersample=2,
                                   curb_label=CURB_AUX, turn_prob=turn_prob)
    frames, labels = [], []
    for rgb, lab in pairs:
        frames.append(resize_image(rgb, input_size))
        labels.append(resize_labels(lab, input_size))
    return np.stack(frames), np.stack(labels)


def _sim_available() -> bool:
    try:
        from services.sim.render import FrameRenderer  # noqa: F401
    except ImportError:
        logger.warning("simulator renderer not available: training on synth frames only")
        return False
    return True


def _sim_frames(world, rng, turn_prob: float = TURN_PROB):
    """The simulator's FrameRenderer (its own random looks per renderer seed) at random poses,
    4 jittered cameras x 6 poses, with random lead / parked cars."""
    from services.sim.render import FrameRenderer
    from training.synth import random_camera, random_pose

    for _ in range(4):
        camera = random_camera(rng)
        renderer = FrameRenderer(world, camera, seed=int(rng.integers(2**31)), jumps=True)
        renderer.look.curb = rng.random() < 0.85  # raised curbs: light edges that are not paint
        renderer.look.curb_face = curb_face_gain(rng)
        for _ in range(CHUNK_FRAMES // 4):
            pose = random_pose(world, rng, turn_prob=turn_prob)
            yield renderer.render(pose, camera.T_vehicle_camera, float(rng.uniform(0, 600)),
                                  random_cars(pose, rng), curb_label=CURB_AUX)


def thinned(world, rng):
    """The world with a random share of its paint removed (labels and looks alike), so that road
    edges without edge lines, and lanes without some markings, occur as in real maps."""
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


def junction_lines(world, rng, dose: str = "light"):
    """Dashed lane lines through the towns' intersections, as real maps paint them and the
    towns (paint stops at the junction box) never do: lines that run on straight across (the
    priority road's edge and lane lines over a side road's mouth) and curved turn guides.
    Seen from an approach or a turn they cross the view like stop lines; only their dashes and
    width tell. On the held-out Karlsruhe frames such lines (thin dashes across junctions,
    thick 0.25 m dashes seen obliquely while turning) were the lane line called stop line or
    ground sign: 0.10 of that world's lane-line IoU. `dose` "light" or "heavy": JUNCTIONS
    (the heavy dashes are of kind "junction", so that `restyled` keeps their widths)."""
    from services.sim import paint

    heavy = dose == "heavy"
    if heavy:
        p_junction = rng.uniform(0.5, 1.0)
    else:
        p_junction = rng.uniform(0.3, 0.9) if rng.random() < 0.8 else 0.0
    if p_junction == 0.0:
        return world
    boxes = [m.polygon_xy_m.astype(np.float32) for m in world.markings
             if m.cls == Cls.ROAD and m.kind == "intersection"]
    ends = _line_ends(world)
    out = list(world.markings)
    for box in boxes:
        if rng.random() >= p_junction:
            continue
        centre = box.mean(axis=0)
        radius = float(np.linalg.norm(box - centre, axis=1).max())
        # (end, direction, its ray's span in the box): each ray traced once for both kinds
        near = [(p, d, _ray_span(box, p, d)) for p, d in ends
                if np.linalg.norm(p - centre) < radius + 12.0]
        width = rng.uniform(0.2, 0.3) if rng.random() < 0.5 else rng.uniform(0.10, 0.16)
        dash = rng.uniform(1.0, 3.5)
        gap = dash * rng.uniform(0.5, 2.0)
        drawn: list = []
        for path in _straight_paths(near) + _turn_paths(box, near, rng, 4 if heavy else 3):
            if any(_same_path(path, q) for q in drawn):
                continue
            drawn.append(path)
            dashes = paint.line_markings(path, "dashed", width, dash, gap, rng.uniform(0, gap))
            out += [dataclasses.replace(m, kind="junction") for m in dashes] if heavy else dashes
    return dataclasses.replace(world, markings=out)


def _line_ends(world) -> list:
    """(end point, outward unit direction) of every lane-line strip (each dash has two)."""
    ends = []
    for m in world.markings:
        if m.cls != Cls.LANE_LINE:
            continue
        half = _strip_halves(m.polygon_xy_m)
        if half is None or len(half[0]) < 2:
            continue
        c = half[0]
        for p, q in ((c[0], c[1]), (c[-1], c[-2])):
            d = p - q
            n = np.linalg.norm(d)
            if n > 1e-6:
                ends.append((p, d / n))
    return ends


def _inside(box, pts) -> np.ndarray:
    """Which points lie in the convex polygon box (an intersection's hull), either winding."""
    edge = np.roll(box, -1, axis=0) - box
    rel = pts[:, None, :] - box[None]
    cross = edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0]
    return (cross >= 0).all(axis=1) | (cross <= 0).all(axis=1)


def _ray_span(box, p, d):
    """(t_in, t_out) of the ray p + t d inside the box (sampled every 0.1 m to 40 m), or None."""
    t = np.arange(0.0, 40.0, 0.1)
    inside = _inside(box, p + t[:, None] * d)
    if not inside.any():
        return None
    k = np.flatnonzero(inside)
    return float(t[k[0]]), float(t[k[-1]])


def _straight_paths(ends) -> list:
    """A line whose ray crosses the box and meets a line on the far side running on; ends are
    (point, direction, span of its ray in the box or None)."""
    paths = []
    for p, d, span in ends:
        if span is None or span[0] > 12.0 or span[1] - span[0] < 3.0:
            continue
        for q, e, _ in ends:
            along = float(np.dot(q - p, d))
            side = abs(float(d[0] * (q - p)[1] - d[1] * (q - p)[0]))
            if float(np.dot(d, e)) < -0.97 and along > span[1] - 1.0 and side < 0.6:
                paths.append(np.stack([p + span[0] * d, p + span[1] * d]))
                break
    return paths


def _turn_paths(box, ends, rng, most: int = 3) -> list:
    """1 to `most` quadratic curves, each joining two lines that meet the box at 60-120 deg."""
    entries = []
    for p, d, span in ends:
        if span is not None and span[0] < 12.0:
            entries.append((p + span[0] * d, d))
    curves = []
    for i in range(len(entries)):
        for j in range(i + 1, len(entries)):
            (a, da), (b, db) = entries[i], entries[j]
            if abs(float(np.dot(da, db))) > 0.5:
                continue
            # the rays' crossing a + s da = b + u db, both ahead
            s, u = np.linalg.solve(np.stack([da, -db], axis=1), b - a)
            if not (1.0 < s < 25.0 and 1.0 < u < 25.0):
                continue
            w = np.linspace(0.0, 1.0, 24)[:, None]
            curve = (1 - w) ** 2 * a + 2 * (1 - w) * w * (a + s * da) + w ** 2 * b
            if _inside(box, curve).mean() > 0.8:
                curves.append(curve)
    order = rng.permutation(len(curves))[:int(rng.integers(1, most + 1))]
    return [curves[k] for k in order]


def _same_path(a, b, tol=0.6) -> bool:
    """Whether path a runs within tol of path b along all of a (either drawn twice)."""
    from services.sim import paint

    for x, y in ((a, b), (b, a)):
        s = paint.arc_length(y)
        dense = np.stack([np.interp(np.linspace(0, s[-1], 50), s, y[:, k]) for k in (0, 1)], 1)
        d = np.linalg.norm(x[::max(len(x) // 8, 1), None] - dense[None], axis=2).min(axis=1)
        if (d < tol).all():
            return True
    return False


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


def town_world(seed: int, rng, junctions: str = "light"):
    """A training town (0.6-1.5 km) with wide roads, lines through its junctions (JUNCTIONS),
    and thinned and restyled paint."""
    from services.sim.town import build_town

    check_junctions(junctions)
    world = build_town(round(rng.uniform(0.6, 1.5), 2), seed, LANE_MIX, MEDIAN_PROB)
    if junctions == "heavy":
        return thinned(restyled(junction_lines(world, rng, "heavy"), rng), rng)
    return thinned(junction_lines(restyled(world, rng), rng), rng)
