"""Replay a stored drive's car through the localizer core, offline: no router, no fleet, no
rendering. The map is every tile the car received in that run (its localizer/tiles.npz, latest
versions), the frames are the production log's labels segmented and lifted as the node does
(cached once per drive in CACHE, replay.cache_file, least recently used evicted past
CACHE_BYTES), and the result is scored as the suite scores a
drive (services/eval/score.py). Minutes per 1 km drive instead of the demo's ten or more: the
loop to iterate the localizer on, paired by drive.

    python -m services.eval.replay DIR [DIR ...] [--set localizer.KEY=VALUE ...] [--out FILE]

DIR: a suite drive folder (DIR/drives/production/<log>, DIR/localizer/tiles.npz); each drive's
figures go to stdout (one line) and, with --out, to FILE as JSON.

The frame cache: ROADMAP_REPLAY_CACHE (default /tmp/roadmap-replay), at most
ROADMAP_REPLAY_CACHE_GB (default 8) GiB; a town drive's frames take 0.3-0.4 GiB."""

import argparse
import hashlib
import json
import logging
import os
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

from common.config import RoiConfig, SegmentationConfig, load_config, with_sections
from common.contours import decode_tile, encode_tile
from common.drivelog import DriveLog
from common.grid import TILE_CELLS, tile_origin_m
from services.eval.run import drive_world
from services.eval.score import markings_in_view, score_frames
from services.localizer.localizer import get_localizer, replay
from services.localizer.map_cache import get_tile_cache
from services.localizer.outputs import read_tiles
from services.localizer.tiles import decode_tile_message

logger = logging.getLogger(__name__)

CACHE = Path(os.environ.get("ROADMAP_REPLAY_CACHE", "/tmp/roadmap-replay"))
# unbounded, the cache of every run ever re-localized filled this machine's disk (41 GB)
CACHE_BYTES = int(float(os.environ.get("ROADMAP_REPLAY_CACHE_GB", "8")) * 2**30)
STALE_PART_S = 3600.0  # a .part file this old is a crashed writer's, not one being written
# what replay_drive says of the run itself, beside the drive's score
RUN_KEYS = ("drive", "inits", "cpu_s", "ok_frames")


def stored_config(drive_dir: Path, sets: list[str], role: str = "localizer"):
    """Today's defaults with the run's segmentation and ROI (what made its frames), then sets.
    Keys that no longer exist are left out. `role`: whose config file ("localizer": the car's
    localizer/config.toml; "fleet": the run's config.toml, the mapping vehicles')."""
    path = drive_dir / ("config.toml" if role == "fleet" else f"{role}/config.toml")
    with open(path, "rb") as f:
        old = tomllib.load(f)
    fields = {"segmentation": SegmentationConfig.__dataclass_fields__,
              "roi": RoiConfig.__dataclass_fields__}
    kept = {name: {k: v for k, v in old.get(name, {}).items() if k in known}
            for name, known in fields.items()}
    return load_config(sets=sets, base=with_sections(load_config(), kept))


def frame_points(log: DriveLog, cfg, cache_path: Path):
    """Per frame (points_v, classes, jacobians) as the node makes them; cached."""
    try:
        with np.load(cache_path) as z:  # each z[key] reads the whole array: once each
            pts, cls, jac, off, in_view = (z[k] for k in ("pts", "cls", "jac", "offsets",
                                                         "in_view"))
        os.utime(cache_path)  # used now: the last to be evicted
        return [(pts[a:b], cls[a:b], jac[a:b])
                for a, b in zip(off[:-1], off[1:], strict=True)], in_view
    except FileNotFoundError:  # never made, or evicted by another run since
        pass
    from services.localizer.node import _FrameSource

    src = _FrameSource(log, cfg)
    frames = [src.points(i) for i in range(len(log))]
    in_view = markings_in_view(log, cfg.roi)
    cache_path.parent.mkdir(parents=True, exist_ok=True)
    part = cache_path.with_name(cache_path.stem + ".part.npz")  # whole or absent
    np.savez(part, pts=np.concatenate([f[0] for f in frames]),
             cls=np.concatenate([f[1] for f in frames]),
             jac=np.concatenate([f[2] for f in frames]),
             offsets=np.cumsum([0] + [len(f[0]) for f in frames]), in_view=in_view)
    part.replace(cache_path)
    evict(cache_path.parent, CACHE_BYTES, keep=cache_path)
    return frames, in_view


