"""`roadmap localize --log DIR --out DIR [--id V]`: localize a production drive log against the map.

Reads the drive log, segments each frame (ground-truth segmenter for simulated logs, or the ONNX
model), lifts the labels to the ground (IPM), fetches the tiles around the car from their owner
shards over Zenoh, runs the Localizer, publishes roadmap/pose/<vehicle>, and writes
OUT/trajectory.tum, OUT/diagnostics.jsonl, OUT/localization.json and OUT/config.toml."""

import json
import logging
import math
import time
from pathlib import Path

import numpy as np

from common import codec, keys
from common.bus import open_session
from common.config import to_toml
from common.drivelog import DriveLog
from common.errors import DriveLogError
from common.geometry import quat_wxyz_from_yaw, transform_points_2d
from common.messages import Pose
from services.eval.localization import localization_metrics, summary_line
from services.localizer.frames import FramePoints
from services.localizer.localizer import get_localizer, replay
from services.localizer.map_cache import TileCache
from services.localizer.tiles import TileClient, tiles_needed

logger = logging.getLogger(__name__)


def main(args, cfg) -> int:
    log = DriveLog(args.log)
    vehicle = args.id or log.meta.vehicle
    out = Path(args.out or Path(args.log) / "localize")
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.toml").write_text(to_toml(cfg))
    with open_session(cfg.bus) as session:
        report = localize_log(log, cfg, session, vehicle, out)
    logger.info("%s: %s", vehicle, summary_line(report))
    return 0


def localize_log(log: DriveLog, cfg, session, vehicle: str, out: Path) -> dict:
    """Localize every frame of a log; writes the outputs and returns the localization section."""
    lc = cfg.localizer
    cache = TileCache(capacity=lc.cache_tiles, line_grow_cells=lc.field_line_grow_cells)
    client = TileClient(session, cache, codec_name=lc.map_codec, timeout_s=cfg.bus.query_timeout_s)
    publisher = session.declare_publisher(keys.pose(vehicle)) if lc.publish else None
    loc = get_localizer(lc, cache, camera=log.meta.camera)
    frames = _FrameSource(log, cfg)
    streams = log.streams
    timings = {"segment_ms": [], "frame_ms": [], "fetch_ms": []}
    on_map: list[bool] = []
    diag_file = open(out / "diagnostics.jsonl", "w")
    try:

        def frame_points(i):
            t0 = time.perf_counter()
            client.poll_updates()
            client.ensure(_wanted_tiles(loc, streams, i, lc))
            t1 = time.perf_counter()
            pts = frames.points(i)
            timings["fetch_ms"].append((t1 - t0) * 1e3)
            timings["segment_ms"].append((time.perf_counter() - t1) * 1e3)
            timings["_t"] = time.perf_counter()
            return pts

        def on_estimate(i, est):
            timings["frame_ms"].append((time.perf_counter() - timings["_t"]) * 1e3)
            on_map.append(map_covers_view(cache, streams["frame_pose_true"][i], cfg.roi))
            if publisher is not None and np.all(np.isfinite(est.pose)):
                publisher.put(
                    codec.encode(
                        Pose(
                            vehicle,
                            int(est.t_ns),
                            *map(float, est.pose),
                            np.asarray(est.cov, float),
                            bool(est.ok),
                        )
                    )
                )
            row = _diag_row(i, est, streams)
            row["on_map"] = on_map[-1]
            diag_file.write(json.dumps(row, separators=(",", ":")) + "\n")

        estimates = replay(loc, streams, frame_points, on_estimate)
    finally:
        diag_file.close()
        client.close()
        if publisher is not None:
            publisher.undeclare()
    poses = np.array([e.pose for e in estimates]).reshape(-1, 3)
    write_tum(out / "trajectory.tum", streams["frame_t_ns"][: len(poses)], poses)
    report = localization_metrics(
        streams["frame_t_ns"][: len(poses)],
        poses,
        streams["frame_pose_true"][: len(poses)],
        on_map=np.array(on_map, dtype=bool),
    )
    report.update(
        map_codec=lc.map_codec,
        segmenter=frames.segmenter_name,
        inits=loc.inits,
        tiles_fetched=client.fetched,
        tile_bytes=client.bytes,
        tile_updates=client.updates,
        per_frame_ms=_percentiles(timings),
    )
    (out / "localization.json").write_text(json.dumps(report, indent=1))
    return report


