"""End to end: `roadmap demo --small` with real processes (router, 2 merger shards, 2 mapping
vehicles, 1 localizer) on the procedural town, and the same run with chaos (SIGKILL + restart of
a shard and a vehicle in the middle of mapping) over mutual TLS with the role ACL (--secure).
Bounds are stated next to each assertion."""

import json
import os
import socket
from pathlib import Path

import pytest

from tests.conftest import REPO, spawn

pytestmark = pytest.mark.integration

# the true labels (segmentation.kind truth, not the default model): the fleet's mechanics, in
# CI time (the model on rendered frames: tests/vehicle/test_mapping.py, bench, roadmap demo)
ARGS = ["--small", "--world", "town", "--vehicles", "2", "--shards", "2", "--seed", "3",
        "--set", 'segmentation.kind="truth"']


def _demos(runs: dict[Path, list[str]], timeout: float = 400) -> dict:
    """`roadmap demo ARGS EXTRA --out DIR` for each {DIR: EXTRA}, all at once (each its own
    router on its own port, its own shards, vehicles and localizer: two fleets on one machine,
    and the fixture's time about 0.65x of one run after the other) -> {DIR: report}."""
    procs = {}
    for out, extra in runs.items():
        with open(f"{out}.stdout", "w") as stdout, open(f"{out}.stderr", "w") as stderr:
            procs[out] = spawn("demo", *ARGS, *extra, "--out", out, stdout=stdout,
                               stderr=stderr)
    try:
        for proc in procs.values():
            proc.wait(timeout=timeout)
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    reports = {}
    for out, proc in procs.items():
        stdout, stderr = (Path(f"{out}.{s}").read_text() for s in ("stdout", "stderr"))
        assert proc.returncode == 0, f"demo {out} failed:\n{stdout[-3000:]}\n{stderr[-6000:]}"
        assert "paper mean" in stdout  # the printed table
        reports[out] = json.loads((out / "report.json").read_text())
    return reports


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    base = tmp_path_factory.mktemp("demo")
    reports = _demos({base / "plain": [], base / "chaos": ["--chaos", "--secure"]})
    return {name: (base / name, reports[base / name]) for name in ("plain", "chaos")}


def _no_leftover_processes(report: dict, out: Path) -> None:
    for name, events in report["processes"].items():
        for e in events:
            if e["event"] != "start":
                continue
            try:
                cmdline = Path(f"/proc/{e['pid']}/cmdline").read_bytes().decode(errors="replace")
            except OSError:
                continue  # gone, as it should be
            assert str(out) not in cmdline and "services.cli" not in cmdline, f"{name} still runs"


def test_report_follows_the_contract(runs):
    _, r = runs["plain"]
    sections = ("world", "map", "segmentation", "mapping", "localization", "pipeline", "timings")
    for section in sections:
        assert section in r, section
    assert {"kb_per_km", "raw_kb_per_km", "png_kb_per_km", "per_class", "digest"} <= set(r["map"])
    assert {"lane_line", "stop_line", "crosswalk", "ground_sign"} == set(r["map"]["per_class"])
    for key in ("x_m", "y_m", "yaw_deg", "lateral_m", "longitudinal_m"):
        assert {"mean", "p90", "max"} <= set(r["localization"][key])
    assert r["world"]["km_mapped"] > 0.1  # a --small drive is ~0.2 km
    # the second localization on the uncompressed map runs only with demo.compare_raw_map
    assert "uncompressed_map" not in r["localization"]


def test_pipeline_counts_are_consistent(runs):
    p = runs["plain"][1]["pipeline"]
    assert p["patches_applied"] > 0
    assert p["patches_acked"] == p["patches_applied"]  # nothing lost, nothing counted twice
    assert p["errors"] == 0
    assert p["patches_sent"] >= p["patches_acked"]
    # sparse/1 patches (the cells form: ~1 byte per swept 0.1 m cell, ~860 KB/km); a --small
    # drive's few patches carry their seams and key poses over fewer km
    assert 0 < p["upload_kb_per_km_driven"] < 30


def test_map_quality_and_size(runs):
    m = runs["plain"][1]["map"]
    lane = m["per_class"]["lane_line"]
    assert lane["precision"] >= 0.85 and lane["recall"] >= 0.8  # vs ground truth, 0.1 m tol.
    assert lane["codec_precision"] >= 0.95 and lane["codec_recall"] >= 0.95  # decoded vs merged
    assert 0 < m["kb_per_km"] < 100  # the paper: 36 KB/km
    assert m["kb_per_km"] < m["png_kb_per_km"] < m["raw_kb_per_km"]


def test_localization_within_bounds(runs):
    loc = runs["plain"][1]["localization"]
    assert loc["convergence_s"] is not None, f"the localizer never converged: {loc}"
    # a 0.2 km drive leaves the filter little time after convergence: loose bounds
    assert loc["lateral_m"]["mean"] < 0.5
    assert loc["yaw_deg"]["mean"] < 2.0
    assert loc["x_m"]["mean"] < 2.0 and loc["y_m"]["mean"] < 2.0
    assert loc["frames"] > 50


def test_figures_written(runs):
    out, _ = runs["plain"]
    for name in ("map.png", "compression.png", "trajectory.png", "errors.png"):
        assert (out / name).stat().st_size > 1000, name


def test_everything_stopped(runs):
    for out, report in runs.values():
        _no_leftover_processes(report, out)
        host, port = report["run"]["router"].split("/", 1)[1].rsplit(":", 1)
        with socket.socket() as s, pytest.raises(OSError):  # the router's port is closed
            s.settimeout(1.0)
            s.connect((host, int(port)))


def test_chaos_loses_nothing_and_keeps_the_map(runs):
    _, plain = runs["plain"]
    _, chaos = runs["chaos"]
    events = chaos["run"]["chaos_events"]
    killed = {e["process"] for e in events if e["event"] == "SIGKILL"}
    assert any(k.startswith("merger-s") for k in killed)
    assert any(k.startswith("vehicle") for k in killed)
    kills = [e for e in events if e["event"] == "SIGKILL"]
    assert kills[0]["shard_applied_before"] > 0  # the shard had to replay its store
    p = chaos["pipeline"]
    assert p["patches_acked"] == p["patches_applied"] == plain["pipeline"]["patches_applied"]
    assert chaos["map"]["digest"] == plain["map"]["digest"]  # same seed, same map


def test_the_chaos_run_is_secure(runs):
    """--secure (throwaway certificates): every role over tls/ with only its own rights, and
    still the plain run's map (test_chaos_loses_nothing_and_keeps_the_map)."""
    out, chaos = runs["chaos"]
    assert chaos["run"]["router"].startswith("tls/")
    assert (out / "certs" / "ca.pem").is_file()
    assert chaos["localization"]["convergence_s"] is not None  # the localizer got its tiles


@pytest.mark.skipif(os.environ.get("ROADMAP_SKIP_COMPOSE_CHECK") == "1", reason="disabled")
def test_compose_file_parses():
    yaml = pytest.importorskip("yaml")
    doc = yaml.safe_load((REPO / "compose.yaml").read_text())
    services = doc["services"]
    assert services["zenoh-router"]["image"].startswith("eclipse/zenoh:1.10")
    shards = [s for s in services if s.startswith("merger-")]
    assert len(shards) >= 2
    volumes = [services[s]["volumes"][0].split(":")[0] for s in shards]
    assert len(set(volumes)) == len(shards)  # each shard its own volume
    for s in shards:
        assert "healthcheck" in services[s]
        assert "ROADMAP_BUS__CONNECT" in services[s]["environment"]
