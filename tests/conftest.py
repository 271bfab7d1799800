"""Shared fixtures: seeded rng, the shared data folder, a real local Zenoh router process; and
how tests start our own processes (`roadmap ARGS` is `python -m services.cli ARGS`)."""

import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from services.sim.worlds import shared_data_dir

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = shared_data_dir()  # $ROADMAP_SHARED_DATA, else ../shared/data


def _argv(module: str, args) -> list[str]:
    return [sys.executable, "-m", module, *map(str, args)]


def spawn(*args, env=None, module: str = "services.cli", stdout=subprocess.DEVNULL,
          stderr=subprocess.PIPE) -> subprocess.Popen:
    """`python -m module ARGS` in the background from the repository root: stdout dropped,
    stderr kept (for the failure message), unless given files for them."""
    return subprocess.Popen(_argv(module, args), cwd=REPO, env=env, stdout=stdout,
                            stderr=stderr)


def kill_all(procs) -> None:
    """SIGKILL every process of `procs` still running (woken first, in case a test SIGSTOPped
    it) and reap them all."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGCONT)
            p.kill()
        p.wait(10)


def roadmap(*args, env=None, timeout: float = 60) -> subprocess.CompletedProcess:
    """`roadmap ARGS` to the end; stdout and stderr captured as text."""
    return subprocess.run(_argv("services.cli", args), cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA} (set ROADMAP_SHARED_DATA)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def frame_cache(tmp_path_factory) -> list[str]:
    """train-seg's options to cache rendered frames in one folder for the whole test run:
    tests that train on the same towns render them once, and the user's own cache in the temp
    dir is neither read nor written."""
    return ["--cache-dir", str(tmp_path_factory.mktemp("roadmap-segtrain"))]


@pytest.fixture
def router():
    """A real Zenoh router in its own process on a free loopback port; yields its endpoint."""
    from common.bus import free_tcp_port, wait_for_tcp

    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    proc = spawn("router", "--listen", endpoint)
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


@pytest.fixture(scope="session")
def s_export(tmp_path_factory) -> str:
    """An exported RoadSegNet of train-seg's default architecture (`s`), seeded random weights:
    the --init, --teacher and --prune file of the training tests, which check what the commands
    do with such a file whatever network the product packages (common/models/roadseg.onnx)."""
    torch = pytest.importorskip("torch", reason="training tests need the .[train] extra (torch)")
    from training.archs import ARCHS
    from training.data import TRAIN_CLASSES
    from training.net import RoadSegNet
    from training.train import export_onnx

    torch.manual_seed(0)
    model = RoadSegNet(num_classes=TRAIN_CLASSES, **ARCHS["s"]).eval()
    path = tmp_path_factory.mktemp("s-export") / "roadseg.onnx"
    export_onnx(model, path, seed=0)
    return str(path)
