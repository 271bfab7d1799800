"""Outbox: durable patches until acked, progress for restarts, counters from the ack log."""

import json

import numpy as np

from common.messages import GridPatch
from services.vehicle.outbox import Outbox
from services.vehicle.voting import patch_id


def _patch(seq, tile=(0, 0)):
    return GridPatch(
        patch_id=patch_id("map-0", "d0", tile, seq),
        vehicle="map-0",
        tile=tile,
        cells=np.array([1, 5], np.uint32),
        votes=np.ones((2, 6), np.uint16),
        t_first_ns=0,
        t_last_ns=1,
        traversal="d0",
    )


def test_patches_stay_until_acked_and_survive_a_reopen(tmp_path):
    box = Outbox(tmp_path)
    box.put([_patch(0), _patch(1), _patch(2, (1, 0))])
    box.ack({_patch(0).patch_id: "accepted"})
    again = Outbox(tmp_path)
    assert sorted(again.pending()) == sorted([_patch(1).patch_id, _patch(2, (1, 0)).patch_id])
    assert again.load(_patch(2, (1, 0)).patch_id).tile == (1, 0)
    assert again.counts() == {"acked": 1, "accepted": 1, "duplicates": 0}


def test_acked_patches_are_not_rewritten_and_not_counted_twice(tmp_path):
    box = Outbox(tmp_path)
    box.put([_patch(0)])
    box.ack({_patch(0).patch_id: "accepted"})
    box.put([_patch(0)])  # a restarted vehicle re-maps the same patch
    assert box.pending() == []
    box.ack({_patch(0).patch_id: "duplicate"})
    assert Outbox(tmp_path).counts() == {"acked": 1, "accepted": 1, "duplicates": 0}


def test_torn_ack_line_and_tmp_files_are_tolerated(tmp_path):
    box = Outbox(tmp_path)
    box.put([_patch(0), _patch(1)])
    with open(tmp_path / "acked.log", "a") as f:
        f.write("map-0.d0.0_0.0000")  # crash in the middle of an append
    (tmp_path / "outbox" / "x.patch.tmp").write_bytes(b"partial")
    box = Outbox(tmp_path)
    assert not list((tmp_path / "outbox").glob("*.tmp"))
    box.ack({_patch(1).patch_id: "accepted"})
    assert Outbox(tmp_path).counts()["acked"] == 1
    assert Outbox(tmp_path).pending() == [_patch(0).patch_id]


def test_progress_is_per_traversal(tmp_path):
    box = Outbox(tmp_path)
    assert box.sealed("d0") == 0
    box.set_sealed("d0", 4)
    assert Outbox(tmp_path).sealed("d0") == 4
    assert Outbox(tmp_path).sealed("d1") == 0


def test_the_mapping_progress_file_leaves_the_sealed_count_a_restart_resumes_from(tmp_path):
    """The vehicle's frames-done file (roadmap demo's progress line) is not the outbox's
    progress.json: writing it once clobbered the sealed count, so a restarted vehicle re-sealed
    its drive from the start."""
    from types import SimpleNamespace

    from services.vehicle.node import FRAMES_FILE, VehicleRun

    Outbox(tmp_path).set_sealed("d0", 7)
    VehicleRun.progress(SimpleNamespace(state=tmp_path, _next_progress=0.0), 120, 900)
    assert Outbox(tmp_path).sealed("d0") == 7
    assert json.loads((tmp_path / FRAMES_FILE).read_text()) == {"frames_done": 120, "frames": 900}
