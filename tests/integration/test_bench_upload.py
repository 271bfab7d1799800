"""services/bench/upload.py's paired comparison of two patch forms' demo reports."""

import json

from services.bench.upload import paired


def _report(path, *, lane_p, lane_r, x, kb):
    path.write_text(json.dumps({
        "pipeline": {"upload_kb_per_km_driven": kb},
        "map": {"per_class": {"lane_line": {"precision": lane_p, "recall": lane_r},
                              "ground_sign": {"precision": None, "recall": None}}},
        "localization": {"x_m": {"mean": x}, "y_m": {"mean": 0.02}, "yaw_deg": {"mean": 0.1}},
    }))
    return path


def test_paired_differences_median_and_worst(tmp_path):
    pairs = {}
    for seed, (dp, dx) in enumerate(((0.01, -0.002), (-0.02, 0.004), (0.0, 0.001))):
        a = _report(tmp_path / f"a{seed}.json", lane_p=0.9, lane_r=0.8, x=0.03, kb=800.0)
        b = _report(tmp_path / f"b{seed}.json", lane_p=0.9 + dp, lane_r=0.8, x=0.03 + dx, kb=7.0)
        pairs[str(seed)] = (a, b)
    out = paired(pairs)
    s = out["summary"]
    assert s["lane_line.precision"] == {"median": 0.0, "worst": -0.02, "n": 3}
    assert s["localization.x_m"]["worst"] == 0.004 and s["localization.x_m"]["median"] == 0.001
    assert s["upload_kb_per_km_driven"]["median"] == -793.0
    assert "ground_sign.precision" not in s  # no figure on either side: nothing to pair
    assert out["per_run"]["1"]["lane_line.precision"]["diff"] == -0.02


def test_the_upload_section_runs_both_forms_on_the_same_drives(tmp_path):
    """`python -m services.bench.upload --quick`: both forms' bytes, ingest CPU and maps in one
    JSON; the sparse form far smaller and merging to (almost) the cells form's map."""
    import subprocess
    import sys

    subprocess.run([sys.executable, "-m", "services.bench.upload", "--quick", "--out", tmp_path],
                   check=True, capture_output=True, timeout=600)
    up = json.loads((tmp_path / "upload.json").read_text())["upload"]
    assert up["km_driven"] > 0.1
    cells, sparse = up["cells"], up["sparse"]
    assert sparse["kb_per_km_driven"] < 0.05 * cells["kb_per_km_driven"]
    for form in (cells, sparse):
        assert form["ingest_cpu_s_per_km"] > 0 and form["patches"] > 0
        assert form["map"]["lane_line"]["precision"] > 0.9
    agreement = up["sparse_vs_cells"]["map_agreement"]
    assert min(agreement[c][m] for c in agreement for m in ("precision", "recall")) > 0.95
