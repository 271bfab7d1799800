"""Real `roadmap worker` processes on a real router and a private PostgreSQL: a worker killed
mid-ingest (another takes over), a worker added mid-run (regions move), fencing (an owner paused
past its lease cannot write), and a database restart mid-ingest. In each: every batch acked,
each patch stored and applied once, and the map equal to one process merging the same patches."""

import hashlib
import os
import signal
import threading
import time

import numpy as np
import pytest

from common import codec, keys
from common.bus import open_session
from common.config import BusConfig
from common.contours import decode_raw
from common.grid import region_of_tile
from common.messages import IngestAck, IngestBatch, Stats, Tile
from services.merger.pgstore import PgDatabase, read_tile
from services.merger.shard import MergerShard
from tests.conftest import kill_all, spawn
from tests.merger.helpers import lane_tile, patches_from_labels

pytestmark = [pytest.mark.integration, pytest.mark.postgres, pytest.mark.timeout(150)]

TILES = [(0, 0), (9, 1), (17, 3), (2, 10), (-5, -7), (30, 30)]  # six regions
LEASE_S = 2.0


def _batches(traversals=4):
    rng = np.random.default_rng(0)
    out = []
    for i in range(traversals):
        for tile in TILES:
            out.append(IngestBatch(patches_from_labels(
                lane_tile(offset_cells=10 if i >= 2 else 0), tile=tile, traversal=f"d{i}",
                t_ns=i * 10**12, rng=rng, flip_rate=0.05, n_patches=2)))
    return out


def _reference(batches):
    shard = MergerShard()
    for b in batches:
        shard.apply_batch(b.patches)
    shard.flush()
    return shard.digest()


class Fleet:
    """Worker processes (logs in tmp), a client session, and an outbox of batches."""

    def __init__(self, router, url, tmp_path, session):
        self.router, self.url, self.tmp, self.session = router, url, tmp_path, session
        self.procs: dict[str, object] = {}
        self.acked: dict[int, IngestAck] = {}
        self.retries = 0

    def start(self, ident):
        env = dict(os.environ, ROADMAP_MERGER__DEBOUNCE_S="0.2",
                   ROADMAP_MERGER__LEASE_S=str(LEASE_S), ROADMAP_MERGER__LEASE_RENEW_S="0.3")
        log = open(self.tmp / f"{ident}.log", "ab")
        self.procs[ident] = spawn("worker", "--id", ident, "--store", self.url, "--connect",
                                  self.router, "--log-level", "INFO", env=env, stderr=log)
        deadline = time.monotonic() + 30
        while not list(self.session.liveliness().get(keys.alive("merger", ident), timeout=1.0)):
            assert time.monotonic() < deadline, self.log(ident)
            time.sleep(0.1)

    def log(self, ident):
        return (self.tmp / f"{ident}.log").read_text()[-3000:]

    def send(self, batches, indices, until=None, deadline_s=60.0):
        """Send until each batch is acked (a vehicle's outbox); stop early once until() is true."""
        pending = [i for i in indices if i not in self.acked]
        deadline = time.monotonic() + deadline_s
        while pending:
            assert time.monotonic() < deadline, f"unacked: {pending}\n" + "\n".join(
                self.log(n) for n in self.procs)
            if until is not None and until():
                return
            i = pending[0]
            region = region_of_tile(batches[i].patches[0].tile)
            ack = None
            for reply in self.session.get(keys.region_ingest(*region),
                                          payload=codec.encode(batches[i]), timeout=2.0):
                if reply.ok is not None:
                    ack = codec.decode(reply.ok.payload.to_bytes(), expect=IngestAck)
            if ack is not None and ack.error is None:
                self.acked[i] = ack
                pending.pop(0)
            else:
                self.retries += 1
                time.sleep(0.1)

    def stats(self, ident, timeout_s=5.0):
        for reply in self.session.get(keys.stats("merger", ident), timeout=timeout_s):
            if reply.ok is not None:
                return codec.decode(reply.ok.payload.to_bytes(), expect=Stats).counters
        return None

    def regions(self, ident, timeout_s=5.0) -> dict:
        c = self.stats(ident, timeout_s) or {}
        out = {}
        for item in filter(None, str(c.get("regions", "")).split(";")):
            r, epoch = item.split("@")
            out[tuple(int(v) for v in r.split(","))] = int(epoch)
        return out

    def map_digest(self) -> str:
        """sha256 as MergerShard.digest, over every tile fetched raw through Zenoh."""
        tiles = set()
        for ident, proc in self.procs.items():
            if proc.poll() is None:
                c = self.stats(ident) or {}
                tiles |= {tuple(int(v) for v in t.split(","))
                          for t in filter(None, c.get("tile_list", "").split(";"))}
        h = hashlib.sha256()
        for t in sorted(tiles):
            (data,) = [r.ok.payload.to_bytes() for r in
                       self.session.get(keys.tile(*t) + "?codec=raw", timeout=5.0) if r.ok]
            h.update(np.asarray(t, dtype="<i8").tobytes())
            h.update(decode_raw(codec.decode(data, expect=Tile).data).tobytes())
        return h.hexdigest()

    def applied(self) -> int:
        return sum(int((self.stats(n) or {}).get("patches_applied", 0))
                   for n, p in self.procs.items() if p.poll() is None)

    def close(self):
        kill_all(self.procs.values())


