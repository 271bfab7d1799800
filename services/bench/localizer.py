"""Localizer benchmark: per-frame latency of matching (ICP) and of the EKF, and tile decoding;
and (--world) accuracy on a simulated production drive.

    python -m services.bench.localizer --out DIR [--quick]   -> DIR/localizer.json
    python -m services.bench.localizer --out DIR --world town --km 0.5 --seed 1 [--codec raw]
        -> DIR/accuracy/localization.json: `roadmap localize` (node, real router, tiles served
        over Zenoh) on a production drive against the world's ground-truth raster coded with
        common.contours (or raw): the map the mapping fleet would build if it were perfect; the
        accuracy of its outputs computed by the evaluation harness (services/eval).

A seeded synthetic production drive along a two-lane road with stop lines, crosswalks and arrows
(services/localizer/synthetic.py): the map is the ground-truth raster coded with common.contours
(contour/2) and decoded as the localizer does; the frame points come from the decoded map seen at
the true pose with noise and outliers (segmentation excluded). Timings on one core, in-process."""

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

from common.config import LocalizerConfig
from common.contours import decode_tile, encode_tile
from services.bench.runner import write_result
from services.eval.localization import evaluate_localizer, localization_metrics, summary_line
from services.localizer.localizer import get_localizer, replay
from services.localizer.map_cache import TileCache
from services.localizer.synthetic import frame_points, straight_road, synthetic_drive, world_tiles

logger = logging.getLogger("bench.localizer")


class _Timed:
    """Proxy that records the wall time of one method of a component."""

    def __init__(self, target, method: str, sink: list):
        self._target, self._method, self._sink = target, method, sink

    def __getattr__(self, name):
        attr = getattr(self._target, name)
        if name != self._method:
            return attr

        def timed(*a, **kw):
            t0 = time.perf_counter()
            try:
                return attr(*a, **kw)
            finally:
                self._sink.append((time.perf_counter() - t0) * 1e3)

        return timed


def _stage(ms: list[float]) -> dict:
    a = np.asarray(ms, dtype=float)
    p50 = float(np.percentile(a, 50))
    return {
        "p50_ms": round(p50, 3),
        "p95_ms": round(float(np.percentile(a, 95)), 3),
        "per_s": round(1e3 / p50, 1) if p50 > 0 else None,
        "n": int(len(a)),
    }


