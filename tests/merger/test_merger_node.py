"""A real `roadmap merger` process behind a real local router: ingest with acks, tiles, stats,
updates, bad input, and kill -9 in the middle of ingest with no acked patch lost or doubled."""

import os
import signal
import threading
import time

import msgpack
import numpy as np
import pytest

from common import codec, keys
from common.bus import open_session
from common.config import BusConfig
from common.contours import decode_raw, decode_tile
from common.messages import IngestAck, IngestBatch, Stats, Tile
from services.merger.shard import MergerShard
from tests.conftest import spawn
from tests.merger.helpers import lane_tile, patches_from_labels

pytestmark = pytest.mark.integration

TILES = ((0, 0), (1, 0), (0, 1))


def _start(router, store, shard=0, shards=1):
    env = dict(os.environ, ROADMAP_MERGER__DEBOUNCE_S="0.2")
    return spawn("merger", "--shard", shard, "--shards", shards, "--store", store, "--connect",
                 router, "--log-level", "WARNING", env=env)


def _wait_alive(session, shard=0, timeout_s=20.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if list(session.liveliness().get(keys.alive("merger", f"s{shard}"), timeout=1.0)):
            return
        time.sleep(0.1)
    raise AssertionError("merger did not come up")


def _send(session, batch: IngestBatch, timeout_s=3.0) -> IngestAck | None:
    for reply in session.get(keys.ingest(0), payload=codec.encode(batch), timeout=timeout_s):
        if reply.ok is not None:
            return codec.decode(reply.ok.payload.to_bytes(), expect=IngestAck)
    return None


def _get(session, key, timeout_s=3.0):
    replies = session.get(key, timeout=timeout_s)
    return [r.ok.payload.to_bytes() for r in replies if r.ok is not None]


def _stats(session) -> dict:
    (data,) = _get(session, keys.stats("merger", "s0"))
    return codec.decode(data, expect=Stats).counters


def _batches(n_traversals=6):
    rng = np.random.default_rng(0)
    out = []
    for i in range(n_traversals):
        for tile in TILES:
            labels = lane_tile(offset_cells=10 if i >= 3 else 0)
            out.append(IngestBatch(patches_from_labels(
                labels, tile=tile, traversal=f"d{i}", t_ns=i * 10**12, rng=rng,
                flip_rate=0.05, n_patches=3)))
    return out


def _reference_digest(batches) -> str:
    shard = MergerShard()
    for b in batches:
        shard.apply_batch(b.patches)
    shard.flush()
    return shard.digest()


@pytest.fixture
def merger(router, tmp_path):
    proc = _start(router, tmp_path / "s0.sqlite")
    yield proc
    if proc.poll() is None:
        proc.kill()
        proc.wait(10)


def test_ingest_tiles_stats_updates_and_bad_input(router, merger):
    batches = _batches(3)
    with open_session(BusConfig(connect=[router])) as session:
        _wait_alive(session)
        updates = []
        sub = session.declare_subscriber(keys.TILE_UPDATE_ALL,
                                         lambda s: updates.append(s.payload.to_bytes()))
        for b in batches:
            ack = _send(session, b)
            assert ack.error is None and set(ack.results.values()) == {"accepted"}
        assert set(_send(session, batches[0]).results.values()) == {"duplicate"}

        # bad input: an error ack, state untouched
        before = _stats(session)
        bad_inputs = [
            b"\xc1garbage",
            msgpack.packb({"v": 2, "type": "IngestBatch", "body": {"patches": []}}),
            msgpack.packb({"v": 1, "type": "Pose", "body": {}}),
        ]
        p = batches[0].patches[0]
        bad_inputs.append(_mutate_patch(p, cells={"dtype": "<u8", "shape": [1], "data": b"\0" * 8}))
        bad_inputs.append(_mutate_patch(p, patch_id="new", cells={
            "dtype": "<u4", "shape": [1], "data": np.array([600000], "<u4").tobytes()}))
        packed = codec._enc_patch(p)["packed"]  # the packed wire form, corrupted
        bad_inputs.append(_mutate_patch(p, packed_form=True, patch_id="new",
                                        packed={**packed, "data": packed["data"][:-4]}))
        bad_inputs.append(_mutate_patch(p, packed_form=True, patch_id="new",
                                        packed={**packed, "n": packed["n"] + 1}))
        for data in bad_inputs:
            (reply,) = [r for r in session.get(keys.ingest(0), payload=data, timeout=3.0)]
            assert codec.decode(reply.ok.payload.to_bytes(), expect=IngestAck).error
        after = _stats(session)
        assert after["errors"] == before["errors"] + len(bad_inputs)
        assert after["digest"] == before["digest"]
        assert after["patches_applied"] == before["patches_applied"]

        # tiles: contour, since, raw
        assert after["tile_list"] == "0,0;0,1;1,0" and after["tiles"] == 3
        (data,) = _get(session, keys.tile(0, 0))
        tile = codec.decode(data, expect=Tile)
        assert tile.codec == "contour/2" and tile.version >= 1
        assert (decode_tile(tile.data) == lane_tile()).mean() > 0.99
        assert _get(session, keys.tile(0, 0) + f"?since={tile.version}") == []
        assert len(_get(session, keys.tile(0, 0) + f"?since={tile.version - 1}")) == 1
        (raw,) = _get(session, keys.tile(0, 0) + "?codec=raw")
        raw = codec.decode(raw, expect=Tile)
        assert raw.codec == "raw/1"
        assert (decode_raw(raw.data) == lane_tile()).mean() > 0.99
        assert _get(session, keys.tile(5, 5)) == []  # nobody holds it: no reply
        deadline = time.monotonic() + 5
        while len({codec.decode(u, expect=Tile).tile for u in updates}) < 3:
            assert time.monotonic() < deadline, "no tile-update publications"
            time.sleep(0.05)
        sub.undeclare()
    merger.send_signal(signal.SIGTERM)
    assert merger.wait(15) == 0


def _mutate_patch(p, packed_form=False, **changes):
    body = codec._enc_patch(p, packed_form)
    body.update(changes)
    return msgpack.packb({"v": 1, "type": "IngestBatch", "body": {"patches": [body]}},
                         use_bin_type=True)


def test_kill_9_mid_ingest_loses_no_acked_patch_and_doubles_none(router, tmp_path):
    batches = _batches(6)
    store = tmp_path / "s0.sqlite"
    proc = {"p": _start(router, store)}
    acked: dict[int, IngestAck] = {}
    killed = threading.Event()
    try:
        with open_session(BusConfig(connect=[router])) as session:
            _wait_alive(session)

            def killer():
                while len(acked) < len(batches) // 2:
                    time.sleep(0.005)
                proc["p"].send_signal(signal.SIGKILL)  # in the middle of ingest
                proc["p"].wait(10)
                killed.set()
                proc["p"] = _start(router, store)

            t = threading.Thread(target=killer)
            t.start()
            pending, retries = list(range(len(batches))), 0
            deadline = time.monotonic() + 60
            while pending:  # the vehicle's outbox: resend until acked
                assert time.monotonic() < deadline, f"unacked: {pending}"
                i = pending[0]
                ack = _send(session, batches[i], timeout_s=2.0)
                if ack is not None and ack.error is None:
                    acked[i] = ack
                    pending.pop(0)
                else:
                    retries += 1
                    time.sleep(0.1)
            t.join()
            assert killed.is_set() and retries >= 1  # the kill did interrupt the ingest
            _wait_alive(session)
            counters = _stats(session)
        n_patches = sum(len(b.patches) for b in batches)
        assert counters["patches_applied"] == n_patches  # none lost, none twice
        assert counters["digest"] == _reference_digest(batches)
    finally:
        proc["p"].kill()
        proc["p"].wait(10)
