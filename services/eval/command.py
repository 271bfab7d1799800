"""`roadmap eval [--suite default|quick] [--world W ...] [--seeds A-B] [--workers N] [--out DIR]`:
run the suite's drives (or the given worlds over the given seeds), score each against the truth,
and write DIR/eval.json (drives and summary) and DIR/eval.png."""

import json
import logging
import sys
from pathlib import Path

from common.errors import ConfigError
from services.eval.figure import eval_figure
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
                 f"{_f(s['frames_without_markings'])}")
    lines.append("  goal: " + ", ".join(f"{k} {v}" for k, v in s["goal_met"].items()))
    return "\n".join(lines) + "\n"

def _f(v, scale=1.0) -> str:
    return "-" if v is None else f"{v * scale:.3f}"

def eval_command(args, cfg) -> int:
    out = Path(args.out)
    drives = chosen_drives(args)
    settings = suite_settings(list(args.set or []), args.vehicles)
    logger.info("eval: %d drives, %d at a time, in %s", len(drives), args.workers, out)
    entries = run_suite(drives, out, settings, args.workers)
    result = write_eval(out, entries)
    sys.stdout.write(format_summary(result["summary"]))
    sys.stdout.write(f"wrote {out / 'eval.json'} and {out / 'eval.png'}\n")
    return 0 if not result["summary"]["failed"] else 1

