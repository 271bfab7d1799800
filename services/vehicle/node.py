"""`roadmap vehicle --log DIR`: map one drive log and upload its patches with acks.

Thin shell around VehicleMapper: replays the log's streams in time order, times every stage,
writes sealed patches to the on-disk outbox, and an uploader thread sends them to
`roadmap/ingest/s<owner>` (waiting while the owner shard is not alive) until every patch is acked.
Writes STATE/summary.json, STATE/local_map.npz and STATE/config.toml."""

import json
import logging
import math
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from common import codec, keys
from common.bus import SampleKind, open_session, stop_event
from common.config import RoadmapConfig, to_toml
from common.drivelog import DriveLog
from common.grid import owner_of_tile
from common.messages import GridPatch, IngestAck, IngestBatch
from common.segmentation import GroundTruthSegmenter, configured_onnx
from services.vehicle.estimator import PoseEstimator, dead_reckon
from services.vehicle.mapper import VehicleMapper
from services.vehicle.outbox import Outbox

logger = logging.getLogger(__name__)

STAGES = ("segmentation", "ipm", "pose_graph", "voting", "outbox")


def build_mapper(log: DriveLog, vehicle: str, cfg: RoadmapConfig, segmenter_kind: str | None):
    """The mapper for one drive log: its camera, the chosen segmenter, the configured estimator."""
    v = cfg.vehicle
    estimator = PoseEstimator(
        settle_lag_s=v.settle_lag_s, max_wait_s=v.max_wait_s, calib_window_s=v.calib_window_s
    )
    return VehicleMapper(
        vehicle=vehicle,
        traversal=log.meta.traversal,
        camera=log.meta.camera,
        segmenter=_segmenter(log, cfg, segmenter_kind),
        roi_x_min_m=cfg.roi.x_min_m,
        roi_length_m=min(cfg.roi.length_m, v.max_range_m - cfg.roi.x_min_m),
        roi_width_m=cfg.roi.width_m,
        estimator=estimator,
        seal_every_frames=v.seal_every_frames,
        ipm_stride=v.ipm_stride,
    )


def _segmenter(log: DriveLog, cfg: RoadmapConfig, kind: str | None):
    kind = kind or cfg.segmentation.kind
    if kind == "onnx" and len(log) and log.image(0) is None:
        logger.warning("log has no camera images: using the ground-truth segmenter")
        kind = "truth"
    if kind == "truth":
        return GroundTruthSegmenter(seed=cfg.vehicle.truth_seed)
    return configured_onnx(cfg.segmentation, min_margin=cfg.vehicle.paint_min_margin,
                           camera=log.meta.camera)


# -- replay ------------------------------------------------------------------------------------


class Replay:
    """Feeds a drive log's sensor streams into the mapper in time order, frame by frame."""

    def __init__(self, log: DriveLog, mapper: VehicleMapper):
        self.s, self.mapper = log.streams, mapper
        self._o = self._i = self._g = 0

    def sensors_until(self, t_ns: int) -> None:
        s, m = self.s, self.mapper
        o = int(np.searchsorted(s["odom_t_ns"], t_ns, "right"))
        m.process_odometry(s["odom_t_ns"][self._o : o], s["odom_speed_mps"][self._o : o])
        i = int(np.searchsorted(s["imu_t_ns"], t_ns, "right"))
        m.process_imu(s["imu_t_ns"][self._i : i], s["imu_yaw_rate_rps"][self._i : i])
        g = int(np.searchsorted(s["gnss_t_ns"], t_ns, "right"))
        for k in range(self._g, g):
            m.process_gnss(
                int(s["gnss_t_ns"][k]),
                s["gnss_xy_m"][k],
                float(s["gnss_sigma_m"][k]),
                bool(s["gnss_ok"][k]),
            )
        self._o, self._i, self._g = o, i, g


class StageTimer:
    def __init__(self):
        self.ms = defaultdict(list)

    def time(self, stage, fn, *args, **kw):
        t0 = time.perf_counter()
        out = fn(*args, **kw)
        self.ms[stage].append((time.perf_counter() - t0) * 1e3)
        return out

    def summary(self) -> dict:
        return {
            k: {"p50": float(np.percentile(v, 50)), "p95": float(np.percentile(v, 95))}
            for k, v in self.ms.items()
            if v
        }


