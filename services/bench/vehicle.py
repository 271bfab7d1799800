"""On-vehicle mapper benchmark: per-stage latency and frames/s on a 640 x 360 stream (no network).

    python -m services.bench.vehicle --out DIR [--quick]   -> DIR/vehicle.json

A seeded synthetic mapping drive (services/vehicle/synthetic.py: curving two-lane road, RTK GNSS
with a 300 m outage, 0.5 % odometry scale error, 0.02 deg/s gyro bias), label frames rendered in
memory. The mapper (segmentation -> IPM -> pose graph -> voting) runs pinned to one core with the
ground-truth segmenter; then on two cores with the ONNX model (our model when it exists, else
TwinLiteNet from ../shared/data) on the colourised frames. Also reports the pose accuracy of the
run and, when ../shared/data exists, the pose graph on the real comma2k19 drive."""

import argparse
import dataclasses
import logging
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

from common.classes import colorize
from common.config import SegmentationConfig
from common.segmentation import DEFAULT_MODEL, configured_onnx, get_segmenter
from services.bench.runner import write_result
from services.eval.mapping import local_map_quality, pose_errors
from services.sim.truth_segmenter import GroundTruthSegmenter
from services.sim.worlds import shared_data_dir
from services.vehicle.mapper import VehicleMapper
from services.vehicle.node import StageTimer, map_log
from services.vehicle.synthetic import LabelRenderer, centreline, drive, mapping_camera, road_world

logger = logging.getLogger("bench.vehicle")
SHARED = shared_data_dir()  # $ROADMAP_SHARED_DATA, else ../shared/data


class MemoryLog:
    """A drive log held in memory (duck-types common.drivelog.DriveLog for map_log)."""

    def __init__(self, streams, labels, images=None):
        self.streams, self._labels, self._images = streams, labels, images

    def __len__(self):
        return len(self._labels)

    def labels(self, i):
        return self._labels[i]

    def image(self, i):
        return None if self._images is None else self._images[i]


def _make_log(length_m: float, outage_m, rng) -> tuple[MemoryLog, object]:
    streams = drive(rng, length_m=length_m, outage_m=outage_m)
    renderer = LabelRenderer(road_world(centreline(length_m)), mapping_camera())
    labels = [renderer.render(p) for p in streams["frame_pose_true"]]
    return MemoryLog(streams, labels), renderer.camera


def _mapper(camera, segmenter):
    return VehicleMapper(
        vehicle="bench",
        traversal="b0",
        camera=camera,
        segmenter=segmenter,
        roi_x_min_m=3.0,
        roi_length_m=8.0,
        roi_width_m=8.0,
    )


def _stage_stats(timer: StageTimer) -> dict:
    out = {}
    for stage, ms in timer.ms.items():
        ms = np.asarray(ms)
        out[stage] = {
            "p50_ms": float(np.percentile(ms, 50)),
            "p95_ms": float(np.percentile(ms, 95)),
            "per_s": float(1e3 / max(ms.mean(), 1e-9)),
        }
    return out


def _run_mapper(log, mapper) -> tuple[StageTimer, float]:
    timer = StageTimer()
    t0 = time.perf_counter()
    map_log(log, mapper, lambda patches: None, threading.Event(), timer)
    return timer, len(log) / (time.perf_counter() - t0)


def _one_core():
    try:
        before = os.sched_getaffinity(0)
        os.sched_setaffinity(0, {min(before)})
        return before
    except (AttributeError, OSError):
        return None


def _onnx_segmenter(camera):
    if DEFAULT_MODEL.exists():  # as the vehicles run it: the camera's sky rows left out
        cfg = dataclasses.replace(SegmentationConfig(), intra_op_threads=2)
        return configured_onnx(cfg, camera=camera), "roadseg"
    twin = SHARED / "models" / "twinlitenet" / "twinlitenet.onnx"
    if twin.exists():
        return get_segmenter("onnx", model_path=twin, intra_op_threads=2), "twinlitenet"
    return None, None


