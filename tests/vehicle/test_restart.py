"""A vehicle waits for its shard to be alive; the outbox survives kill -9 of the vehicle
process: a restart finishes the upload over a real router to a real queryable peer process, and
no patch is applied twice."""

import json
import os
import signal
import sqlite3
import threading
import time

import numpy as np

from common.config import load_config
from common.drivelog import DriveLog
from services.vehicle.node import StageTimer, build_mapper, map_log
from services.vehicle.synthetic import write_drive_log
from tests.conftest import spawn

SETS = [
    "--set",
    "grid.shards=1",
    "--set",
    "vehicle.upload_batch=1",
    "--set",
    "vehicle.seal_every_frames=20",
    "--set",
    "vehicle.sparse_seal_every_frames=20",
]


def _applied(db) -> list[str]:
    if not db.exists():
        return []
    con = sqlite3.connect(db)
    try:
        return [r[0] for r in con.execute("SELECT patch_id FROM applied")]
    except sqlite3.OperationalError:
        return []
    finally:
        con.close()


def _vehicle(log, state, router):
    return spawn("vehicle", "--log", log, "--state", state, "--connect", router, "--segmenter",
                 "truth", *SETS)


def _expected_ids(log_dir) -> set[str]:
    cfg = load_config(sets=[s for s in SETS if s != "--set"])
    log = DriveLog(log_dir)
    mapper = build_mapper(log, log.meta.vehicle, cfg)
    patches = []
    map_log(log, mapper, patches.extend, threading.Event(), StageTimer())
    return {p.patch_id for p in patches}


def test_outbox_survives_kill_and_restart_without_double_counting(tmp_path, router):
    log_dir = tmp_path / "log"
    write_drive_log(
        log_dir, np.random.default_rng(2), length_m=200.0, outage_m=(80.0, 130.0), frame_stride=2
    )
    db, state = tmp_path / "peer.db", tmp_path / "state"
    first = _vehicle(log_dir, state, router)  # no shard alive yet: it must wait, not drop
    time.sleep(3.0)
    assert first.poll() is None
    peer = spawn("--connect", router, "--db", db, "--delay", 0.15,
                 module="tests.vehicle.ingest_peer")
    try:
        deadline = time.monotonic() + 60
        while len(_applied(db)) < 3 and time.monotonic() < deadline and first.poll() is None:
            time.sleep(0.05)
        assert first.poll() is None, "the first run finished before it could be killed"
        os.kill(first.pid, signal.SIGKILL)
        first.wait(10)
        applied_before = set(_applied(db))
        assert len(applied_before) >= 3
        assert list((state / "outbox").glob("*.patch")), "nothing left to resend after the kill"

        second = _vehicle(log_dir, state, router)
        _, err = second.communicate(timeout=120)
        assert second.returncode == 0, err.decode()[-3000:]
    finally:
        peer.send_signal(signal.SIGTERM)
        peer.wait(10)

    summary = json.loads((state / "summary.json").read_text())
    applied = _applied(db)
    assert len(applied) == len(set(applied))  # each patch applied once
    assert set(applied) == _expected_ids(log_dir)  # all of them, and the same ids after restart
    assert summary["patches_acked"] == len(applied)
    assert summary["patches_pending"] == 0 and summary["resumed_from_seq"] > 0
    assert not list((state / "outbox").glob("*.patch"))
