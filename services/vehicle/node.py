"""`roadmap vehicle --log DIR`: map one drive log and upload its patches with acks.

Thin shell around VehicleMapper: replays the log's streams in time order, times every stage,
writes sealed patches to the on-disk outbox, and an uploader thread sends them to
`roadmap/ingest/s<owner>` (waiting while the owner shard is not alive) until every patch is acked;
a batch the shard refused as `throttled` is retried after a backoff. Holds the liveliness token
`roadmap/alive/vehicle/<id>` while it runs.
Writes STATE/summary.json (counters), STATE/poses.npz and STATE/trajectory.tum (the committed
pose-graph poses), STATE/local_map.npz and STATE/config.toml (services/vehicle/outputs.py); the
accuracy of poses and map is the evaluation harness's (services/eval/mapping.py)."""

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
from common.grid import owner_of_tile, region_of_tile
from common.messages import THROTTLED, GridPatch, IngestAck, batch_of
from common.segmentation import segmenter_for
from services.vehicle.estimator import PoseEstimator
from services.vehicle.mapper import VehicleMapper
from services.vehicle.outbox import Outbox, write_atomic
from services.vehicle.outputs import write_local_map, write_poses, write_summary
from services.vehicle.patchform import get_patch_form

logger = logging.getLogger(__name__)

STAGES = ("segmentation", "ipm", "pose_graph", "voting", "outbox")
PROGRESS_S = 5.0  # how often a mapping run writes STATE/frames.json
# (not progress.json: that is the outbox's sealed count, which a restart resumes from)
FRAMES_FILE = "frames.json"


