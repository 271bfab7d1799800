"""PostgreSQL cloud benchmark (bench.json `postgres`): real `roadmap worker` and `roadmap
tileserver` processes on a real router and one private PostgreSQL server on this machine
(services/merger/pglocal.py); skipped, saying why, where its binaries or psycopg are missing.

  ingest   acked + merged + compressed patches/s with 1, 2 and 4 workers, as ratios to 1 worker
  sqlite   the same batches through 1 SQLite shard (services/bench/merger.py) beside 1 worker
  takeover seconds from SIGKILL of one of 2 workers until the other serves all its regions
  reads    tile queries/s answered by 1 and 2 read-only tile servers (workers stopped), read
           as the localizers read (services/localizer/tiles.py TileSource: each reader a client
           of its own, the server chosen per (client, tile) by rendezvous hashing, on the
           server's own key), each server's share of the answers, and the CPU seconds of each
           process (where the time goes on a small shared machine)

Data: dense label tiles of the town world, one per region (so the regions spread over the
workers), seen by several traversals, each traversal's votes split into patches; batches hold
one region's patches each (as a vehicle's uploads do with grid.routing = "region")."""

import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

from common import codec, keys
from common.config import RoadmapConfig
from common.grid import REGION_TILES, region_of_tile
from common.messages import IngestAck, IngestBatch, Stats
from services.bench import merger as bench_merger
from services.bench.runner import run_senders, write_result

logger = logging.getLogger("bench.postgres")

WORKER_ENV = {"ROADMAP_MERGER__DEBOUNCE_S": "0.2"}


