"""Two settings of the car compared on the same simulated drives: mean localization errors,
paired over seeds.

    python -m services.bench.compare_localizer --out DIR --seeds 1-12 \
        --common 'segmentation.kind="onnx"' \
        --a 'segmentation.flip="average"' --b 'segmentation.flip="alternate"'

Each (side, seed) is one `services/bench/localizer.py --world W --km K --seed S --set ...` run
(a real router and localizer node per drive), in DIR/a/sS and DIR/b/sS with its log beside
it; `--jobs` of them at a time (one core each). A run whose localization.json is already
there is read, not run again, so a stopped comparison resumes and more seeds can be added
later; DIR/settings.json records the world, length and settings, and other ones are refused
there. DIR/compare.json holds each side's settings, the per-seed means of x, y and yaw error,
their means over the seeds both sides finished, b's relative difference to a and the paired t
of b - a (services.bench.runner.paired_comparison).

How to read it: over twelve 0.6 km Karlsruhe drives, two settings that are the same by
construction differed by up to 4 % in a metric's mean (training/HISTORY.md, 2026-11-29
morning); differences of that size need more seeds before they mean anything."""

import argparse
import json
import logging
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from services.bench.runner import LOCALIZATION_METRICS, paired_comparison
from services.sim.worlds import shared_data_dir

logger = logging.getLogger("bench.compare_localizer")

KARLSRUHE = shared_data_dir() / "lanelet2-karlsruhe" / "mapping_example.osm"


def parse_seeds(text: str) -> list[int]:
    """"1-12", "1,3,5" or "1-4,9" -> ascending distinct seeds."""
    seeds = set()
    try:
        for part in text.split(","):
            lo, _, hi = part.strip().partition("-")
            seeds.update(range(int(lo), int(hi or lo) + 1))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"seeds: expected e.g. 1-12 or 1,3,5, got {text!r}") from None
    if not seeds:
        raise argparse.ArgumentTypeError(f"seeds: none in {text!r}")
    return sorted(seeds)


def drive_command(out: Path, *, world: str, km: float, seed: int, sets: list[str]) -> list[str]:
    argv = [sys.executable, "-m", "services.bench.localizer", "--out", str(out),
            "--world", world, "--km", str(km), "--seed", str(seed)]
    for s in sets:
        argv += ["--set", s]
    return argv


def read_errors(run_dir: Path) -> dict | None:
    """{metric: mean error} of a finished drive, or None."""
    path = run_dir / "accuracy" / "localization.json"
    if not path.is_file():
        return None
    acc = json.loads(path.read_text())
    return {m: acc[m]["mean"] for m in LOCALIZATION_METRICS}


def run_drive(out: Path, argv: list[str]) -> dict | None:
    """The drive's errors, running it first unless it has finished before; None if it fails
    (its log, out.with_suffix('.log'), says why)."""
    done = read_errors(out)
    if done is not None:
        return done
    log = out.with_suffix(".log")
    with open(log, "w") as fh:
        rc = subprocess.call(argv, stdout=fh, stderr=subprocess.STDOUT)
    errors = read_errors(out)
    if rc != 0 or errors is None:
        logger.error("drive %s failed (exit %s): see %s", out, rc, log)
        return None
    return errors


class SettingsMismatch(ValueError):
    """DIR holds drives of other settings, which a resumed comparison would read as its own."""


def check_settings(out: Path, settings: dict) -> None:
    """Record what the drives in `out` are run with (out/settings.json) on the first call;
    on a later one, refuse other settings: finished drives are read back, not run again."""
    path = out / "settings.json"
    if path.is_file():
        before = json.loads(path.read_text())
        if before != json.loads(json.dumps(settings)):
            raise SettingsMismatch(f"{out} holds drives run with {before}, not {settings}: "
                                   "give another --out")
        return
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(settings, indent=2) + "\n")


def compare(out: Path, *, world: str, km: float, seeds: list[int], common: list[str],
            a: list[str], b: list[str], jobs: int = 2) -> dict:
    sides = {"a": common + a, "b": common + b}
    check_settings(out, {"world": world, "km": km, "settings": sides})
    for side in sides:
        (out / side).mkdir(parents=True, exist_ok=True)
    def drive(task):
        side, seed = task
        run_dir = out / side / f"s{seed}"
        return run_drive(run_dir, drive_command(run_dir, world=world, km=km, seed=seed,
                                                sets=sides[side]))

    tasks = [(side, seed) for seed in seeds for side in sides]
    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        results = list(pool.map(drive, tasks))
    per_side = {side: {} for side in sides}
    failed = []
    for (side, seed), res in zip(tasks, results, strict=True):
        if res is None:
            failed.append({"side": side, "seed": seed})
        else:
            per_side[side][seed] = res
    report = {"world": world, "km": km, "seeds": seeds,
              "settings": {side: sets for side, sets in sides.items()},
              **paired_comparison(per_side["a"], per_side["b"]), "failed": failed}
    (out / "compare.json").write_text(json.dumps(report, indent=2) + "\n")
    return report


def summary(report: dict) -> str:
    lines = [f"{len(report['paired_seeds'])} drives paired ({report['world']}, {report['km']} km)"]
    if not report["paired_seeds"]:
        lines.append("  no seed finished on both sides")
        return "\n".join(lines)
    for m in LOCALIZATION_METRICS:
        t = report["t"][m]
        lines.append(f"  {m:8s} a {report['a'][m]:.4f}  b {report['b'][m]:.4f}  "
                     f"b vs a {100 * report['b_vs_a'][m]:+.1f} %  "
                     f"t {'-' if t is None else f'{t:+.2f}'}")
    if report["failed"]:
        lines.append(f"  failed: {report['failed']}")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--world", default=None,
                        help=f"bench_localizer's --world (default: lanelet2:{KARLSRUHE})")
    parser.add_argument("--km", type=float, default=0.6)
    parser.add_argument("--seeds", type=parse_seeds, default=parse_seeds("1-12"))
    parser.add_argument("--common", action="append", default=[],
                        help="a --set for both sides (repeatable), e.g. "
                             "'segmentation.kind=\"onnx\"'")
    parser.add_argument("--a", action="append", default=[], help="a --set for side a")
    parser.add_argument("--b", action="append", default=[], help="a --set for side b")
    parser.add_argument("--jobs", type=int, default=2, help="drives at a time (one core each)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    world = args.world
    if world is None:
        if not KARLSRUHE.is_file():
            logger.error("no %s: give --world (e.g. town), or put the shared data at "
                         "../shared/data or set ROADMAP_SHARED_DATA", KARLSRUHE)
            return 2
        world = f"lanelet2:{KARLSRUHE}"
    try:
        report = compare(args.out, world=world, km=args.km, seeds=args.seeds,
                         common=args.common, a=args.a, b=args.b, jobs=args.jobs)
    except SettingsMismatch as exc:
        logger.error("%s", exc)
        return 2
    sys.stdout.write(summary(report) + "\n")
    return 1 if report["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
