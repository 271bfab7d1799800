"""Two meshed routers, a shard on each, a client on the second with the first as fail-over:
ingest and tile queries reach the owner shard across the mesh, and when the second router is
killed (-9) the shard and the client behind it move to the first, re-declare, and go on: every
acked patch stays applied once, and the maps equal a single-process merge of the same patches."""

import os
import signal
import subprocess
import time

import numpy as np
import pytest

from common import codec, keys
from common.bus import free_tcp_port, open_session, wait_for_tcp
from common.config import BusConfig
from common.contours import decode_tile, encode_tile
from common.grid import owner_of_tile
from common.messages import ACCEPTED, DUPLICATE, IngestAck, IngestBatch, Stats, Tile
from services.merger.shard import MergerShard
from tests.conftest import spawn
from tests.merger.helpers import lane_tile, patches_from_labels

pytestmark = pytest.mark.integration

SHARDS = 2


def _router(peers=()) -> tuple[subprocess.Popen, str]:
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    proc = spawn("router", "--listen", endpoint, *[a for p in peers for a in ("--peer", p)])
    if not wait_for_tcp("127.0.0.1", port, 15.0):
        proc.kill()
        raise RuntimeError(f"router did not start: {proc.stderr.read().decode()[-2000:]}")
    return proc, endpoint


def _alive(session, shard: int, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if list(session.liveliness().get(keys.alive("merger", f"s{shard}"), timeout=1.0)):
            return
        time.sleep(0.1)
    raise AssertionError(f"shard s{shard} not visible through the mesh")


def _ingest(session, batch: IngestBatch, timeout_s: float = 20.0) -> IngestAck:
    """Send until acked (a request in flight while a router dies gets no reply: resend, as the
    vehicles do; the shard's dedupe makes the resend harmless)."""
    shard = owner_of_tile(batch.patches[0].tile, SHARDS)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for reply in session.get(keys.ingest(shard), payload=codec.encode(batch), timeout=3.0):
            if reply.ok is not None:
                return codec.decode(reply.ok.payload.to_bytes(), expect=IngestAck)
        time.sleep(0.2)
    raise AssertionError(f"no ack from s{shard}")


def _one(session, key: str, expect):
    replies = [r.ok for r in session.get(key, timeout=5.0) if r.ok is not None]
    assert len(replies) == 1, f"{key}: {len(replies)} replies (only the owner answers)"
    return codec.decode(replies[0].payload.to_bytes(), expect=expect)


def _tiles_by_owner() -> dict[int, tuple[int, int]]:
    out: dict[int, tuple[int, int]] = {}
    tx = 0
    while len(out) < SHARDS:
        out.setdefault(owner_of_tile((tx, 0), SHARDS), (tx, 0))
        tx += 8  # the next region (8 x 8 tiles)
    return out


def _batches(tile, traversals) -> list[IngestBatch]:
    return [IngestBatch(patches_from_labels(lane_tile(offset_cells=4 * (i % 2)), tile=tile,
                                            traversal=f"d{i}", t_ns=i * 10**12,
                                            rng=np.random.default_rng(i), flip_rate=0.05))
            for i in traversals]


def test_ingest_and_tiles_cross_the_mesh_and_survive_a_router_kill(tmp_path):
    procs = []
    try:
        router_a, a = _router()
        procs.append(router_a)
        router_b, b = _router(peers=[a])
        procs.append(router_b)
        env = dict(os.environ, ROADMAP_MERGER__DEBOUNCE_S="0.2")
        connects = {0: [a], 1: [b, a]}  # s1 sits behind router B, with A as its fail-over
        for s in range(SHARDS):
            procs.append(spawn("merger", "--shard", str(s), "--shards", str(SHARDS), "--store",
                                str(tmp_path / f"s{s}.sqlite"), *[x for c in connects[s] for x in
                                                                  ("--connect", c)],
                                "--log-level", "WARNING", env=env))
        tiles = _tiles_by_owner()
        before = {s: _batches(tile, range(0, 3)) for s, tile in tiles.items()}
        after = {s: _batches(tile, range(3, 6)) for s, tile in tiles.items()}
        with open_session(BusConfig(connect=[b, a])) as session:
            for s in range(SHARDS):
                _alive(session, s)  # s0 only through the A-B link
            for s in range(SHARDS):
                for batch in before[s]:
                    ack = _ingest(session, batch)
                    assert not ack.error and set(ack.results.values()) == {ACCEPTED}

            router_b.send_signal(signal.SIGKILL)  # s1 and this client fail over to A
            router_b.wait(10)
            _alive(session, 1)
            for s in range(SHARDS):
                for batch in after[s]:
                    ack = _ingest(session, batch)
                    assert not ack.error and set(ack.results.values()) == {ACCEPTED}
                assert set(_ingest(session, before[s][0]).results.values()) == {DUPLICATE}

            for s, tile in tiles.items():
                counters = _one(session, keys.stats("merger", f"s{s}"), Stats).counters
                patches = [p for batch in before[s] + after[s] for p in batch.patches]
                assert counters["patches_applied"] == len(patches)  # each acked patch once
                assert counters["duplicates"] == len(before[s][0].patches)
                reference = MergerShard()
                reference.apply_batch(patches)
                reference.flush()
                assert counters["digest"] == reference.digest()
                served = _one(session, keys.tile(*tile), Tile)  # reaches the owner only
                expected = decode_tile(encode_tile(reference.labels(tile)))
                assert np.array_equal(decode_tile(served.data), expected)
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(15)

