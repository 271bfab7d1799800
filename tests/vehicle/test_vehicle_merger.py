"""The vehicle node against a real merger shard process over a real router: every patch acked and
applied once; a vehicle that re-maps the same drive from scratch gets only duplicates."""

import json
import signal
import time

import numpy as np
import pytest

from common import codec, keys
from common.bus import open_session
from common.config import BusConfig
from common.drivelog import DriveLog
from common.messages import Stats
from services.eval.mapping import pose_errors
from services.vehicle.outputs import read_poses
from services.vehicle.synthetic import write_drive_log
from tests.conftest import roadmap, spawn

SETS = ["--set", "grid.shards=1", "--set", "vehicle.seal_every_frames=40"]


FORMS = {"cells": [], "sparse": ["--set", "vehicle.patch_form=sparse",
                                  "--set", "vehicle.sparse_seal_every_frames=40"]}


def _run_vehicle(log, state, router, form=()):
    return roadmap("vehicle", "--log", log, "--state", state, "--connect", router, "--segmenter",
                   "truth", *SETS, *form, timeout=180)


def _merger_counters(router) -> dict:
    with open_session(BusConfig(connect=[router])) as session:
        for _ in range(50):
            for reply in session.get(keys.stats("merger", "s0"), timeout=5.0):
                if reply.ok is not None:
                    return codec.decode(reply.ok.payload.to_bytes(), expect=Stats).counters
            time.sleep(0.1)
    raise AssertionError("merger stats never answered")


@pytest.mark.parametrize("form", sorted(FORMS))
def test_vehicle_uploads_to_a_real_shard_exactly_once(tmp_path, router, form):
    log = tmp_path / "log"
    write_drive_log(log, np.random.default_rng(3), length_m=160.0, outage_m=None, frame_stride=2)
    merger = spawn("merger", "--shard", 0, "--shards", 1, "--store", tmp_path / "s0.sqlite",
                   "--connect", router, *SETS)
    try:
        first = _run_vehicle(log, tmp_path / "state-a", router, FORMS[form])
        assert first.returncode == 0, first.stderr[-3000:]
        a = json.loads((tmp_path / "state-a" / "summary.json").read_text())
        assert a["patches_acked"] == a["patches_accepted"] > 0 and a["duplicates"] == 0
        applied = _merger_counters(router)["patches_applied"]
        assert applied == a["patches_accepted"]
        assert "pose_error_m" not in a  # accuracy is the harness's, from the node's poses:
        truth = DriveLog(log).streams["frame_pose_true"]
        err = pose_errors(read_poses(tmp_path / "state-a"), truth)
        assert err["pose_error_m"]["mean"] < 0.05
        assert len(np.loadtxt(tmp_path / "state-a" / "trajectory.tum")) == a["frames"]

        second = _run_vehicle(log, tmp_path / "state-b", router, FORMS[form])  # fresh state
        assert second.returncode == 0, second.stderr[-3000:]
        b = json.loads((tmp_path / "state-b" / "summary.json").read_text())
        assert b["duplicates"] == b["patches_acked"] == a["patches_acked"]
        assert _merger_counters(router)["patches_applied"] == applied
    finally:
        merger.send_signal(signal.SIGTERM)
        merger.wait(15)
