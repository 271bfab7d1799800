"""`roadmap eval [--suite default|quick] [--world W ...] [--seeds A-B] [--workers N] [--out DIR]`:
run the suite's drives (or the given worlds over the given seeds), score each against the truth,
and write DIR/eval.json (drives and summary) and DIR/eval.png.

`roadmap eval --relocalize RUN --out DIR [--set localizer.KEY=VALUE ...]`: the drives of an
earlier run (RUN/drives/*) re-localized offline with today's localizer (services/eval/replay.py:
the same frames, the tiles the car received, the car's own noise), each scored and summarized as
above: minutes instead of the suite's forty, to judge a localizer change paired by drive. The
fleet, the map and the frames stay those of RUN (its map figures are RUN's).

`roadmap eval --remerge RUN --out DIR [--set merger.KEY=VALUE ...]`: RUN's maps rebuilt offline
from the patches its shards stored, with today's merger (services/eval/remerge.py), and their
per-class figures scored anew: seconds a drive, to judge an evidence-rule change paired by drive.
The cars' figures stay RUN's.

`roadmap eval --remap RUN --out DIR [--set vehicle.KEY=VALUE ...]`: RUN's maps made again
offline from its mapping drives' stored frames with today's mapper and segmenter
(services/eval/remap.py) and merged and scored anew: minutes for the suite, to judge a change of
the vehicles' side of the map paired by drive. The cars' figures stay RUN's.

`roadmap eval --compare A B [A2 B2 ...] [--out DIR]`: runs paired by drive, several pairs pooled
(services/eval/compare.py), to the terminal and DIR/compare.json."""

import json
import logging
import sys
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path

from common.errors import ConfigError
from services.eval.compare import compare_runs, format_comparison, pooled, read_eval
from services.eval.figure import eval_figure
from services.eval.remap import remap_drive
from services.eval.remerge import remerge_drive
from services.eval.replay import RUN_KEYS, replay_drive
from services.eval.run import run_suite, suite_settings
from services.eval.suite import DEFAULT_SEEDS, Drive, parse_seeds, suite_drives
from services.eval.summary import summarize

logger = logging.getLogger(__name__)

def chosen_drives(args) -> list[Drive]:
    """--world and --seeds replace the suite's worlds and seeds; either alone keeps the other."""
    if not args.world and not args.seeds:
        return suite_drives(args.suite)
    try:
        seeds = parse_seeds(args.seeds) if args.seeds else list(DEFAULT_SEEDS)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    worlds = args.world or sorted({d.world for d in suite_drives(args.suite)})
    return [Drive(w, s) for w in worlds for s in seeds]

def write_eval(out: Path, entries: list[dict]) -> dict:
    drives = [{k: v for k, v in e.items() if k != "score"}
              | ({"score": {k: v for k, v in e["score"].items() if k != "errors_m"}}
                 if e.get("ok") else {}) for e in entries]
    for d in drives:
        (d.get("report") or {}).pop("processes", None)
    result = {"drives": drives, "summary": summarize(entries)}
    (out / "eval.json").write_text(json.dumps(result, indent=1))
    eval_figure([e["score"] for e in entries if e["ok"]], out / "eval.png")
    return result

def format_summary(s: dict) -> str:
    def row(k, scale=1.0):
        d = s[k]
        return (f"  {k:15s} median {_f(d['median'], scale)}  p90 {_f(d['p90'], scale)}  "
                f"worst {_f(d['worst'], scale)}  (paper mean {s['paper_mean'].get(k, '-')})")
    lines = [f"eval: {s['drives']} drives, {s['failed']} failed; per-drive mean errors over "
             "frames with markings in view:"]
    lines += [row(k) for k in ("x_m", "y_m", "lateral_m", "longitudinal_m", "yaw_deg")]
    lines.append(f"  availability min {_f(s['availability_0_5m']['min'])}, convergence max "
                 f"{_f(s['convergence_s']['max'])} s, integrity violations "
                 f"{s['integrity_violations']}, frames without markings "
                 f"{_f(s['frames_without_markings'])}, said ok min "
                 f"{_f(s['ok_share']['min'])} median {_f(s['ok_share']['median'])}")
    since = s.get("from_first_marking")
    if since:
        lines.append(f"  from the first marking on, converged or not: x median "
                     f"{_f(since['x_m']['median'])} p90 {_f(since['x_m']['p90'])} worst "
                     f"{_f(since['x_m']['worst'])}, availability min "
                     f"{_f(since['availability_0_5m']['min'])}")
    for cls, q in (s.get("map") or {}).items():
        lines.append(f"  map {cls:12s} precision min {_f(q['precision']['min'])} median "
                     f"{_f(q['precision']['median'])}, recall min {_f(q['recall']['min'])} "
                     f"median {_f(q['recall']['median'])}")
    for world, w in (s.get("by_world") or {}).items():
        lines.append(f"  world {world.split('/')[-1][:40]}: {w['drives']} drives, x median "
                     f"{_f(w['x_m']['median'])} worst {_f(w['x_m']['worst'])}, yaw median "
                     f"{_f(w['yaw_deg']['median'])} worst {_f(w['yaw_deg']['worst'])}, "
                     f"availability min {_f(w['availability_0_5m_min'])}, said ok median "
                     f"{_f(w['ok_share_median'])}, integrity violations "
                     f"{w['integrity_violations']}")
    lines.append("  goal: " + ", ".join(f"{k} {v}" for k, v in s["goal_met"].items()))
    return "\n".join(lines) + "\n"

