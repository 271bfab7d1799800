"""Helpers for tests that run a small live fleet: real `roadmap` processes behind the real local
router of the `router` fixture, and a test session that ingests patches as a vehicle does."""

import json
import os
import subprocess
import time
import urllib.request
from pathlib import Path

from common import codec, keys
from common.messages import ACCEPTED, IngestAck, IngestBatch
from tests.conftest import spawn


def start(*args, log: Path, env=None) -> subprocess.Popen:
    """`roadmap ARGS` in the background, its output in `log`."""
    with open(log, "ab") as f:
        return spawn(*args, env=env, stdout=f, stderr=subprocess.STDOUT)


def start_merger(router: str, store: Path, log: Path, shard: int = 0, shards: int = 1):
    env = dict(os.environ, ROADMAP_MERGER__DEBOUNCE_S="0.2")
    return start("merger", "--shard", shard, "--shards", shards, "--store", store,
                 "--connect", router, "--set", f"grid.shards={shards}", log=log, env=env)


def stop(*procs: subprocess.Popen, timeout_s: float = 10.0) -> None:
    """SIGTERM each (the nodes close their sessions), SIGKILL what is still up after timeout."""
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def wait_alive(session, role: str, ident: str, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if list(session.liveliness().get(keys.alive(role, ident), timeout=1.0)):
            return
        time.sleep(0.1)
    raise AssertionError(f"{role} {ident} did not come up within {timeout_s:.0f} s")


def ingest(session, batch: IngestBatch, shard: int = 0, timeout_s: float = 10.0) -> IngestAck:
    """Send a batch as a vehicle does and return the ack; every patch must be accepted."""
    for reply in session.get(keys.ingest(shard), payload=codec.encode(batch), timeout=timeout_s):
        if reply.ok is not None:
            ack = codec.decode(reply.ok.payload.to_bytes(), expect=IngestAck)
            assert ack.error is None and set(ack.results.values()) == {ACCEPTED}, ack
            return ack
    raise AssertionError("no ack from the shard")


def http_json(url: str, timeout_s: float = 2.0):
    with urllib.request.urlopen(url, timeout=timeout_s) as r:
        return json.loads(r.read())


def wait_http(url: str, proc: subprocess.Popen, log: Path, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise AssertionError(f"{url}: server exited {proc.returncode}:\n"
                                 f"{log.read_text()[-3000:]}")
        try:
            http_json(url)
            return
        except OSError:
            time.sleep(0.2)
    raise AssertionError(f"{url} did not answer within {timeout_s:.0f} s")