def run(quick: bool = False) -> dict:
    rng = np.random.default_rng(0)
    length = 400.0 if quick else 1100.0
    outage = (150.0, 300.0) if quick else (600.0, 900.0)
    log, camera = _make_log(length, outage, rng)

    # 1. no model, one core: the mapper's own cost
    affinity = _one_core()
    try:
        mapper = _mapper(camera, GroundTruthSegmenter(seed=0))
        timer, fps = _run_mapper(log, mapper)
    finally:
        if affinity:
            os.sched_setaffinity(0, affinity)
    stages = _stage_stats(timer)
    stages = {k: v for k, v in stages.items() if k in ("ipm", "pose_graph", "voting")}
    result = {
        "stages": stages,
        "mapper": {
            "frames_per_s_1_core_no_model": fps,
            "frames": len(log),
            "stream": f"{camera.width}x{camera.height}",
            "per_stage_ms_no_model": _stage_stats(timer),
            **pose_errors(mapper.trajectory(), log.streams["frame_pose_true"]),
            "outage_m": list(outage),
        },
    }

    # 2. with the ONNX model on two cores
    segmenter, model = _onnx_segmenter(camera)
    if segmenter is not None:
        n = 20 if quick else 80
        images = [colorize(lab) for lab in log._labels[:n]]
        sub = {k: v for k, v in log.streams.items()}
        sub["frame_t_ns"], sub["frame_pose_true"] = (
            sub["frame_t_ns"][:n],
            sub["frame_pose_true"][:n],
        )
        mlog = MemoryLog(sub, log._labels[:n], images)
        timer_m, fps_m = _run_mapper(mlog, _mapper(camera, segmenter))
        result["mapper"]["frames_per_s_with_model"] = fps_m
        result["mapper"]["model"] = model
        result["mapper"]["per_stage_ms_with_model"] = _stage_stats(timer_m)
    else:
        result["mapper"]["frames_per_s_with_model"] = None
        result["mapper"]["model"] = "none found"

    # 3. the pose graph on real data
    seg = SHARED / "comma2k19" / "segment40"
    if seg.is_dir():
        from services.eval.comma2k19 import evaluate

        result["mapper"]["comma2k19"] = evaluate(seg)

    # 4. one traversal of the simulated Karlsruhe world: map quality and poses (full run only)
    osm = SHARED / "lanelet2-karlsruhe" / "mapping_example.osm"
    if not quick and osm.exists():
        result["mapper"]["karlsruhe"] = karlsruhe_traversal(osm)
    return result


def karlsruhe_traversal(osm: Path, max_km: float | None = None) -> dict:
    """Simulate one mapping drive (labels only) and map it with the node's configuration."""
    import tempfile

    from common.config import load_config
    from common.drivelog import DriveLog
    from services.sim.simulate import simulate_drives
    from services.sim.worlds import load_world
    from services.vehicle.node import build_mapper

    world = load_world(f"lanelet2:{osm}")
    with tempfile.TemporaryDirectory() as tmp:
        (path,) = simulate_drives(world, tmp, profile="mapping", images=False, max_km=max_km)
        log = DriveLog(path)
        mapper = build_mapper(log, log.meta.vehicle, load_config(env={}))
        timer, fps = _run_mapper(log, mapper)
        labels, x0, y0 = mapper.local_map()
        km = (
            float(
                np.sum(
                    np.linalg.norm(np.diff(log.streams["frame_pose_true"][:, :2], axis=0), axis=1)
                )
            )
            / 1000.0
        )
        return {
            "km": km,
            "frames": len(log),
            "gnss_ok_fraction": float(log.streams["gnss_ok"].mean()),
            "quality": local_map_quality(labels, x0, y0, world),
            **pose_errors(mapper.trajectory(), log.streams["frame_pose_true"]),
            "calibration": {
                "odometry_scale": mapper.estimator.calibration.scale,
                "gyro_bias_dps": float(np.degrees(mapper.estimator.calibration.gyro_bias_rps)),
            },
            "frames_per_s": fps,
        }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO)
    result = run(args.quick)
    write_result(args.out, "vehicle.json", result, result["mapper"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