@pytest.fixture
def fleet(router, pg_url, tmp_path):
    with open_session(BusConfig(connect=[router])) as session:
        f = Fleet(router, pg_url, tmp_path, session)
        try:
            yield f
        finally:
            f.close()


def _stored(url) -> list[tuple]:
    db = PgDatabase(url)
    with db.transaction() as cur:
        cur.execute("SELECT patch_id, rx, ry, epoch FROM patches")
        rows = cur.fetchall()
    db.close()
    return rows


def _check_map(fleet, batches):
    n = sum(len(b.patches) for b in batches)
    rows = _stored(fleet.url)
    assert len(rows) == n and len({r[0] for r in rows}) == n  # each patch stored once
    assert fleet.applied() == n  # ... and applied once
    assert fleet.map_digest() == _reference(batches)
    shard = MergerShard()  # the stored tiles (what tile servers serve) are that map too
    for b in batches:
        shard.apply_batch(b.patches)
    shard.flush()
    db = PgDatabase(fleet.url)
    for tile in shard.tiles():
        version, _, raw = read_tile(db, tile, raw=True)
        assert np.array_equal(decode_raw(raw), shard.labels(tile)), tile
    db.close()


def test_sigkill_a_worker_mid_ingest_another_takes_over(fleet):
    batches = _batches()
    fleet.start("s0")
    fleet.start("s1")
    everything = range(len(batches))
    fleet.send(batches, everything, until=lambda: len(fleet.acked) >= len(batches) // 2)
    victim = max(("s0", "s1"), key=lambda n: len(fleet.regions(n)))
    held = fleet.regions(victim)
    assert held, "the victim holds no region"
    fleet.procs[victim].kill()  # SIGKILL mid-ingest
    killed_at = time.time()
    fleet.procs[victim].wait(10)
    fleet.send(batches, everything)
    survivor = "s1" if victim == "s0" else "s0"
    taken = fleet.regions(survivor)
    assert set(held) <= set(taken) and all(taken[r] > held[r] for r in held)
    import json

    log = json.loads(fleet.stats(survivor)["lease_log"])
    serving = [e["serving_at"] for e in log if tuple(e["region"]) in held]
    assert max(serving) - killed_at <= 10.0  # takeover within 10 s
    _check_map(fleet, batches)


def test_adding_a_worker_mid_run_moves_regions(fleet):
    batches = _batches()
    fleet.start("s0")
    half = range(len(batches) // 2)
    fleet.send(batches, half)
    assert len(fleet.regions("s0")) == len(TILES)
    fleet.start("s1")
    deadline = time.monotonic() + 20
    while not fleet.regions("s1"):  # s0 releases s1's share, s1 claims and replays it
        assert time.monotonic() < deadline, fleet.log("s1")
        time.sleep(0.3)
    fleet.send(batches, range(len(batches)))
    r0, r1 = fleet.regions("s0"), fleet.regions("s1")
    assert r0 and r1 and not set(r0) & set(r1)
    _check_map(fleet, batches)


def test_an_owner_paused_past_its_lease_cannot_write(fleet):
    batches = _batches()
    fleet.start("s0")
    fleet.start("s1")
    first = range(len(batches) // 2)
    fleet.send(batches, first)
    held = fleet.regions("s0")
    assert held
    before = {r[0] for r in _stored(fleet.url)}
    fleet.procs["s0"].send_signal(signal.SIGSTOP)
    # a batch for s0's region goes out now: s0 is still routed to, but frozen
    target = next(i for i in range(len(batches)) if i not in fleet.acked
                  and region_of_tile(batches[i].patches[0].tile) in held)
    t = threading.Thread(target=lambda: list(fleet.session.get(
        keys.region_ingest(*region_of_tile(batches[target].patches[0].tile)),
        payload=codec.encode(batches[target]), timeout=1.0)))
    t.start()
    # s1 takes over once the router drops frozen s0's session (Zenoh's transport lease, ~10 s)
    # and with it s0's liveliness; a correctness test, with room for a loaded machine
    deadline = time.monotonic() + 45
    while not set(held) <= set(fleet.regions("s1", timeout_s=2.0)):  # lease expired: s1 took over
        assert time.monotonic() < deadline, fleet.log("s1")
        time.sleep(0.3)
    t.join()
    taken = fleet.regions("s1")
    fleet.procs["s0"].send_signal(signal.SIGCONT)  # s0 wakes up, still believing it holds them
    time.sleep(2 * LEASE_S)
    fleet.send(batches, range(len(batches)))
    old_epoch_rows = [r for r in _stored(fleet.url) if (r[1], r[2]) in held
                      and r[3] == held[(r[1], r[2])]]
    assert {r[0] for r in old_epoch_rows} <= before  # nothing written at the old epoch after
    for region, epoch in fleet.regions("s0").items():
        if region in held:
            assert epoch > taken[region]  # if it holds it again, at a newer epoch
    _check_map(fleet, batches)


def test_database_restart_mid_ingest_loses_nothing(fleet, pg_server):
    batches = _batches()
    fleet.start("s0")
    fleet.start("s1")
    everything = range(len(batches))
    fleet.send(batches, everything, until=lambda: len(fleet.acked) >= len(batches) // 3)
    restarter = threading.Thread(target=pg_server.restart, kwargs={"down_s": 1.0})
    restarter.start()
    fleet.send(batches, everything)
    restarter.join()
    assert fleet.retries >= 1  # the restart did interrupt the ingest
    _check_map(fleet, batches)
