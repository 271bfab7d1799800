"""Benchmark of the simulator's camera renderer: ms per 640 x 360 frame (RGB + labels, and labels
only) along a town drive and (RGB + labels) at random poses, as the model's frames are rendered,
plus label-only simulation speed (training/bench/render_chunks.py times the lab's training
chunks). Writes JSON. Wall-clock and CPU-time
percentiles are both reported (on a shared, loaded machine CPU time is the steadier one).

    python -m services.bench.render [--out bench_render.json] [--frames 200] [--world town]
"""

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from common.camera import camera_from_config
from common.config import CameraConfig
from services.sim import motion, sensors
from services.sim.poses import random_pose
from services.sim.render import FrameRenderer
from services.sim.simulate import _other_vehicles, simulate_drives
from services.sim.worlds import load_world

# a share of random poses turned off the route, as training frames are (training/data.py
# TURN_PROB): rendering them costs what a route's pose costs
RANDOM_TURN_PROB = 0.2


def _stats(ms: list[float]) -> dict:
    a = np.array(ms)
    return {
        "p50_ms": round(float(np.percentile(a, 50)), 2),
        "p95_ms": round(float(np.percentile(a, 95)), 2),
        "frames": len(a),
    }


def run(quick: bool = False, frames: int | None = None, world_spec: str = "town",
        sim_km: float | None = None) -> dict:
    """Renderer timings (ms per frame, wall and CPU) and label-only simulation speed."""
    frames = frames or (40 if quick else 200)
    sim_km = sim_km if sim_km is not None else (0.3 if quick else 2.0)
    world = load_world(world_spec, seed=0)
    camera = camera_from_config(CameraConfig())
    rng = np.random.default_rng(0)
    drive_ms = _drive_frames(world, camera, rng, frames)
    jump_ms, jump_cpu = _random_pose_frames(world, camera, rng, max(frames // 5, 10))
    return {
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "world": world.name,
        "size": [camera.width, camera.height],
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "render_rgb_and_labels": _stats(drive_ms["rgb"]),
        "render_labels_only": _stats(drive_ms["lab"]),
        "render_random_poses": _stats(jump_ms),
        "cpu_time": {
            "render_rgb_and_labels": _stats(drive_ms["rgb_cpu"]),
            "render_labels_only": _stats(drive_ms["lab_cpu"]),
            "render_random_poses": _stats(jump_cpu),
        },
        "label_only_sim": _label_only_sim(world, sim_km),
    }


def _drive_frames(world, camera, rng, frames: int) -> dict[str, list[float]]:
    """ms per frame along a drive (wall and CPU; RGB + labels, and labels alone), after a
    10-frame warm-up (tile cache, first window)."""
    traj = motion.drive(world.routes[0], rng)
    t = np.arange(0.0, traj.duration_s, 0.1)[: frames + 10]
    poses = traj.poses(t)
    others = _other_vehicles(traj, rng)
    shake = sensors.vibration(len(t), sensors.PROFILES["mapping"], rng)
    renderer = FrameRenderer(world, camera, seed=0)
    ms = {"rgb": [], "lab": [], "rgb_cpu": [], "lab_cpu": []}
    for i, (ti, pose) in enumerate(zip(t, poses, strict=False)):
        T = camera.perturbed(shake[i, 0], shake[i, 1]).T_vehicle_camera
        c0, t0 = time.process_time(), time.perf_counter()
        renderer.render(pose, T, float(ti), others(ti))
        c1, t1 = time.process_time(), time.perf_counter()
        renderer.labels(pose, T, others(ti))
        c2, t2 = time.process_time(), time.perf_counter()
        if i >= 10:
            ms["rgb"].append(1000 * (t1 - t0))
            ms["lab"].append(1000 * (t2 - t1))
            ms["rgb_cpu"].append(1000 * (c1 - c0))
            ms["lab_cpu"].append(1000 * (c2 - c1))
    return ms


def _random_pose_frames(world, camera, rng, n: int) -> tuple[list[float], list[float]]:
    """ms per frame (wall, CPU) of frames away from a drive (the segmentation model's): each
    at a random pose, so each in a label window of its own, whose surface masks the renderer
    computes for the frame's box of it (jumps)."""
    jumper = FrameRenderer(world, camera, seed=0, jumps=True)
    jump_ms, jump_cpu = [], []
    for i in range(n):
        pose = random_pose(world, rng, turn_prob=RANDOM_TURN_PROB)
        c0, t0 = time.process_time(), time.perf_counter()
        jumper.render(pose, camera.T_vehicle_camera, float(i))
        jump_ms.append(1000 * (time.perf_counter() - t0))
        jump_cpu.append(1000 * (time.process_time() - c0))
    return jump_ms, jump_cpu


def _label_only_sim(world, sim_km: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        path = simulate_drives(world, tmp, images=False, max_km=sim_km)[0]
        sim_s = time.perf_counter() - t0
        n_frames = len(list((Path(path) / "labels").glob("*.png")))
    return {"km": sim_km, "frames": n_frames, "wall_s": round(sim_s, 2),
            "frames_per_s": round(n_frames / sim_s, 1)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench_render.json")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--world", default="town")
    ap.add_argument("--sim-km", type=float, default=2.0, help="label-only drive length")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    report = run(args.quick, args.frames if not args.quick else None, args.world,
                 args.sim_km if not args.quick else None)
    Path(args.out).write_text(json.dumps(report, indent=1))
    sys.stdout.write(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