def build_mapper(log: DriveLog, vehicle: str, cfg: RoadmapConfig):
    """The mapper for one drive log: its camera, the configured segmenter and estimator."""
    v = cfg.vehicle
    estimator = PoseEstimator(
        settle_lag_s=v.settle_lag_s, max_wait_s=v.max_wait_s, calib_window_s=v.calib_window_s
    )
    mapper = VehicleMapper(
        vehicle=vehicle,
        traversal=log.meta.traversal,
        camera=log.meta.camera,
        segmenter=segmenter_for(cfg, "vehicle", camera=log.meta.camera,
                                images=not len(log) or log.image(0) is not None),
        roi_x_min_m=cfg.roi.x_min_m,
        roi_length_m=min(cfg.roi.length_m, v.max_range_m - cfg.roi.x_min_m),
        roi_width_m=cfg.roi.width_m,
        estimator=estimator,
        seal_every_frames=(v.sparse_seal_every_frames if v.patch_form == "sparse"
                           else v.seal_every_frames),
        ipm_stride=v.ipm_stride,
        min_paint_frames=v.min_paint_frames,
        min_symbol_frames=v.min_symbol_frames,
        symbol_lane_frames=v.symbol_lane_frames,
    )
    mapper.patch_form = get_patch_form(
        v.patch_form, ipm=mapper.ipm, camera_x_m=float(log.meta.camera.T_vehicle_camera[0, 3]),
        roi_width_m=cfg.roi.width_m, ipm_stride=v.ipm_stride)
    return mapper


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
    log: DriveLog, mapper: VehicleMapper, on_patches, stop: threading.Event, timer: StageTimer,
    progress=None,
) -> bool:
    """Replay and map the whole log; on_patches(list) gets every sealed batch, `progress(done,
    total)` (if given) every frame before it is mapped. False if stopped."""
    replay = Replay(log, mapper)
    frames_t_ns = log.streams["frame_t_ns"]
    for i, t_ns in enumerate(frames_t_ns):
        if stop.is_set():
            return False
        if progress is not None:
            progress(i, len(frames_t_ns))
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

    def __init__(self, session, outbox: Outbox, cfg: RoadmapConfig, stop: threading.Event,
                 vehicle: str = ""):
        super().__init__(name="uploader", daemon=True)
        self.session, self.outbox, self.cfg, self.stop = session, outbox, cfg, stop
        self.vehicle = vehicle  # sent as each query's attachment: the shard's throttle key
        self.throttled = 0  # batches a shard refused for this vehicle's rate (then retried)
        self.mapping_done = threading.Event()
        self.wake = threading.Event()
        # held while a seal's patches go into the outbox, so a send round takes them all or
        # none (one batch per seal, not a seal split over two requests)
        self.sealing = threading.Lock()
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
            with self.sealing:
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
        by_key = defaultdict(list)  # (key, owner, form): one batch holds patches of one form
        for pid in pending:
            patch = self._cache.get(pid) or self._cache.setdefault(pid, self.outbox.load(pid))
            by_key[(*self._destination(patch), type(patch))].append(patch)
        progressed = False
        for (key, ident, _), patches in by_key.items():
            if ident not in self.alive and not (ident is None and self.alive):
                continue  # wait for the owner (liveliness) rather than drop
            for k in range(0, len(patches), self.cfg.vehicle.upload_batch):
                if self.stop.is_set() or not self._send(
                    key, patches[k : k + self.cfg.vehicle.upload_batch]
                ):
                    break
                progressed = True
        return progressed

    def _destination(self, patch: GridPatch) -> tuple[str, str | None]:
        """(ingest key, the merger that must be alive): the owner shard's key, or with
        grid.routing = "region" the region's key (any live worker will do: the holder answers,
        or one claims the region; common/keys.py)."""
        if self.cfg.grid.routing == "region":
            return keys.region_ingest(*region_of_tile(tuple(patch.tile))), None
        shard = owner_of_tile(patch.tile, self.cfg.grid.shards, self.cfg.grid.shard_map)
        return keys.ingest(shard), f"s{shard}"

    def _send(self, key: str, patches: list) -> bool:
        payload = codec.encode(batch_of(patches))
        self.sent += len(patches)
        self.bytes_sent += len(payload)
        self.sent_ids.update(p.patch_id for p in patches)
        replies = self.session.get(key, payload=payload, attachment=self.vehicle.encode(),
                                   timeout=self.cfg.vehicle.upload_timeout_s)
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                ack = codec.decode(reply.ok.payload.to_bytes(), expect=IngestAck)
            except Exception as exc:  # noqa: BLE001 - a bad ack is retried like no ack
                logger.warning("%s: undecodable ack: %s", key, exc)
                continue
            if ack.error and ack.error.startswith(THROTTLED):
                self.throttled += 1  # not an error: retried after the backoff
                logger.debug("%s: %s", key, ack.error)
                return False
            if ack.error:
                logger.warning("%s rejected a batch: %s", key, ack.error)
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


# -- entry point -------------------------------------------------------------------------------


def main(args, cfg: RoadmapConfig) -> int:
    log = DriveLog(args.log)
    state = Path(args.state or Path(args.log) / ".vehicle")
    state.mkdir(parents=True, exist_ok=True)
    (state / "config.toml").write_text(to_toml(cfg))
    run = VehicleRun(log, args.id or log.meta.vehicle, cfg, state)
    with open_session(cfg.bus, "vehicle") as session:
        run.map_and_upload(session)  # map here while the uploader thread sends and collects acks
    run.write_outputs()  # summary.json, poses.npz, trajectory.tum, local_map.npz
    return 0 if run.complete() else 1


