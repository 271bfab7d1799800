"""roadmap eval: per-frame scoring against the truth, the suite's summary, and one real drive
(router, shards, vehicles, localizer) through the command, resumed on a second call."""

import json
import os

import numpy as np
import pytest

from common.camera import camera_from_config
from common.config import RoadmapConfig
from common.grid import TILE_CELLS
from services.eval import map as ev
from services.eval.compare import compare_runs, format_comparison, pooled
from services.eval.replay import evict
from services.eval.score import score_frames
from services.eval.suite import Drive, parse_seeds, suite_drives
from services.eval.summary import summarize
from tests.conftest import roadmap


def _truth(n):
    return np.stack([np.arange(n) * 1.0, np.zeros(n), np.zeros(n)], 1)


def test_a_wrong_pose_reported_ok_is_an_integrity_violation():
    n = 50
    truth = _truth(n)
    est = truth.copy()
    est[30:35, 0] += 0.8  # five frames 0.8 m off
    ok = np.ones(n, bool)
    ok[33:35] = False  # the car flagged two of them
    t_ns = np.arange(n) * 100_000_000
    s = score_frames(t_ns, est, ok, truth, np.ones(n, bool))
    assert s["integrity_violations"] == 3
    assert s["markings_in_view"]["availability_0_5m"] == pytest.approx(45 / 50)
    assert s["markings_in_view"]["ok_share"] == pytest.approx(48 / 50)


def test_statistics_are_taken_over_frames_with_markings_in_view_and_over_all():
    n = 40
    truth = _truth(n)
    est = truth.copy()
    est[:, 1] += np.where(np.arange(n) < 20, 0.02, 0.2)  # worse where nothing is in view
    in_view = np.arange(n) < 20
    s = score_frames(np.arange(n) * 100_000_000, est, np.ones(n, bool), truth, in_view)
    assert s["markings_in_view"]["y_m"]["mean"] == pytest.approx(0.02)
    assert s["all_frames"]["y_m"]["mean"] == pytest.approx(0.11)
    assert s["frames_without_markings"] == 20


def test_convergence_counts_from_the_first_marking_in_view():
    n = 100
    truth = _truth(n)
    est = np.full((n, 3), np.nan)
    est[40:] = truth[40:]  # a pose from frame 40 (4.0 s) on
    in_view = np.arange(n) >= 10  # the first marking at frame 10 (1.0 s)
    s = score_frames(np.arange(n) * 100_000_000, est, np.zeros(n, bool), truth, in_view)
    assert s["convergence_s"] == pytest.approx(3.0)


def test_a_start_metres_off_counts_from_the_first_marking_though_not_after_convergence():
    n = 100
    truth = _truth(n)
    est = np.full((n, 3), np.nan)
    est[20:] = truth[20:]
    est[20:50, 0] += 4.0  # a pose from frame 20 on, 4 m off until frame 50
    in_view = np.arange(n) >= 10
    s = score_frames(np.arange(n) * 100_000_000, est, np.zeros(n, bool), truth, in_view)
    assert s["convergence_s"] == pytest.approx(4.0)
    assert s["markings_in_view"]["x_m"]["mean"] == pytest.approx(0.0)
    since = s["from_first_marking"]
    assert since["frames"] == 90 and since["availability_0_5m"] == pytest.approx(50 / 90)
    assert since["x_m"]["mean"] == pytest.approx(4.0 * 30 / 80)


def test_a_drive_that_never_converges_is_scored_over_all_its_frames():
    n = 60
    truth = _truth(n)
    est = truth.copy()
    est[:, 0] += np.where(np.arange(n) % 8 == 0, 0.1, 0.9)  # never 1 s below 0.5 m
    s = score_frames(np.arange(n) * 100_000_000, est, np.zeros(n, bool), truth,
                     np.ones(n, bool))
    assert s["convergence_s"] is None
    assert s["markings_in_view"]["frames"] == n
    assert s["markings_in_view"]["availability_0_5m"] == pytest.approx(8 / 60)
    assert s["markings_in_view"]["x_m"]["mean"] == pytest.approx((8 * 0.1 + 52 * 0.9) / 60)


