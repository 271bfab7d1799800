"""CLI smoke tests through a real subprocess: help, dump-config, error mapping to exit codes."""

import tomllib

from tests.conftest import roadmap


def test_help_lists_every_command():
    out = roadmap("--help").stdout
    for cmd in ("sim", "world", "vehicle", "merger", "localize", "demo", "bench", "dump-config"):
        assert cmd in out


def test_dump_config_is_valid_toml_with_overrides():
    import os

    env = dict(os.environ, ROADMAP_GRID__SHARDS="7")
    res = roadmap("dump-config", "--set", "camera.fx=512", env=env)
    assert res.returncode == 0, res.stderr
    cfg = tomllib.loads(res.stdout)
    assert cfg["grid"]["shards"] == 7 and cfg["camera"]["fx"] == 512.0


def test_bad_setting_is_one_line_and_exit_1():
    res = roadmap("dump-config", "--set", "grid.shards=none")
    assert res.returncode == 1
    assert res.stderr.strip().count("\n") == 0 and "grid.shards" in res.stderr


def test_deploy_advanced_config_lists_the_current_defaults():
    """deploy/config/advanced.toml is generated; regenerate it when a setting changes:
    python -m services.demo.configdoc > deploy/config/advanced.toml"""
    from pathlib import Path

    from services.demo.configdoc import render

    path = Path(__file__).resolve().parents[1] / "deploy" / "config" / "advanced.toml"
    assert path.read_text() == render(), "stale: python -m services.demo.configdoc > " + str(path)


def test_demo_checks_the_configured_segmentation_model_before_driving(tmp_path):
    """`segmentation.kind="onnx"` runs segmentation.model_path: a missing file stops the demo at
    once (exit 1, one line), instead of the packaged model being checked and the fleet failing
    later."""
    res = roadmap("demo", "--small", "--out", str(tmp_path / "out"),
                  "--set", 'segmentation.kind="onnx"',
                  "--set", f'segmentation.model_path="{tmp_path / "missing.onnx"}"', timeout=60)
    assert res.returncode == 1, res.stderr[-2000:]
    assert "segmentation model not found" in res.stderr and "missing.onnx" in res.stderr
    assert not (tmp_path / "out" / "drives").exists()  # stopped before simulating any drive