class VehicleRun:
    """One `roadmap vehicle` run: the mapper on one drive log, its outbox and its uploader."""

    def __init__(self, log: DriveLog, vehicle: str, cfg: RoadmapConfig, state: Path):
        self.log, self.vehicle, self.cfg, self.state = log, vehicle, cfg, state
        self.stop = stop_event()
        self.mapper = build_mapper(log, vehicle, cfg)
        self.outbox = Outbox(state)
        self.resumed_from_seq = self.outbox.sealed(log.meta.traversal)
        if self.resumed_from_seq:
            logger.info("resuming: %d patch sequences already in the outbox or acked",
                        self.resumed_from_seq)
        self.timer = StageTimer()
        self.uploader: Uploader | None = None
        self.finished = self.stopped_upload = False
        self.map_s = self.pending = None
        self.t0 = time.perf_counter()
        self._next_progress = 0.0

    def on_patches(self, patches: list[GridPatch]) -> None:
        """Sealed patches into the outbox (sequences sealed before a restart are there already),
        then wake the uploader."""
        traversal = self.log.meta.traversal
        sealed = self.outbox.sealed(traversal)
        with self.uploader.sealing:  # one seal goes up in one request
            self.outbox.put([p for p in patches if int(p.patch_id.rsplit(".", 1)[1]) >= sealed])
        if self.mapper.seq > self.outbox.sealed(traversal):
            self.outbox.set_sealed(traversal, self.mapper.seq)
        self.uploader.wake.set()

    def progress(self, done: int, total: int) -> None:
        """STATE/frames.json every PROGRESS_S seconds while mapping (roadmap demo shows it)."""
        now = time.perf_counter()
        if now < self._next_progress and done:
            return
        self._next_progress = now + PROGRESS_S
        logger.info("mapping frame %d of %d", done, total)
        write_atomic(self.state / FRAMES_FILE,
                     json.dumps({"frames_done": done, "frames": total}).encode())

    def map_and_upload(self, session) -> None:
        """Map the whole log, then wait until every patch is acked (or the run is stopped)."""
        self.token = session.liveliness().declare_token(keys.alive("vehicle", self.vehicle))
        self.uploader = Uploader(session, self.outbox, self.cfg, self.stop, vehicle=self.vehicle)
        self.uploader.start()
        try:
            self.finished = map_log(self.log, self.mapper, self.on_patches, self.stop, self.timer,
                                    progress=self.progress)
            self.map_s = time.perf_counter() - self.t0
            self.uploader.mapping_done.set()
            self.uploader.wake.set()
            while self.uploader.is_alive() and not self.stop.is_set():
                self.uploader.join(0.2)
        finally:
            self.stopped_upload = self.stop.is_set()
            self.stop.set()
            self.uploader.join(10.0)
            self.uploader.close()
            self.token.undeclare()

    def write_outputs(self) -> None:
        counts = self.outbox.counts()
        self.pending = len(self.outbox.pending())
        write_summary(self.state, self._summary(counts))
        write_poses(self.state, self.mapper.trajectory())
        write_local_map(self.state, *self.mapper.local_map())
        logger.info("vehicle %s: %d frames, %d patches acked, %d pending", self.vehicle,
                    self.mapper.frames_committed, counts["acked"], self.pending)

    def complete(self) -> bool:
        """Mapped to the end and every patch acked, without being stopped."""
        return self.finished and not self.stopped_upload and not self.pending

    def _summary(self, counts: dict) -> dict:
        m, up = self.mapper, self.uploader
        return {
            "vehicle": self.vehicle,
            "traversal": self.log.meta.traversal,
            "frames": m.frames_committed,
            # distinct patches that left the vehicle, also in runs before a restart (acked ones)
            "patches_sent": len(up.sent_ids | self.outbox.acked_ids()),
            "send_attempts": up.sent,
            "bytes_sent": up.bytes_sent,  # ingest payloads of this run, retries included
            "patches_acked": counts["acked"],
            "patches_accepted": counts["accepted"],
            "duplicates": counts["duplicates"],
            "patches_pending": self.pending,
            "errors": up.errors,
            "throttled": up.throttled,
            "resumed_from_seq": self.resumed_from_seq,
            "calibration": {
                "odometry_scale": m.estimator.calibration.scale,
                "gyro_bias_dps": math.degrees(m.estimator.calibration.gyro_bias_rps),
            },
            "per_stage_ms": self.timer.summary(),
            "mapping_frames_per_s": (m.frames_committed / self.map_s
                                     if self.finished and self.map_s > 0 else None),
            "wall_s": time.perf_counter() - self.t0,
        }
