"""The demo's cloud on PostgreSQL (`roadmap demo --store postgresql://...`, `roadmap up --store`):
workers `s0..s<K-1>` (`roadmap worker`, regions by lease) and read-only tile servers instead of
the SQLite shards, and the chaos of that fleet: SIGKILL the busiest worker mid-ingest, no
restart, and measure how long until the others serve all its regions (pipeline.takeover_s)."""

import dataclasses
import json
import logging
import time

from common.config import RoadmapConfig
from services.demo.fetch import run_fetch
from services.demo.procs import Supervisor, cli_argv

logger = logging.getLogger(__name__)

TAKEOVER_TIMEOUT_S = 60.0


def is_postgres(store: str | None) -> bool:
    return bool(store) and store.startswith(("postgresql://", "postgres://"))


def pg_config(cfg: RoadmapConfig, store: str) -> RoadmapConfig:
    """The fleet's config on PostgreSQL: merger.store = the URL, vehicles route by region."""
    return dataclasses.replace(
        cfg, merger=dataclasses.replace(cfg.merger, store=store),
        grid=dataclasses.replace(cfg.grid, routing="region"))


def reset_database(url: str) -> None:
    """A demo run starts from an empty map: drop the previous run's patches, tiles, leases."""
    from services.merger.pgstore import wait_for_database

    db = wait_for_database(url)
    with db.transaction() as cur:
        cur.execute("TRUNCATE patches, tiles, leases")
    db.close()
    logger.warning("demo: emptied the tables patches, tiles, leases of %s", url.split("@")[-1])


def start_workers(sup: Supervisor, workers: int, url: str, tile_servers: int = 1) -> None:
    for i in range(workers):
        sup.start(f"merger-s{i}", cli_argv("worker", "--id", f"s{i}", "--store", url,
                                           *sup._client_args()))
    for i in range(tile_servers):
        sup.start(f"tileserver-t{i}", cli_argv("tileserver", "--id", f"t{i}", "--store", url,
                                               *sup._client_args()))


def _regions(counters: dict | None) -> set[str]:
    return {item.split("@")[0] for item in str((counters or {}).get("regions", "")).split(";")
            if item}


def kill_busiest_worker(sup: Supervisor, workers: int, wait_applied_s: float = 120.0,
                        after_s: float = 0.0) -> dict:
    """Once a worker has applied patches, SIGKILL the one that applied most (no restart); then
    wait until the live workers hold every region it held. Returns the chaos event with
    takeover_s = (latest serving_at of its regions at their new owners) - kill time."""
    deadline = time.monotonic() + wait_applied_s
    stats = {}
    while time.monotonic() < deadline:
        stats = run_fetch(sup.router_endpoint, "stats", workers)
        if any(int((c or {}).get("patches_applied", 0)) > 0 for c in stats.values()):
            break
        time.sleep(0.2)
    time.sleep(after_s)
    stats = run_fetch(sup.router_endpoint, "stats", workers)
    victim = max(stats, key=lambda k: int((stats[k] or {}).get("patches_applied", 0)))
    held = _regions(stats[victim])
    applied = int((stats[victim] or {}).get("patches_applied", 0))
    sup.kill(f"merger-{victim}")
    killed_at = time.time()
    event = {"t_s": sup.elapsed(), "event": "SIGKILL", "process": f"merger-{victim}",
             "shard_applied_before": applied, "regions": sorted(held), "restarted": False}
    event["takeover_s"] = _wait_takeover(sup, workers, victim, held, killed_at)
    logger.info("chaos: killed worker %s (%d patches applied, regions %s); taken over in %s s",
                victim, applied, sorted(held), event["takeover_s"])
    return event


def _wait_takeover(sup, workers, victim, held, killed_at) -> float | None:
    deadline = time.monotonic() + TAKEOVER_TIMEOUT_S
    while time.monotonic() < deadline:
        stats = run_fetch(sup.router_endpoint, "stats", workers)
        live = {k: c for k, c in stats.items() if k != victim and c}
        served = set().union(*(_regions(c) for c in live.values())) if live else set()
        if held <= served:
            serving = [e["serving_at"] for c in live.values()
                       for e in json.loads(c.get("lease_log") or "[]")
                       if f"{e['region'][0]},{e['region'][1]}" in held
                       and e["serving_at"] >= killed_at]
            return round(max(serving) - killed_at, 3) if serving else 0.0
        time.sleep(0.2)
    return None