def region_tiles(tiles: dict, regions: int) -> dict:
    """The `regions` densest label rasters, each on the corner tile of its own region."""
    import numpy as np

    dense = sorted(tiles.values(), key=np.count_nonzero, reverse=True)
    return {((k % 4) * REGION_TILES, (k // 4) * REGION_TILES): dense[k % len(dense)]
            for k in range(regions)}


def region_batches(patches, size: int) -> list[IngestBatch]:
    """Batches of `size` patches of one region each, the regions' batches interleaved."""
    by_region: dict = {}
    for p in patches:
        by_region.setdefault(region_of_tile(tuple(p.tile)), []).append(p)
    queues = [[IngestBatch(ps[i:i + size]) for i in range(0, len(ps), size)]
              for ps in by_region.values()]
    return [q[k] for k in range(max(map(len, queues))) for q in queues if k < len(q)]


class Cloud:
    """A router, workers and tile servers as processes (logs in one file), and a session."""

    def __init__(self, tmp: Path, url: str):
        from common.bus import free_tcp_port, wait_for_tcp

        self.tmp, self.url = tmp, url
        self.log = open(tmp / "processes.log", "ab")
        port = free_tcp_port()
        self.endpoint = f"tcp/127.0.0.1:{port}"
        self.procs: dict[str, subprocess.Popen] = {}
        self._spawn("router", ["router", "--listen", self.endpoint])
        if not wait_for_tcp("127.0.0.1", port, 15.0):
            raise RuntimeError("the router did not start")
        from common.bus import open_session
        from common.config import BusConfig

        self._session_cm = open_session(BusConfig(connect=[self.endpoint]))
        self.session = self._session_cm.__enter__()

    def _spawn(self, name: str, args: list[str]) -> None:
        self.procs[name] = subprocess.Popen(
            [sys.executable, "-m", "services.cli", *args], stdout=subprocess.DEVNULL,
            stderr=self.log, stdin=subprocess.DEVNULL, env={**os.environ, **WORKER_ENV})

    def start(self, role: str, ident: str) -> None:
        """`roadmap worker` or `roadmap tileserver` with this id; returns once it is alive."""
        self._spawn(ident, [role, "--id", ident, "--store", self.url, "--connect", self.endpoint,
                            "--log-level", "WARNING"])
        liveliness = "merger" if role == "worker" else "tileserver"
        deadline = time.monotonic() + 60.0
        while not list(self.session.liveliness().get(keys.alive(liveliness, ident),
                                                     timeout=1.0)):
            if time.monotonic() > deadline or self.procs[ident].poll() is not None:
                raise RuntimeError(f"{role} {ident} did not come up: {self.log_tail()}")
            time.sleep(0.1)

    def stop(self, ident: str, sig=signal.SIGTERM) -> None:
        proc = self.procs.pop(ident)
        proc.send_signal(sig)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)

    def stats(self, ident: str, role: str = "merger", timeout_s: float = 60.0) -> dict | None:
        for reply in self.session.get(keys.stats(role, ident), timeout=timeout_s):
            if reply.ok is not None:
                return codec.decode(reply.ok.payload.to_bytes(), expect=Stats).counters
        return None

    def log_tail(self) -> str:
        self.log.flush()
        return (self.tmp / "processes.log").read_text(errors="replace")[-2000:]

    def close(self) -> None:
        for name in [n for n in self.procs if n != "router"] + ["router"]:
            if name in self.procs:
                self.stop(name)
        self._session_cm.__exit__(None, None, None)
        self.log.close()


def reset(url: str) -> None:
    from services.merger.pgstore import wait_for_database

    db = wait_for_database(url)
    with db.transaction() as cur:
        cur.execute("TRUNCATE patches, tiles, leases")
    db.close()


def send_all(session, batches: list[IngestBatch], window: int, timeout_s: float = 120.0) -> int:
    """Each batch to its region's key until acked without error (`window` senders, one query in
    flight each, as a fleet's outboxes; an unclaimed region's first query may find no holder
    yet and is sent again); returns the number of resends."""
    todo = list(enumerate(batches))
    lock, resends, failed = threading.Lock(), [0], []
    deadline = time.monotonic() + timeout_s

    def sender() -> None:
        while not failed:
            with lock:
                if not todo:
                    return
                _, batch = todo.pop(0)
            key = keys.region_ingest(*region_of_tile(tuple(batch.patches[0].tile)))
            payload = codec.encode(batch)
            while not _acked(session, key, payload):
                if time.monotonic() > deadline:
                    failed.append(RuntimeError(f"no ack for {key} after {timeout_s} s"))
                    return
                with lock:
                    resends[0] += 1
                time.sleep(0.05)

    run_senders(sender, window, failed)
    return resends[0]


def _acked(session, key: str, payload: bytes) -> bool:
    for reply in session.get(key, payload=payload, timeout=10.0):
        if reply.ok is not None:
            return codec.decode(reply.ok.payload.to_bytes(), expect=IngestAck).error is None
    return False


def ingest_run(cloud: Cloud, workers: int, batches, window: int) -> dict:
    """Patches/s from the first send until every batch is acked and every worker's stats reply
    (which comes after its flush: merged, compressed, stored) is in."""
    idents = [f"w{k}" for k in range(workers)]
    for ident in idents:
        cloud.start("worker", ident)
    t0 = time.perf_counter()
    resends = send_all(cloud.session, batches, window)
    acked_s = time.perf_counter() - t0
    counters = {ident: cloud.stats(ident) for ident in idents}
    wall = time.perf_counter() - t0
    if any(c is None for c in counters.values()):
        raise RuntimeError(f"a worker did not answer its stats: {cloud.log_tail()}")
    n = sum(len(b.patches) for b in batches)
    applied = sum(int(c.get("patches_applied", 0)) for c in counters.values())
    return {"per_s": round(n / wall, 1), "wall_s": round(wall, 3), "acked_s": round(acked_s, 3),
            "patches": n, "patches_applied": applied, "resends": resends,
            "regions_per_worker": {i: len(list(filter(None, str(c.get("regions", ""))
                                                      .split(";"))))
                                   for i, c in counters.items()}}


def _regions(counters: dict | None) -> set[str]:
    return {item.split("@")[0] for item in str((counters or {}).get("regions", "")).split(";")
            if item}


def takeover_run(cloud: Cloud, timeout_s: float = 60.0) -> dict:
    """With workers w0, w1 holding the map: SIGKILL the one holding more regions; seconds until
    the other holds every one of them (the latest serving_at in its lease log - kill time)."""
    stats = {i: cloud.stats(i) for i in ("w0", "w1")}
    victim = max(stats, key=lambda i: len(_regions(stats[i])))
    survivor = "w1" if victim == "w0" else "w0"
    held = _regions(stats[victim])
    cloud.stop(victim, signal.SIGKILL)
    killed_at = time.time()
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        c = cloud.stats(survivor, timeout_s=5.0)
        if c and held <= _regions(c):
            serving = [e["serving_at"] for e in json.loads(c.get("lease_log") or "[]")
                       if f"{e['region'][0]},{e['region'][1]}" in held]
            return {"takeover_s": round(max(serving) - killed_at, 3), "regions_moved": len(held),
                    "lease_s": RoadmapConfig().merger.lease_s,
                    "lease_renew_s": RoadmapConfig().merger.lease_renew_s}
        time.sleep(0.05)
    raise RuntimeError(f"{survivor} did not take over {sorted(held)} in {timeout_s} s")


def read_run(cloud: Cloud, servers: int, tiles: list, queries: int, window: int) -> dict:
    """Tile queries/s answered by `servers` tile servers alone, read as the localizers read:
    `window` readers, each a TileSource of its own (its own client id, as one car each, one
    query in flight), choosing a server per (client, tile). served_per_server: each server's
    own count; cpu_s: where the time went (our processes, PostgreSQL, and the rest of the
    machine: whatever else runs there)."""
    from services.localizer.tiles import TileSource

    idents = [f"t{k}" for k in range(servers)]
    for ident in idents:
        cloud.start("tileserver", ident)
    sources = [TileSource(cloud.session, client_id=f"reader{k}", timeout_s=10.0)
               for k in range(window)]
    try:
        _wait_for_servers(sources, idents)
        for source in sources:  # warm-up, untimed: each server's connections and first reads
            for tile in tiles:
                source.get(tile)
        before = {i: int((cloud.stats(i, "tileserver") or {}).get("served", 0)) for i in idents}
        answered_before = sum((s.answered for s in sources), Counter())
        cpu0 = _cpu(cloud, idents)
        wall = _read_all(sources, tiles, queries)
        cpu = {k: round(v - cpu0.get(k, v), 2) for k, v in _cpu(cloud, idents).items()}
        answered = sum((s.answered for s in sources), Counter()) - answered_before
    finally:
        for source in sources:
            source.close()
    served = {i: int((cloud.stats(i, "tileserver") or {}).get("served", 0)) - before[i]
              for i in idents}
    for ident in idents:
        cloud.stop(ident)
    cpu["rest_of_machine"] = round(cpu.pop("machine") - sum(cpu.values()), 2)
    return {"per_s": round(queries / wall, 1), "wall_s": round(wall, 3), "queries": queries,
            "answered": sum(answered.values()), "served_per_server": served,
            "share_per_server": {i: round(n / queries, 3) for i, n in served.items()},
            "answered_by": {i or "plain_key": n for i, n in sorted(answered.items())},
            "no_reply": sum(s.no_reply for s in sources), "cpu_s": cpu}


def _wait_for_servers(sources, idents: list[str], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while any(s.live() != idents for s in sources):
        if time.monotonic() > deadline:
            raise RuntimeError(f"the readers do not see tile servers {idents}")
        time.sleep(0.05)


def _read_all(sources, tiles: list, queries: int) -> float:
    """Seconds for `queries` tile reads shared out over the readers (one thread each)."""
    work = [tiles[i % len(tiles)] for i in range(queries)]
    lock = threading.Lock()

    def reader(source) -> None:
        while True:
            with lock:
                if not work:
                    return
                tile = work.pop()
            source.get(tile)

    t0 = time.perf_counter()
    threads = [threading.Thread(target=reader, args=(s,), daemon=True) for s in sources]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return time.perf_counter() - t0


def _cpu(cloud: Cloud, idents: list[str]) -> dict:
    """CPU seconds so far: this process (the readers and their Zenoh session), the router, each
    tile server, the PostgreSQL server, and the whole machine (busy time over all cores, from
    /proc/stat)."""
    out = {"bench_client": sum(os.times()[:2]), "router": _proc_cpu_s(cloud.procs["router"].pid)}
    out.update({i: _proc_cpu_s(cloud.procs[i].pid) for i in idents})
    pg = _postgres_cpu_s(cloud.url)
    if pg is not None:
        out["postgres"] = pg
    fields = [int(v) for v in Path("/proc/stat").read_text().split("\n")[0].split()[1:]]
    out["machine"] = (sum(fields[:8]) - fields[3] - fields[4]) / os.sysconf("SC_CLK_TCK")
    return out


def _proc_cpu_s(pid: int) -> float:
    after_name = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(after_name[11]) + int(after_name[12])) / os.sysconf("SC_CLK_TCK")


def _postgres_cpu_s(url: str) -> float | None:
    """CPU seconds of the private server at url (services/merger/pglocal.py: ?host=<dir>): its
    postmaster and the backends it forked; None where that cannot be read."""
    from urllib.parse import parse_qs, urlparse

    try:
        host = parse_qs(urlparse(url).query)["host"][0]
        master = int((Path(host) / "data" / "postmaster.pid").read_text().split()[0])
        total = _proc_cpu_s(master)
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                after_name = stat.read_text().rsplit(")", 1)[1].split()
                if int(after_name[1]) == master:
                    total += _proc_cpu_s(int(stat.parent.name))
            except (OSError, ValueError, IndexError):
                continue  # gone meanwhile
        return total
    except (OSError, KeyError, ValueError, IndexError):
        return None


def postgres_section(url: str, *, regions: int = 16, traversals: int = 8, workers=(1, 2, 4),
                     reads: int = 1000, window: int = 8, rounds: int = 3,
                     with_sqlite: bool = True) -> dict:
    """The bench.json `postgres` section against the database at url (emptied before each
    fleet). Fleet sizes alternate over `rounds` (the machine is shared): best round of each;
    takeover and reads once, after the first 2-worker ingest."""
    tiles = region_tiles(bench_merger.world_label_tiles(True), regions)
    patches = bench_merger.traversal_patches(tiles, traversals=traversals, pieces=8)
    batches = region_batches(patches, RoadmapConfig().vehicle.upload_batch)
    out = {"unit": "patches/s acked + merged + compressed; tile queries/s",
           "regions": regions, "patches": len(patches), "batches": len(batches),
           "cores": os.cpu_count(), "requests_in_flight": window, "ingest": {}}
    runs: dict[str, list[dict]] = {f"{n}_workers": [] for n in workers}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(rounds):
            for n in workers:  # a fresh fleet and an empty database each time
                reset(url)
                cloud = Cloud(Path(tmp), url)
                try:
                    runs[f"{n}_workers"].append(ingest_run(cloud, n, batches, window))
                    if n == 2 and "takeover" not in out:
                        _takeover_and_reads(cloud, out, sorted(tiles), reads, window)
                finally:
                    cloud.close()
    out["ingest"] = {k: max(v, key=lambda r: r["per_s"]) for k, v in runs.items()}
    out["ingest_rounds_per_s"] = {k: [r["per_s"] for r in v] for k, v in runs.items()}
    _ratios(out, workers)
    if with_sqlite:  # the same batches through the SQLite path (shard routing, 1 shard)
        sqlite = max((bench_merger.ingest_rate(1, batches, window) for _ in range(rounds)),
                     key=lambda r: r["per_s"])
        out["sqlite_1_shard"] = {"per_s": round(sqlite["per_s"], 1),
                                 "wall_s": round(sqlite["wall_s"], 3)}
        one = out["ingest"].get("1_workers", {}).get("per_s")
        if one:
            out["postgres_1_worker_vs_sqlite_1_shard"] = round(one / sqlite["per_s"], 3)
    out["load_average_1m"] = round(os.getloadavg()[0], 2)
    return out


def _takeover_and_reads(cloud: Cloud, out: dict, tiles: list, reads: int, window: int) -> None:
    out["takeover"] = takeover_run(cloud)
    for ident in [i for i in cloud.procs if i.startswith("w")]:
        cloud.stop(ident)  # a clean stop stores the tiles; the tile servers alone answer now
    out["reads"] = {f"{k}_tile_servers": read_run(cloud, k, tiles, reads, window)
                    for k in (1, 2)}
    r1 = out["reads"]["1_tile_servers"]["per_s"]
    out["reads_ratio_2_to_1"] = round(out["reads"]["2_tile_servers"]["per_s"] / r1, 3)


def _ratios(out: dict, workers) -> None:
    one = out["ingest"]["1_workers"]["per_s"] if 1 in workers else None
    out["ingest_ratio_to_1_worker"] = {k: round(v["per_s"] / one, 3) if one else None
                                       for k, v in out["ingest"].items()}


def run(quick: bool = False) -> dict:
    """{"postgres": section} on a private server; {"postgres": {"skipped": why}} without one."""
    try:
        import psycopg  # noqa: F401

        from services.merger.pglocal import LocalPostgres, PgUnavailable
    except ImportError as exc:
        return {"postgres": {"skipped": f"psycopg 3 missing (pip install 'roadmap[postgres]'): "
                                        f"{exc}"}}
    try:
        server = LocalPostgres()
    except PgUnavailable as exc:
        return {"postgres": {"skipped": f"no PostgreSQL server binaries here: {exc}"}}
    try:
        url = server.create_database("bench")
        kw = {"regions": 8, "traversals": 2, "reads": 200, "rounds": 1} if quick else {}
        return {"postgres": {**postgres_section(url, **kw), "server": "private, fsync=off, "
                             "unix socket (services/merger/pglocal.py)"}}
    finally:
        server.close()


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO)
    result = run(args.quick)
    write_result(args.out, "postgres.json", result)


if __name__ == "__main__":
    main()
