"""`python -m services.merger.flood --out FLOOD.json`: one vehicle flooding ingest against three
normal ones, measured on real processes (a router, one merger shard, the flooder in its own
process; the normal vehicles are threads here, one session each).

Three runs: the normal vehicles alone (baseline), with the flooder and the per-client throttle
off (merger.ingest_rate_per_s = 0), and with the flooder and the throttle on (the defaults).
The flooder sends new batches as fast as its threads can, never backing off; each normal
vehicle sends one batch every --period-s. Writes, per run, the normal vehicles' ack latency
(p50, p95, max ms) and counts, and the flooder's accepted / throttled / other counts. A
measurement, not a test: nothing here asserts a time."""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from pathlib import Path

import numpy as np

from common import codec, keys
from common.classes import NUM_CLASSES
from common.messages import THROTTLED, GridPatch, IngestAck, IngestBatch

PATCHES, CELLS = 16, 300  # a batch: 16 patches of 300 cells (a vehicle's upload_batch)


def batch(client: str, seq: int, rng) -> bytes:
    patches = []
    for k in range(PATCHES):
        cells = np.sort(rng.choice(512 * 512, CELLS, replace=False)).astype(np.uint32)
        votes = np.zeros((CELLS, NUM_CLASSES), np.uint16)
        votes[:, 1] = 3
        patches.append(GridPatch(patch_id=f"{client}/{seq}/{k}", vehicle=client, tile=(0, 0),
                                 cells=cells, votes=votes, t_first_ns=10**12 + seq,
                                 t_last_ns=10**12 + seq + 1, traversal=f"{client}-drive"))
    return codec.encode(IngestBatch(patches))


def send(session, payload: bytes, client: str, timeout_s: float = 10.0) -> str:
    """'accepted', 'throttled', 'error' or 'no reply'."""
    for reply in session.get(keys.ingest(0), payload=payload, attachment=client.encode(),
                             timeout=timeout_s):
        if reply.ok is None:
            continue
        ack = codec.decode(reply.ok.payload.to_bytes(), expect=IngestAck)
        if ack.error is None:
            return "accepted"
        return "throttled" if ack.error.startswith(THROTTLED) else "error"
    return "no reply"


# -- the flooder (its own process) --------------------------------------------------------------


def flooder(endpoint: str, seconds: float, threads: int) -> dict:
    from common.bus import open_session
    from common.config import BusConfig

    counts: dict[str, int] = {}
    lock = threading.Lock()
    with open_session(BusConfig(connect=[endpoint])) as session:
        time.sleep(0.3)
        deadline = time.monotonic() + seconds

        def run(t: int) -> None:
            rng = np.random.default_rng(1000 + t)
            payloads = [batch("flooder", t * 10**6 + i, rng) for i in range(64)]
            i = 0
            while time.monotonic() < deadline:
                # a new patch id for every send: each accepted batch is stored and applied
                data = payloads[i % 64].replace(b"flooder/", f"floo{i // 64:04d}/".encode()[:8])
                result = send(session, data, "flooder")
                with lock:
                    counts[result] = counts.get(result, 0) + 1
                i += 1

        workers = [threading.Thread(target=run, args=(t,)) for t in range(threads)]
        for w in workers:
            w.start()
        for w in workers:
            w.join()
    return {"sent": sum(counts.values()), **counts, "seconds": seconds, "threads": threads}


# -- the measurement -----------------------------------------------------------------------------


def normal_vehicles(endpoint: str, seconds: float, period_s: float, n: int = 3) -> dict:
    from common.bus import open_session
    from common.config import BusConfig

    results: dict[str, list] = {f"veh-{k}": [] for k in range(n)}

    def run(client: str) -> None:
        rng = np.random.default_rng(zlib.crc32(client.encode()))
        with open_session(BusConfig(connect=[endpoint])) as session:
            time.sleep(0.3)
            deadline, seq = time.monotonic() + seconds, 0
            while time.monotonic() < deadline:
                payload = batch(client, seq, rng)
                t0 = time.perf_counter()
                result = send(session, payload, client)
                results[client].append((result, (time.perf_counter() - t0) * 1e3))
                seq += 1
                time.sleep(max(0.0, period_s - (time.perf_counter() - t0)))

    workers = [threading.Thread(target=run, args=(c,)) for c in results]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    rows = [r for rs in results.values() for r in rs]
    ms = np.array([t for res, t in rows if res == "accepted"])
    counts = {res: sum(1 for r, _ in rows if r == res) for res in {r for r, _ in rows}}
    return {"batches": len(rows), **counts,
            "ack_ms": {"p50": _pct(ms, 50), "p95": _pct(ms, 95),
                       "max": float(ms.max()) if len(ms) else None}}


