"""Upload benchmark (issue #68): what the mapping fleet sends per km driven and what the shard
spends to ingest it, for the cells and the sparse patch form (vehicle.patch_form), on the same
simulated drives in the same run; and the maps both merge to, against the world's truth and
against each other.

    python -m services.bench.upload --out DIR [--quick]          -> DIR/upload.json
    python -m services.bench.upload pair --out DIR --seeds 0 1 2 [--world town] [--demo-arg A]
        `roadmap demo` per seed with each form, one run at a time -> DIR/pair.json: per seed
        both reports' map precision/recall per class and localization x/y/yaw means, the
        differences (sparse - cells), their median and worst
    python -m services.bench.upload pair --out DIR --reports CELLS.json:SPARSE.json ...
        the same from finished runs' report.json files

Drives: the simulator's mapping drives (truth segmenter with its corruption, as the demo runs
them) of the default world (Karlsruhe when ../shared/data holds it, else the town; --quick:
town:1, shorter drives), mapped in-process with each form's configuration (cells: seal every
vehicle.seal_every_frames; sparse: every vehicle.sparse_seal_every_frames). Upload: one
request per seal and owner shard (at most vehicle.upload_batch patches), encoded as the
uploader does. Ingest CPU: process time of a DurableShard (SQLite, synchronous OFF) taking
those requests (decode, expand, store, apply), best of `repeats`; flush CPU: the labels and
tile compression after them."""

import argparse
import json
import logging
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from common import codec
from common.config import load_config
from common.drivelog import DriveLog
from common.evaluation import per_class_precision_recall
from common.grid import owner_of_tile
from common.messages import batch_of
from services.bench.runner import write_result
from services.merger.durable import DurableShard
from services.merger.shard import MergerShard
from services.merger.store import ShardStore

logger = logging.getLogger("bench.upload")

FORMS = ("cells", "sparse")
MAP_METRICS = ("precision", "recall")
LOC_METRICS = ("x_m", "y_m", "yaw_deg")


# -- drives and their patches -----------------------------------------------------------------


def simulate(out: Path, quick: bool) -> tuple[object, list[Path]]:
    from services.sim.simulate import simulate_drives
    from services.sim.worlds import load_world

    world = load_world("town:1" if quick else None, seed=0)
    logs = simulate_drives(world, out, vehicles=2 if quick else 3, profile="mapping", seed=0,
                           images=False, max_km=0.15 if quick else 0.4)
    return world, logs


def map_drives(logs: list[Path], form: str) -> tuple[list[list], object]:
    """Per drive its seals (lists of patches in `form`), and the config they were made with."""
    from services.vehicle.node import StageTimer, build_mapper, map_log

    cfg = load_config(env={}, sets=["segmentation.kind=truth", f"vehicle.patch_form={form}"])
    drives = []
    for path in logs:
        log = DriveLog(path)
        mapper = build_mapper(log, log.meta.vehicle, cfg)
        seals: list[list] = []
        map_log(log, mapper, _collect(seals), threading.Event(), StageTimer())
        drives.append(seals)
    return drives, cfg


def _collect(seals: list):
    return lambda patches: seals.append(list(patches)) if patches else None


def requests(drives: list[list], cfg) -> list[bytes]:
    """The uploader's ingest payloads: per seal and owner shard, upload_batch patches each."""
    out = []
    for seals in drives:
        for seal in seals:
            by_shard = defaultdict(list)
            for p in seal:
                by_shard[owner_of_tile(p.tile, cfg.grid.shards, cfg.grid.shard_map)].append(p)
            for patches in by_shard.values():
                n = cfg.vehicle.upload_batch
                out += [codec.encode(batch_of(patches[k:k + n]))
                        for k in range(0, len(patches), n)]
    return out


# -- shard cost and maps ------------------------------------------------------------------------


