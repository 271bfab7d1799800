"""`roadmap demo` and `roadmap up`: the whole fleet as local processes, and the one report.

demo: world -> simulated drives -> router + K merger shards + M mapping vehicles (separate
processes) -> every tile fetched over Zenoh -> a localizer process on a production drive ->
OUT/report.json (DESIGN.md: Evaluation) from what the services wrote and the drives' truth
(report.py, services/eval), a table next to the paper's numbers, and figures (figures.py).
up: router + shards (+ vehicles) until Ctrl-C."""

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
from common.errors import ConfigError
from common.grid import owner_of_tile, tile_of_point
from services.demo import figures, pgfleet, report, spread
from services.demo.errors import DemoError
from services.demo.fetch import load_tiles, run_fetch
from services.demo.procs import ProcessError, Supervisor
from services.demo.secure import fleet_scheme, secure_fleet
from services.viewer.demo import start_viewer

logger = logging.getLogger("roadmap.demo")


def _require(module: str, what: str):
    """Import a service module, or fail naming the service that is not there yet."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise DemoError(f"{what} is not available ({module}: {exc})") from exc


# -- the run -------------------------------------------------------------------------------------


class DemoRun:
    """One demo run in OUT: named steps (simulate, start the cloud, map, fetch, localize), then
    the report and the figures from what the services wrote (report.py, figures.py)."""

    def __init__(self, args, cfg: RoadmapConfig):
        cfg = fleet_config(cfg, args.shards)
        self.store = getattr(args, "store", None)  # postgresql://: workers (services/demo/pgfleet)
        if pgfleet.is_postgres(self.store):
            cfg = pgfleet.pg_config(cfg, self.store)
        elif self.store:
            raise ConfigError(f"--store must be postgresql://..., got {self.store!r}")
        self.dead: set[str] = set()  # shards killed by --chaos and not restarted
        self.takeover_s: float | None = None
        cfg = secure_fleet(cfg, getattr(args, "secure", None), Path(args.out).resolve())
        if args.vehicles < 1 or args.shards < 1:
            raise ConfigError("roadmap demo needs --vehicles >= 1 and --shards >= 1")
        self.args, self.cfg, self.d = args, cfg, cfg.demo
        self.kind = cfg.segmentation.kind  # the fleet's and the car's segmenter
        self.onnx = self.kind == "onnx"  # the model segments rendered frames
        self.out = Path(args.out).resolve()
        self.t0 = time.monotonic()
        self.stage_ms: dict[str, float] = {}
        self.chaos_events: list[dict] = []
        self.vehicles: list[tuple[Path, Path]] = []  # (STATE, drive log), as vehicles finish
        self.max_km = self.d.small_max_km if args.small else self.d.max_km
        if args.scenario == "repaint":
            self.max_km = max(self.max_km, self.d.repaint_min_km)
        self.world = self.world_after = None
        self.router_endpoint: str | None = None
        self.spread: dict = {}  # the extra vehicles' route and the shard_map (spread.py)

    def step(self, name: str, fn, *a, **kw):
        logger.info("[%5.1f s] %s ...", time.monotonic() - self.t0, name)
        t = time.monotonic()
        result = fn(*a, **kw)
        self.stage_ms[name] = round((time.monotonic() - t) * 1000.0, 1)
        return result

    def run(self) -> dict:
        self._prepare_out()
        if self.onnx:  # fail now, not after the drives, if the model is missing
            report.fleet_segmenter(self.cfg)
        self.world = self.step("load world", self._load_world)
        logs = self.step("simulate drives", self._simulate)
        self._spread_shards(logs)
        with Supervisor(self.out / "logs", config=self.out / "config.toml") as sup:
            self.step("start router and shards", self._start_cloud, sup)
            start_viewer(sup, getattr(self.args, "viewer", None))  # roadmap demo --viewer [PORT]
            update = self._mapping(sup, logs)
            tiles_path = self.out / "run" / "tiles.npz"
            stats = self.step("fetch stats and tiles", self._fetch, sup, tiles_path)
            self.step("localize the production drive", self._localize, sup, logs["production"])
        outputs = self._outputs(stats, logs["production"], update)
        result = self.step("evaluate", self._evaluate, outputs)
        result["timings"] = report.timings_section(time.monotonic() - self.t0, self.stage_ms,
                                                   report.vehicle_summaries(outputs))
        result["processes"] = sup.history()
        (self.out / "report.json").write_text(json.dumps(result, indent=1))
        return result

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
        """Every drive's log, rendered demo.render_workers at a time (camera frames for the
        model: most of a demo's time), with a progress line per drive every 10 s."""
        sim = _require("services.sim.simulate", "the simulator (services.sim.simulate)")
        drives, seed, m = self.out / "drives", self.args.seed, self.args.vehicles
        kw = {"images": self.d.images or self.onnx, "max_km": self.max_km}
        groups = {}
        if self.args.scenario == "repaint":
            worlds = _require("services.sim.worlds", "the simulator (services.sim.worlds)")
            self.world_after = worlds.repaint(self.world, seed)
            groups["mapping"] = sim.drive_jobs(self.world, drives / "before", vehicles=m,
                                               drives=self.d.repaint_drives_before,
                                               profile="mapping", seed=seed, **kw)
            groups["after"] = sim.drive_jobs(self.world_after, drives / "after", vehicles=1,
                                             drives=self.d.repaint_drives_after,
                                             profile="mapping", seed=seed + 500, **kw)
        else:
            groups["mapping"] = sim.drive_jobs(self.world, drives / "mapping", vehicles=m,
                                               drives=self.d.drives, profile="mapping",
                                               seed=seed, **kw)
            groups["spread"] = self._spread_drives(sim, drives / "mapping", kw)
        groups["production"] = sim.drive_jobs(
            self.world_after or self.world, drives / "production", vehicles=1, drives=1,
            profile="production", seed=seed + 1000, images=self.onnx, max_km=self.max_km)
        jobs = [job for group in groups.values() for job in group]
        for job in jobs:
            if job["images"]:
                job["progress"] = _RenderProgress(f"{job['profile']} drive v{job['v']} "
                                                  f"d{job['d']}")
        paths = iter(sim.run_drives(jobs, workers=self.d.render_workers))
        logs = {name: [next(paths) for _ in group] for name, group in groups.items()}
        logs["production"] = logs["production"][0]
        logs["mapping"] += logs.pop("spread", [])
        logger.info("drive logs: %d mapping, %d after repaint, 1 production",
                    len(logs["mapping"]), len(logs.get("after", [])))
        return logs

    def _spread_drives(self, sim, out: Path, kw: dict) -> list[dict]:
        """demo.spread_vehicles more mapping vehicles (ids after the fleet's) on the route
        reaching most regions the shared route does not, when that one touches fewer regions
        than there are shards (services/demo/spread.py)."""
        n, shards, routes = self.d.spread_vehicles, self.args.shards, self.world.routes
        if self.args.small or n < 1 or shards < 2 or not routes:
            return []
        if len(spread.route_regions(routes[0], self.max_km)) >= shards:
            return []  # the shared route alone reaches as many regions as there are shards
        route = spread.spread_route(routes, self.max_km)
        if route is None:
            return []
        logger.info("fleet: %d more vehicles on route %d (regions %s) so every shard has work",
                    n, route, sorted(spread.route_regions(routes[route], self.max_km)))
        self.spread.update(vehicles=n, route=route)
        return sim.drive_jobs(self.world, out, vehicles=n, drives=self.d.drives,
                              profile="mapping", seed=self.args.seed, route=route,
                              first_vehicle=self.args.vehicles, **kw)

    def _spread_shards(self, logs: dict) -> None:
        """grid.shard_map spreading the regions the mapping drives touch over the SQLite shards
        (with --store: merger.region_owners over the workers s<k>); demo.spread_shards, neither
        set already, not --small. Every process reads config.toml."""
        g, m = self.cfg.grid, self.cfg.merger
        if self.args.small or not self.d.spread_shards or g.shard_map or m.region_owners:
            return
        mapping = [log for key, group in logs.items() if key != "production" for log in group]
        shard_map = spread.spread_shard_map(spread.frames_per_region(mapping), self.args.shards)
        if self.store:  # the workers pgfleet starts are s0..s<K-1>
            m = dataclasses.replace(m, region_owners={k: f"s{v}" for k, v in shard_map.items()})
        else:
            g = dataclasses.replace(g, shard_map=shard_map)
        self.cfg = dataclasses.replace(self.cfg, grid=g, merger=m)
        (self.out / "config.toml").write_text(to_toml(self.cfg))
        self.spread["shard_map"] = shard_map
        logger.info("regions over the shards (%s): %s",
                    "merger.region_owners" if self.store else "grid.shard_map", shard_map)

    def _start_cloud(self, sup: Supervisor) -> None:
        _require("services.merger.node", "the merger service (services.merger.node)")
        self.router_endpoint = sup.start_router()
        if self.store:
            pgfleet.reset_database(self.store)
            pgfleet.start_workers(sup, self.args.shards, self.store,
                                  getattr(self.args, "tile_servers", 1))
        for i in range(0 if self.store else self.args.shards):
            sup.start_merger(i, self.args.shards, self.out / "run" / f"merger-s{i}.sqlite")
        self._wait_shards_ready(sup, timeout_s=60.0)

    def _wait_shards_ready(self, sup: Supervisor, timeout_s: float) -> dict:
        deadline = time.monotonic() + timeout_s
        while True:
            sup.check_alive(self._shard_names())
            stats = run_fetch(sup.router_endpoint, "stats", self.args.shards)
            if all(v is not None for k, v in stats.items() if f"merger-{k}" not in self.dead):
                return stats
            if time.monotonic() > deadline:
                missing = [k for k, v in stats.items() if v is None]
                raise DemoError(f"merger shards {missing} do not answer their stats query")
            time.sleep(0.5)

    def _shard_names(self) -> list[str]:
        return [f"merger-s{i}" for i in range(self.args.shards)
                if f"merger-s{i}" not in self.dead]

    def _mapping(self, sup: Supervisor, logs: dict) -> dict | None:
        """The mapping drives through the fleet; the repaint check's section with --scenario
        repaint."""
        if self.args.scenario == "repaint":
            return self.step("map, repaint, map again", self._map_repaint, sup, logs)
        self.step("map (vehicles upload)", self._map, sup, logs["mapping"])
        return None

    def _map(self, sup: Supervisor, logs: list[Path]) -> None:
        """One vehicle process per drive log, all at once; chaos kills one shard and one vehicle."""
        _require("services.vehicle.node", "the vehicle service (services.vehicle.node)")
        started = {self._start_vehicle(sup, log): log for log in logs}
        if self.args.chaos and self.store and not self.dead:
            self._pg_chaos(sup, next(iter(started)))
        elif self.args.chaos and not self.store:
            self._chaos(sup, next(iter(started)), logs)
        self._wait_vehicles(sup, started)

    def _start_vehicle(self, sup: Supervisor, log: Path) -> str:
        name = f"vehicle-{log.parent.name}-{log.name}"
        sup.start_vehicle(name, log, vehicle_id=log.name, state=self._state(name))
        return name

    def _state(self, vehicle: str) -> Path:
        return self.out / "run" / vehicle

    def _wait_vehicles(self, sup: Supervisor, started: dict[str, Path]) -> None:
        deadline = time.monotonic() + self.d.vehicle_timeout_s
        pending, next_report = list(started), time.monotonic() + 10.0
        while pending:
            sup.check_alive(self._shard_names())
            for n in list(pending):
                if sup.procs[n].poll() is not None:
                    sup.wait(n, 0)  # raises with the log tail on a non-zero exit
                    self._vehicle_done(n, started[n])
                    pending.remove(n)
                    logger.info("%s done (%d left)", n, len(pending))
            if time.monotonic() > deadline:
                raise ProcessError(f"vehicles {pending} not done after "
                                   f"{self.d.vehicle_timeout_s} s")
            if pending and time.monotonic() > next_report:
                applied = _applied(run_fetch(sup.router_endpoint, "stats", self.args.shards))
                logger.info("mapping: %d of %d vehicles still running (%s), shards applied %d "
                            "patches", len(pending), len(started),
                            ", ".join(self._frames_done(n) for n in pending), applied)
                next_report = time.monotonic() + 10.0
            time.sleep(0.2)

    def _frames_done(self, vehicle: str) -> str:
        """'frame i of N' from the vehicle's STATE/frames.json (services/vehicle/node.py)."""
        try:
            p = json.loads((self._state(vehicle) / "frames.json").read_text())
            return f"frame {p['frames_done']} of {p['frames']}"
        except (OSError, ValueError, KeyError):
            return "starting"

    def _vehicle_done(self, name: str, log: Path) -> None:
        """A finished vehicle's outputs are there (the report reads them)."""
        state = self._state(name)
        for file in ("summary.json", "poses.npz"):
            if not (state / file).is_file():
                raise DemoError(f"{name}: no vehicle {file} in {state}")
        self.vehicles.append((state, log))

    def _chaos(self, sup: Supervisor, vehicle: str, logs: list[Path]) -> None:
        """SIGKILL the busiest shard and one vehicle once the shard has applied patches (so it
        must replay its store), while the vehicle is still mapping; then restart both. The wait
        is for the shard, not the vehicle: on a loaded machine the vehicle can finish before the
        shard has applied anything, and a shard killed empty tests no replay."""
        shard = self._busiest_shard(logs)
        applied, deadline = 0, time.monotonic() + 120.0
        while time.monotonic() < deadline:
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

    def _pg_chaos(self, sup: Supervisor, vehicle: str) -> None:
        """On PostgreSQL: SIGKILL the busiest worker mid-ingest and do not restart it (the
        others take its regions over: pipeline.takeover_s); kill and restart a vehicle."""
        event = pgfleet.kill_busiest_worker(sup, self.args.shards, after_s=self.d.chaos_after_s)
        self.dead.add(event["process"])
        self.takeover_s = event["takeover_s"]
        self.chaos_events.append(event)
        if sup.procs[vehicle].running():
            sup.kill(vehicle)
            self.chaos_events.append({"t_s": sup.elapsed(), "event": "SIGKILL",
                                      "process": vehicle, "vehicle_was_running": True})
            time.sleep(1.0)
            sup.restart(vehicle)
            self.chaos_events.append({"t_s": sup.elapsed(), "event": "restart",
                                      "process": vehicle})

    def _busiest_shard(self, logs: list[Path]) -> int:
        """The shard owning most of the drives' frames (where they truly are: the chaos test
        is the simulation's, not a service's)."""
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

    def _localize(self, sup: Supervisor, log: Path) -> None:
        """The production drive on the compressed map; then, one after the other (the first
        run's per-frame timings stay its own), on the uncompressed one."""
        _require("services.localizer.node", "the localizer service (services.localizer.node)")
        self._localizer_run(sup, log, "localizer", [])
        if self.d.compare_raw_map:
            self._localizer_run(sup, log, "localizer-raw", [
                "--set", 'localizer.map_codec="raw"', "--set", "localizer.publish=false"])

    def _localizer_run(self, sup: Supervisor, log: Path, name: str, extra: list[str]) -> None:
        out = self.out / name
        sup.start_localizer(name, log, out, extra)
        sup.wait(name, self.d.localizer_timeout_s)
        if not (out / "summary.json").is_file():
            raise DemoError(f"{name} wrote no summary.json in {out}")

    # -- repaint -----------------------------------------------------------------------------

    def _map_repaint(self, sup: Supervisor, logs: dict) -> dict:
        """Rounds of the old paint (all vehicles at once per round), then single traversals of
        the new paint, one at a time, until the map follows the repaint."""
        for round_logs in _rounds(logs["mapping"]):
            self._map(sup, round_logs)
        check = report.RepaintCheck(self._snapshot(sup, "before"), self.world, self.world_after,
                                    self._observed_area)
        for i, log in enumerate(logs["after"], start=1):
            self._map(sup, [log])
            state = check.add(i, self._snapshot(sup, f"after{i}"))
            logger.info("repaint: traversal %d: new line %.0f %%, old line %.0f %%", i,
                        100 * state["new_shown"], 100 * state["old_shown"])
            if state["followed"]:
                break
        figures.repaint_strip(*check.strip(), self.out / "repaint.png")
        return check.section(traversals_before=len(logs["mapping"]))

    def _snapshot(self, sup: Supervisor, name: str) -> dict:
        path = self.out / "run" / f"tiles-{name}.npz"
        run_fetch(sup.router_endpoint, "tiles", self.args.shards, out=path)
        return load_tiles(path)

    def _observed_area(self, mosaic) -> np.ndarray:
        return report.observed_area(self.cfg, mosaic, report.mapping_logs(self.out))

    # -- report ------------------------------------------------------------------------------

    def _outputs(self, stats: dict, production_log: Path, update: dict | None):
        a = self.args
        settings = {"seed": a.seed, "vehicles": a.vehicles, "shards": a.shards,
                    "scenario": a.scenario, "chaos": a.chaos, "small": a.small,
                    "max_km_per_drive": self.max_km, "segmenter": self.kind,
                    "images": self.d.images, "store": "postgresql" if self.store else "sqlite",
                    "spread": self.spread}
        return report.DemoOutputs(
            out=self.out, cfg=self.cfg, world=self.world_after or self.world,
            production_log=production_log, stats=stats, vehicles=self.vehicles, update=update,
            settings=settings, chaos_events=self.chaos_events, router=self.router_endpoint,
            takeover_s=self.takeover_s if self.store and self.args.chaos else None)

    def _evaluate(self, outputs: "report.DemoOutputs") -> dict:
        """report.json's sections from the services' outputs and the truth, then the figures."""
        contours = _require("common.contours", "the tile codec (common.contours)")
        maps = report.map_rasters(outputs, contours.decode_tile)  # merged, decoded, true map
        frames = report.localizer_frames(outputs)  # the localizer's estimates vs the truth
        result = report.build_report(outputs, maps, frames)
        figures.map_figures(maps.raw, maps.decoded, maps.truth, self.out)
        track = report.localizer_track(outputs, frames, result["localization"]["convergence_s"])
        if track is not None:
            figures.trajectory_figures(maps.raw, maps.mosaic.to_cells, track, self.out)
        return result