def map_log(
    log: DriveLog, mapper: VehicleMapper, on_patches, stop: threading.Event, timer: StageTimer
) -> bool:
    """Replay and map the whole log; on_patches(list) gets every sealed batch. False if stopped."""
    replay = Replay(log, mapper)
    for i, t_ns in enumerate(log.streams["frame_t_ns"]):
        if stop.is_set():
            return False
        replay.sensors_until(int(t_ns))
        labels = timer.time("segmentation", mapper.segment, log.image(i), log.labels(i))
        pts, cls = timer.time("ipm", mapper.inverse_perspective, labels)
        timer.time("pose_graph", mapper.add_pose, int(t_ns), pts, cls)
        patches = timer.time("voting", mapper.commit_settled)
        if patches:
            timer.time("outbox", on_patches, patches)
    on_patches(mapper.flush())
    return True


# -- upload ------------------------------------------------------------------------------------


class Uploader(threading.Thread):
    """Sends outbox patches to their owner shards until acked; waits while a shard is not alive."""

    def __init__(self, session, outbox: Outbox, cfg: RoadmapConfig, stop: threading.Event):
        super().__init__(name="uploader", daemon=True)
        self.session, self.outbox, self.cfg, self.stop = session, outbox, cfg, stop
        self.mapping_done = threading.Event()
        self.wake = threading.Event()
        self.alive: set[str] = set()
        self.sent = self.errors = 0  # send attempts of this run (retries included)
        self.bytes_sent = 0  # their request payloads
        self.sent_ids: set[str] = set()
        self._cache: dict[str, GridPatch] = {}
        self._live = session.liveliness().declare_subscriber(
            keys.alive_all("merger"), self._on_alive, history=True
        )

    def _on_alive(self, sample) -> None:
        _, ident = keys.parse_alive(str(sample.key_expr))
        if sample.kind == SampleKind.DELETE:
            self.alive.discard(ident)
        else:
            self.alive.add(ident)
            self.wake.set()

    def run(self) -> None:
        v = self.cfg.vehicle
        backoff = v.backoff_min_s
        while not self.stop.is_set():
            pending = self.outbox.pending()
            if not pending and self.mapping_done.is_set():
                return
            progressed = self._send_round(pending) if pending else False
            if progressed:
                backoff = v.backoff_min_s
                continue
            self.wake.wait(backoff if pending else 0.1)
            self.wake.clear()
            backoff = min(backoff * 2, v.backoff_max_s) if pending else backoff

    def _send_round(self, pending: list[str]) -> bool:
        by_shard = defaultdict(list)
        for pid in pending:
            patch = self._cache.get(pid) or self._cache.setdefault(pid, self.outbox.load(pid))
            shard = owner_of_tile(patch.tile, self.cfg.grid.shards, self.cfg.grid.shard_map)
            by_shard[shard].append(patch)
        progressed = False
        for shard, patches in by_shard.items():
            if f"s{shard}" not in self.alive:
                continue  # wait for the owner (liveliness) rather than drop
            for k in range(0, len(patches), self.cfg.vehicle.upload_batch):
                if self.stop.is_set() or not self._send(
                    shard, patches[k : k + self.cfg.vehicle.upload_batch]
                ):
                    break
                progressed = True
        return progressed

    def _send(self, shard: int, patches: list[GridPatch]) -> bool:
        payload = codec.encode(IngestBatch(patches))
        self.sent += len(patches)
        self.bytes_sent += len(payload)
        self.sent_ids.update(p.patch_id for p in patches)
        replies = self.session.get(
            keys.ingest(shard), payload=payload, timeout=self.cfg.vehicle.upload_timeout_s
        )
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                ack = codec.decode(reply.ok.payload.to_bytes(), expect=IngestAck)
            except Exception as exc:  # noqa: BLE001 - a bad ack is retried like no ack
                logger.warning("shard s%d: undecodable ack: %s", shard, exc)
                continue
            if ack.error:
                logger.warning("shard s%d rejected a batch: %s", shard, ack.error)
                break
            ids = {p.patch_id for p in patches}
            results = {pid: st for pid, st in ack.results.items() if pid in ids}
            self.outbox.ack(results)
            for pid in results:
                self._cache.pop(pid, None)
            return len(results) == len(ids)
        self.errors += 1
        return False

    def close(self) -> None:
        self._live.undeclare()


# -- summary -----------------------------------------------------------------------------------


def _stats(err: np.ndarray):
    err = err[np.isfinite(err)]
    if not len(err):
        return {"mean": None, "max": None}
    return {"mean": float(err.mean()), "max": float(err.max())}


