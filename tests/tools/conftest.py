"""One `roadmap demo --small --viewer PORT` on the Karlsruhe world (the real Lanelet2 HD map:
1 mapping vehicle, 1 shard, truth segmenter, ~30 s), shared by the export, trajectory and
status tests; while it runs, the viewer it keeps up is asked for its state every second."""

import json
import subprocess
import time
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import pytest

from common.bus import free_tcp_port
from tests.conftest import spawn

DEMO_TIMEOUT_S = 480.0  # ~30 s on 2 idle cores; a busy machine takes several times that


def karlsruhe_osm(shared_data: Path) -> Path:
    return shared_data / "lanelet2-karlsruhe" / "mapping_example.osm"


@pytest.fixture(scope="session")
def karlsruhe_demo(shared_data, tmp_path_factory):
    base = tmp_path_factory.mktemp("karlsruhe-demo")
    out, port = base / "out", free_tcp_port()
    args = ["demo", "--small", "--world", f"lanelet2:{karlsruhe_osm(shared_data)}",
            "--vehicles", "1", "--shards", "1", "--seed", "0", "--viewer", port,
            "--set", "demo.compare_raw_map=false", "--set", 'segmentation.kind="truth"',
            "--out", out]
    with open(base / "stdout", "w") as stdout, open(base / "stderr", "w") as stderr:
        proc = spawn(*args, stdout=stdout, stderr=stderr)
    states, deadline = [], time.monotonic() + DEMO_TIMEOUT_S
    try:
        while proc.poll() is None and time.monotonic() < deadline:
            try:
                url = f"http://127.0.0.1:{port}/api/state"
                with urllib.request.urlopen(url, timeout=1.0) as r:
                    states.append(json.loads(r.read()))
            except OSError:
                pass
            # often: on a fast machine the small demo's vehicle maps its 271 frames in 2 s
            time.sleep(0.25)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
    logs = (base / "stdout").read_text()[-3000:] + (base / "stderr").read_text()[-5000:]
    assert proc.returncode == 0, f"demo failed:\n{logs}"
    return SimpleNamespace(out=out, report=json.loads((out / "report.json").read_text()),
                           osm=karlsruhe_osm(shared_data), viewer_port=port,
                           viewer_states=states)


def roadmap_ok(*args, timeout: float = 120) -> subprocess.CompletedProcess:
    """`roadmap ARGS`, which must exit 0."""
    from tests.conftest import roadmap

    res = roadmap(*map(str, args), timeout=timeout)
    assert res.returncode == 0, f"roadmap {' '.join(map(str, args))}:\n{res.stdout}\n{res.stderr}"
    return res
