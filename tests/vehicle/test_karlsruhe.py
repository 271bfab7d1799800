"""Local map quality of one traversal of the simulated Karlsruhe world (real Lanelet2 HD map),
ground-truth segmenter with corruption, the full mapper with the pose graph (sim noise profile)."""

import threading

import pytest

from common.config import load_config
from common.drivelog import DriveLog
from services.eval.mapping import local_map_quality, pose_errors
from services.vehicle.node import StageTimer, build_mapper, map_log


@pytest.fixture(scope="module")
def karlsruhe_drive(shared_data, tmp_path_factory):
    from services.sim.simulate import simulate_drives
    from services.sim.worlds import load_world

    world = load_world(
        "lanelet2:" + str(shared_data / "lanelet2-karlsruhe" / "mapping_example.osm")
    )
    (path,) = simulate_drives(
        world, tmp_path_factory.mktemp("ka"), profile="mapping", images=False, max_km=0.4
    )
    log = DriveLog(path)
    mapper = build_mapper(log, log.meta.vehicle, load_config(env={}))
    map_log(log, mapper, lambda patches: None, threading.Event(), StageTimer())
    return world, log, mapper


def test_lane_lines_meet_the_quality_target(karlsruhe_drive):
    world, _, mapper = karlsruhe_drive
    labels, x0, y0 = mapper.local_map()
    q = local_map_quality(labels, x0, y0, world)
    assert q["lane_line"]["cells_true"] > 1000
    assert q["lane_line"]["precision"] >= 0.95
    assert q["lane_line"]["recall"] >= 0.90


def test_poses_are_centimetre_level(karlsruhe_drive):
    _, log, mapper = karlsruhe_drive
    err = pose_errors(mapper.trajectory(), log.streams["frame_pose_true"])
    assert err["pose_error_m"]["mean"] <= 0.10
