"""`roadmap sim` (write drive logs and print a summary) and `roadmap world render` (a world's
label map as a PNG in the paper's colours)."""

import sys
import time
from pathlib import Path

import numpy as np

from common.camera import camera_from_config
from common.drivelog import DriveLog
from common.world import render_png
from services.sim.worlds import load_world


class Progress:
    """A one-line progress bar on stderr (only when stderr is a terminal or forced)."""

    def __init__(self, label: str, stream=sys.stderr, force: bool = False):
        self.label, self.stream = label, stream
        self.enabled = force or getattr(stream, "isatty", lambda: False)()
        self.last = 0.0

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if not self.enabled or (done < total and now - self.last < 0.2):
            return
        self.last = now
        n = int(30 * done / max(total, 1))
        self.stream.write(f"\r{self.label} [{'#' * n}{'.' * (30 - n)}] {done}/{total} frames")
        if done >= total:
            self.stream.write("\n")
        self.stream.flush()


def sim_command(args, cfg) -> int:
    world = load_world(args.world, seed=args.seed)
    camera = camera_from_config(cfg.camera)
    out = Path(args.out)
    t0 = time.perf_counter()
    paths = []
    for v in range(args.vehicles):
        for d in range(args.drives):
            bar = Progress(f"{world.name} {args.profile} vehicle {v} drive {d}")
            # one (vehicle, drive) at a time so the bar follows; same seeds as a single call
            paths += _one(world, out, v, d, args, camera, bar)
    summary = summarize(paths)
    sys.stdout.write(
        f"world {world.name}: {world.km_of_road:.2f} km of road\n"
        f"{len(paths)} drive logs in {out} ({args.profile}): {summary['km']:.2f} km driven, "
        f"{summary['frames']} frames, GNSS outages {summary['outages']} "
        f"({summary['outage_s']:.0f} s), {time.perf_counter() - t0:.1f} s\n"
    )
    return 0


def _one(world, out, v, d, args, camera, bar):
    """Drive (v, d) exactly as simulate_drives(vehicles, drives) would, alone."""
    from services.sim import simulate

    return [
        simulate._drive_one(
            world,
            out,
            v=v,
            d=d,
            vehicles=args.vehicles,
            profile=args.profile,
            seed=args.seed,
            images=not args.no_images,
            max_km=args.max_km,
            route=None,
            camera=camera,
            progress=bar,
        )
    ]


def summarize(paths) -> dict:
    """km driven, frames, GNSS outages (count of contiguous outage spans) over drive logs."""
    km, frames, outages, outage_s = 0.0, 0, 0, 0.0
    for p in paths:
        s = DriveLog(p).streams
        pose = s["truth_pose"] if "truth_pose" in s else s["frame_pose_true"]
        km += float(np.sum(np.linalg.norm(np.diff(pose[:, :2], axis=0), axis=1))) / 1000.0
        frames += len(s["frame_t_ns"])
        bad = ~s["gnss_ok"].astype(bool)
        outages += int(np.sum(bad[1:] & ~bad[:-1]) + (1 if len(bad) and bad[0] else 0))
        if bad.any() and len(s["gnss_t_ns"]) > 1:
            dt = float(np.median(np.diff(s["gnss_t_ns"]))) / 1e9
            outage_s += float(bad.sum()) * dt
    return {"km": km, "frames": frames, "outages": outages, "outage_s": outage_s}


def world_command(args, cfg) -> int:
    world = load_world(args.world, seed=args.seed)
    x0, y0, x1, y1 = world.bounds()
    # 0.1 m cells; big worlds at 0.2 m (the PNG is shrunk to 4000 px anyway, paint max-pooled)
    cell_m = 0.1 if max(x1 - x0, y1 - y0) <= 1500.0 else 0.2
    labels, x0, y0 = world.rasterize_all(cell_m=cell_m)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    render_png(labels, args.out)
    sys.stdout.write(
        f"world {world.name}: {world.km_of_road:.2f} km of road, {len(world.markings)} polygons, "
        f"{labels.shape[1] * cell_m:.0f} x {labels.shape[0] * cell_m:.0f} m at {cell_m} m "
        f"from ({x0:.1f}, {y0:.1f}) -> {args.out}\n"
    )
    return 0
