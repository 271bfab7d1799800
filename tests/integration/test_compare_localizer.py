"""services/bench/compare_localizer.py: two settings of the car on the same drives, paired by seed
(real bench_localizer runs: a local router and a localizer node per drive, on a short town
drive), and the paired statistics it reports (services.bench.runner.paired_comparison)."""

import json
import math

import pytest

from services.bench.runner import LOCALIZATION_METRICS, paired_comparison

pytestmark = pytest.mark.integration


def _tool():
    from services.bench import compare_localizer

    return compare_localizer


def _errors(x, y, yaw):
    return dict(zip(LOCALIZATION_METRICS, (x, y, yaw), strict=True))


def test_paired_comparison_means_relative_difference_and_t():
    a = {1: _errors(0.04, 0.05, 0.10), 2: _errors(0.06, 0.05, 0.20), 3: _errors(0.05, 0.05, 0.3)}
    b = {1: _errors(0.05, 0.05, 0.10), 2: _errors(0.06, 0.05, 0.20), 4: _errors(1.0, 1.0, 1.0)}
    out = paired_comparison(a, b)
    assert out["paired_seeds"] == [1, 2]  # seed 3 lacks b, seed 4 lacks a
    assert out["a"]["x_m"] == pytest.approx(0.05) and out["b"]["x_m"] == pytest.approx(0.055)
    assert out["b_vs_a"]["x_m"] == pytest.approx(0.1)
    # differences 0.01 and 0: mean 0.005, standard error 0.005 -> t = 1
    assert out["t"]["x_m"] == pytest.approx(1.0)
    assert out["b_vs_a"]["y_m"] == 0.0 and out["t"]["y_m"] is None  # every pair equal
    assert out["per_seed"]["b"] == {1: b[1], 2: b[2]}
    one = paired_comparison({1: a[1]}, {1: b[1]})
    assert one["t"]["x_m"] is None and one["b_vs_a"]["x_m"] == pytest.approx(0.25)
    none = paired_comparison(a, {})
    assert none["paired_seeds"] == [] and none["a"]["x_m"] is None


def test_parse_seeds():
    tool = _tool()
    assert tool.parse_seeds("1-3,7,2") == [1, 2, 3, 7]
    for bad in ("a-3", "3-1", ""):
        with pytest.raises(Exception, match="seeds"):
            tool.parse_seeds(bad)


def test_same_setting_twice_reads_equal_and_another_differs(tmp_path):
    tool = _tool()
    run = {"world": "town", "km": 0.15, "seeds": [1], "jobs": 2}
    # max_points 700 is the default: the same drive by another spelling
    same = tool.compare(tmp_path / "same", common=[], a=[], b=["localizer.max_points=700"], **run)
    assert same["failed"] == [] and same["paired_seeds"] == [1]
    for m in LOCALIZATION_METRICS:
        assert same["b_vs_a"][m] == 0.0 and 0 < same["a"][m] < 1.0
    assert tool.summary(same).count("b vs a +0.0 %") == len(LOCALIZATION_METRICS)
    report = json.loads((tmp_path / "same" / "compare.json").read_text())
    assert report["settings"]["b"] == ["localizer.max_points=700"]
    log = tmp_path / "same" / "a" / "s1.log"
    stamp = log.stat().st_mtime_ns
    again = tool.compare(tmp_path / "same", common=[], a=[], b=["localizer.max_points=700"],
                         **run)  # finished drives are read back, not run again
    assert again["a"] == same["a"] and log.stat().st_mtime_ns == stamp
    with pytest.raises(tool.SettingsMismatch, match="another --out"):
        tool.compare(tmp_path / "same", common=[], a=[], b=["localizer.max_points=200"], **run)
    other = tool.compare(tmp_path / "other", common=[], a=[], b=["localizer.max_points=150"],
                         **run)
    assert other["failed"] == []
    assert any(not math.isclose(other["b_vs_a"][m], 0.0, abs_tol=1e-12)
               for m in LOCALIZATION_METRICS)


def test_a_failing_drive_is_reported_not_paired(tmp_path):
    tool = _tool()
    report = tool.compare(tmp_path, world="town", km=0.15, seeds=[1], common=[], a=[],
                          b=["localizer.no_such_key=1"], jobs=2)
    assert report["failed"] == [{"side": "b", "seed": 1}]
    assert report["paired_seeds"] == []
    assert "no seed finished on both sides" in tool.summary(report)
    assert "no_such_key" in (tmp_path / "b" / "s1.log").read_text()
