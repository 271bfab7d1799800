"""`roadmap demo` and `roadmap up`: the whole fleet as local processes, and the one report.

demo: world -> simulated drives -> router + K merger shards + M mapping vehicles (separate
processes) -> every tile fetched over Zenoh -> evaluation against the world's ground truth ->
a localizer process on a production drive -> OUT/report.json (DESIGN.md: Evaluation), a table
next to the paper's numbers, and figures. up: router + shards (+ vehicles) until Ctrl-C."""

import dataclasses
import json
import logging
import shutil
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from common.config import RoadmapConfig, to_toml
from common.drivelog import DriveLog
from common.errors import ConfigError, RoadmapError
from common.grid import owner_of_tile, tile_of_point
from common.trajectory import read_tum
from services.demo import figures
from services.demo.fetch import load_tiles, run_fetch
from services.demo.procs import ProcessError, Supervisor
from services.eval import map as ev
from services.eval.localization import (
    evaluate_localizer,
    interp_poses,
    localized_frames,
    pose_errors,
)
from services.eval.mapping import mapping_section
from services.eval.mapping import pose_errors as vehicle_pose_errors
from services.vehicle.outputs import read_poses

logger = logging.getLogger("roadmap.demo")


class DemoError(RoadmapError):
    """The demo cannot run (a service missing or failing); the message names which."""


