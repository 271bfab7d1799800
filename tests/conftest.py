"""Shared fixtures: seeded rng, the shared data folder, a real local Zenoh router process."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("ROADMAP_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA} (set ROADMAP_SHARED_DATA)")
    return SHARED_DATA


@pytest.fixture
def router():
    """A real Zenoh router in its own process on a free loopback port; yields its endpoint."""
    from common.bus import free_tcp_port, wait_for_tcp

    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "router", "--listen", endpoint],
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )
    try:
        if not wait_for_tcp("127.0.0.1", port, 15.0):
            raise RuntimeError(f"router did not start: {proc.stderr.read().decode()[-2000:]}")
        yield endpoint
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
