"""Merger benchmark: merged cell-votes per second per shard next to a plain numpy bincount over the
same data in the same run, and acked ingest throughput with 2 shards against 1 through a real
router (separate processes, SQLite durable store).

    python -m services.bench.merger --out DIR [--quick] [--shard-cpus 0,1]   -> DIR/merger.json

--shard-cpus pins the shard processes to those CPUs and the router and this load generator to
all the others (Linux sched_setaffinity): on a machine with more than 2 cores, "2 shards against
1 on 2 cores" then measures the shards alone on their 2 cores, with the router and the load
generator, which a real deployment runs elsewhere, not taking those cores' time.

A cell-vote is one patch row: one cell with its 6 class counts. "Merged" = MergerShard.apply_batch
of every patch + flush() (the evidence rule's labels for every tile), from patch objects to label
rasters. The bincount reference sums the same rows per tile (paper: plain vote accumulation)
with np.bincount, including the concatenation of each tile's patches: the practical limit of
numpy. Data: every tile of a world (town) observed by several traversals, each traversal's votes
for a tile split into spatially contiguous patches as a vehicle sends them."""

import argparse
import logging
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from common import codec, keys
from common.classes import NUM_CLASSES
from common.config import RoadmapConfig
from common.grid import CELLS_PER_TILE, owner_of_tile
from common.messages import GridPatch, IngestAck, IngestBatch
from services.bench.runner import run_senders, write_result
from services.merger.shard import MergerShard

logger = logging.getLogger("bench.merger")


# -- data --------------------------------------------------------------------------------------


def world_label_tiles(quick: bool) -> dict:
    from services.bench import codec as bench_codec

    return bench_codec.world_tiles(bench_codec.load_world("town:1" if quick else "town:3", quick))


