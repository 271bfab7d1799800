"""The demo's tools without the fleet: process supervisor (kill, restart, clean stop), the bench
runner's tolerance of a missing or failing benchmark, and the map digest."""

import json
import os
import time

import numpy as np
import pytest

from services.bench import runner as bench
from services.demo.fetch import run_fetch
from services.demo.procs import Supervisor, cli_argv
from services.eval import map as ev

pytestmark = pytest.mark.integration


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_supervisor_kill_restart_and_clean_stop(tmp_path):
    with Supervisor(tmp_path / "logs") as sup:
        endpoint = sup.start_router()
        first = sup.procs["router"].pid
        sup.kill("router")
        assert _gone(first)
        sup.restart("router")
        stats = run_fetch(endpoint, "stats", shards=1)  # nobody serves stats: None, no hang
        assert stats == {"s0": None}
        second = sup.procs["router"].pid
        sup.start("sleeper", cli_argv("router", "--listen", "tcp/127.0.0.1:1"))  # to be stopped
    for pid in (second, sup.procs["sleeper"].pid):
        for _ in range(50):
            if _gone(pid) or open(f"/proc/{pid}/stat").read().split()[2] == "Z":
                break
            time.sleep(0.1)
        else:
            pytest.fail(f"pid {pid} still running after close()")
    assert [e["event"] for e in sup.procs["router"].history] == ["start", "SIGKILL", "start"]


def test_bench_records_missing_and_failing_benchmarks(tmp_path):
    (tmp_path / "bench_ok.py").write_text(
        "def run(quick):\n    return {'stages': {'x': {'p50_ms': 1.0}}}\n")
    (tmp_path / "bench_bad.py").write_text("def run(quick):\n    raise RuntimeError('boom')\n")
    out = bench.run_all(True, names=("ok", "bad", "absent"), bench_dir=tmp_path)
    assert out["stages"] == {"x": {"p50_ms": 1.0}}
    assert out["benchmarks"]["ok"]["ok"] and not out["benchmarks"]["bad"]["ok"]
    assert "boom" in out["benchmarks"]["bad"]["error"]
    assert "does not exist" in out["benchmarks"]["absent"]["error"]
    assert out["cores"] == os.cpu_count()


def test_a_benchmark_command_writes_its_json_and_shows_a_part(tmp_path, capsys):
    result = {"stages": {"a": 1.5}, "cpu_count": 2}
    path = bench.write_result(tmp_path / "new", "x.json", result, result["stages"])
    assert json.loads(path.read_text()) == result
    assert json.loads(capsys.readouterr().out) == {"a": 1.5}


def test_the_environment_names_the_cpu_and_the_vector_units_the_timings_depend_on():
    cpuinfo = ("processor\t: 0\nmodel name\t: AMD EPYC 9B14\nflags\t\t: fpu sse2 avx2 fma "
               "avx512f avx512_bf16 avx512_vnni\n\nprocessor\t: 1\nmodel name\t: AMD EPYC 9B14\n")
    assert bench.cpu_description(cpuinfo) == {
        "cpu": "AMD EPYC 9B14", "simd": ["avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16"]}
    avx2 = bench.cpu_description("model name : AMD EPYC\nflags : sse2 avx2 fma\n")
    assert avx2["simd"] == ["avx2", "fma"]
    here = bench.environment()
    assert set(here["simd"] or []) <= set(bench.SIMD_FLAGS) and "cpu" in here


def test_a_flat_benchmark_result_becomes_a_stage_with_its_quality_figures():
    seg = {"model": "roadseg", "ms_p50": 12.5, "ms_p95": 16.0, "iou": {"lane_line": 0.72},
           "iou_ci90": {"lane_line": [0.71, 0.73]}, "speed": {"threads": 1},
           "stop_facing": {"frames": 300, "iou": {"stop_line": 0.705}}}
    out = bench.merge_results({"segmentation": {"ok": True, "result": seg}})
    stage = out["stages"]["segmentation"]
    assert stage["p50_ms"] == 12.5 and stage["per_s"] == 80.0
    assert stage["iou_ci90"] == {"lane_line": [0.71, 0.73]}
    assert stage["stop_facing_iou"] == {"stop_line": 0.705} and "speed" not in stage


def test_bench_kills_what_a_benchmark_leaves_running(tmp_path):
    pidfile = tmp_path / "pid"
    (tmp_path / "bench_leak.py").write_text(
        "import subprocess, numpy as np\n"
        "def run(quick):\n"
        "    p = subprocess.Popen(['sleep', '300'])\n"
        f"    open({str(pidfile)!r}, 'w').write(str(p.pid))\n"
        "    return {'stages': {'leak': {'p50_ms': np.float32(2.0)}}}\n")
    out = bench.run_all(True, names=("leak",), bench_dir=tmp_path)
    assert out["stages"]["leak"]["p50_ms"] == 2.0
    pid = int(pidfile.read_text())
    for _ in range(50):
        if _gone(pid):
            break
        time.sleep(0.1)
    assert _gone(pid), "the benchmark's child outlived it"


def test_map_digest_depends_on_content_not_order():
    a, b = np.zeros((512, 512), np.uint8), np.ones((512, 512), np.uint8)
    assert ev.map_digest([(0, 0), (1, -1)], [a, b]) == ev.map_digest([(1, -1), (0, 0)], [b, a])
    assert ev.map_digest([(0, 0), (1, -1)], [a, b]) != ev.map_digest([(0, 0), (1, -1)], [b, a])