def test_the_summary_takes_distributions_over_drives_and_checks_the_goal():
    def entry(x, avail=1.0, conv=1.0, viol=0, said_ok=0.8):
        stats = {k: {"mean": x, "p90": x, "max": x}
                 for k in ("x_m", "y_m", "lateral_m", "longitudinal_m", "yaw_deg")}
        over = {**stats, "availability_0_5m": avail, "ok_share": said_ok, "frames": 10}
        return {"ok": True, "score": {"markings_in_view": over, "all_frames": over,
                                      "frames": 10, "frames_without_markings": 2,
                                      "integrity_violations": viol, "convergence_s": conv},
                "report": {"map": {"per_class": {"lane_line": {"precision": 0.97,
                                                               "recall": 0.9}}}}}

    entries = [entry(0.01), entry(0.02, said_ok=0.5), entry(0.03, avail=0.95, viol=2),
               {"ok": False}]
    for e, world in zip(entries, ("town", "town", "av2:/data/3bff", "town"), strict=True):
        e["world"] = world
    s = summarize(entries)
    assert (s["drives"], s["failed"]) == (4, 1)
    assert s["x_m"]["median"] == pytest.approx(0.02) and s["x_m"]["worst"] == 0.03
    assert s["availability_0_5m"] == {"min": 0.95, "median": 1.0}
    assert s["ok_share"] == {"min": 0.5, "median": 0.8}
    town, av2 = s["by_world"]["town"], s["by_world"]["av2:/data/3bff"]
    assert town["drives"] == 2 and town["x_m"] == {"median": 0.015, "worst": 0.02}
    assert town["ok_share_median"] == pytest.approx(0.65) and town["integrity_violations"] == 0
    assert av2["availability_0_5m_min"] == 0.95 and av2["integrity_violations"] == 2
    assert s["integrity_violations"] == 2 and s["frames_without_markings"] == pytest.approx(0.2)
    assert s["map"]["lane_line"]["precision"] == {"min": 0.97, "median": 0.97}
    assert s["goal_met"]["x_m_median"] and not s["goal_met"]["no_integrity_violation"]
    assert not s["goal_met"]["availability_every_drive"]


def test_suites_and_seeds():
    assert len(suite_drives("default")) >= 24 or not suite_drives("default")[0].world.startswith(
        ("lanelet2", "av2"))
    assert parse_seeds("3-5,9") == [3, 4, 5, 9]
    with pytest.raises(ValueError):
        parse_seeds("a-b")
    assert Drive("town:2", 7).name == "town-2-s7"


def test_map_recall_counts_only_the_cells_the_camera_saw_of_the_roi():
    """The ROI rectangle's near corners lie outside the image: they are not 'observed'."""
    cfg = RoadmapConfig()
    roi = cfg.roi
    outline = ev.visible_outline(camera_from_config(cfg.camera), roi.x_min_m, 8.0, roi.width_m)
    x, y = outline.T
    near, far = np.abs(y[x < x.min() + 0.2]).max(), np.abs(y[x > x.max() - 0.2]).max()
    assert x.min() > roi.x_min_m + 1.0 and x.max() <= roi.x_min_m + 8.0
    assert near < 0.7 * roi.width_m / 2 and far > 0.98 * roi.width_m / 2
    # one pose on tile (0, 0): the footprint is the trapezoid, not the 8 m x 8 m rectangle
    mosaic = ev.Mosaic([(0, 0)])
    pose = np.array([[10.0, 25.0, 0.0]])
    seen = ev.roi_footprint(mosaic, [(pose, outline)])
    rect = np.array([[3.0, -4.0], [11.0, -4.0], [11.0, 4.0], [3.0, 4.0]])
    swept = ev.roi_footprint(mosaic, [(pose, rect)])
    assert seen.shape == (TILE_CELLS, TILE_CELLS) and not (seen & ~swept).any()
    assert 0.5 < seen.sum() / swept.sum() < 0.8
    # a true line 3.7 m to the left, 3-6 m ahead, was never in view: no recall is owed
    truth = np.zeros_like(seen, np.uint8)
    cols, row = mosaic.to_cells(np.array([[13.0 + i * 0.1, 28.7] for i in range(30)])).T
    truth[row.astype(int), cols.astype(int)] = 2
    assert ev.map_quality(np.zeros_like(truth), truth, seen)["lane_line"]["recall"] is None
    assert ev.map_quality(np.zeros_like(truth), truth, swept)["lane_line"]["recall"] == 0.0


def test_the_replay_cache_evicts_the_least_recently_used_past_its_budget(tmp_path):
    now = 1_000_000.0
    ages = {"a.npz": 500, "b.npz": 400, "c.npz": 300, "new.npz": 10,
            "x.part.npz": 5, "dead.part.npz": 7200}
    for name, age in ages.items():
        (tmp_path / name).write_bytes(b"0" * 100)
        os.utime(tmp_path / name, (now - age, now - age))
    # 600 bytes, budget 150: oldest first, but the file just written (keep) and another
    # writer's fresh .part stay, even if the folder then stays over its budget
    gone = evict(tmp_path, 150, keep=tmp_path / "a.npz", now=now)
    assert sorted(p.name for p in gone) == ["b.npz", "c.npz", "dead.part.npz", "new.npz"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "x.part.npz"]
    assert evict(tmp_path, 10_000, keep=tmp_path / "a.npz", now=now) == []


