"""Localizer benchmark: per-frame latency of matching (ICP) and of the EKF, and tile decoding;
and (--world) accuracy on a simulated production drive.

    python -m services.bench.localizer --out DIR [--quick]   -> DIR/localizer.json
    python -m services.bench.localizer --out DIR --world town --km 0.5 --seed 1 [--codec raw]
        -> DIR/accuracy/localization.json: `roadmap localize` (node, real router, tiles served
        over Zenoh) on a production drive against the world's ground-truth raster coded with
        common.contours (or raw): the map the mapping fleet would build if it were perfect.

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
from services.eval.localization import localization_metrics
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
    world = straight_road()
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
    streams = synthetic_drive(rng, duration_s=8.0 if quick else 20.0)
    frames = [frame_points(cache, p, rng) for p in streams["frame_pose_true"]]
    loc = get_localizer(LocalizerConfig(), cache)
    match_ms, update_ms, predict_ms, frame_ms = [], [], [], []
    loc.icp = _Timed(loc.icp, "register", match_ms)
    ekf = loc.ekf
    update = "update_posterior" if loc.use_prior else "update_pose"  # the ICP pose's update
    loc.ekf = _Timed(_Timed(ekf, update, update_ms), "predict", predict_ms)
    t_frame = {}

    def points(i):
        t_frame["t"] = time.perf_counter()
        return frames[i]

    def done(i, est):
        frame_ms.append((time.perf_counter() - t_frame["t"]) * 1e3)

    est = replay(loc, streams, points, done)
    tracking = [
        ms for ms, e in zip(frame_ms, est, strict=False) if e.diag.get("state") == "tracking"
    ]
    m = localization_metrics(
        streams["frame_t_ns"], np.array([e.pose for e in est]), streams["frame_pose_true"]
    )
    # EKF per frame = its updates + the predictions between two frames
    predicts_per_frame = max(len(predict_ms) // max(len(frame_ms), 1), 1)
    ekf_frame = np.asarray(update_ms) + np.median(predict_ms) * predicts_per_frame
    return {
        "stages": {
            "localizer_match": _stage(match_ms[-len(tracking) :] if tracking else match_ms),
            "localizer_ekf": _stage(ekf_frame),
            "localizer_frame": _stage(tracking),
            "tile_decode": _stage(decode_ms),
        },
        "localizer": {
            "tile_fields_ms": _stage(fields_ms),
            "ekf_predict": _stage(predict_ms),
            "ekf_update": _stage(update_ms),
            "tile_kb_mean": round(float(np.mean(sizes)) / 1024, 2),
            "frames": len(frame_ms),
            "points_per_frame": LocalizerConfig().max_points,
            "synthetic_accuracy": {
                k: m[k] for k in ("x_m", "y_m", "yaw_deg", "availability_0_5m", "convergence_s")
            },
            "note": "synthetic straight road, ground-truth map coded contour/2; one core; "
            "segmentation excluded",
        },
    }


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
    """`roadmap localize` on a simulated production drive against the ground-truth map.
    gnss_bias_m: the std per axis of the consumer GNSS's slowly varying bias (production
    profile: 1.6 m); the result then also says how far off the GNSS was at the first frame.
    With `segmentation.kind="onnx"` among `sets`, the drive is rendered and the car segments
    its camera frames with the ONNX model: a perfect map, the model's errors in the car only."""
    import argparse as _ap
    import subprocess
    from dataclasses import replace

    from common import codec, keys
    from common.bus import free_tcp_port, open_session, wait_for_tcp
    from common.config import BusConfig, load_config
    from common.contours import CODEC, RAW_CODEC, encode_raw
    from common.drivelog import DriveLog
    from common.messages import Tile
    from services.localizer.node import main as localize
    from services.sim import sensors
    from services.sim.simulate import simulate_drives
    from services.sim.worlds import load_world

    w = load_world(world, 0)
    noise = None
    if gnss_bias_m is not None:
        noise = replace(sensors.PROFILES["production"], gnss_bias_m=float(gnss_bias_m))
    cfg = load_config(sets=[f'localizer.map_codec="{codec_name}"', *sets])
    logs = simulate_drives(
        w, out / "logs", profile="production", images=cfg.segmentation.kind == "onnx",
        max_km=km, seed=seed, noise=noise,
    )
    streams = DriveLog(logs[0]).streams
    first_fix = int(np.flatnonzero(streams["gnss_ok"])[0])
    t_fix = streams["gnss_t_ns"][first_fix]
    k = min(int(np.searchsorted(streams["truth_t_ns"], t_fix)), len(streams["truth_t_ns"]) - 1)
    gnss_error_m = float(np.hypot(*(streams["gnss_xy_m"][first_fix]
                                    - streams["truth_pose"][k][:2])))
    tiles = {t: (encode_tile(lab), encode_raw(lab)) for t, lab in world_tiles(w).items()}
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    router = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "router", "--listen", endpoint]
    )
    try:
        wait_for_tcp("127.0.0.1", port, 15.0)
        with open_session(BusConfig(connect=[endpoint])) as server:
            for tile, (contour, raw) in tiles.items():

                def on_query(q, tile=tile, contour=contour, raw=raw):
                    with q:
                        want_raw = dict(q.parameters).get("codec") == "raw"
                        msg = Tile(
                            tile, 1, RAW_CODEC if want_raw else CODEC, raw if want_raw else contour
                        )
                        q.reply(q.key_expr, codec.encode(msg))

                server.declare_queryable(keys.tile(*tile), on_query, complete=True)
            cfg = replace(cfg, bus=replace(cfg.bus, connect=[endpoint]))
            localize(_ap.Namespace(log=str(logs[0]), out=str(out / "accuracy"), id=None), cfg)
    finally:
        router.terminate()
        router.wait(10)
    result = json.loads((out / "accuracy" / "localization.json").read_text())
    result["gnss_error_at_start_m"] = round(gnss_error_m, 2)
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
    maps = simulate_drives(
        w,
        out / "map",
        vehicles=vehicles,
        profile="mapping",
        images=False,
        max_km=km,
        seed=seed + 100,
    )
    prod = simulate_drives(
        w, out / "prod", profile="production", images=False, max_km=km, seed=seed
    )
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    cli = [sys.executable, "-m", "services.cli"]
    one = ["--connect", ep, "--set", "grid.shards=1"]
    router = subprocess.Popen([*cli, "router", "--listen", ep])
    wait_for_tcp("127.0.0.1", port, 15.0)
    merger = subprocess.Popen(
        [*cli, "merger", "--shard", "0", "--shards", "1", "--store", str(out / "s0.sqlite"), *one]
    )
    results = {}
    try:
        for log in maps:
            subprocess.run(
                [
                    *cli,
                    "vehicle",
                    "--log",
                    str(log),
                    "--segmenter",
                    "truth",
                    "--state",
                    str(out / f"state-{log.name}"),
                    *one,
                ],
                check=True,
                timeout=1800,
            )
        time.sleep(3.0)  # merger debounce: the last tiles are recompressed
        for name in codecs:
            dest = out / f"localize-{name}"
            subprocess.run(
                [
                    *cli,
                    "localize",
                    "--log",
                    str(prod[0]),
                    "--out",
                    str(dest),
                    *one,
                    "--set",
                    f'localizer.map_codec="{name}"',
                ],
                check=True,
                timeout=1800,
            )
            results[name] = json.loads((dest / "localization.json").read_text())
    finally:
        for proc in (merger, router):
            proc.terminate()
            proc.wait(10)
    return results


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
        from services.eval.localization import summary_line

        res = fleet_accuracy(
            Path(args.out), world=args.world, km=args.km, vehicles=args.fleet, seed=args.seed
        )
        for name, acc in res.items():
            sys.stdout.write(f"{name}: {summary_line(acc)}\n")
        return 0
    if args.world:
        from services.eval.localization import summary_line

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
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "localizer.json").write_text(json.dumps(result, indent=1))
    sys.stdout.write(json.dumps(result["stages"], indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
