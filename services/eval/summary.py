"""The suite's summary: distributions over drives of each drive's mean errors (over frames with
markings in view, after convergence), availability, convergence, integrity and map quality,
next to the paper's means and the goal the product is held to."""

import numpy as np

STATS = ("x_m", "y_m", "lateral_m", "longitudinal_m", "yaw_deg")
PAPER_MEAN = {"x_m": 0.043, "y_m": 0.040, "yaw_deg": 0.124}  # Qin et al., table of errors
GOAL = {"median_of_means": "<= paper", "p90_of_means": "<= 1.5 x paper",
        "availability_0_5m": 0.99, "convergence_s": 5.0, "integrity_violations": 0}
MAP_CLASSES = ("lane_line", "stop_line", "crosswalk", "ground_sign")


def distribution(values: list[float]) -> dict:
    """Median, p90 and worst of values (None left out; all None when there are none)."""
    v = np.array([x for x in values if x is not None], float)
    if not len(v):
        return {"median": None, "p90": None, "worst": None}
    return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)),
            "worst": float(v.max())}


def min_median(values: list) -> dict:
    """Least and median of values (None left out)."""
    v = np.array([x for x in values if x is not None], float)
    return ({"min": None, "median": None} if not len(v)
            else {"min": float(v.min()), "median": float(np.median(v))})


def _errors(scores: list[dict], over: str) -> dict:
    return {k: distribution([s[over][k]["mean"] for s in scores]) for k in STATS}


def _map_quality(reports: list[dict]) -> dict:
    out = {}
    for cls in MAP_CLASSES:
        rows = [r["map"]["per_class"].get(cls) or {} for r in reports]
        out[cls] = {m: min_median([row.get(m) for row in rows]) for m in ("precision", "recall")}
    return out


def _by_world(entries: list[dict]) -> dict:
    """Per world (as named on the command line), over its finished drives: their count, the
    median and worst of the per-drive mean x, y and yaw, the least availability, the median
    share of frames said ok, and the integrity violation frames: where a suite over several
    worlds stands, world by world."""
    groups: dict[str, list[dict]] = {}
    for e in entries:
        if e["ok"]:
            groups.setdefault(e.get("world", "?"), []).append(e["score"])
    out = {}
    for world, scores in groups.items():
        over = [s["markings_in_view"] for s in scores]
        row: dict = {"drives": len(scores)}
        for k in PAPER_MEAN:
            d = distribution([o[k]["mean"] for o in over])
            row[k] = {"median": d["median"], "worst": d["worst"]}
        row["availability_0_5m_min"] = min_median([o["availability_0_5m"] for o in over])["min"]
        row["ok_share_median"] = min_median([o.get("ok_share") for o in over])["median"]
        row["integrity_violations"] = sum(s["integrity_violations"] for s in scores)
        out[world] = row
    return out


def goal_met(summary: dict) -> dict:
    """Each of the goal's conditions, true or false (None: not measured)."""
    met = {}
    for k, paper in PAPER_MEAN.items():
        d = summary[k]
        met[f"{k}_median"] = None if d["median"] is None else d["median"] <= paper
        met[f"{k}_p90"] = None if d["p90"] is None else d["p90"] <= 1.5 * paper
    a, c = summary["availability_0_5m"]["min"], summary["convergence_s"]["max"]
    met["availability_every_drive"] = None if a is None else a >= GOAL["availability_0_5m"]
    met["convergence_every_drive"] = (None if c is None else
                                      c <= GOAL["convergence_s"]
                                      and not summary["convergence_s"].get("never"))
    met["no_integrity_violation"] = summary["integrity_violations"] == 0
    return met


def summarize(entries: list[dict]) -> dict:
    """eval.json's summary over the drives that finished (failed ones are counted)."""
    ok = [e for e in entries if e["ok"]]
    scores, reports = [e["score"] for e in ok], [e["report"] for e in ok]
    frames = sum(s["frames"] for s in scores)
    summary = {
        "drives": len(entries), "failed": len(entries) - len(ok),
        **_errors(scores, "markings_in_view"),
        "availability_0_5m": min_median([s["markings_in_view"]["availability_0_5m"]
                                          for s in scores]),
        "convergence_s": {k: v for k, v in distribution([s["convergence_s"]
                                                          for s in scores]).items()
                          if k != "p90"},
        "integrity_violations": sum(s["integrity_violations"] for s in scores),
        # the share of frames (markings in view, after convergence) the car said ok; runs
        # scored before 2026-12-07 (second stop) have none
        "ok_share": min_median([s["markings_in_view"].get("ok_share") for s in scores]),
        "frames_without_markings": (sum(s["frames_without_markings"] for s in scores) / frames
                                    if frames else None),
        "map": _map_quality(reports),
        "all_frames": {**_errors(scores, "all_frames"),
                       "availability_0_5m": min_median([s["all_frames"]["availability_0_5m"]
                                                         for s in scores])},
        "paper_mean": PAPER_MEAN,
        "by_world": _by_world(entries),
    }
    since = [s for s in scores if "from_first_marking" in s]  # runs before 2026-12-07: none
    if since:
        summary["from_first_marking"] = {
            **_errors(since, "from_first_marking"),
            "availability_0_5m": min_median([s["from_first_marking"]["availability_0_5m"]
                                              for s in since])}
    summary["convergence_s"]["max"] = summary["convergence_s"].pop("worst")
    never = sum(s["convergence_s"] is None for s in scores)
    if never:
        summary["convergence_s"]["never"] = never
    summary["goal_met"] = goal_met(summary)
    return summary