def ingest(payloads: list[bytes], repeats: int) -> dict:
    """Best-of-repeats process CPU of a fresh durable shard ingesting `payloads` (one request
    each, as they arrive), then of its flush; and the merged shard of the last repeat."""
    best_ingest = best_flush = float("inf")
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as tmp:
            durable = DurableShard(MergerShard(max_batch_patches=1 << 16),
                                   ShardStore(Path(tmp) / "s.sqlite", synchronous="OFF"),
                                   ident="bench")
            c0 = time.process_time()
            for payload in payloads:
                ack = durable.ingest(payload)
                if ack.error:
                    raise RuntimeError(f"the shard refused a batch: {ack.error}")
            c1 = time.process_time()
            durable.flush()
            c2 = time.process_time()
            durable.store.close()
        best_ingest, best_flush = min(best_ingest, c1 - c0), min(best_flush, c2 - c1)
    return {"ingest_cpu_s": best_ingest, "flush_cpu_s": best_flush, "shard": durable.shard}


def mosaic(shard: MergerShard, tiles) -> np.ndarray:
    return np.concatenate([shard.labels(t) if t in shard.tiles_state else
                           np.zeros((512, 512), np.uint8) for t in tiles], axis=1)


def map_quality(shard: MergerShard, world, logs, cfg) -> dict:
    """Per marking class, precision and recall of the merged map against the world's truth
    (recall inside the part of the ROI the drives' cameras saw), as the demo's report computes
    them."""
    from services.demo.report import observed_area
    from services.eval import map as ev

    tiles = shard.tiles()
    m = ev.Mosaic(tiles)
    raw = m.paste(tiles, [shard.labels(t) for t in tiles])
    truth = ev.truth_mosaic(world, m, tiles)
    observed = observed_area(cfg, m, logs)
    q = ev.map_quality(raw, truth, observed)
    return {k: {n: v[n] for n in MAP_METRICS} for k, v in q.items()}


def km_driven(logs) -> float:
    km = 0.0
    for p in logs:
        xy = DriveLog(p).streams["frame_pose_true"][:, :2]
        km += float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()) / 1000.0
    return km


def _rounded(d):
    if isinstance(d, dict):
        return {k: _rounded(v) for k, v in d.items()}
    if isinstance(d, float):
        return round(d, 4) if np.isfinite(d) else None
    return d


def run(quick: bool = False, repeats: int | None = None) -> dict:
    repeats = repeats or (1 if quick else 3)
    with tempfile.TemporaryDirectory() as tmp:
        world, logs = simulate(Path(tmp) / "drives", quick)
        km = km_driven(logs)
        out, shards = {}, {}
        for form in FORMS:
            drives, cfg = map_drives(logs, form)
            payloads = requests(drives, cfg)
            cost = ingest(payloads, repeats)
            shards[form] = cost["shard"]
            nbytes = sum(len(p) for p in payloads)
            out[form] = {
                "upload_bytes": nbytes, "kb_per_km_driven": nbytes / 1024 / km,
                "requests": len(payloads),
                "patches": sum(len(seal) for seals in drives for seal in seals),
                "ingest_cpu_s_per_km": cost["ingest_cpu_s"] / km,
                "flush_cpu_s_per_km": cost["flush_cpu_s"] / km,
                "map": map_quality(cost["shard"], world, logs, cfg),
                "digest": cost["shard"].digest()[:16],
            }
        tiles = shards["cells"].tiles()
        agreement = per_class_precision_recall(mosaic(shards["sparse"], tiles),
                                               mosaic(shards["cells"], tiles))
    return {"upload": _rounded({
        "world": world.name, "drives": len(logs), "km_driven": km, **out,
        "sparse_vs_cells": {
            "bytes_ratio": out["sparse"]["upload_bytes"] / out["cells"]["upload_bytes"],
            "ingest_cpu_ratio": (out["sparse"]["ingest_cpu_s_per_km"]
                                 / max(out["cells"]["ingest_cpu_s_per_km"], 1e-9)),
            "map_agreement": {k: {n: v[n] for n in MAP_METRICS} for k, v in agreement.items()
                              if v["cells_true"]},
        },
        "goal": {"kb_per_km_driven_max": 10.0},
        "timing": f"process CPU time, best of {repeats}, one process",
    })}