@pytest.mark.integration
def test_roadmap_eval_runs_a_drive_scores_it_and_resumes(tmp_path):
    out = tmp_path / "eval"
    args = ("eval", "--world", "town", "--seeds", "101", "--vehicles", "2",
            "--set", "demo.max_km=0.15", "--set", 'segmentation.kind="truth"',  # the harness,
            "--out", str(out))  # not the model (rendering every frame would triple the time)
    res = roadmap(*args, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    result = json.loads((out / "eval.json").read_text())
    (drive,) = result["drives"]
    assert drive["ok"] and drive["world"] == "town" and drive["seed"] == 101
    assert drive["report"]["pipeline"]["patches_acked"] == drive["report"]["pipeline"][
        "patches_applied"]
    s = result["summary"]
    assert s["drives"] == 1 and s["failed"] == 0 and s["x_m"]["median"] is not None
    assert (out / "eval.png").stat().st_size > 1000
    again = roadmap(*args, timeout=120)  # read back, not driven again
    assert again.returncode == 0 and "town-s101: ok" in again.stderr
    other = roadmap("eval", "--world", "town", "--seeds", "101", "--out", str(out), timeout=60)
    assert other.returncode == 1 and "other settings" in other.stderr
    # re-localized offline with the same localizer: the live car's figures, to 1e-6
    relocal = tmp_path / "relocalized"
    res = roadmap("eval", "--relocalize", str(out), "--out", str(relocal), timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    (redo,) = json.loads((relocal / "eval.json").read_text())["drives"]
    live, replayed = drive["score"], redo["score"]
    assert replayed["integrity_violations"] == live["integrity_violations"]
    for k in ("x_m", "y_m", "yaw_deg"):
        assert replayed["markings_in_view"][k]["mean"] == pytest.approx(
            live["markings_in_view"][k]["mean"], rel=1e-6)
    assert (relocal / "eval.png").stat().st_size > 1000
    same = roadmap("eval", "--relocalize", str(out), "--out", str(out), timeout=60)
    assert same.returncode != 0 and "another --out" in same.stderr
    # ... and on the world's true markings (the oracle map): another map, the same frames
    oracle = tmp_path / "oracle"
    res = roadmap("eval", "--relocalize", str(out), "--truth-map", "--out", str(oracle),
                  timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    (truth,) = json.loads((oracle / "eval.json").read_text())["drives"]
    assert truth["relocalized"] == {"sets": [], "truth_map": True}
    assert truth["score"]["markings_in_view"]["x_m"]["mean"] != pytest.approx(
        live["markings_in_view"]["x_m"]["mean"], rel=1e-6)
    assert truth["score"]["markings_in_view"]["x_m"]["mean"] < 0.2
    lone = roadmap("eval", "--truth-map", "--out", str(oracle), timeout=60)
    assert lone.returncode != 0 and "--relocalize RUN" in lone.stderr
    # re-merged offline from the shards' stored patches: the same merger gives the same map
    remerged = tmp_path / "remerged"
    res = roadmap("eval", "--remerge", str(out), "--out", str(remerged), timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    (redo,) = json.loads((remerged / "eval.json").read_text())["drives"]
    assert redo["report"]["map"]["remerged"]["changed_cells"] == 0
    for name, q in redo["report"]["map"]["per_class"].items():  # precision, recall, cells
        assert q == {k: drive["report"]["map"]["per_class"][name][k] for k in q}
    assert redo["score"] == drive["score"]  # the car's figures stay the run's
    # ... and a stricter rule another map: no label carries 1000 votes
    strict = roadmap("eval", "--remerge", str(out), "--out", str(tmp_path / "strict"),
                     "--set", "merger.min_votes=1000", timeout=120)
    assert strict.returncode == 0, strict.stderr[-3000:]
    (hard,) = json.loads((tmp_path / "strict" / "eval.json").read_text())["drives"]
    assert hard["report"]["map"]["remerged"]["changed_cells"] > 1000
    assert hard["report"]["map"]["per_class"]["lane_line"]["cells_map"] == 0
    # made again from the mapping drives' stored frames: the same mapper, the same map ...
    remapped = tmp_path / "remapped"
    res = roadmap("eval", "--remap", str(out), "--out", str(remapped), timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    (redo,) = json.loads((remapped / "eval.json").read_text())["drives"]
    assert redo["report"]["map"]["remapped"] == {"sets": [], "changed_cells": 0}
    for name, q in redo["report"]["map"]["per_class"].items():
        assert q == {k: drive["report"]["map"]["per_class"][name][k] for k in q}
    assert redo["score"] == drive["score"]
    # ... and paint that must be seen in 1000 frames of a vehicle is never voted
    rare = tmp_path / "rare"
    res = roadmap("eval", "--remap", str(out), "--out", str(rare),
                  "--set", "vehicle.min_paint_frames=1000", timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    (hard,) = json.loads((rare / "eval.json").read_text())["drives"]
    assert hard["report"]["map"]["remapped"]["changed_cells"] > 1000
    assert hard["report"]["map"]["per_class"]["lane_line"]["cells_map"] == 0
    both = roadmap("eval", "--remap", str(out), "--remerge", str(out), "--out", str(rare),
                   timeout=60)
    assert both.returncode != 0 and "one at a time" in both.stderr
    # the live run and the car on the true markings, paired by drive
    res = roadmap("eval", "--compare", str(out), str(oracle), "--out", str(tmp_path / "cmp"))
    assert res.returncode == 0, res.stderr[-3000:]
    cmp = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert cmp["paired"] == 1 and cmp["metrics"]["x_m"]["mean_diff"] == pytest.approx(
        truth["score"]["markings_in_view"]["x_m"]["mean"]
        - live["markings_in_view"]["x_m"]["mean"])
    assert "paired drives: 1" in res.stdout
    bad = roadmap("eval", "--compare", str(out), str(tmp_path / "nowhere"))
    assert bad.returncode != 0 and "no eval.json" in bad.stderr


def _scored(world, seed, x, yaw=0.1, viol=0):
    seen = {"x_m": {"mean": x}, "y_m": {"mean": 0.03}, "yaw_deg": {"mean": yaw},
            "availability_0_5m": 1.0 if not viol else 0.9, "ok_share": 0.8 if not viol else 0.5}
    return {"world": world, "seed": seed, "ok": True,
            "score": {"markings_in_view": seen, "integrity_violations": viol,
                      "convergence_s": 2.0}}


def test_two_runs_are_compared_drive_by_drive():
    """Drives pair by world and seed; a drive only one side finished is listed, not paired;
    differences within the tolerance count neither way; a drive newly with violation frames
    is named."""
    a = {"drives": [_scored("town", 1, 0.05), _scored("town", 2, 0.10),
                    _scored("av2:/d/3bff", 1, 0.20), _scored("town", 3, 0.07),
                    {"world": "town", "seed": 4, "ok": False}]}
    b = {"drives": [_scored("town", 1, 0.052), _scored("town", 2, 0.06, yaw=0.2),
                    _scored("av2:/d/3bff", 1, 0.25, viol=3), _scored("town", 9, 0.01)]}
    c = compare_runs(a, b)
    assert c["paired"] == 3 and c["only_a"] == ["town s3"] and c["only_b"] == ["town s9"]
    x = c["metrics"]["x_m"]
    assert (x["better"], x["worse"]) == (1, 1)
    assert x["mean_diff"] == pytest.approx((0.002 - 0.04 + 0.05) / 3)
    assert x["a"]["worst"] == 0.20 and x["b"]["worst"] == 0.25
    assert c["metrics"]["yaw_deg"]["worse"] == 1 and c["metrics"]["y_m"]["t"] is None
    assert c["integrity_violations"] == {"a": 0, "b": 3, "new_on_b": ["av2:/d/3bff s1"]}
    assert c["availability_0_5m_min"] == {"a": 1.0, "b": 0.9}
    assert c["ok_share"]["a"] == {"min": 0.8, "median": 0.8} and c["ok_share"]["b"]["min"] == 0.5
    assert "new on: av2:/d/3bff s1" in format_comparison(c)


def test_several_pairs_of_runs_pool_into_one_comparison(tmp_path):
    """The suite and a held-out set, each before and after: their drives pair across both; a
    drive in two runs of one side is an error, as is an odd number of runs."""
    from common.errors import ConfigError
    from services.eval.command import compare_command

    runs = {"suite_a": [_scored("town", 1, 0.05), _scored("town", 2, 0.10)],
            "suite_b": [_scored("town", 1, 0.04), _scored("town", 2, 0.12)],
            "held_a": [_scored("town", 41, 0.05)], "held_b": [_scored("town", 41, 0.03)]}
    for name, drives in runs.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "eval.json").write_text(json.dumps({"drives": drives}))
    paths = [str(tmp_path / n) for n in ("suite_a", "suite_b", "held_a", "held_b")]
    assert compare_command(paths, tmp_path / "cmp") == 0
    c = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert c["paired"] == 3 and c["a"] == paths[0::2] and c["b"] == paths[1::2]
    assert (c["metrics"]["x_m"]["better"], c["metrics"]["x_m"]["worse"]) == (2, 1)
    with pytest.raises(ConfigError, match="in two of the a runs"):
        pooled([{"drives": runs["held_a"]}, {"drives": runs["held_a"]}], "a")
    with pytest.raises(ConfigError, match="pairs of runs"):
        compare_command(paths[:3], tmp_path / "cmp")