class _FrameSource:
    """Frame i -> ground points (vehicle frame), classes and attitude jacobians: segment, IPM."""

    def __init__(self, log: DriveLog, cfg):
        from common.segmentation import segmenter_for

        self.log = log
        lc, roi = cfg.localizer, cfg.roi
        self.stride = lc.ipm_stride
        self.estimate_attitude = lc.estimate_attitude
        self.roll = lc.attitude_roll
        self.ipm = FramePoints(
            log.meta.camera, x_min_m=roi.x_min_m, length_m=roi.length_m, width_m=roi.width_m
        )
        self.segmenter = segmenter_for(cfg, "localizer", camera=log.meta.camera,
                                       images=not len(log) or log.image(0) is not None)
        self.segmenter_name = self.segmenter.name

    def points(self, i: int):
        truth = self.log.labels(i)
        image = self.log.image(i)
        if image is None and truth is None:
            raise DriveLogError(f"{self.log.root}: frame {i} has neither an image nor labels")
        labels = self.segmenter.segment(image, truth)
        pts, cls, jac = self.ipm.points(labels, stride=self.stride)
        if not self.estimate_attitude:
            return pts, cls
        return pts, cls, (jac if self.roll else jac[:, :, :1])


def map_covers_view(cache, true_pose, roi, min_fraction: float = 0.25) -> bool:
    """Whether the map has road or paint under at least min_fraction of the ROI seen from the
    true pose (a 1 m grid); False without a true pose. Evaluation only: the car does not know it."""
    if not np.all(np.isfinite(true_pose)):
        return False
    xs = roi.x_min_m + 0.5 + np.arange(int(roi.length_m))
    ys = -roi.width_m / 2 + 0.5 + np.arange(int(roi.width_m))
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    world = transform_points_2d(np.asarray(true_pose, dtype=float), grid)
    return bool(np.mean(cache.class_at(world) != 0) >= min_fraction)


def _wanted_tiles(loc, streams, i: int, lc):
    """Around the estimate when tracking, else around the latest GNSS fix before frame i."""
    if loc.ekf.initialized:
        x, y, yaw = loc.ekf.pose
        return tiles_needed(x, y, yaw, radius_m=lc.fetch_radius_m, ahead_m=lc.prefetch_ahead_m)
    t = streams["frame_t_ns"][i]
    k = max(int(np.searchsorted(streams["gnss_t_ns"], t, side="right")) - 1, 0)
    if len(streams["gnss_t_ns"]) == 0:
        return []
    x, y = streams["gnss_xy_m"][k]
    return tiles_needed(x, y, None, radius_m=lc.fetch_radius_m + 10.0, ahead_m=0.0)


def _diag_row(i: int, est, streams) -> dict:
    true = streams["frame_pose_true"][i]
    row = {
        "i": int(i),
        "t_ns": int(est.t_ns),
        "ok": bool(est.ok),
        "pose": [round(float(v), 4) for v in est.pose] if np.all(np.isfinite(est.pose)) else None,
        "sigma_xy_m": [round(float(math.sqrt(max(est.cov[k, k], 0.0))), 4) for k in (0, 1)],
    }
    if row["pose"] is not None and np.all(np.isfinite(true)):
        dx, dy = est.pose[0] - true[0], est.pose[1] - true[1]
        c, s = math.cos(true[2]), math.sin(true[2])
        row["err_lon_m"] = round(c * dx + s * dy, 4)
        row["err_lat_m"] = round(-s * dx + c * dy, 4)
        row["err_yaw_deg"] = round(
            math.degrees(math.remainder(est.pose[2] - true[2], 2 * math.pi)), 4
        )
    row.update(est.diag)
    return row


def write_tum(path: Path, t_ns: np.ndarray, poses: np.ndarray) -> None:
    """TUM trajectory (`timestamp x y z qx qy qz qw`, seconds), frames with an estimate only."""
    with open(path, "w") as f:
        for t, (x, y, yaw) in zip(t_ns, poses, strict=True):
            if not np.all(np.isfinite([x, y, yaw])):
                continue
            w, qx, qy, qz = quat_wxyz_from_yaw(float(yaw))
            f.write(f"{int(t) / 1e9:.9f} {x:.4f} {y:.4f} 0.0 {qx:.8f} {qy:.8f} {qz:.8f} {w:.8f}\n")


def _percentiles(timings: dict) -> dict:
    out = {}
    for name, vals in timings.items():
        if name.startswith("_") or not vals:
            continue
        a = np.asarray(vals)
        out[name] = {"p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95))}
    return out