def run(quick: bool = False) -> dict:
    rng = np.random.default_rng(0)
    cache, decode_ms, sizes, fields_ms = _decoded_map(straight_road())
    streams = synthetic_drive(rng, duration_s=8.0 if quick else 20.0)
    frames = [frame_points(cache, p, rng) for p in streams["frame_pose_true"]]
    t = _timed_replay(get_localizer(LocalizerConfig(), cache), streams, frames)
    m = localization_metrics(
        streams["frame_t_ns"], np.array([e.pose for e in t["est"]]), streams["frame_pose_true"]
    )
    # EKF per frame = its updates + the predictions between two frames
    predicts_per_frame = max(len(t["predict"]) // max(len(t["frame"]), 1), 1)
    ekf_frame = np.asarray(t["update"]) + np.median(t["predict"]) * predicts_per_frame
    tracking, match_ms = t["tracking"], t["match"]
    return {
        "stages": {
            "localizer_match": _stage(match_ms[-len(tracking) :] if tracking else match_ms),
            "localizer_ekf": _stage(ekf_frame),
            "localizer_frame": _stage(tracking),
            "tile_decode": _stage(decode_ms),
        },
        "localizer": {
            "tile_fields_ms": _stage(fields_ms),
            "ekf_predict": _stage(t["predict"]),
            "ekf_update": _stage(t["update"]),
            "tile_kb_mean": round(float(np.mean(sizes)) / 1024, 2),
            "frames": len(t["frame"]),
            "points_per_frame": LocalizerConfig().max_points,
            "synthetic_accuracy": {
                k: m[k] for k in ("x_m", "y_m", "yaw_deg", "availability_0_5m", "convergence_s")
            },
            "note": "synthetic straight road, ground-truth map coded contour/2; one core; "
            "segmentation excluded",
        },
    }


def _decoded_map(world):
    """The world's tiles coded contour/2 and decoded into a cache: (cache, decode ms, coded
    sizes, ms to build each tile's matching fields)."""
    cache = TileCache(capacity=30)
    decode_ms, sizes = [], []
    for tile, labels in world_tiles(world).items():
        data = encode_tile(labels)
        t0 = time.perf_counter()
        decoded = decode_tile(data)
        decode_ms.append((time.perf_counter() - t0) * 1e3)
        sizes.append(len(data))
        cache.put(tile, 1, decoded)
    fields_ms = []
    for tile in cache.tiles():
        t0 = time.perf_counter()
        cache.fields(tile)
        fields_ms.append((time.perf_counter() - t0) * 1e3)
    return cache, decode_ms, sizes, fields_ms


def _timed_replay(loc, streams: dict, frames: list) -> dict:
    """Replay the drive with ICP, EKF update and predict timed: {est, match, update, predict,
    frame, tracking} (ms lists; tracking: the frame times of tracking frames)."""
    t = {"match": [], "update": [], "predict": [], "frame": []}
    loc.icp = _Timed(loc.icp, "register", t["match"])
    ekf = loc.ekf
    loc.ekf = _Timed(_Timed(ekf, "update_posterior", t["update"]), "predict", t["predict"])
    t_frame = {}

    def points(i):
        t_frame["t"] = time.perf_counter()
        return frames[i]

    def done(i, est):
        t["frame"].append((time.perf_counter() - t_frame["t"]) * 1e3)

    t["est"] = replay(loc, streams, points, done)
    t["tracking"] = [
        ms for ms, e in zip(t["frame"], t["est"], strict=False)
        if e.diag.get("state") == "tracking"
    ]
    return t


def sim_accuracy(
    out: Path,
    *,
    world: str = "town",
    km: float = 0.5,
    seed: int = 1,
    codec_name: str = "contour",
    sets: tuple = (),
    gnss_bias_m: float | None = None,
) -> dict:
    """`roadmap localize` on a simulated production drive against the ground-truth map;
    writes out/accuracy/localization.json (the harness's localization section).
    gnss_bias_m: the std per axis of the consumer GNSS's slowly varying bias (production
    profile: 1.6 m); the result then also says how far off the GNSS was at the first frame.
    With `segmentation.kind="onnx"` among `sets`, the drive is rendered and the car segments
    its camera frames with the ONNX model: a perfect map, the model's errors in the car only."""
    from common.config import load_config
    from services.sim.worlds import load_world

    w = load_world(world, 0)
    cfg = load_config(sets=[f'localizer.map_codec="{codec_name}"', *sets])
    log = _production_drive(w, out / "logs", cfg, km=km, seed=seed, gnss_bias_m=gnss_bias_m)
    _localize_on_world_map(w, log, out / "accuracy", cfg)
    result = write_localization(out / "accuracy", log)
    result["gnss_error_at_start_m"] = round(gnss_error_at_start(log), 2)
    return result


def _production_drive(w, out: Path, cfg, *, km: float, seed: int,
                      gnss_bias_m: float | None) -> Path:
    """One simulated production drive (rendered when the car runs the ONNX model)."""
    from dataclasses import replace

    from services.sim import sensors
    from services.sim.simulate import simulate_drives

    noise = None
    if gnss_bias_m is not None:
        noise = replace(sensors.PROFILES["production"], gnss_bias_m=float(gnss_bias_m))
    logs = simulate_drives(
        w, out, profile="production", images=cfg.segmentation.kind == "onnx",
        max_km=km, seed=seed, noise=noise,
    )
    return logs[0]


def gnss_error_at_start(log_path: Path) -> float:
    """How far (m) the first good GNSS fix of a drive is from the true position then."""
    from common.drivelog import DriveLog

    streams = DriveLog(log_path).streams
    first_fix = int(np.flatnonzero(streams["gnss_ok"])[0])
    t_fix = streams["gnss_t_ns"][first_fix]
    k = min(int(np.searchsorted(streams["truth_t_ns"], t_fix)), len(streams["truth_t_ns"]) - 1)
    return float(np.hypot(*(streams["gnss_xy_m"][first_fix] - streams["truth_pose"][k][:2])))


def _localize_on_world_map(w, log: Path, out: Path, cfg) -> None:
    """`roadmap localize` (in process) through a local router, every tile of the world's
    ground-truth raster served on its key (contour/2, or raw/1 on ?codec=raw)."""
    import argparse as _ap
    import subprocess
    from dataclasses import replace

    from common.bus import free_tcp_port, open_session, wait_for_tcp
    from common.config import BusConfig
    from services.localizer.node import main as localize

    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    router = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "router", "--listen", endpoint]
    )
    try:
        wait_for_tcp("127.0.0.1", port, 15.0)
        with open_session(BusConfig(connect=[endpoint])) as server:
            _serve_tiles(server, w)
            cfg = replace(cfg, bus=replace(cfg.bus, connect=[endpoint]))
            localize(_ap.Namespace(log=str(log), out=str(out), id=None), cfg)
    finally:
        router.terminate()
        router.wait(10)


def _serve_tiles(server, w) -> None:
    """One complete queryable per tile of the world, as a merger shard serves its tiles."""
    from common import codec, keys
    from common.contours import CODEC, RAW_CODEC, encode_raw
    from common.messages import Tile

    tiles = {t: (encode_tile(lab), encode_raw(lab)) for t, lab in world_tiles(w).items()}
    for tile, (contour, raw) in tiles.items():

        def on_query(q, tile=tile, contour=contour, raw=raw):
            with q:
                want_raw = dict(q.parameters).get("codec") == "raw"
                msg = Tile(
                    tile, 1, RAW_CODEC if want_raw else CODEC, raw if want_raw else contour
                )
                q.reply(q.key_expr, codec.encode(msg))

        server.declare_queryable(keys.tile(*tile), on_query, complete=True)


