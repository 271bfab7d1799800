"""Status and export against a live local fleet, and the demo's viewer during its run.

The fleet: a real router, a `roadmap merger` shard on a fresh store, a `roadmap vehicle` mapping
the Karlsruhe demo's mapping drive and a `roadmap localize` on its production drive, all real
processes. `roadmap status` sees the shard, its tiles and regions, patches/s while the vehicle
uploads, and the vehicle and the localizer alive; `roadmap export --connect` writes what the
shard's store holds."""

import json
import time
import urllib.request

import pytest

from common.bus import free_tcp_port, open_session
from common.config import BusConfig
from services.status import fleet_status
from tests import fleet
from tests.tools.conftest import roadmap_ok

pytestmark = [pytest.mark.integration, pytest.mark.shared_data]


def test_status_and_export_against_a_live_fleet(karlsruhe_demo, router, tmp_path):
    demo = karlsruhe_demo.out
    config = demo / "config.toml"  # the demo's effective config: 1 shard, truth segmenters
    (mapping,) = sorted((demo / "drives" / "mapping").iterdir())
    (production,) = sorted((demo / "drives" / "production").iterdir())
    store = tmp_path / "s0.sqlite"
    shard = fleet.start_merger(router, store, tmp_path / "merger.log")
    procs = [shard]
    try:
        with open_session(BusConfig(connect=[router])) as session:
            fleet.wait_alive(session, "merger", "s0")
            vehicle = fleet.start("vehicle", "--log", mapping, "--id", "car-a", "--state",
                                  tmp_path / "car-a", "--segmenter", "truth", "--config", config,
                                  "--connect", router, log=tmp_path / "vehicle.log")
            localizer = fleet.start("localize", "--log", production, "--id", "car-b", "--out",
                                    tmp_path / "loc", "--config", config, "--connect", router,
                                    log=tmp_path / "localizer.log")
            procs += [vehicle, localizer]
            samples = _sample(session, vehicle, localizer)
            assert vehicle.wait(120) == 0, (tmp_path / "vehicle.log").read_text()[-3000:]
            assert any("car-a" in s["alive"]["vehicle"] for s in samples), samples[-1]
            assert any("car-b" in s["alive"]["localizer"] for s in samples), samples[-1]
            assert all(s["alive"]["merger"] == ["s0"] for s in samples)
            assert max(s["totals"]["patches_per_s"] or 0 for s in samples) > 0
        status = json.loads(roadmap_ok("status", "--json", "--connect", router,
                                       "--interval", "0.3").stdout)
        (row,) = status["shards"]
        summary = json.loads((tmp_path / "car-a" / "summary.json").read_text())
        assert row["id"] == "s0" and row["alive"] and row["errors"] == 0
        assert row["patches_applied"] == summary["patches_acked"] > 0
        assert row["tiles"] == karlsruhe_demo.report["map"]["tiles"] and row["regions"] >= 1
        assert status["counts"]["vehicles_alive"] == 0  # done and gone
        text = roadmap_ok("status", "--connect", router, "--interval", "0.3").stdout
        assert "s0" in text and "vehicles alive" in text and "localizers alive" in text

        # the map over Zenoh is the map in the shard's store (read while the shard runs)
        lat, lon = status_origin(demo)
        origin = ["--set", f"world.origin_lat_deg={lat}", "--set", f"world.origin_lon_deg={lon}"]
        (tmp_path / "zenoh").mkdir()
        (tmp_path / "disk").mkdir()
        roadmap_ok("export", "--format", "geojson", "--connect", router, *origin,
                   "--out", tmp_path / "zenoh" / "map.geojson")
        roadmap_ok("export", "--format", "geojson", "--from", store, *origin,
                   "--out", tmp_path / "disk" / "map.geojson")
        live = json.loads((tmp_path / "zenoh" / "map.geojson").read_text())
        assert live["features"] and live == json.loads(
            (tmp_path / "disk" / "map.geojson").read_text())
    finally:
        fleet.stop(*reversed(procs))


def status_origin(demo) -> tuple[float, float]:
    log = json.loads(next((demo / "drives").glob("*/*/log.json")).read_text())
    return log["world"]["origin_lat"], log["world"]["origin_lon"]


def _sample(session, vehicle, localizer, timeout_s: float = 120.0) -> list[dict]:
    """fleet_status back to back (0.5 s windows) until both the vehicle and the localizer were
    seen alive and the vehicle is done, or one of them ended before it was seen."""
    samples, deadline = [], time.monotonic() + timeout_s
    seen = {"vehicle": False, "localizer": False}
    while time.monotonic() < deadline:
        s = fleet_status(session, interval_s=0.5)
        samples.append(s)
        seen["vehicle"] |= bool(s["alive"]["vehicle"])
        seen["localizer"] |= bool(s["alive"]["localizer"])
        if vehicle.poll() is not None and (all(seen.values()) or localizer.poll() is not None):
            return samples
    raise AssertionError(f"fleet status: not every process seen within {timeout_s:.0f} s: "
                         f"{seen}")


def test_demo_kept_the_viewer_up_during_the_run(karlsruhe_demo):
    """`roadmap demo --viewer PORT`: the page answered during the run, showed the shard's
    tiles at their final versions, the vehicle and the localizer alive and the car's pose; it is
    gone once the demo ended."""
    states = karlsruhe_demo.viewer_states
    assert len(states) >= 5, len(states)
    report = karlsruhe_demo.report
    tiles = {(t["tx"], t["ty"]): t["version"] for t in states[-1]["tiles"]}
    assert len(tiles) == report["map"]["tiles"]
    assert sorted(tiles.values()) == sorted(report["run"]["tile_versions"])
    assert all(t["shard"] == "s0" for t in states[-1]["tiles"])
    assert any(s["alive"].get("vehicle") for s in states)
    assert any(s["alive"].get("localizer") for s in states)
    assert any(p["vehicle"] for s in states for p in s["poses"])
    with pytest.raises(OSError):
        urllib.request.urlopen(f"http://127.0.0.1:{karlsruhe_demo.viewer_port}/api/state",
                               timeout=1.0)


def test_status_and_viewer_of_a_demo_folder(karlsruhe_demo, tmp_path):
    """Against a demo's output instead of a live fleet: what its shard store holds."""
    report = karlsruhe_demo.report
    status = json.loads(roadmap_ok("status", "--json", "--from", karlsruhe_demo.out).stdout)
    (row,) = status["shards"]
    assert row["id"] == "s0" and row["alive"] is None and row["patches_per_s"] is None
    assert row["patches_applied"] == report["pipeline"]["patches_applied"]
    assert row["tiles"] == report["map"]["tiles"] and row["regions"] >= 1
    port = free_tcp_port()
    viewer = fleet.start("viewer", "--from", karlsruhe_demo.out, "--port", port,
                         log=tmp_path / "viewer.log")
    try:
        url = f"http://127.0.0.1:{port}/api/state"
        fleet.wait_http(url, viewer, tmp_path / "viewer.log")
        state = fleet.http_json(url)
        versions = sorted(t["version"] for t in state["tiles"])
        assert versions == sorted(report["run"]["tile_versions"])
        assert {t["shard"] for t in state["tiles"]} == {"s0"}
        tile = state["tiles"][0]
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/tile/{tile['tx']}/"
                                    f"{tile['ty']}.png") as r:
            assert r.headers["Content-Type"] == "image/png" and len(r.read()) > 100
    finally:
        fleet.stop(viewer)