def pose_errors(mapper: VehicleMapper, truth: np.ndarray) -> dict:
    """Position errors vs truth: all frames, GNSS-outage frames, and raw odometry in outages.

    Odometry-only: uncalibrated wheel + gyro dead reckoning from the optimized pose of the last
    GNSS-covered frame before each outage, through the outage (what the map would get without
    the pose graph)."""
    est = mapper.estimator
    n = len(mapper.poses)
    if n == 0:
        return {
            k: {"mean": None, "max": None}
            for k in ("pose_error_m", "outage_pose_error_m", "odometry_only_error_m")
        }
    poses = np.array([mapper.poses[i] for i in range(n)])
    err = np.linalg.norm(poses[:, :2] - truth[:n, :2], axis=1)
    outage = np.array([not est.covered(i) for i in range(n)])
    raw = est.raw_deltas()
    odo_err = []
    i = 0
    while i < n:
        if not outage[i] or i == 0:
            i += 1
            continue
        j = i
        while j < n and outage[j]:
            j += 1
        dr = dead_reckon(poses[i - 1], raw[i:j])[1:]
        odo_err.append(np.linalg.norm(dr[:, :2] - truth[i:j, :2], axis=1))
        i = j
    odo = np.concatenate(odo_err) if odo_err else np.zeros(0)
    return {
        "pose_error_m": _stats(err),
        "outage_pose_error_m": _stats(err[outage]),
        "odometry_only_error_m": _stats(odo),
    }


def _write_json(path: Path, obj) -> None:
    path.write_text(json.dumps(obj, indent=1, default=lambda o: None, allow_nan=False))


def _clean(obj):
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    return obj


# -- entry point -------------------------------------------------------------------------------


def main(args, cfg: RoadmapConfig) -> int:
    log = DriveLog(args.log)
    vehicle = args.id or log.meta.vehicle
    state = Path(args.state or Path(args.log) / ".vehicle")
    state.mkdir(parents=True, exist_ok=True)
    (state / "config.toml").write_text(to_toml(cfg))
    stop = stop_event()
    mapper = build_mapper(log, vehicle, cfg, args.segmenter)
    outbox = Outbox(state)
    sealed = outbox.sealed(log.meta.traversal)
    if sealed:
        logger.info("resuming: %d patch sequences already in the outbox or acked", sealed)
    timer = StageTimer()

    def on_patches(patches):
        new = [
            p
            for p in patches
            if int(p.patch_id.rsplit(".", 1)[1]) >= outbox.sealed(log.meta.traversal)
        ]
        outbox.put(new)
        if mapper.seq > outbox.sealed(log.meta.traversal):
            outbox.set_sealed(log.meta.traversal, mapper.seq)
        uploader.wake.set()

    t0 = time.perf_counter()
    with open_session(cfg.bus) as session:
        alive = session.liveliness().declare_token(keys.alive("vehicle", vehicle))
        uploader = Uploader(session, outbox, cfg, stop)
        uploader.start()
        try:
            finished = map_log(log, mapper, on_patches, stop, timer)
            map_s = time.perf_counter() - t0
            uploader.mapping_done.set()
            uploader.wake.set()
            while uploader.is_alive() and not stop.is_set():
                uploader.join(0.2)
        finally:
            stop_upload = stop.is_set()
            stop.set()
            uploader.join(10.0)
            uploader.close()
            alive.undeclare()
    counts = outbox.counts()
    pending = len(outbox.pending())
    summary = {
        "vehicle": vehicle,
        "traversal": log.meta.traversal,
        "frames": mapper.frames_committed,
        # distinct patches that left the vehicle, also in runs before a restart (acked ones)
        "patches_sent": len(uploader.sent_ids | outbox.acked_ids()),
        "send_attempts": uploader.sent,
        "bytes_sent": uploader.bytes_sent,  # ingest payloads of this run, retries included
        "patches_acked": counts["acked"],
        "patches_accepted": counts["accepted"],
        "duplicates": counts["duplicates"],
        "patches_pending": pending,
        "errors": uploader.errors,
        "resumed_from_seq": sealed,
        **pose_errors(mapper, log.streams["frame_pose_true"]),
        "calibration": {
            "odometry_scale": mapper.estimator.calibration.scale,
            "gyro_bias_dps": math.degrees(mapper.estimator.calibration.gyro_bias_rps),
        },
        "per_stage_ms": timer.summary(),
        "mapping_frames_per_s": mapper.frames_committed / map_s if finished and map_s > 0 else None,
        "wall_s": time.perf_counter() - t0,
    }
    _write_json(state / "summary.json", _clean(summary))
    labels, x0, y0 = mapper.local_map()
    np.savez_compressed(state / "local_map.npz", labels=labels, origin_m=np.array([x0, y0]))
    logger.info(
        "vehicle %s: %d frames, %d patches acked, %d pending",
        vehicle,
        mapper.frames_committed,
        counts["acked"],
        pending,
    )
    if not finished or stop_upload or pending:
        return 1
    return 0