def traversal_patches(tiles: dict, traversals: int, pieces: int, seed: int = 0,
                      overlap: float = 0.0, spacing_ns: int = 10**12) -> list[GridPatch]:
    """Every tile seen by every traversal, votes 1..12 for the true class plus noise votes.
    `overlap`: each piece also takes that fraction of the next piece's cells (with votes of its
    own), as a vehicle's successive patches share the cells its ROI swept in both."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(traversals):
        for tile, labels in tiles.items():
            flat = labels.ravel()
            cells = np.flatnonzero(flat).astype(np.uint32)
            votes = np.zeros((len(cells), NUM_CLASSES), np.uint16)
            votes[np.arange(len(cells)), flat[cells]] = rng.integers(1, 13, len(cells))
            noisy = rng.random(len(cells)) < 0.1
            votes[np.flatnonzero(noisy), rng.integers(0, NUM_CLASSES, noisy.sum())] += 2
            for j, part in enumerate(np.array_split(np.arange(len(cells)), pieces)):
                if overlap and j < pieces - 1:
                    extra = int(len(part) * overlap)
                    part = np.arange(part[0], min(len(cells), part[-1] + 1 + extra))
                v = votes[part]
                if overlap:
                    v = np.maximum(1, v // 2) * (v > 0)
                out.append(GridPatch(f"{tile}/{k}/{j}", "bench", tile, cells[part], v,
                                     k * spacing_ns + j, k * spacing_ns + j + 1, f"d{k}"))
    return out


# -- merge throughput ----------------------------------------------------------------------------


def _ours(patches) -> None:
    shard = MergerShard(max_batch_patches=len(patches), max_batch_cells=1 << 40)
    shard.apply_batch(patches)
    shard.flush()


def _bincount(patches) -> None:
    by_tile: dict = {}
    for p in patches:
        by_tile.setdefault(p.tile, []).append(p)
    classes = np.arange(NUM_CLASSES, dtype=np.int64)
    for group in by_tile.values():
        cells = np.concatenate([p.cells for p in group]).astype(np.int64)
        votes = np.concatenate([p.votes for p in group])
        idx = (cells[:, None] * NUM_CLASSES + classes).ravel()
        np.bincount(idx, weights=votes.ravel(), minlength=CELLS_PER_TILE * NUM_CLASSES)


def _best_times(fn, patches, repeats: int) -> tuple[float, float]:
    """(min wall s, min process CPU s) over repeats: the machine is shared, CPU time is what a
    shard with a core of its own would take."""
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn(patches)
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return min(wall), min(cpu)


def merge_throughput(quick: bool) -> dict:
    """Headline: pieces that overlap by 15 % of their cells (as in the demo's real patches:
    about half of a traversal's pieces in a tile share cells); `disjoint_pieces`: the same
    without overlap (the merger then only concatenates a traversal's pieces)."""
    tiles = world_label_tiles(quick)
    repeats = 3 if quick else 7
    out = {}
    for name, overlap in (("overlapping_pieces", 0.15), ("disjoint_pieces", 0.0)):
        patches = traversal_patches(tiles, traversals=6, pieces=4, overlap=overlap)
        rows = sum(len(p.cells) for p in patches)
        ours_w, ours_c = _best_times(_ours, patches, repeats)
        ref_w, ref_c = _best_times(_bincount, patches, repeats)
        out[name] = {
            "cell_votes_per_s": round(rows / ours_c),
            "bincount_cell_votes_per_s": round(rows / ref_c),
            "ratio_to_bincount": round(ref_c / ours_c, 3),
            "wall_clock": {"cell_votes_per_s": round(rows / ours_w),
                           "bincount_cell_votes_per_s": round(rows / ref_w)},
            "cell_votes": rows, "patches": len(patches), "piece_overlap": overlap,
        }
    return {
        **out["overlapping_pieces"],
        "disjoint_pieces": out["disjoint_pieces"],
        "timing": f"process CPU time, best of {repeats}, one core (wall_clock: best wall time)",
        "load_average_1m": round(os.getloadavg()[0], 2),
        "tiles": len(tiles), "traversals": 6,
        "goal": {"cell_votes_per_s_min": 5_000_000, "ratio_to_bincount_min": 0.333},
    }


def retirement(quick: bool) -> dict:
    """Memory of a shard as traversals keep coming (an hour apart, every tile seen each time,
    flushed after each): traversal records and vote bytes held, keeping all against retiring
    those out of every cell's window (services/merger/shard.py), and the maps' digests."""
    tiles = world_label_tiles(True)
    n = 12 if quick else 40
    patches = traversal_patches(tiles, traversals=n, pieces=2, spacing_ns=3600 * 10**9)
    by_trav: dict = {}
    for p in patches:
        by_trav.setdefault(p.traversal, []).append(p)
    out = {}
    for name, after in (("keep_all", -1.0), ("retire", 3600.0)):
        shard = MergerShard(retire_after_s=after, max_batch_patches=1 << 20,
                            max_batch_cells=1 << 40)
        c0 = time.process_time()
        for group in by_trav.values():
            shard.apply_batch(group)
            shard.flush()
        held = sum(sum(c.nbytes + v.nbytes for c, v in t.pieces)
                   for s in shard.tiles_state.values() for t in s.traversals.values())
        out[name] = {"traversals_held": shard.traversals_held(),
                     "vote_mb_held": round(held / 2**20, 2),
                     "cpu_s": round(time.process_time() - c0, 2), "digest": shard.digest()[:16]}
    out["same_map"] = out["keep_all"]["digest"] == out["retire"]["digest"]
    out.update(traversals=n, tiles=len(tiles))
    return out


# -- ingest scaling ------------------------------------------------------------------------------


PINNING: dict = {}  # role ("shard", "other") -> CPU set, from --shard-cpus


def _spawn(args: list[str], log, role: str = "other") -> subprocess.Popen:
    cpus = PINNING.get(role)
    return subprocess.Popen([sys.executable, "-m", "services.cli", *args],
                            stdout=subprocess.DEVNULL, stderr=log,
                            preexec_fn=(lambda: os.sched_setaffinity(0, cpus)) if cpus else None)


def pin(shard_cpus: set[int]) -> dict:
    """Shards on shard_cpus, router and load generator (this process) on the other CPUs."""
    others = set(os.sched_getaffinity(0)) - shard_cpus
    if not shard_cpus or not others:
        raise SystemExit(f"--shard-cpus {sorted(shard_cpus)}: needs CPUs left for the router "
                         f"and load generator (this machine: {sorted(os.sched_getaffinity(0))})")
    PINNING.update(shard=shard_cpus, other=others)
    os.sched_setaffinity(0, others)
    return {"shards": sorted(shard_cpus), "router_and_load_generator": sorted(others)}


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc), 0 where unavailable."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return 0.0


def ingest_rate(n_shards: int, batches: list[IngestBatch], window: int = 8) -> dict:
    """Patches per second for `batches` sent to their owner shards (n_shards processes), from
    the first send until every batch is acked AND every shard has merged and compressed it;
    with the CPU seconds each process (router, shards, this load generator) spent meanwhile."""
    from common.bus import free_tcp_port, open_session, wait_for_tcp
    from common.config import BusConfig

    procs = []
    with tempfile.TemporaryDirectory() as tmp, open(Path(tmp) / "log.txt", "w") as log:
        port = free_tcp_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        try:
            procs.append(_spawn(["router", "--listen", endpoint], log))
            wait_for_tcp("127.0.0.1", port, 15)
            for s in range(n_shards):
                procs.append(_spawn(["merger", "--shard", str(s), "--shards", str(n_shards),
                                     "--store", f"{tmp}/s{s}.sqlite", "--connect", endpoint,
                                     "--log-level", "WARNING"], log, role="shard"))
            with open_session(BusConfig(connect=[endpoint])) as session:
                _wait_shards(session, n_shards)
                work = [(keys.ingest(owner_of_tile(b.patches[0].tile, n_shards)), codec.encode(b))
                        for b in batches]
                n = sum(len(b.patches) for b in batches)
                cpu0, own0 = [_cpu_s(p.pid) for p in procs], time.process_time()
                t0 = time.perf_counter()
                _pipelined(session, work, window)
                acked_s = time.perf_counter() - t0
                # every shard's stats reply comes after its flush: labels merged, tiles compressed
                handles = [session.get(keys.stats("merger", f"s{k}"), timeout=120.0)
                           for k in range(n_shards)]
                if not all(any(r.ok is not None for r in h) for h in handles):
                    raise RuntimeError("a shard did not answer its stats")
                wall = time.perf_counter() - t0
                cpu = [_cpu_s(p.pid) - c for p, c in zip(procs, cpu0, strict=True)]
                return {"per_s": n / wall, "wall_s": wall, "acked_s": acked_s,
                        "cpu_s": {"router": round(cpu[0], 3),
                                  **{f"s{k}": round(cpu[k + 1], 3) for k in range(n_shards)},
                                  "load_generator": round(time.process_time() - own0, 3)}}
        finally:
            for p in reversed(procs):
                p.terminate()
            for p in procs:
                try:
                    p.wait(15)
                except subprocess.TimeoutExpired:  # never leave a process behind
                    p.kill()
                    p.wait(15)


def _wait_shards(session, n_shards: int, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        alive = list(session.liveliness().get(keys.alive_all("merger"), timeout=1.0))
        if len(alive) >= n_shards:
            return
        time.sleep(0.1)
    raise RuntimeError("merger shards did not come up")


def _pipelined(session, work, window: int) -> None:
    """`window` senders, each with one get in flight, taking the next batch as soon as its own
    is acked (as `window` vehicles do; acks awaited in send order would hold back a fast
    shard's senders behind a slow shard's oldest request); every batch must be acked without
    error."""
    todo = iter(work)
    lock = threading.Lock()
    failed: list[BaseException] = []

    def sender() -> None:
        while not failed:
            with lock:
                item = next(todo, None)
            if item is None:
                return
            try:
                _expect_ack(session.get(item[0], payload=item[1], timeout=30.0))
            except BaseException as exc:  # noqa: BLE001 - re-raised on the calling thread
                failed.append(exc)

    run_senders(sender, window, failed)


def _expect_ack(handler) -> None:
    for reply in handler:
        if reply.ok is not None:
            ack = codec.decode(reply.ok.payload.to_bytes(), expect=IngestAck)
            if ack.error:
                raise RuntimeError(ack.error)
            return
    raise RuntimeError("no ack")


def balanced_tiles(tiles: dict, per_shard: int) -> dict:
    """The `per_shard` densest label rasters, each placed on one tile owned by shard 0 and one
    owned by shard 1 (of 2): both shards get the same work, cell for cell (a world's own tiles
    split very unevenly between 2 shards: whole 8 x 8 tile regions go to one owner)."""
    dense = sorted(tiles.values(), key=np.count_nonzero, reverse=True)[:per_shard]
    free = {0: [], 1: []}
    tx = 0
    while min(len(v) for v in free.values()) < len(dense):
        for ty in range(0, 64, 8):  # one tile per region (8 x 8 tiles), regions side by side
            free[owner_of_tile((tx, ty), 2)].append((tx, ty))
        tx += 8
    out = {}
    for k, labels in enumerate(dense):
        out[free[0][k]] = labels
        out[free[1][k]] = labels
    return out


def upload_batches(patches: list[GridPatch], size: int, shards: int = 2) -> list[IngestBatch]:
    """Batches of `size` patches with one owner shard (of `shards`) each, as vehicles send them
    (services/vehicle/node.py), the owners' batches interleaved in the order the patches came."""
    by_owner: dict[int, list[GridPatch]] = {}
    for p in patches:
        by_owner.setdefault(owner_of_tile(p.tile, shards), []).append(p)
    queues = [[IngestBatch(ps[i:i + size]) for i in range(0, len(ps), size)]
              for ps in by_owner.values()]
    return [q[k] for k in range(max(map(len, queues))) for q in queues if k < len(q)]


def ingest_scaling(quick: bool, window: int = 8) -> dict:
    """1 shard against 2 on the same batches (vehicle.upload_batch patches each, as vehicles
    send them); `window` ingest requests in flight at once (a fleet of `window` vehicles with
    one upload each outstanding)."""
    tiles = balanced_tiles(world_label_tiles(True), per_shard=4 if quick else 8)
    patches = traversal_patches(tiles, traversals=2 if quick else 24, pieces=8)
    batch_size = RoadmapConfig().vehicle.upload_batch
    batches = upload_batches(patches, batch_size)
    rounds = 1 if quick else 5
    ones, twos = [], []
    for _ in range(rounds):  # alternate, best of each: the machine is shared
        ones.append(ingest_rate(1, batches, window))
        twos.append(ingest_rate(2, batches, window))
    one = max(ones, key=lambda r: r["per_s"])
    two = max(twos, key=lambda r: r["per_s"])
    wire = sum(len(codec.encode(b)) for b in batches)
    return {"ingest_1_shard_per_s": round(one["per_s"], 1),
            "ingest_2_shards_per_s": round(two["per_s"], 1),
            "ratio": round(two["per_s"] / one["per_s"], 3),
            "unit": "patches/s, acked + merged + compressed (stats reply after the last flush)",
            "cores": os.cpu_count(),
            "shard_cores": len(PINNING.get("shard", ())) or os.cpu_count(),
            "requests_in_flight": window,
            "opencv_threads_per_shard": RoadmapConfig().merger.opencv_threads,
            "rounds": {"one_shard": [round(r["per_s"], 1) for r in ones],
                       "two_shards": [round(r["per_s"], 1) for r in twos]},
            "best_runs": {"one_shard": _rounded(one), "two_shards": _rounded(two)},
            "cpu_bound_ratio_2_cores": _cpu_bound_ratio(ones, twos),
            "load_average_1m": round(os.getloadavg()[0], 2),
            "patches": len(patches), "patches_per_batch": batch_size, "batches": len(batches),
            "tiles": len(tiles), "tiles_per_shard": len(tiles) // 2,
            "cell_votes": sum(len(p.cells) for p in patches),
            "wire_bytes_per_cell_vote": round(wire / sum(len(p.cells) for p in patches), 3),
            "wire_bytes_per_cell_vote_unpacked": round(
                sum(len(codec.encode(b, packed=False)) for b in batches[:8])
                / sum(len(p.cells) for b in batches[:8] for p in b.patches), 3),
            "goal_ratio_min": 1.7}


def _cpu_bound_ratio(ones: list[dict], twos: list[dict], cores: int = 2) -> dict:
    """What the measured CPU seconds allow on `cores` cores of their own (the shared machine's
    wall clock does not show it): each run takes at least its busiest process's CPU time and
    at least all its processes' CPU time over the cores (router and load generator included).
    Median over the rounds."""
    def bound(run):
        cpu = run["cpu_s"]
        return max(max(v for k, v in cpu.items() if k.startswith("s")), sum(cpu.values()) / cores)

    one = float(np.median([bound(r) for r in ones]))
    two = float(np.median([bound(r) for r in twos]))
    return {"ratio": round(one / two, 3), "one_shard_s": round(one, 3),
            "two_shards_s": round(two, 3), "cores": cores,
            "cpu_s_shards_total": {"one_shard": _median_cpu(ones, "s"),
                                   "two_shards": _median_cpu(twos, "s")},
            "cpu_s_router_and_load_generator": {
                "one_shard": _median_cpu(ones, ("router", "load_generator")),
                "two_shards": _median_cpu(twos, ("router", "load_generator"))}}


def _median_cpu(runs: list[dict], prefix) -> float:
    return round(float(np.median([sum(v for k, v in r["cpu_s"].items() if k.startswith(prefix))
                                  for r in runs])), 3)


def _rounded(run: dict) -> dict:
    return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in run.items()}


def run(quick: bool = False, window: int = 8) -> dict:
    return {"merge": merge_throughput(quick), "retirement": retirement(quick),
            "scaling": ingest_scaling(quick, window)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--window", type=int, default=8, help="ingest requests in flight")
    ap.add_argument("--shard-cpus", default="",
                    help="comma-separated CPUs for the shards; the rest run router + load")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO)
    pinning = pin({int(c) for c in args.shard_cpus.split(",")}) if args.shard_cpus else None
    result = run(args.quick, args.window)
    if pinning:
        result["scaling"]["pinning"] = pinning
    write_result(args.out, "merger.json", result)


if __name__ == "__main__":
    main()
