"""IPM against analytic projection, and the mapper's local map quality on a synthetic drive."""

import numpy as np
import pytest

from common.camera import build_ipm_lookup
from common.config import load_config
from common.drivelog import STREAM_KEYS, DriveLog, DriveLogMeta, DriveLogWriter
from common.segmentation import DEFAULT_MODEL
from services.eval.mapping import local_map_quality
from services.sim.truth_segmenter import GroundTruthSegmenter
from services.vehicle.mapper import VehicleMapper
from services.vehicle.node import StageTimer, build_mapper, map_log
from services.vehicle.synthetic import mapping_camera, write_drive_log


def test_ipm_matches_analytic_projection(rng):
    cam = mapping_camera()
    ipm = build_ipm_lookup(cam, x_min_m=3.0, length_m=12.0, width_m=8.0)
    ground = np.stack([rng.uniform(3.5, 14.5, 300), rng.uniform(-3.5, 3.5, 300), np.zeros(300)], 1)
    uv, front = cam.project_vehicle_points(ground)
    inside = (
        front & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    )
    assert inside.sum() > 200
    ground, uv = ground[inside], uv[inside]
    labels = np.zeros((cam.height, cam.width), np.uint8)
    u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    labels[v, u] = 2
    xy, cls = ipm.lookup(labels)
    assert len(xy) == len(np.unique(v * cam.width + u)) and np.all(cls == 2)
    # each looked-up pixel centre lies within its pixel's ground footprint of a true point
    d = np.linalg.norm(xy[:, None, :] - ground[None, :, :2], axis=2).min(axis=1)
    range_m = np.linalg.norm(xy, axis=1)
    footprint = range_m * range_m / (cam.K[0, 0] * cam.T_vehicle_camera[2, 3])  # m per pixel
    assert np.all(d <= 0.6 * footprint + 0.02)


@pytest.fixture(scope="module")
def mapped(tmp_path_factory):
    root = tmp_path_factory.mktemp("drive") / "log"
    _, world, streams = write_drive_log(
        root, np.random.default_rng(1), length_m=260.0, outage_m=(80.0, 180.0), frame_stride=2
    )
    log = DriveLog(root)
    mapper = VehicleMapper(
        vehicle="map-0",
        traversal="d0",
        camera=log.meta.camera,
        segmenter=GroundTruthSegmenter(seed=0),
        roi_x_min_m=3.0,
        roi_length_m=12.0,
        roi_width_m=8.0,
        seal_every_frames=50,
    )
    patches = []
    import threading

    map_log(log, mapper, patches.extend, threading.Event(), StageTimer())
    return mapper, world, streams, patches


def test_local_map_quality_with_truth_segmenter(mapped):
    mapper, world, _, _ = mapped
    labels, x0, y0 = mapper.local_map()
    q = local_map_quality(labels, x0, y0, world)
    assert q["lane_line"]["precision"] >= 0.95
    assert q["lane_line"]["recall"] >= 0.90
    assert q["stop_line"]["recall"] >= 0.8


def test_points_are_committed_with_optimized_poses(mapped):
    mapper, _, streams, patches = mapped
    truth = streams["frame_pose_true"]
    poses = np.array([mapper.poses[i] for i in range(len(mapper.poses))])
    assert len(poses) == len(truth)
    assert np.linalg.norm(poses[:, :2] - truth[:, :2], axis=1).mean() < 0.05
    assert len({p.patch_id for p in patches}) == len(patches)
    assert sum(int(p.votes.sum()) for p in patches) == int(mapper.grid.items()[1].astype(int).sum())


@pytest.mark.skipif(not DEFAULT_MODEL.is_file(), reason="no packaged model")
def test_the_fleet_votes_only_paint_its_model_is_sure_of(tmp_path):
    """vehicle.paint_min_margin reaches the ONNX segmenter the mapper runs (localizer: its own)."""
    meta = DriveLogMeta(vehicle="map-0", traversal="t0", profile="mapping",
                        world={"name": "x", "origin_lat": 0.0, "origin_lon": 0.0},
                        camera=mapping_camera(), notes={})
    writer = DriveLogWriter(tmp_path / "log", meta)
    writer.write_frame(0, np.full((360, 640, 3), 90, np.uint8), None)
    writer.close({k: np.zeros(1) for k in STREAM_KEYS})
    log = DriveLog(tmp_path / "log")
    onnx = 'segmentation.kind="onnx"'
    mapper = build_mapper(log, "map-0", load_config(env={}, sets=[onnx]))
    assert mapper.segmenter.min_margin == 1.0
    cfg = load_config(env={}, sets=[onnx, "vehicle.paint_min_margin=0.5"])
    assert build_mapper(log, "map-0", cfg).segmenter.min_margin == 0.5
    assert cfg.localizer.paint_min_margin == 0.0
