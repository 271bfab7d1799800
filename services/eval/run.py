"""Running the suite's drives: one `roadmap demo` process per drive, up to `workers` at a time,
each in DIR/drives/<name>/, scored there (drive.json). A drive already scored with the same
settings is read back, so a suite resumes or grows; DIR/settings.json records the settings and
a folder made with others is refused."""

import dataclasses
import json
import logging
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from common.config import DemoConfig, RoiConfig
from common.errors import ConfigError
from services.eval.score import score_drive
from services.eval.suite import PRODUCTION_KM, Drive
from services.sim.worlds import load_world

logger = logging.getLogger(__name__)

DRIVE_TIMEOUT_S = 1800.0


def drive_world(drive_dir: Path):
    """The world (with its truth) a suite drive's folder was run on, as its drive.json names."""
    info = json.loads((Path(drive_dir) / "drive.json").read_text())
    return load_world(info["world"], info["seed"])


def suite_settings(sets: list[str], vehicles: int) -> dict:
    """What every drive of a suite folder shares: the demo's options and config overrides."""
    base = [f"demo.max_km={PRODUCTION_KM}"]
    if any(f.name == "compare_raw_map" for f in dataclasses.fields(DemoConfig)):
        base.append("demo.compare_raw_map=false")  # the suite scores the compressed map only
    return {"vehicles": vehicles, "sets": base + list(sets)}


def check_settings(out: Path, settings: dict) -> None:
    path = out / "settings.json"
    if path.exists():
        old = json.loads(path.read_text())
        if old != settings:
            raise ConfigError(f"{out} holds drives run with other settings ({old}); "
                              "use another --out")
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(settings, indent=1))


def demo_argv(drive: Drive, out: Path, settings: dict) -> list[str]:
    argv = [sys.executable, "-m", "services.cli", "demo", "--world", drive.world,
            "--seed", str(drive.seed), "--vehicles", str(settings["vehicles"]),
            "--out", str(out)]
    for s in settings["sets"]:
        argv += ["--set", s]
    return argv


def run_drive(drive: Drive, root: Path, settings: dict) -> dict:
    """{world, seed, ok, report, score} of one drive (ok False with the error when it failed)."""
    out = root / "drives" / drive.name
    done = out / "drive.json"
    if done.exists():
        return json.loads(done.read_text())
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    with open(out / "demo.log", "w") as log:
        try:
            rc = subprocess.call(demo_argv(drive, out, settings), stdout=log,
                                 stderr=subprocess.STDOUT, timeout=DRIVE_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            rc = "timeout"
    entry = {"world": drive.world, "seed": drive.seed, "name": drive.name,
             "wall_s": round(time.monotonic() - t0, 1)}
    if rc != 0:
        tail = (out / "demo.log").read_text()[-1500:]
        logger.warning("%s failed (%s): %s", drive.name, rc, tail.splitlines()[-1:] or "")
        return {**entry, "ok": False, "error": f"demo exited {rc}: {tail}"}
    entry.update(ok=True, report=json.loads((out / "report.json").read_text()),
                 score=score_drive(out, RoiConfig()))
    done.write_text(json.dumps(entry))
    return entry


def run_suite(drives: list[Drive], root: Path, settings: dict, workers: int) -> list[dict]:
    """Every drive's entry, in the order given; up to `workers` demos at once."""
    check_settings(root, settings)
    finished = []

    def one(drive):
        entry = run_drive(drive, root, settings)
        finished.append(drive.name)
        logger.info("[%d/%d] %s: %s", len(finished), len(drives), drive.name,
                    "ok" if entry["ok"] else "FAILED")
        return entry

    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        return list(pool.map(one, drives))