def _require(module: str, what: str):
    """Import a service module, or fail naming the service that is not there yet."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise DemoError(f"{what} is not available ({module}: {exc})") from exc


# -- the run -------------------------------------------------------------------------------------


class DemoRun:
    """One demo run in OUT: drives, fleet, fetch, evaluation, report. Steps are methods."""

    def __init__(self, args, cfg: RoadmapConfig):
        cfg = fleet_config(cfg, args.shards)
        if args.vehicles < 1 or args.shards < 1:
            raise ConfigError("roadmap demo needs --vehicles >= 1 and --shards >= 1")
        self.args, self.cfg, self.d = args, cfg, cfg.demo
        self.kind = cfg.segmentation.kind  # the fleet's and the car's segmenter
        self.onnx = self.kind == "onnx"  # the model segments rendered frames
        self.out = Path(args.out).resolve()
        self.t0 = time.monotonic()
        self.stage_ms: dict[str, float] = {}
        self.chaos_events: list[dict] = []
        self.vehicle_summaries: list[dict] = []
        self.vehicles: list[tuple[Path, Path]] = []  # (STATE, drive log), as vehicles finish
        self.max_km = self.d.small_max_km if args.small else self.d.max_km
        if args.scenario == "repaint":
            self.max_km = max(self.max_km, self.d.repaint_min_km)
        self.world = self.world_after = None
        self.router_endpoint: str | None = None

    def step(self, name: str, fn, *a, **kw):
        logger.info("[%5.1f s] %s ...", time.monotonic() - self.t0, name)
        t = time.monotonic()
        result = fn(*a, **kw)
        self.stage_ms[name] = round((time.monotonic() - t) * 1000.0, 1)
        return result

    def run(self) -> dict:
        self._prepare_out()
        if self.onnx:  # fail now, not after the drives, if the model is missing
            self._segmenter()
        self.world = self.step("load world", self._load_world)
        logs = self.step("simulate drives", self._simulate)
        with Supervisor(self.out / "logs", config=self.out / "config.toml") as sup:
            self.step("start router and shards", self._start_cloud, sup)
            if self.args.scenario == "repaint":
                update = self.step("map, repaint, map again", self._map_repaint, sup, logs)
            else:
                self.step("map (vehicles upload)", self._map, sup, logs["mapping"])
                update = None
            tiles_path = self.out / "run" / "tiles.npz"
            stats = self.step("fetch stats and tiles", self._fetch, sup, tiles_path)
            loc = self.step("localize the production drive", self._localize, sup,
                            logs["production"])
        report = self.step("evaluate", self._evaluate, stats, loc, logs, update)
        report["timings"] = {"wall_s": round(time.monotonic() - self.t0, 2),
                             "per_stage_ms": {**self.stage_ms, "vehicle": self._vehicle_stage_ms()}}
        report["processes"] = sup.history()
        (self.out / "report.json").write_text(json.dumps(report, indent=1))
        return report

    # -- steps -----------------------------------------------------------------------------------

    def _prepare_out(self) -> None:
        """Fresh run directories (old stores would change the map); keep anything else in OUT."""
        self.out.mkdir(parents=True, exist_ok=True)
        for sub in ("run", "drives", "logs", "localizer", "localizer-raw"):
            shutil.rmtree(self.out / sub, ignore_errors=True)
        (self.out / "run").mkdir()
        (self.out / "config.toml").write_text(to_toml(self.cfg))

    def _load_world(self):
        worlds = _require("services.sim.worlds", "the simulator (services.sim.worlds)")
        return worlds.load_world(self.args.world, seed=self.args.seed)

    def _simulate(self) -> dict:
        sim = _require("services.sim.simulate", "the simulator (services.sim.simulate)")
        drives, seed, m = self.out / "drives", self.args.seed, self.args.vehicles
        kw = {"images": self.d.images or self.onnx, "max_km": self.max_km}
        logs = {}
        if self.args.scenario == "repaint":
            worlds = _require("services.sim.worlds", "the simulator (services.sim.worlds)")
            self.world_after = worlds.repaint(self.world, seed)
            logs["mapping"] = sim.simulate_drives(self.world, drives / "before", vehicles=m,
                                                  drives=self.d.repaint_drives_before,
                                                  profile="mapping", seed=seed, **kw)
            logs["after"] = sim.simulate_drives(self.world_after, drives / "after", vehicles=1,
                                                drives=self.d.repaint_drives_after,
                                                profile="mapping", seed=seed + 500, **kw)
        else:
            logs["mapping"] = sim.simulate_drives(self.world, drives / "mapping", vehicles=m,
                                                  drives=self.d.drives, profile="mapping",
                                                  seed=seed, **kw)
        world_now = self.world_after or self.world
        logs["production"] = sim.simulate_drives(
            world_now, drives / "production", vehicles=1, drives=1, profile="production",
            seed=seed + 1000, images=self.onnx, max_km=self.max_km)[0]
        logger.info("drive logs: %d mapping, %d after repaint, 1 production",
                    len(logs["mapping"]), len(logs.get("after", [])))
        return logs

    def _start_cloud(self, sup: Supervisor) -> None:
        _require("services.merger.node", "the merger service (services.merger.node)")
        self.router_endpoint = sup.start_router()
        for i in range(self.args.shards):
            sup.start_merger(i, self.args.shards, self.out / "run" / f"merger-s{i}.sqlite")
        self._wait_shards_ready(sup, timeout_s=60.0)

    def _wait_shards_ready(self, sup: Supervisor, timeout_s: float) -> dict:
        deadline = time.monotonic() + timeout_s
        while True:
            sup.check_alive(self._shard_names())
            stats = run_fetch(sup.router_endpoint, "stats", self.args.shards)
            if all(v is not None for v in stats.values()):
                return stats
            if time.monotonic() > deadline:
                missing = [k for k, v in stats.items() if v is None]
                raise DemoError(f"merger shards {missing} do not answer their stats query")
            time.sleep(0.5)

    def _shard_names(self) -> list[str]:
        return [f"merger-s{i}" for i in range(self.args.shards)]

    def _map(self, sup: Supervisor, logs: list[Path]) -> None:
        """One vehicle process per drive log, all at once; chaos kills one shard and one vehicle."""
        _require("services.vehicle.node", "the vehicle service (services.vehicle.node)")
        started = {self._start_vehicle(sup, log): log for log in logs}
        if self.args.chaos:
            self._chaos(sup, next(iter(started)), logs)
        self._wait_vehicles(sup, started)

    def _start_vehicle(self, sup: Supervisor, log: Path) -> str:
        name = f"vehicle-{log.parent.name}-{log.name}"
        sup.start_vehicle(name, log, vehicle_id=log.name, state=self.out / "run" / name)
        return name

    def _wait_vehicles(self, sup: Supervisor, started: dict[str, Path]) -> None:
        deadline = time.monotonic() + self.d.vehicle_timeout_s
        pending, next_report = list(started), time.monotonic() + 10.0
        while pending:
            sup.check_alive(self._shard_names())
            for n in list(pending):
                if sup.procs[n].poll() is not None:
                    sup.wait(n, 0)  # raises with the log tail on a non-zero exit
                    self.vehicle_summaries.append(self._read_summary(n))
                    self.vehicles.append((self.out / "run" / n, started[n]))
                    pending.remove(n)
                    logger.info("%s done (%d left)", n, len(pending))
            if time.monotonic() > deadline:
                raise ProcessError(f"vehicles {pending} not done after "
                                   f"{self.d.vehicle_timeout_s} s")
            if pending and time.monotonic() > next_report:
                applied = _applied(run_fetch(sup.router_endpoint, "stats", self.args.shards))
                logger.info("mapping: %d of %d vehicles still running, shards applied %d patches",
                            len(pending), len(started), applied)
                next_report = time.monotonic() + 10.0
            time.sleep(0.2)

    def _read_summary(self, name: str) -> dict:
        path = self.out / "run" / name / "summary.json"
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise DemoError(f"{name}: no vehicle summary at {path} ({exc})") from exc

    def _chaos(self, sup: Supervisor, vehicle: str, logs: list[Path]) -> None:
        """SIGKILL the busiest shard and one vehicle once the shard has applied patches (so it
        must replay its store), while the vehicle is still mapping; then restart both."""
        shard = self._busiest_shard(logs)
        applied, deadline = 0, time.monotonic() + 120.0
        while sup.procs[vehicle].running() and time.monotonic() < deadline:
            stats = run_fetch(sup.router_endpoint, "stats", self.args.shards)
            applied = int((stats.get(f"s{shard}") or {}).get("patches_applied", 0))
            if applied > 0:
                break
            time.sleep(0.2)
        time.sleep(self.d.chaos_after_s)
        running = sup.procs[vehicle].running()
        if not running:
            logger.warning("chaos: %s finished before it could be killed", vehicle)
        for name in (f"merger-s{shard}", vehicle):
            sup.kill(name)
            self.chaos_events.append({"t_s": sup.elapsed(), "event": "SIGKILL", "process": name,
                                      "shard_applied_before": applied,
                                      "vehicle_was_running": running})
        time.sleep(1.0)
        for name in (f"merger-s{shard}", vehicle):
            sup.restart(name)
            self.chaos_events.append({"t_s": sup.elapsed(), "event": "restart", "process": name})
        logger.info("chaos: killed and restarted merger-s%d (%d patches applied) and %s", shard,
                    applied, vehicle)

    def _busiest_shard(self, logs: list[Path]) -> int:
        owners = Counter()
        for log in logs:
            poses = DriveLog(log).streams["frame_pose_true"]
            for x, y, _ in poses[np.all(np.isfinite(poses), axis=1)]:
                owners[owner_of_tile(tile_of_point(x, y), self.args.shards,
                                     self.cfg.grid.shard_map)] += 1
        return owners.most_common(1)[0][0] if owners else 0

    def _fetch(self, sup: Supervisor, path: Path) -> dict:
        """Shard counters once every shard answers and applied counts are stable, then tiles."""
        before = self._wait_shards_ready(sup, timeout_s=30.0)
        for _ in range(20):
            time.sleep(0.5)
            after = run_fetch(sup.router_endpoint, "stats", self.args.shards)
            if _applied(after) == _applied(before):
                break
            before = after
        return run_fetch(sup.router_endpoint, "tiles", self.args.shards, out=path)

    def _localize(self, sup: Supervisor, log: Path) -> dict:
        """The production drive on the compressed map; then, one after the other (the first
        run's per-frame timings stay its own), on the uncompressed one."""
        _require("services.localizer.node", "the localizer service (services.localizer.node)")
        loc = self._localizer_run(sup, log, "localizer", [])
        if self.d.compare_raw_map:
            raw = self._localizer_run(sup, log, "localizer-raw", [
                "--set", 'localizer.map_codec="raw"', "--set", "localizer.publish=false"])
            loc["uncompressed_map"] = {k: raw.get(k) for k in (
                "x_m", "y_m", "yaw_deg", "lateral_m", "longitudinal_m", "availability_0_5m",
                "convergence_s", "tile_bytes")}
        return loc

    def _localizer_run(self, sup: Supervisor, log: Path, name: str, extra: list[str]) -> dict:
        """The localizer process on the drive; its accuracy from its outputs (the harness)."""
        out = self.out / name
        sup.start_localizer(name, log, out, extra)
        sup.wait(name, self.d.localizer_timeout_s)
        if not (out / "summary.json").is_file():
            raise DemoError(f"{name} wrote no summary.json in {out}")
        return evaluate_localizer(out, DriveLog(log))

    # -- repaint -----------------------------------------------------------------------------

    def _map_repaint(self, sup: Supervisor, logs: dict) -> dict:
        """Rounds of the old paint (all vehicles at once per round), then single traversals of
        the new paint, one at a time, until the map follows the repaint."""
        rounds: dict[str, list[Path]] = {}  # drive index -> the logs of that round
        for log in logs["mapping"]:
            rounds.setdefault(log.name.rsplit("-d", 1)[-1], []).append(log)
        for key in sorted(rounds, key=int):
            self._map(sup, rounds[key])
        before = self._snapshot(sup, "before")
        if not before["tiles"]:
            raise DemoError("the shards hold no tiles after the rounds of the old paint")
        mosaic = ev.Mosaic(before["tiles"])
        masks, new_truth = self._repaint_masks(mosaic, before["tiles"])
        snapshots = [("before repaint", _paste_within(mosaic, before))]
        history, followed_at = [], None
        for i, log in enumerate(logs["after"], start=1):
            self._map(sup, [log])
            labels = _paste_within(mosaic, self._snapshot(sup, f"after{i}"))
            state = ev.follow_state(labels, *masks)
            history.append({"traversal": i, **state})
            logger.info("repaint: traversal %d: new line %.0f %%, old line %.0f %%", i,
                        100 * state["new_shown"], 100 * state["old_shown"])
            if i == 1 or state["followed"]:
                snapshots.append((f"after {i} traversal{'s' if i > 1 else ''}", labels))
            if state["followed"]:
                followed_at = i
                break
        snapshots.append(("new paint (ground truth)", new_truth))
        figures.repaint_strip(snapshots, masks[0] | masks[1], self.out / "repaint.png")
        return {"traversals_to_follow": followed_at, "traversals_before": len(logs["mapping"]),
                "repainted_cells": {"old_only": int(masks[0].sum()),
                                    "new_only": int(masks[1].sum())},
                "history": history, "rule": {"new_shown_min": ev.FOLLOW_NEW_MIN,
                                             "old_shown_max": ev.FOLLOW_OLD_MAX}}

    def _snapshot(self, sup: Supervisor, name: str) -> dict:
        path = self.out / "run" / f"tiles-{name}.npz"
        run_fetch(sup.router_endpoint, "tiles", self.args.shards, out=path)
        return load_tiles(path)

    def _repaint_masks(self, mosaic, tiles):
        """Old-only and new-only lane-line cells inside the area the drives observed."""
        observed = self._observed(mosaic, self._logs_mapping_all())
        old = ev.truth_mosaic(self.world, mosaic, tiles)
        new = ev.truth_mosaic(self.world_after, mosaic, tiles)
        old_only, new_only = ev.repaint_masks(old, new, observed)
        if not old_only.any() or not new_only.any():
            raise DemoError("the repainted lane line is outside the mapped area: choose another "
                            "--seed or a longer drive")
        return (old_only, new_only), new

    def _logs_mapping_all(self):
        return sorted(p for p in (self.out / "drives").glob("*/*/log.json")
                      if p.parent.parent.name != "production")

    # -- evaluation --------------------------------------------------------------------------

    def _observed(self, mosaic, log_jsons) -> np.ndarray:
        poses = [DriveLog(p.parent if p.name == "log.json" else p).streams["frame_pose_true"]
                 for p in log_jsons]
        roi, length_m = self.cfg.roi, self.cfg.roi.length_m
        if hasattr(self.cfg, "vehicle"):  # the vehicles vote only up to vehicle.max_range_m
            length_m = min(length_m, self.cfg.vehicle.max_range_m - roi.x_min_m)
        return ev.roi_footprint(mosaic, np.concatenate(poses), roi.x_min_m, length_m, roi.width_m)

    def _evaluate(self, stats: dict, loc: dict, logs: dict, update: dict | None) -> dict:
        contours = _require("common.contours", "the tile codec (common.contours)")
        world = self.world_after or self.world
        t = load_tiles(self.out / "run" / "tiles.npz")
        if not t["tiles"]:
            raise DemoError("the shards hold no tiles after mapping (see OUT/logs)")
        mosaic = ev.Mosaic(t["tiles"])
        raw = mosaic.paste(t["tiles"], t["raw"])
        decoded = mosaic.paste(t["tiles"], [contours.decode_tile(b) for b in t["compressed"]])
        truth = ev.truth_mosaic(world, mosaic, t["tiles"])
        observed = self._observed(mosaic, self._logs_mapping_all())
        report = {
            "world": self._world_section(world),
            "map": self._map_section(t, raw, decoded, truth, observed),
            "segmentation": self._segmentation(logs["production"]),
            "mapping": self._mapping_section(),
        }
        if update is not None:
            report["update"] = update
        report["localization"] = loc
        report["pipeline"] = self._pipeline(stats)
        report["run"] = self._run_section(t)
        self._figures(mosaic, raw, decoded, truth, logs["production"], loc["convergence_s"])
        return report

    def _world_section(self, world) -> dict:
        drives = [_truth_xy(p.parent) for p in self._logs_mapping_all()]
        self.km_mapped = ev.km_mapped(drives)
        self.km_driven = sum(_path_km(xy) for xy in drives)  # the pipeline's upload per km
        return {"name": world.name, "km": round(float(world.km_of_road), 4),
                "km_mapped": round(self.km_mapped, 4)}

    def _map_section(self, t, raw, decoded, truth, observed) -> dict:
        sizes = ev.map_sizes(t["compressed"], t["raw"])
        km = max(self.km_mapped, 1e-9)
        per_class = ev.map_quality(raw, truth, observed)
        for name, fid in ev.codec_fidelity(decoded, raw).items():
            per_class[name].update(fid)
        return {
            "kb_per_km": sizes["compressed_bytes"] / 1024 / km,
            "raw_kb_per_km": sizes["raw_sparse_bytes"] / 1024 / km,
            "png_kb_per_km": sizes["png_bytes"] / 1024 / km,
            "per_class": per_class,
            "digest": ev.map_digest(t["tiles"], t["raw"]),
            "tiles": len(t["tiles"]), "codecs": t["codecs"], **sizes,
            "notes": "kb_per_km divides by world.km_mapped (km of road the mapping drives "
                     "covered, each road once); recall counts true cells inside that footprint; "
                     "raw = sparse grid of 5 bytes per labelled cell; png = one PNG per tile",
        }

    def _segmentation(self, log_path: Path, n_frames: int = 20) -> dict:
        """IoU of the segmenter the fleet used, on frames of the production drive."""
        log = DriveLog(log_path)
        seg = self._segmenter(log.meta.camera)
        inter, union, n_true, ms = np.zeros(6), np.zeros(6), np.zeros(6), []
        for i in np.linspace(0, len(log) - 1, min(n_frames, len(log))).astype(int):
            truth, image = log.labels(int(i)), log.image(int(i))
            t = time.perf_counter()
            pred = seg.segment(image, truth)
            ms.append((time.perf_counter() - t) * 1000.0)
            for c in range(2, 6):
                n_true[c] += np.sum(truth == c)
                inter[c] += np.sum((pred == c) & (truth == c))
                union[c] += np.sum((pred == c) | (truth == c))
        names = {2: "lane_line", 3: "stop_line", 4: "crosswalk", 5: "ground_sign"}
        return {"model": seg.name,
                "iou": {n: (float(inter[c] / union[c]) if n_true[c] else None)
                        for c, n in names.items()},
                "ms_p50": float(np.percentile(ms, 50)) if ms else None,
                "ms_p95": float(np.percentile(ms, 95)) if ms else None,
                "frames": len(ms)}

    def _segmenter(self, camera=None):
        """The segmenter the fleet runs (common.segmentation.segmenter_for, the vehicles' role)."""
        from common.segmentation import segmenter_for

        return segmenter_for(self.cfg, "vehicle", camera=camera)

    def _mapping_section(self) -> dict:
        """The vehicles' pose errors (their poses.npz vs their drive's truth), over the fleet."""
        errors = [vehicle_pose_errors(read_poses(state), DriveLog(log).streams["frame_pose_true"])
                  for state, log in self.vehicles]
        return mapping_section(list(zip(self.vehicle_summaries, errors, strict=True)),
                               segmenter=self.kind)

    def _pipeline(self, stats: dict) -> dict:
        v = self.vehicle_summaries
        shards = [c or {} for c in stats.values()]
        upload = sum(int(x.get("bytes_sent", 0)) for x in v)
        driven = self.km_driven  # _world_section
        return {
            "upload_bytes": upload,  # every ingest request's payload, retries included
            "upload_kb_per_km_driven": round(upload / 1024 / driven, 2) if driven > 0 else None,
            "patches_sent": sum(int(x.get("patches_sent", 0)) for x in v),
            "patches_acked": sum(int(x.get("patches_acked", 0)) for x in v),
            "patches_applied": sum(int(c.get("patches_applied", 0)) for c in shards),
            "duplicates": sum(int(c.get("duplicates", 0)) for c in shards),
            "errors": sum(int(c.get("errors", 0)) for c in shards)
            + sum(int(x.get("errors", 0)) for x in v),
            "vehicle_duplicates": sum(int(x.get("duplicates", 0)) for x in v),
            "shards": {k: {n: c.get(n) for n in
                           ("patches_applied", "duplicates", "errors", "tiles", "digest")}
                       for k, c in stats.items() if c},
        }

    def _run_section(self, t) -> dict:
        a = self.args
        return {"seed": a.seed, "vehicles": a.vehicles, "shards": a.shards, "scenario": a.scenario,
                "chaos": a.chaos, "small": a.small, "max_km_per_drive": self.max_km,
                "segmenter": self.kind, "images": self.d.images,
                "chaos_events": self.chaos_events, "tile_versions": t["versions"],
                "router": self.router_endpoint}

    def _vehicle_stage_ms(self) -> dict:
        """Per-frame stage times of the mapping vehicles: {stage: {p50, p95}} averaged over them."""
        acc: dict[str, dict[str, list[float]]] = {}
        for s in self.vehicle_summaries:
            for stage, v in (s.get("per_stage_ms") or {}).items():
                items = v.items() if isinstance(v, dict) else [("mean", v)]
                for k, x in items:
                    if isinstance(x, int | float):
                        acc.setdefault(stage, {}).setdefault(k, []).append(float(x))
        return {st: {k: round(float(np.mean(v)), 3) for k, v in d.items()} for st, d in acc.items()}

    def _figures(self, mosaic, raw, decoded, truth, prod_log: Path, conv) -> None:
        figures.save_map(raw, self.out / "map.png")
        figures.save_map(truth, self.out / "map_truth.png")
        figures.side_by_side([("merged map (before compression)", raw),
                              ("decoded from contours (after)", decoded),
                              ("ground truth", truth)], self.out / "compression.png")
        self._trajectory_figures(mosaic, raw, prod_log, conv)

    def _trajectory_figures(self, mosaic, raw, prod_log: Path, conv) -> None:
        tum = self.out / "localizer" / "trajectory.tum"
        if not tum.exists():
            logger.warning("no %s: skipping the trajectory figures", tum)
            return
        est = read_tum(tum.read_text())
        log = DriveLog(prod_log)
        t_ns = log.streams.get("truth_t_ns", log.streams["frame_t_ns"])
        poses = log.streams.get("truth_pose", log.streams["frame_pose_true"])
        if len(est) == 0:
            return
        truth = interp_poses(est[:, 0], t_ns / 1e9, poses)
        errs = pose_errors(est[:, 1:], truth)
        pos = np.hypot(errs["x_m"], errs["y_m"])
        figures.trajectory_by_error(raw, mosaic.to_cells, truth[:, :2], est[:, 1:3], pos,
                                    self.out / "trajectory.png")
        scored = self._scored_frames(est[:, 0], log, conv)
        figures.error_histograms({k: v[scored] for k, v in errs.items()}, self.out / "errors.png")

    def _scored_frames(self, t_est_s: np.ndarray, log: DriveLog, conv) -> np.ndarray:
        """The estimates the report's statistics are taken over: on-map frames after
        convergence (the harness's, from localizer/); all when no frame was localized."""
        frames = localized_frames(self.out / "localizer", log)
        if len(frames.t_ns) == 0:
            return np.ones(len(t_est_s), dtype=bool)
        t_diag, on_map, frame_t_ns = frames.t_ns, frames.on_map, log.streams["frame_t_ns"]
        # nearest localized frame of each estimate (TUM times are float seconds)
        rel = t_est_s - int(t_diag[0]) * 1e-9
        k = np.clip(np.searchsorted((t_diag - t_diag[0]) * 1e-9, rel - 1e-3), 0, len(t_diag) - 1)
        t0 = (int(t_diag[0]) - int(frame_t_ns[0])) * 1e-9
        after = rel + t0 >= conv - 1e-3 if conv is not None else np.zeros(len(k), dtype=bool)
        return on_map[k] & after


def _path_km(xy: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()) / 1000.0 if len(xy) else 0.0


def _truth_xy(log_dir: Path) -> np.ndarray:
    s = DriveLog(log_dir).streams
    poses = s.get("truth_pose", s["frame_pose_true"])
    return poses[np.all(np.isfinite(poses), axis=1), :2]


def _paste_within(mosaic, fetched: dict) -> np.ndarray:
    """The fetched tiles that fall inside `mosaic`, pasted (others dropped)."""
    keep = [i for i, (tx, ty) in enumerate(fetched["tiles"])
            if 0 <= tx - mosaic.tx0 < mosaic.ntx and 0 <= ty - mosaic.ty0 < mosaic.nty]
    return mosaic.paste([fetched["tiles"][i] for i in keep], [fetched["raw"][i] for i in keep])


def fleet_config(cfg: RoadmapConfig, shards: int) -> RoadmapConfig:
    """The config every process of the fleet gets: grid.shards = the number of shards started
    (the fleet and the production car run the same segmentation.kind)."""
    return dataclasses.replace(cfg, grid=dataclasses.replace(cfg.grid, shards=shards))


def _has_files(path: Path) -> bool:
    return path.is_dir() and any(p.is_file() for p in path.rglob("*"))


def _applied(stats: dict) -> int:
    return sum(int((c or {}).get("patches_applied", 0)) for c in stats.values())


# -- the printed table ---------------------------------------------------------------------------


def _f(v, fmt="{:.3f}"):
    return "-" if v is None else fmt.format(v)


def format_table(report: dict) -> str:
    loc, m, p = report.get("localization", {}), report["map"], report["pipeline"]
    lines = [f"RoadMap demo: world {report['world']['name']} ({report['world']['km_mapped']:.2f} "
             f"km mapped), wall {report['timings']['wall_s']:.0f} s",
             f"{'':22s}{'ours mean':>10s}{'ours p90':>10s}{'paper mean':>12s}{'paper p90':>11s}"]
    rows = (("x_m", "x error [m]"), ("y_m", "y error [m]"), ("yaw_deg", "yaw error [deg]"))
    for key, label in rows:
        ours, paper = loc.get(key) or {}, ev.PAPER[key]
        lines.append(f"{label:22s}{_f(ours.get('mean')):>10s}{_f(ours.get('p90')):>10s}"
                     f"{paper['mean']:>12.3f}{paper['p90']:>11.3f}")
    for key, label in (("lateral_m", "lateral [m]"), ("longitudinal_m", "longitudinal [m]")):
        ours = loc.get(key) or {}
        lines.append(f"{label:22s}{_f(ours.get('mean')):>10s}{_f(ours.get('p90')):>10s}")
    if "frames_on_map" in loc:
        every = loc.get("all_frames") or {}
        x_all, y_all = ((every.get(k) or {}).get("mean") for k in ("x_m", "y_m"))
        lines.append(
            f"  (on-map frames: {loc['frames_on_map']} of {loc.get('frames')}; all frames: x "
            f"{_f(x_all)}, y {_f(y_all)} m, availability "
            f"{_f(every.get('availability_0_5m'), '{:.2f}')})"
        )
    raw = loc.get("uncompressed_map")
    if raw:
        x, y, yaw = ((raw.get(k) or {}).get("mean") for k in ("x_m", "y_m", "yaw_deg"))
        lines.append(f"  (uncompressed map: x {_f(x)}, y {_f(y)} m, yaw {_f(yaw)} deg mean)")
    lines.append(f"{'map size [KB/km]':22s}{m['kb_per_km']:>10.1f}{'':10s}"
                 f"{ev.PAPER['kb_per_km']:>12.1f}"
                 f"   (raw grid {m['raw_kb_per_km']:.0f}, PNG {m['png_kb_per_km']:.0f})")
    for name, c in m["per_class"].items():
        lines.append(f"  {name:20s}precision {_f(c['precision'], '{:.2f}')}  recall "
                     f"{_f(c['recall'], '{:.2f}')}  codec P/R "
                     f"{_f(c.get('codec_precision'), '{:.2f}')}"
                     f"/{_f(c.get('codec_recall'), '{:.2f}')}")
    lines.append(f"pipeline: sent {p['patches_sent']} acked {p['patches_acked']} applied "
                 f"{p['patches_applied']} duplicates {p['duplicates']} errors {p['errors']}; "
                 f"upload {_f(p.get('upload_kb_per_km_driven'), '{:.0f}')} KB per km driven")
    if "update" in report:
        n = report["update"]["traversals_to_follow"]
        lines.append(f"repaint: map followed after {n} traversals")
    lines.append(f"map digest {m['digest'][:16]}...  availability(0.5 m) "
                 f"{_f(loc.get('availability_0_5m'), '{:.2f}')}  convergence "
                 f"{_f(loc.get('convergence_s'), '{:.1f}')} s  segmenter "
                 f"{report['segmentation']['model']}")
    return "\n".join(lines) + "\n"


def demo_command(args, cfg: RoadmapConfig) -> int:
    report = DemoRun(args, cfg).run()
    sys.stdout.write(format_table(report))
    sys.stdout.write(f"report: {Path(args.out) / 'report.json'}\n")
    return 0


# -- roadmap up ----------------------------------------------------------------------------------


def up_command(args, cfg: RoadmapConfig) -> int:
    """Router + K shards (+ vehicles on simulated logs) as local processes until Ctrl-C;
    a process that dies is restarted."""
    from common.bus import stop_event

    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    cfg = fleet_config(cfg, args.shards)
    (out / "config.toml").write_text(to_toml(cfg))
    stop = stop_event()
    with Supervisor(out / "logs", config=out / "config.toml") as sup:
        endpoint = sup.start_router(getattr(args, "listen", None) or "tcp/127.0.0.1:7447")
        for i in range(args.shards):
            sup.start_merger(i, args.shards, out / "run" / f"merger-s{i}.sqlite")
        vehicles = _up_vehicles(sup, args, cfg, out) if args.vehicles > 0 else []
        sys.stderr.write(f"roadmap up: router {endpoint}, {args.shards} shards, "
                         f"{len(vehicles)} vehicles; logs in {out / 'logs'}; Ctrl-C stops\n")
        while not stop.wait(1.0):
            for name, proc in sup.procs.items():
                if name not in vehicles and not proc.running():
                    logger.warning("%s exited (%s): restarting", name, proc.poll())
                    sup.restart(name)
    return 0


def _up_vehicles(sup: Supervisor, args, cfg: RoadmapConfig, out: Path) -> list[str]:
    worlds = _require("services.sim.worlds", "the simulator (services.sim.worlds)")
    sim = _require("services.sim.simulate", "the simulator (services.sim.simulate)")
    world = worlds.load_world(args.world, seed=args.seed)
    images = cfg.demo.images or cfg.segmentation.kind == "onnx"
    logs = sim.simulate_drives(world, out / "drives" / "up", vehicles=args.vehicles, drives=1,
                               profile="mapping", seed=args.seed, images=images,
                               max_km=cfg.demo.max_km)
    names = []
    for log in logs:
        name = f"vehicle-{log.name}"
        sup.start_vehicle(name, log, vehicle_id=log.name, state=out / "run" / name)
        names.append(name)
    return names
