"""Render workers (services.sim.simulate.run_drives' forked pool) die with their parent, even
when the parent is SIGKILLed mid-render and runs no cleanup."""

import os
import signal
import subprocess
import sys
import time

import pytest

from tests.conftest import REPO

PARENT = """
import multiprocessing, os, sys, time
from services.sim.simulate import die_with_parent

def work(_):
    os.write(1, f"{os.getpid()}\\n".encode())  # one write a line: print's two can interleave
    time.sleep(60)

with multiprocessing.get_context("fork").Pool(2, initializer=die_with_parent) as pool:
    pool.map(work, range(2), chunksize=1)
"""


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_render_workers_die_when_the_demo_is_killed():
    parent = subprocess.Popen([sys.executable, "-c", PARENT], cwd=REPO, stdout=subprocess.PIPE,
                              text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        workers = [int(parent.stdout.readline()) for _ in range(2)]
        assert all(_alive(p) for p in workers)
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=10)
        deadline = time.monotonic() + 10.0
        while any(_alive(p) for p in workers) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not any(_alive(p) for p in workers), "a render worker outlived its parent"
    finally:
        parent.kill()
        parent.wait()
