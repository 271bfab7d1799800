"""`roadmap bench`: run every stage's benchmark (services/bench/<name>.py, each
`run(quick) -> dict`) and write OUT/bench.json in the shape of DESIGN.md (cores, python,
onnxruntime; stages; merge; scaling; mapper; and upload: both patch forms' bytes per km
driven and shard ingest CPU per km, services/bench/upload.py; postgres: workers, takeover and
tile servers on a private PostgreSQL, services/bench/postgres.py). A benchmark that is missing or
fails is recorded with its error. Each runs in its own process group (`python -m
services.bench.runner NAME`), killed afterwards, so a crash or a process a benchmark leaves
behind cannot outlive it."""

import importlib.util
import json
import logging
import os
import platform
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path

logger = logging.getLogger("roadmap.bench")

BENCHMARKS = ("render", "segmentation", "vehicle", "merger", "codec", "localizer", "upload",
              "postgres")
SECTIONS = ("stages", "merge", "scaling", "mapper", "upload", "postgres")


def run_senders(sender, window: int, failed: list) -> None:
    """`sender` on `window` threads at once (each one request in flight, as a fleet's
    outboxes), all joined; the first failure a sender recorded in `failed` is raised here."""
    threads = [threading.Thread(target=sender, daemon=True) for _ in range(window)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if failed:
        raise failed[0]


def write_result(out_dir, name: str, result: dict, shown=None) -> Path:
    """A benchmark's own command line: `result` to OUT_DIR/NAME (JSON) and `shown` (default:
    all of it) to stdout."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / name).write_text(json.dumps(result, indent=1))
    sys.stdout.write(json.dumps(result if shown is None else shown, indent=1) + "\n")
    return out / name


def load_bench(name: str, bench_dir: Path | None = None):
    """The benchmark module services.bench.<name>; with `bench_dir`, a folder's
    bench_<name>.py imported by its path instead (a user's own benchmarks, and the tests')."""
    if bench_dir is None:
        if name not in BENCHMARKS:
            raise FileNotFoundError(f"services.bench.{name} does not exist "
                                    f"(benchmarks: {', '.join(BENCHMARKS)})")
        return importlib.import_module(f"services.bench.{name}")
    path = Path(bench_dir) / f"bench_{name}.py"
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist")
    spec = importlib.util.spec_from_file_location(f"roadmap_bench_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run_in_process(name: str, quick: bool, bench_dir: Path | None = None) -> dict:
    """{"ok": True, "result": {...}, "wall_s"} or {"ok": False, "error": "..."}."""
    t = time.monotonic()
    try:
        result = load_bench(name, bench_dir).run(quick)
        if not isinstance(result, dict):
            raise TypeError(f"run() returned {type(result).__name__}, expected dict")
        return {"ok": True, "result": result, "wall_s": round(time.monotonic() - t, 2)}
    except Exception as exc:  # noqa: BLE001 -- one failing benchmark must not stop the others
        logger.warning("bench_%s failed: %s", name, exc)
        return {"ok": False, "error": f"{type(exc).__name__}: {exc}",
                "traceback": traceback.format_exc()[-2000:],
                "wall_s": round(time.monotonic() - t, 2)}


def run_one(name: str, quick: bool, bench_dir: Path | None = None,
            timeout_s: float = 1800.0) -> dict:
    """Run one benchmark in a child process group; whatever it leaves running is killed."""
    t = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "result.json"
        argv = ([sys.executable, "-m", "services.bench.runner", name, "--json", str(out)]
                + (["--dir", str(bench_dir)] if bench_dir else []) + (["--quick"] if quick else []))
        proc = subprocess.Popen(argv, start_new_session=True,
                                stdin=subprocess.DEVNULL)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            logger.warning("bench_%s: no result after %.0f s", name, timeout_s)
        finally:
            try:
                os.killpg(proc.pid, signal.SIGKILL)  # the benchmark and anything it left behind
            except ProcessLookupError:
                pass
            proc.wait()
        try:
            return json.loads(out.read_text())
        except (OSError, ValueError):
            return {"ok": False, "error": f"benchmark process ended with {proc.returncode} "
                    "and wrote no result", "wall_s": round(time.monotonic() - t, 2)}


def merge_results(runs: dict[str, dict]) -> dict:
    """Contract sections from the benchmarks' dicts: a benchmark returns the sections directly
    ({"stages": {...}, "merge": {...}}), or one flat dict that becomes stages[<its name>]."""
    out = {s: {} for s in SECTIONS}
    for name, run in runs.items():
        if not run["ok"]:
            continue
        result = run["result"]
        if not any(k in SECTIONS for k in result):
            out["stages"][name] = _latency_entry(result)
            continue
        for key, value in result.items():
            if key in SECTIONS and isinstance(value, dict):
                out[key].update(value)
    return out


def _latency_entry(result: dict) -> dict:
    """A flat result with ms_p50/ms_p95 (e.g. segmentation) as {p50_ms, p95_ms, per_s, ...}."""
    p50 = result.get("p50_ms", result.get("ms_p50"))
    p95 = result.get("p95_ms", result.get("ms_p95"))
    entry = {"p50_ms": p50, "p95_ms": p95,
             "per_s": round(1000.0 / p50, 2) if isinstance(p50, int | float) and p50 > 0 else None}
    for key in ("model", "iou", "iou_ci90", "iou_roi"):
        if key in result:
            entry[key] = result[key]
    if isinstance(result.get("stop_facing"), dict):  # segmentation: frames facing stop lines
        entry["stop_facing_iou"] = result["stop_facing"].get("iou")
    return entry


# what bench_localizer's accuracy runs report per drive (accuracy/localization.json: the mean
# of each over the drive's frames), in the order comparisons print them
LOCALIZATION_METRICS = ("x_m", "y_m", "yaw_deg")


def paired_comparison(a: dict[int, dict], b: dict[int, dict]) -> dict:
    """Two settings' drives paired by seed: `a`, `b` map seed -> {metric: mean error} (the
    LOCALIZATION_METRICS). Over the seeds both have: each side's mean of each metric, b's
    relative difference b / a - 1, and the paired t of b - a (mean difference over its
    standard error; None with fewer than two pairs or where every pair is equal), with the
    per-seed values. Drives of one seed share the world, route and sensor noise, so pairing
    takes the seeds' own spread (0.03-0.08 m a drive here) out of the difference."""
    seeds = sorted(set(a) & set(b))
    out = {"paired_seeds": seeds, "a": {}, "b": {}, "b_vs_a": {}, "t": {},
           "per_seed": {"a": {s: a[s] for s in seeds}, "b": {s: b[s] for s in seeds}}}
    for m in LOCALIZATION_METRICS:
        va = [float(a[s][m]) for s in seeds]
        vb = [float(b[s][m]) for s in seeds]
        mean_a = sum(va) / len(va) if seeds else None
        mean_b = sum(vb) / len(vb) if seeds else None
        out["a"][m], out["b"][m] = mean_a, mean_b
        out["b_vs_a"][m] = mean_b / mean_a - 1 if seeds and mean_a else None
        out["t"][m] = paired_t([y - x for x, y in zip(va, vb, strict=True)])
    return out