def _f(v, scale=1.0) -> str:
    return "-" if v is None else f"{v * scale:.3f}"

def relocalized(run: Path, sets: list[str], workers: int, truth_map: bool = False) -> list[dict]:
    """The entries of RUN's drives, each finished one's score replaced by its re-localization's
    (the report, map figures included, stays RUN's); `truth_map`: on the world's true markings
    (replay.received_map)."""
    entries, redo = _finished(run, "re-localize")
    with ProcessPoolExecutor(max_workers=max(workers, 1)) as pool:
        scores = pool.map(replay_drive, [d for d, _ in redo], [sets] * len(redo),
                          [True] * len(redo), [truth_map] * len(redo))
        for (drive_dir, entry), r in zip(redo, scores, strict=True):
            entry["score"] = {k: v for k, v in r.items() if k not in RUN_KEYS}
            entry["relocalized"] = {"sets": sets, "truth_map": truth_map}
            logger.info("%s re-localized: %d ok frames, %d inits, %.0f s CPU", drive_dir.name,
                        r["ok_frames"], r["inits"], r["cpu_s"])
    return entries

def remerged(run: Path, sets: list[str], workers: int, *, remap: bool = False) -> list[dict]:
    """The entries of RUN's drives, each finished one's map figures replaced by those of its
    map rebuilt with today's merger (the car's score stays RUN's); with `remap`, made again
    from its mapping drives' frames with today's mapper first (remap_drive)."""
    verb, done, key = (("re-map", "re-mapped", "remapped") if remap
                       else ("re-merge", "re-merged", "remerged"))
    entries, redo = _finished(run, verb)
    with ProcessPoolExecutor(max_workers=max(workers, 1)) as pool:
        maps = pool.map(remap_drive if remap else remerge_drive, [d for d, _ in redo],
                        [sets] * len(redo))
        for (drive_dir, entry), m in zip(redo, maps, strict=True):
            entry["report"]["map"]["per_class"] = m["per_class"]
            entry["report"]["map"][key] = {"sets": sets, "changed_cells": m["changed_cells"]}
            logger.info("%s %s: %d cells differ from the run's map", drive_dir.name, done,
                        m["changed_cells"])
    return entries


def _finished(run: Path, verb: str) -> tuple[list[dict], list[tuple[Path, dict]]]:
    """(every drive entry of RUN, the (folder, entry) of those that finished ok)."""
    done = sorted(run.glob("drives/*/drive.json"))
    if not done:
        raise ConfigError(f"{run}: no finished drives (drives/*/drive.json) to {verb}")
    entries = [json.loads(f.read_text()) for f in done]
    return entries, [(f.parent, e) for f, e in zip(done, entries, strict=True) if e.get("ok")]


def eval_command(args, cfg) -> int:
    out = Path(args.out)
    if getattr(args, "compare", None):
        return compare_command(args.compare, out)
    remerge, remap = getattr(args, "remerge", None), getattr(args, "remap", None)
    if sum(bool(r) for r in (args.relocalize, remerge, remap)) > 1:
        raise ConfigError("--relocalize, --remerge and --remap: one at a time")
    run = args.relocalize or remerge or remap
    truth_map = bool(getattr(args, "truth_map", False))
    if truth_map and not args.relocalize:
        raise ConfigError("--truth-map re-localizes a run: give --relocalize RUN")
    if run:
        flag, offline = (("--relocalize", partial(relocalized, truth_map=truth_map))
                         if args.relocalize else ("--remap", partial(remerged, remap=True))
                         if remap else ("--remerge", remerged))
        if Path(run).resolve() == out.resolve():
            raise ConfigError(f"{flag}: give another --out (RUN keeps its own eval.json)")
        entries = offline(Path(run), list(args.set or []), args.workers)
        out.mkdir(parents=True, exist_ok=True)
    else:
        drives = chosen_drives(args)
        settings = suite_settings(list(args.set or []), args.vehicles)
        logger.info("eval: %d drives, %d at a time, in %s", len(drives), args.workers, out)
        entries = run_suite(drives, out, settings, args.workers)
    result = write_eval(out, entries)
    sys.stdout.write(format_summary(result["summary"]))
    sys.stdout.write(f"wrote {out / 'eval.json'} and {out / 'eval.png'}\n")
    return 0 if not result["summary"]["failed"] else 1


def compare_command(runs: list[str], out: Path) -> int:
    """`--compare A B [A2 B2 ...]`: the runs paired by drive (several pairs pooled), to the
    terminal and OUT/compare.json."""
    if len(runs) < 2 or len(runs) % 2:
        raise ConfigError(f"--compare takes pairs of runs (A B [A2 B2 ...]), got {len(runs)}")
    a_runs, b_runs = runs[0::2], runs[1::2]
    a = pooled([read_eval(Path(r)) for r in a_runs], "a")
    b = pooled([read_eval(Path(r)) for r in b_runs], "b")
    one = len(a_runs) == 1
    comparison = {"a": str(a_runs[0]) if one else [str(r) for r in a_runs],
                  "b": str(b_runs[0]) if one else [str(r) for r in b_runs], **compare_runs(a, b)}
    if not comparison["paired"]:
        raise ConfigError(f"--compare: {' '.join(a_runs)} and {' '.join(b_runs)} have no "
                          "finished drive in common")
    out.mkdir(parents=True, exist_ok=True)
    (out / "compare.json").write_text(json.dumps(comparison, indent=1))
    sys.stdout.write(format_comparison(comparison))
    sys.stdout.write(f"wrote {out / 'compare.json'}\n")
    return 0