def write_localization(out: Path, log: Path) -> dict:
    """The localization section of `roadmap localize --out OUT` on the drive `log`, as the
    evaluation harness computes it; also written to OUT/localization.json."""
    from common.drivelog import DriveLog

    result = evaluate_localizer(out, DriveLog(log))
    (out / "localization.json").write_text(json.dumps(result, indent=1))
    return result


def fleet_accuracy(
    out: Path,
    *,
    world: str = "town",
    km: float = 0.5,
    vehicles: int = 4,
    seed: int = 1,
    codecs: tuple = ("contour", "raw"),
) -> dict:
    """The whole chain as processes: router, merger shard, `roadmap vehicle` per mapping drive
    (ground-truth segmenter), then `roadmap localize` on a production drive per map codec."""
    import subprocess

    from common.bus import free_tcp_port, wait_for_tcp
    from services.sim.simulate import simulate_drives
    from services.sim.worlds import load_world

    w = load_world(world, 0)
    maps = simulate_drives(w, out / "map", vehicles=vehicles, profile="mapping", images=False,
                           max_km=km, seed=seed + 100)
    prod = simulate_drives(
        w, out / "prod", profile="production", images=False, max_km=km, seed=seed
    )
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    router = subprocess.Popen([*_CLI, "router", "--listen", ep])
    wait_for_tcp("127.0.0.1", port, 15.0)
    merger = subprocess.Popen([*_CLI, "merger", "--shard", "0", "--shards", "1", "--store",
                               str(out / "s0.sqlite"), *_one_shard(ep)])
    try:
        _map_with_vehicles(maps, out, ep)
        time.sleep(3.0)  # merger debounce: the last tiles are recompressed
        return {name: _localize_fleet_map(prod[0], out / f"localize-{name}", ep, name)
                for name in codecs}
    finally:
        for proc in (merger, router):
            proc.terminate()
            proc.wait(10)


_CLI = [sys.executable, "-m", "services.cli"]


def _one_shard(endpoint: str) -> list[str]:
    return ["--connect", endpoint, "--set", "grid.shards=1"]


def _map_with_vehicles(logs: list[Path], out: Path, endpoint: str) -> None:
    """`roadmap vehicle` (ground-truth segmenter) on each mapping drive, one after the other."""
    import subprocess

    for log in logs:
        subprocess.run(
            [*_CLI, "vehicle", "--log", str(log), "--segmenter", "truth", "--state",
             str(out / f"state-{log.name}"), *_one_shard(endpoint)],
            check=True,
            timeout=1800,
        )


def _localize_fleet_map(log: Path, dest: Path, endpoint: str, codec_name: str) -> dict:
    """`roadmap localize` on the fleet's map with one codec; the harness's section."""
    import subprocess

    subprocess.run(
        [*_CLI, "localize", "--log", str(log), "--out", str(dest), *_one_shard(endpoint),
         "--set", f'localizer.map_codec="{codec_name}"'],
        check=True,
        timeout=1800,
    )
    return write_localization(dest, log)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--world", default=None, help="accuracy run on this world (e.g. town)")
    parser.add_argument("--km", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--codec", choices=["contour", "raw"], default="contour")
    parser.add_argument("--set", action="append", default=[], help="localizer.KEY=VALUE")
    parser.add_argument("--gnss-bias-m", type=float, default=None,
                        help="consumer GNSS bias std per axis (production profile: 1.6)")
    parser.add_argument(
        "--fleet",
        type=int,
        default=0,
        help="with --world: map with this many mapping vehicles first (real "
        "merger and vehicle processes), then localize against that map",
    )
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO)
    if args.world and args.fleet:
        res = fleet_accuracy(
            Path(args.out), world=args.world, km=args.km, vehicles=args.fleet, seed=args.seed
        )
        for name, acc in res.items():
            sys.stdout.write(f"{name}: {summary_line(acc)}\n")
        return 0
    if args.world:
        acc = sim_accuracy(
            Path(args.out),
            world=args.world,
            km=args.km,
            seed=args.seed,
            codec_name=args.codec,
            sets=tuple(args.set),
            gnss_bias_m=args.gnss_bias_m,
        )
        off = acc["gnss_error_at_start_m"]
        sys.stdout.write(f"{summary_line(acc)}, GNSS {off} m off at start\n")
        return 0
    result = {"cores_used": 1, "cpu_count": os.cpu_count(), **run(args.quick)}
    write_result(args.out, "localizer.json", result, result["stages"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