def paired_t(differences: list[float]) -> float | None:
    """The paired t of per-pair differences: their mean over its standard error (None with
    fewer than two pairs or where every difference is the same)."""
    d = [float(x) for x in differences]
    if len(d) < 2:
        return None
    mean_d = sum(d) / len(d)
    var = sum((x - mean_d) ** 2 for x in d) / (len(d) - 1)
    return mean_d / (var / len(d)) ** 0.5 if var > 0 else None


def environment() -> dict:
    try:
        import onnxruntime

        ort = onnxruntime.__version__
    except ImportError:
        ort = None
    return {"cores": os.cpu_count(), "python": platform.python_version(), "onnxruntime": ort,
            "platform": platform.platform(), "machine": platform.machine(), **cpu_description()}


# the vector extensions that decide onnxruntime's and torch's CPU kernels: blocked convolutions
# work on 8 channels with AVX2 and 16 with AVX-512; bfloat16 is native with AVX-512 BF16 or AMX
SIMD_FLAGS = ("avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16", "avx_vnni", "amx_tile")


def cpu_description(cpuinfo: str | None = None) -> dict:
    """{"cpu": the processor's model name, "simd": which of SIMD_FLAGS it has} from
    /proc/cpuinfo (Linux; elsewhere the platform's processor name and no flags), so that a
    benchmark's milliseconds can be read against the machine that gave them (the same model
    file ran 11, 18 and 38 ms a frame on three EPYCs of different vector units)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return {"cpu": platform.processor() or None, "simd": None}
    fields = {}
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    flags = set(fields.get("flags", "").split())
    return {"cpu": fields.get("model name") or platform.processor() or None,
            "simd": [f for f in SIMD_FLAGS if f in flags]}


def run_all(quick: bool, names=BENCHMARKS, bench_dir: Path | None = None) -> dict:
    runs = {}
    for name in names:
        logger.info("bench_%s ...", name)
        runs[name] = run_one(name, quick, bench_dir)
    return {**environment(), "quick": quick, **merge_results(runs),
            "benchmarks": {n: {k: v for k, v in r.items() if k != "result"}
                           for n, r in runs.items()},
            "raw": {n: r.get("result") for n, r in runs.items()}}


def _jsonable(obj):
    """numpy scalars and arrays as plain numbers and lists; anything else as text."""
    if hasattr(obj, "tolist"):
        return obj.tolist()
    return str(obj)


def _child_main(argv: list[str] | None = None) -> int:
    import argparse

    from common.log import configure_logging

    p = argparse.ArgumentParser(prog="python -m services.bench.runner")
    p.add_argument("name")
    p.add_argument("--dir", default=None, help="a folder of bench_<name>.py files")
    p.add_argument("--json", required=True)
    p.add_argument("--quick", action="store_true")
    args = p.parse_args(argv)
    configure_logging("INFO")
    result = run_in_process(args.name, args.quick, args.dir and Path(args.dir))
    Path(args.json).write_text(json.dumps(result, default=_jsonable))
    return 0


def bench_command(args, cfg) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = run_all(args.quick)
    (out / "bench.json").write_text(json.dumps(report, indent=1, default=_jsonable))
    failed = [n for n, r in report["benchmarks"].items() if not r["ok"]]
    sys.stdout.write(f"bench: {len(BENCHMARKS) - len(failed)}/{len(BENCHMARKS)} benchmarks ran"
                     + (f" (failed: {', '.join(failed)})" if failed else "")
                     + f"; wrote {out / 'bench.json'}\n")
    return 0


if __name__ == "__main__":
    sys.exit(_child_main())
