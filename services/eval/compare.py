"""Two evaluation runs paired by drive: `roadmap eval --compare A B [A2 B2 ...] [--out DIR]`.

A change to the car is kept when the suite, paired by drive, says it helps: one drive's numbers
move by 15-20 % from noise alone, so only the same drive (world and seed: the same route, fleet,
map and sensor noise) scored both ways tells a change from chance. Each run is a directory with
an eval.json (`roadmap eval`, `--relocalize`) or the file itself.

Per metric (the per-drive means over frames with a marking in view, after convergence): each
side's median / p90 / worst over the paired drives, the mean of the per-drive differences b - a,
their paired t, and how many drives b is better or worse on by more than a tolerance (noise a
change should not be credited with). Integrity: each side's violation frames, and the drives
with violation frames on b that had none on a; what it costs: the least availability and the
share of frames said ok. Drives only one side finished are listed, not
paired. Several pairs (the suite and held-out sets, each run before and after) are pooled: the
a runs' drives against the b runs', one paired comparison over all of them."""

import json
from pathlib import Path

import numpy as np

from common.errors import ConfigError
from services.bench.runner import paired_t
from services.eval.summary import distribution, min_median

METRICS = ("x_m", "y_m", "yaw_deg")
# per-drive differences within these count neither way
TOLERANCE = {"x_m": 0.005, "y_m": 0.005, "yaw_deg": 0.01}


def read_eval(path: Path) -> dict:
    """eval.json of a run directory, or the file itself."""
    path = Path(path)
    file = path / "eval.json" if path.is_dir() else path
    try:
        data = json.loads(file.read_text())
    except FileNotFoundError:
        raise ConfigError(f"--compare: no eval.json at {path}") from None
    except json.JSONDecodeError as exc:
        raise ConfigError(f"--compare: {file} is not JSON ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("drives"), list):
        raise ConfigError(f"--compare: {file} has no drives (not a roadmap eval.json)")
    return data


def pooled(runs: list[dict], side: str) -> dict:
    """Several eval.json contents as one run (their drives together): a change judged over the
    suite and held-out sets at once. A drive (world and seed) in two of them is an error: which
    one to pair would be a guess."""
    drives, seen = [], set()
    for data in runs:
        for e in data["drives"]:
            key = drive_key(e)
            if key in seen:
                raise ConfigError(f"--compare: drive {key} is in two of the {side} runs")
            seen.add(key)
            drives.append(e)
    return {"drives": drives}


def drive_key(entry: dict) -> str:
    """A drive's identity across runs, 'world s<seed>': the same route, fleet, map and noise."""
    return f"{entry.get('world')} s{entry.get('seed')}"


def drive_scores(data: dict) -> dict[str, dict]:
    """'world s<seed>' -> the drive's per-drive means, violation frames, availability and
    convergence, for every finished drive."""
    out = {}
    for e in data["drives"]:
        score = e.get("score")
        if not e.get("ok") or not score:
            continue
        seen = score["markings_in_view"]
        out[drive_key(e)] = {
            **{m: seen[m]["mean"] for m in METRICS},
            "integrity_violations": int(score["integrity_violations"]),
            "availability_0_5m": seen["availability_0_5m"],
            "ok_share": seen.get("ok_share"),  # runs scored before 2026-12-07: none
            "convergence_s": score.get("convergence_s"),
        }
    return out


def _metric(a: dict, b: dict, keys: list[str], m: str) -> dict:
    pairs = [(a[k][m], b[k][m]) for k in keys if a[k][m] is not None and b[k][m] is not None]
    va, vb = (np.array([p[i] for p in pairs], float) for i in (0, 1))
    d = vb - va
    tol = TOLERANCE[m]
    return {"a": distribution(list(va)), "b": distribution(list(vb)), "drives": len(pairs),
            "mean_diff": float(d.mean()) if len(d) else None, "t": paired_t(list(d)),
            "better": int(np.sum(d < -tol)), "worse": int(np.sum(d > tol)), "tolerance": tol}


def compare_runs(a_data: dict, b_data: dict) -> dict:
    """The comparison of two eval.json contents (a: before, b: after), paired by drive."""
    a, b = drive_scores(a_data), drive_scores(b_data)
    keys = sorted(set(a) & set(b))
    viol = {side: sum(s[k]["integrity_violations"] for k in keys) for side, s in (("a", a),
                                                                                  ("b", b))}
    return {
        "paired": len(keys),
        "only_a": sorted(set(a) - set(b)), "only_b": sorted(set(b) - set(a)),
        "metrics": {m: _metric(a, b, keys, m) for m in METRICS},
        "integrity_violations": {
            **viol,
            "new_on_b": [k for k in keys if b[k]["integrity_violations"]
                         and not a[k]["integrity_violations"]]},
        "availability_0_5m_min": {side: min((s[k]["availability_0_5m"] for k in keys),
                                            default=None) for side, s in (("a", a), ("b", b))},
        "ok_share": {side: min_median([s[k]["ok_share"] for k in keys])
                     for side, s in (("a", a), ("b", b))},
        "per_drive": {k: {"a": a[k], "b": b[k]} for k in keys},
    }


def format_comparison(c: dict) -> str:
    """A few lines for the terminal."""
    lines = [f"paired drives: {c['paired']}"
             + (f" (only in a: {len(c['only_a'])}, only in b: {len(c['only_b'])})"
                if c["only_a"] or c["only_b"] else "")]
    for m, r in c["metrics"].items():
        if not r["drives"]:
            continue
        dist = "  ".join(f"{q} {r['a'][q]:.3f} -> {r['b'][q]:.3f}" for q in ("median", "p90",
                                                                             "worst"))
        t = "-" if r["t"] is None else f"{r['t']:+.2f}"
        lines.append(f"{m:8s} {dist}  mean diff {r['mean_diff']:+.4f} (t {t}), better on "
                     f"{r['better']}, worse on {r['worse']} (beyond {r['tolerance']})")
    v = c["integrity_violations"]
    lines.append(f"integrity violation frames {v['a']} -> {v['b']}"
                 + (f"; new on: {', '.join(v['new_on_b'])}" if v["new_on_b"] else ""))
    av = c["availability_0_5m_min"]
    if av["a"] is not None:
        lines.append(f"availability min {av['a']:.3f} -> {av['b']:.3f}")
    ok = c["ok_share"]
    if ok["a"]["median"] is not None and ok["b"]["median"] is not None:
        lines.append(f"share of frames said ok, min / median: {ok['a']['min']:.3f} / "
                     f"{ok['a']['median']:.3f} -> {ok['b']['min']:.3f} / {ok['b']['median']:.3f}")
    return "\n".join(lines) + "\n"