def evict(folder: Path, budget: int, keep: Path, now: float | None = None) -> list[Path]:
    """Delete the least recently used cache files (oldest mtime first; a hit touches its file)
    until the folder's files fit `budget` bytes; never `keep`, nor another writer's fresh
    .part file. Files another process removes meanwhile are skipped. Returns those deleted."""
    now = time.time() if now is None else now
    files = []
    for path in folder.glob("*.npz"):
        try:
            st = path.stat()
        except FileNotFoundError:
            continue
        files.append((st.st_mtime, st.st_size, path))
    total = sum(size for _, size, _ in files)
    gone = []
    for mtime, size, path in sorted(files):
        if total <= budget:
            break
        writing = path.name.endswith(".part.npz") and now - mtime < STALE_PART_S
        if path == keep or writing:
            continue
        path.unlink(missing_ok=True)
        total -= size
        gone.append(path)
    if gone:
        logger.info("replay cache: evicted %d least recently used file(s) to stay under "
                    "%.1f GiB", len(gone), budget / 2**30)
    return gone


def cache_file(drive_dir: Path) -> Path:
    """CACHE/<drive>-<hash of its path>.npz: two runs' drives of one name never share frames."""
    key = hashlib.blake2b(str(Path(drive_dir).resolve()).encode(), digest_size=6).hexdigest()
    return CACHE / f"{Path(drive_dir).name}-{key}.npz"


def received_map(drive_dir: Path, lc, truth: bool = False):
    """A TileCache holding every tile the car received in the run, in its latest version; or,
    `truth`, the world's true labels of those tiles through the tile codec (an oracle map: what
    the car's figures owe to the fleet's map, and what to its own matching and filter)."""
    received = read_tiles(drive_dir / "localizer" / "tiles.npz")
    cache = get_tile_cache(lc)
    cache.capacity = max(cache.capacity, len(received) + 1)
    world = drive_world(drive_dir) if truth else None
    for _, msg in received:
        labels = (decode_tile(encode_tile(world.rasterize(*tile_origin_m(msg.tile), TILE_CELLS,
                                                          TILE_CELLS)))
                  if truth else decode_tile_message(msg))
        cache.put(msg.tile, msg.version, labels)
    return cache


def replay_drive(drive_dir: Path, sets: list[str], keep_errors: bool = False,
                 truth_map: bool = False) -> dict:
    """The suite's score of the stored drive re-localized with today's localizer (+ sets);
    keep_errors: with the per-frame errors (`errors_m`, for the suite's figure); truth_map: on
    the world's true markings instead of the map the car received (received_map)."""
    drive_dir = Path(drive_dir)
    cfg = stored_config(drive_dir, sets)
    (prod,) = sorted((drive_dir / "drives" / "production").iterdir())
    log = DriveLog(prod)
    frames, in_view = frame_points(log, cfg, cache_file(drive_dir))
    loc = get_localizer(cfg.localizer, received_map(drive_dir, cfg.localizer, truth_map),
                        camera=log.meta.camera)
    t0 = time.process_time()
    est = replay(loc, log.streams, lambda i: _pick(frames[i], cfg.localizer.attitude_roll))
    cpu_s = time.process_time() - t0
    poses = np.array([e.pose for e in est]).reshape(-1, 3)
    ok = np.array([bool(e.ok) for e in est])
    score = score_frames(log.streams["frame_t_ns"], poses, ok,
                         log.streams["frame_pose_true"], in_view)
    if not keep_errors:
        score.pop("errors_m")
    run = dict(zip(RUN_KEYS, (drive_dir.name, loc.inits, round(cpu_s, 1), int(ok.sum())),
                   strict=True))
    return {**run, **score}


def _pick(frame, roll: bool):
    pts, cls, jac = frame
    return pts, cls, (jac if roll else jac[:, :, :1])


def line(r: dict) -> str:
    m = r["markings_in_view"]

    def mean(k):
        v = m[k]["mean"]
        return "-" if v is None else f"{v:.3f}"

    conv, avail = r["convergence_s"], m["availability_0_5m"]
    return (f"{r['drive']}: x {mean('x_m')} y {mean('y_m')} yaw {mean('yaw_deg')} "
            f"avail {'-' if avail is None else round(avail, 3)} "
            f"conv {'-' if conv is None else round(conv, 1)} s viol {r['integrity_violations']} "
            f"ok {r['ok_frames']}/{r['frames']} inits {r['inits']} cpu {r['cpu_s']} s")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("drives", nargs="+")
    p.add_argument("--set", action="append", default=[])
    p.add_argument("--out")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    results = []
    for d in args.drives:
        results.append(replay_drive(Path(d), args.set))
        sys.stdout.write(line(results[-1]) + "\n")
        sys.stdout.flush()
    if args.out:
        Path(args.out).write_text(json.dumps({"sets": args.set, "drives": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