class _RenderProgress:
    """simulate_drive's progress(done, total) per frame -> a console line every REPORT_S
    seconds and at the end of the drive, while its camera frames are rendered."""

    REPORT_S = 10.0

    def __init__(self, what: str):
        self.what, self.t0, self.next = what, 0.0, 0.0

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if done == 1:
            self.t0, self.next = now, now + self.REPORT_S
        if now >= self.next or done == total:
            rate = done / max(now - self.t0, 1e-9)
            logger.info("rendering %s: frame %d of %d (%.0f %%, %.1f frames/s)",
                        self.what, done, total, 100.0 * done / total, rate)
            self.next = now + self.REPORT_S


def _rounds(logs: list[Path]) -> list[list[Path]]:
    """Mapping logs grouped by drive index (the -d<k> suffix), in drive order."""
    rounds: dict[str, list[Path]] = {}
    for log in logs:
        rounds.setdefault(log.name.rsplit("-d", 1)[-1], []).append(log)
    return [rounds[key] for key in sorted(rounds, key=int)]


def fleet_config(cfg: RoadmapConfig, shards: int) -> RoadmapConfig:
    """The config every process of the fleet gets: grid.shards = the number of shards started
    (the fleet and the production car run the same segmentation.kind)."""
    return dataclasses.replace(cfg, grid=dataclasses.replace(cfg.grid, shards=shards))


def _applied(stats: dict) -> int:
    return sum(int((c or {}).get("patches_applied", 0)) for c in stats.values())


def demo_command(args, cfg: RoadmapConfig) -> int:
    result = DemoRun(args, cfg).run()
    sys.stdout.write(report.format_table(result))
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
    store = getattr(args, "store", None)
    if store:  # the same topology on PostgreSQL: workers + tile servers (no reset: a live map)
        cfg = pgfleet.pg_config(cfg, store)
    cfg = secure_fleet(cfg, getattr(args, "secure", None), out)
    (out / "config.toml").write_text(to_toml(cfg))
    stop = stop_event()
    with Supervisor(out / "logs", config=out / "config.toml") as sup:
        endpoint = sup.start_router(getattr(args, "listen", None)
                                    or f"{fleet_scheme()}/127.0.0.1:7447")
        if store:
            pgfleet.start_workers(sup, args.shards, store, getattr(args, "tile_servers", 1))
        for i in range(0 if store else args.shards):
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