# -- paired demo runs -----------------------------------------------------------------------------


def report_figures(path: Path) -> dict:
    """The paired figures of one report.json: map P/R per class, localization means, upload."""
    r = json.loads(Path(path).read_text())
    out = {"upload_kb_per_km_driven": r["pipeline"].get("upload_kb_per_km_driven")}
    for name, v in r["map"]["per_class"].items():
        for m in MAP_METRICS:
            out[f"{name}.{m}"] = v.get(m)
    for m in LOC_METRICS:
        out[f"localization.{m}"] = r["localization"][m]["mean"]
    return out


def paired(pairs: dict[str, tuple[Path, Path]]) -> dict:
    """pairs: label -> (cells report, sparse report). Per label both figures and sparse - cells;
    per figure the median and the worst difference over the labels (worst: lowest for
    precision / recall, highest for localization errors and upload)."""
    per = {}
    for label, (a, b) in pairs.items():
        fa, fb = report_figures(a), report_figures(b)
        per[label] = {k: {"cells": fa[k], "sparse": fb.get(k),
                          "diff": (fb[k] - fa[k]) if _num(fa[k]) and _num(fb.get(k)) else None}
                      for k in fa}
    summary = {}
    for k in next(iter(per.values()), {}):
        diffs = [per[lab][k]["diff"] for lab in per if per[lab][k]["diff"] is not None]
        if not diffs:
            continue
        higher_is_worse = k.startswith("localization") or k.startswith("upload")
        summary[k] = {"median": statistics.median(diffs),
                      "worst": max(diffs) if higher_is_worse else min(diffs), "n": len(diffs)}
    return _rounded({"per_run": per, "summary": summary})


def _num(v) -> bool:
    return isinstance(v, int | float) and np.isfinite(v)


def run_demos(out: Path, seeds: list[int], world: str | None, extra: list[str]) -> dict:
    pairs = {}
    for seed in seeds:
        label = f"{world or 'default'}:{seed}"
        dirs = []
        for form in FORMS:
            d = out / f"{(world or 'default').replace(':', '_')}-s{seed}-{form}"
            argv = [sys.executable, "-m", "services.cli", "demo", "--seed", str(seed),
                    "--out", str(d), "--set", f"vehicle.patch_form={form}", *extra]
            if world:
                argv += ["--world", world]
            logger.info("%s", " ".join(argv[2:]))
            subprocess.run(argv, check=True, stdout=subprocess.DEVNULL)
            dirs.append(d / "report.json")
        pairs[label] = tuple(dirs)
    return paired(pairs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd")
    pair = sub.add_parser("pair", help="paired demo runs of both forms")
    pair.add_argument("--out", required=True)
    pair.add_argument("--seeds", type=int, nargs="*", default=[])
    pair.add_argument("--world", default=None)
    pair.add_argument("--demo-arg", action="append", default=[],
                      help="passed on to roadmap demo (repeatable)")
    pair.add_argument("--reports", nargs="*", default=[], metavar="CELLS:SPARSE",
                      help="pair finished runs' report.json files instead of running demos")
    ap.add_argument("--out", default=None)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO)
    out = Path(args.out or "out/bench")
    out.mkdir(parents=True, exist_ok=True)
    if args.cmd == "pair":
        if args.reports:
            result = paired({f"{a}": (Path(a), Path(b)) for a, b in
                             (r.split(":", 1) for r in args.reports)})
        else:
            result = run_demos(out, args.seeds, args.world, args.demo_arg)
        name = "pair.json"
    else:
        result, name = run(args.quick), "upload.json"
    write_result(out, name, result, result.get("summary", result))


if __name__ == "__main__":
    main()