def _pct(a, q):
    return round(float(np.percentile(a, q)), 2) if len(a) else None


def _spawn(args, env, log):
    return subprocess.Popen([sys.executable, "-m", *args], env=env, stdout=log,
                            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)


def _wait_alive(endpoint: str, timeout_s: float = 60.0) -> None:
    from common.bus import open_session
    from common.config import BusConfig

    with open_session(BusConfig(connect=[endpoint])) as session:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if list(session.liveliness().get(keys.alive("merger", "s0"), timeout=1.0)):
                return
            time.sleep(0.2)
    raise RuntimeError("the merger did not come up")


def run_case(name: str, endpoint: str, work: Path, *, throttle: bool, flood: bool,
             args) -> dict:
    env = dict(os.environ, ROADMAP_LOG_LEVEL="WARNING")
    if not throttle:
        env["ROADMAP_MERGER__INGEST_RATE_PER_S"] = "0"
    with open(work / f"{name}-merger.log", "wb") as log:
        merger = _spawn(["services.cli", "merger", "--shard", "0", "--shards", "1", "--store",
                         str(work / f"{name}.sqlite"), "--connect", endpoint], env, log)
    flood_proc = None
    try:
        _wait_alive(endpoint)
        if flood:
            flood_proc = subprocess.Popen(
                [sys.executable, "-m", "services.merger.flood", "--flooder", "--connect",
                 endpoint, "--seconds", str(args.seconds + args.flood_lead_s), "--threads",
                 str(args.flood_threads)], stdout=subprocess.PIPE, stdin=subprocess.DEVNULL)
            time.sleep(args.flood_lead_s)  # the flood is on (its burst spent) before them
        normal = normal_vehicles(endpoint, args.seconds, args.period_s)
        out = {"throttle": throttle, "normal": normal}
        if flood_proc is not None:
            stdout, _ = flood_proc.communicate(timeout=args.seconds + 60)
            out["flooder"] = json.loads(stdout.decode().strip().splitlines()[-1])
        return out
    finally:
        for p in (flood_proc, merger):
            if p is not None and p.poll() is None:
                p.terminate()
                p.wait(15)


def measure(args) -> dict:
    from common.bus import free_tcp_port, wait_for_tcp
    from common.config import MergerConfig

    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with tempfile.TemporaryDirectory(prefix="roadmap-flood-") as tmp:
        work = Path(tmp)
        with open(work / "router.log", "wb") as log:
            router = _spawn(["services.cli", "router", "--listen", endpoint], dict(os.environ),
                            log)
        try:
            if not wait_for_tcp("127.0.0.1", port, 15.0):
                raise RuntimeError("the router did not start")
            cases = {
                "baseline": run_case("baseline", endpoint, work, throttle=True, flood=False,
                                     args=args),
                "flood_throttle_off": run_case("off", endpoint, work, throttle=False,
                                               flood=True, args=args),
                "flood_throttle_on": run_case("on", endpoint, work, throttle=True, flood=True,
                                              args=args),
            }
        finally:
            router.terminate()
            router.wait(15)
    m = MergerConfig()
    return {"cores": os.cpu_count(), "python": sys.version.split()[0],
            "setup": {"normal_vehicles": 3, "normal_period_s": args.period_s,
                      "seconds": args.seconds, "flooder_threads": args.flood_threads,
                      "flood_lead_s": args.flood_lead_s,
                      "batch": {"patches": PATCHES, "cells_per_patch": CELLS},
                      "throttle": {"ingest_rate_per_s": m.ingest_rate_per_s,
                                   "ingest_burst": m.ingest_burst,
                                   "ingest_token_bytes": m.ingest_token_bytes}},
            "cases": cases}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m services.merger.flood")
    p.add_argument("--out", default="flood.json")
    p.add_argument("--seconds", type=float, default=8.0, help="normal vehicles' run per case")
    p.add_argument("--period-s", type=float, default=0.1, help="a normal vehicle's batch period")
    p.add_argument("--flood-threads", type=int, default=4)
    p.add_argument("--flood-lead-s", type=float, default=4.0,
                   help="the flood starts this long before the normal vehicles")
    p.add_argument("--flooder", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--connect", default=None, help=argparse.SUPPRESS)
    p.add_argument("--threads", type=int, default=4, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.flooder:
        sys.stdout.write(json.dumps(flooder(args.connect, args.seconds, args.threads)) + "\n")
        return 0
    result = measure(args)
    Path(args.out).write_text(json.dumps(result, indent=1))
    sys.stdout.write(json.dumps(result["cases"], indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
