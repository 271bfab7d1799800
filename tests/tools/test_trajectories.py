"""Trajectories for standard tools: `roadmap trajectory` writes the Karlsruhe demo's localized
trajectory and the production drive's ground truth as TUM (and KITTI) files, the real `evo_ape`
reads them, and evo's absolute pose error agrees with what report.json says about the drive.

Like with like: report.json's localization statistics are taken over the frames after
convergence (`all_frames`), and its headline numbers over those of them where the map covers the
camera's view (on_map, localizer/diagnostics.jsonl); evo's APE is over every matched pose. The
test takes evo's per-pose errors over the same frames and compares: availability (share of
frames under 0.5 m, a frame without an estimate counting as unavailable) exactly, the mean x / y
errors from evo's own reading of the files to 1 mm, and evo's translation error (the norm of x
and y) against the report's per-axis maxima, which bound it."""

import json
import shutil
import subprocess
import zipfile

import numpy as np
import pytest

from common.trajectory import read_kitti, read_tum, stamp_ns
from tests.tools.conftest import roadmap_ok

pytestmark = [pytest.mark.integration, pytest.mark.shared_data]


def _evo_ape(fmt: str, ref, est, out_zip) -> dict:
    exe = shutil.which("evo_ape")
    if exe is None:
        pytest.skip("needs evo (pip install evo, in .[test]): evo_ape not on PATH")
    res = subprocess.run([exe, fmt, str(ref), str(est), "--save_results", str(out_zip),
                          "--no_warnings"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    with zipfile.ZipFile(out_zip) as z:
        stats = json.loads(z.read("stats.json"))
    from evo.tools import file_interface

    result = file_interface.load_res_file(str(out_zip))
    return {"stats": stats, "errors": result.np_arrays["error_array"],
            "stamps": result.np_arrays.get("timestamps")}


@pytest.fixture(scope="module")
def tum(karlsruhe_demo, tmp_path_factory):
    d = tmp_path_factory.mktemp("tum")
    roadmap_ok("trajectory", "--from", karlsruhe_demo.out, "--out", d, "--format", "tum")
    return d


def _scored(karlsruhe_demo, t_truth_ns: np.ndarray):
    """Per truth frame: after convergence (all_frames), and on the map too (the headline)."""
    loc = karlsruhe_demo.report["localization"]
    t_rel = (t_truth_ns - t_truth_ns[0]) * 1e-9
    after = t_rel >= loc["convergence_s"] - 1e-6
    diag = [json.loads(line) for line in
            (karlsruhe_demo.out / "localizer" / "diagnostics.jsonl").read_text().splitlines()]
    if not diag or "on_map" not in diag[0] or "frames_on_map" not in loc:
        return after, None  # no map coverage recorded: the all-frames figures only
    on_map = {int(r["t_ns"]): bool(r["on_map"]) for r in diag}
    mapped = np.array([on_map.get(int(t), False) for t in t_truth_ns])
    return after, after & mapped


def test_evo_ape_agrees_with_the_report(tum, karlsruhe_demo):
    from evo.core import sync
    from evo.tools import file_interface

    ape = _evo_ape("tum", tum / "truth.tum", tum / "estimate.tum", tum / "ape.zip")
    loc = karlsruhe_demo.report["localization"]
    t_truth, _ = read_tum(tum / "truth.tum")
    t_est, _ = read_tum(tum / "estimate.tum")
    assert len(ape["errors"]) == len(t_est)  # every estimate met its truth frame

    # evo's own reading and matching of the two files: per-axis errors of each matched pose
    ref = file_interface.read_tum_trajectory_file(str(tum / "truth.tum"))
    est = file_interface.read_tum_trajectory_file(str(tum / "estimate.tum"))
    ref, est = sync.associate_trajectories(ref, est)
    dxy = est.positions_xyz[:, :2] - ref.positions_xyz[:, :2]
    assert np.allclose(np.hypot(dxy[:, 0], dxy[:, 1]), ape["errors"], atol=1e-9)
    matched_ns = np.array([stamp_ns(f"{t:.9f}") for t in ref.timestamps])
    index = {int(t): k for k, t in enumerate(t_truth)}
    frame = np.array([index[min(index, key=lambda s: abs(s - int(t)))] for t in matched_ns])

    after, headline = _scored(karlsruhe_demo, t_truth)
    subsets = [(after, loc.get("all_frames", loc))]
    if headline is not None:
        subsets.append((headline, loc))
    for use, section in subsets:
        pick = use[frame]
        err, d = ape["errors"][pick], dxy[pick]
        # availability: frames of the subset under 0.5 m / all frames of the subset
        assert (err < 0.5).sum() / use.sum() == pytest.approx(section["availability_0_5m"],
                                                              abs=0.5 / use.sum())
        assert np.abs(d[:, 0]).mean() == pytest.approx(section["x_m"]["mean"], abs=1e-3)
        assert np.abs(d[:, 1]).mean() == pytest.approx(section["y_m"]["mean"], abs=1e-3)
        bound = np.hypot(section["x_m"]["max"], section["y_m"]["max"])
        assert max(section["x_m"]["max"], section["y_m"]["max"]) - 1e-3 <= err.max() <= \
            bound + 1e-3
        lat, lon = section["lateral_m"]["max"], section["longitudinal_m"]["max"]
        assert max(lat, lon) - 1e-3 <= err.max() <= np.hypot(lat, lon) + 1e-3
    print(f"evo_ape tum: {ape['stats']}; report all frames x {loc['all_frames']['x_m']['mean']:.3f}"  # noqa: T201
          f" y {loc['all_frames']['y_m']['mean']:.3f} m, availability "
          f"{loc['all_frames']['availability_0_5m']:.3f}")


def test_kitti_files_give_evo_the_same_ape(tum, karlsruhe_demo, tmp_path):
    roadmap_ok("trajectory", "--from", karlsruhe_demo.out, "--out", tmp_path, "--format",
               "kitti")
    est, truth = read_kitti(tmp_path / "estimate.kitti"), read_kitti(tmp_path / "truth.kitti")
    stamps = (tmp_path / "times.txt").read_text().split()
    assert len(est) == len(truth) == len(stamps) > 100
    kitti = _evo_ape("kitti", tmp_path / "truth.kitti", tmp_path / "estimate.kitti",
                     tmp_path / "ape.zip")
    tum_ape = _evo_ape("tum", tum / "truth.tum", tum / "estimate.tum", tmp_path / "tum.zip")
    for key in ("rmse", "mean", "max"):
        assert kitti["stats"][key] == pytest.approx(tum_ape["stats"][key], abs=1e-4)
