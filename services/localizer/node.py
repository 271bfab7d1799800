"""`roadmap localize --log DIR --out DIR [--id V]`: localize a production drive log against the map.

Reads the drive log, segments each frame (ground-truth segmenter for simulated logs, or the ONNX
model), lifts the labels to the ground (IPM), fetches the tiles around the car from their owner
shards over Zenoh, runs the Localizer, publishes roadmap/pose/<vehicle> (holding the liveliness
token roadmap/alive/localizer/<vehicle> meanwhile), and writes
OUT/trajectory.tum, OUT/diagnostics.jsonl, OUT/tiles.npz, OUT/summary.json and OUT/config.toml
(services/localizer/outputs.py). It never reads the true poses: the accuracy of its estimates is
the evaluation harness's (services/eval/localization.py)."""

import json
import logging
import time
from pathlib import Path

import numpy as np

from common import codec, keys
from common.bus import open_session
from common.config import to_toml
from common.drivelog import DriveLog
from common.errors import DriveLogError
from common.messages import Pose
from common.trajectory import write_tum
from services.localizer.frames import FramePoints
from services.localizer.localizer import get_localizer, replay
from services.localizer.map_cache import get_tile_cache
from services.localizer.outputs import TileLog, diag_row, write_summary
from services.localizer.tiles import TileClient, tiles_needed

logger = logging.getLogger(__name__)


def main(args, cfg) -> int:
    log = DriveLog(args.log)
    vehicle = args.id or log.meta.vehicle
    out = Path(args.out or Path(args.log) / "localize")
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.toml").write_text(to_toml(cfg))
    with open_session(cfg.bus, "localizer") as session:
        token = session.liveliness().declare_token(keys.alive("localizer", vehicle))
        try:
            localize_log(log, cfg, session, vehicle, out)
        finally:
            token.undeclare()
    return 0


def localize_log(log: DriveLog, cfg, session, vehicle: str, out: Path) -> dict:
    """Localize every frame of a log; writes the outputs and returns the summary."""
    run = _LocalizerRun(log, cfg, session, vehicle, out)  # tile client, publisher, localizer
    try:
        estimates = replay(run.loc, log.streams, run.frame_points, run.on_estimate)
    finally:
        run.close()
    summary = run.write_outputs(estimates)  # trajectory, received tiles, summary
    ok = sum(bool(e.ok) for e in estimates)
    logger.info("%s: %d frames, %d with an integrity-ok estimate, %d initializations, %d tiles "
                "(%d bytes)", vehicle, len(estimates), ok, summary["inits"],
                summary["tiles_fetched"], summary["tile_bytes"])
    return summary


class _LocalizerRun:
    """The transport around one drive's Localizer: the tile client, the pose publisher, the frame
    source, per-frame timings, and the outputs written as the frames come."""

    def __init__(self, log: DriveLog, cfg, session, vehicle: str, out: Path):
        lc = self.lc = cfg.localizer
        self.vehicle, self.out, self.streams = vehicle, out, log.streams
        self.cache = get_tile_cache(lc)
        self.tiles = TileLog()  # the map as received: tiles.npz
        self.client = TileClient(session, self.cache, codec_name=lc.map_codec,
                                 timeout_s=cfg.bus.query_timeout_s, on_tile=self.tiles.add)
        self.publisher = session.declare_publisher(keys.pose(vehicle)) if lc.publish else None
        self.loc = get_localizer(lc, self.cache, camera=log.meta.camera)
        self.frames = _FrameSource(log, cfg)
        self.timings = {"segment_ms": [], "frame_ms": [], "fetch_ms": []}
        self._t_points = 0.0
        self.diag_file = open(out / "diagnostics.jsonl", "w")

    def frame_points(self, i: int):
        """The tiles around the car, then frame i's ground points (fetch and segment timed)."""
        self.tiles.frame = i
        t0 = time.perf_counter()
        self.client.poll_updates()
        self.client.ensure(_wanted_tiles(self.loc, self.streams, i, self.lc))
        t1 = time.perf_counter()
        pts = self.frames.points(i)
        self.timings["fetch_ms"].append((t1 - t0) * 1e3)
        self.timings["segment_ms"].append((time.perf_counter() - t1) * 1e3)
        self._t_points = time.perf_counter()
        return pts

    def on_estimate(self, i: int, est) -> None:
        """Frame i's estimate: its time since the points (frame_ms), published, one diagnostics
        line."""
        self.timings["frame_ms"].append((time.perf_counter() - self._t_points) * 1e3)
        if self.publisher is not None and np.all(np.isfinite(est.pose)):
            pose = Pose(self.vehicle, int(est.t_ns), *map(float, est.pose),
                        np.asarray(est.cov, float), bool(est.ok))
            self.publisher.put(codec.encode(pose))
        self.diag_file.write(json.dumps(diag_row(i, est), separators=(",", ":")) + "\n")

    def close(self) -> None:
        self.diag_file.close()
        self.client.close()
        if self.publisher is not None:
            self.publisher.undeclare()

    def write_outputs(self, estimates: list) -> dict:
        """trajectory.tum, tiles.npz and summary.json; returns the summary."""
        poses = np.array([e.pose for e in estimates]).reshape(-1, 3)
        write_tum(self.out / "trajectory.tum", self.streams["frame_t_ns"][: len(poses)], poses)
        self.tiles.save(self.out / "tiles.npz")
        summary = {
            "map_codec": self.lc.map_codec,
            "segmenter": self.frames.segmenter_name,
            "inits": self.loc.inits,
            "tiles_fetched": self.client.fetched,
            "tile_bytes": self.client.bytes,
            "tile_updates": self.client.updates,
            "tiles_rejected": self.client.rejected,
            "per_frame_ms": _percentiles(self.timings),
        }
        write_summary(self.out, summary)
        return summary


class _FrameSource:
    """Frame i -> ground points (vehicle frame), classes and attitude jacobians: segment, IPM."""

    def __init__(self, log: DriveLog, cfg):
        from common.segmentation import segmenter_for

        self.log = log
        lc, roi = cfg.localizer, cfg.roi
        self.stride = lc.ipm_stride
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
        return pts, cls, (jac if self.roll else jac[:, :, :1])


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


def _percentiles(timings: dict) -> dict:
    out = {}
    for name, vals in timings.items():
        if name.startswith("_") or not vals:
            continue
        a = np.asarray(vals)
        out[name] = {"p50": float(np.percentile(a, 50)), "p95": float(np.percentile(a, 95))}
    return out
