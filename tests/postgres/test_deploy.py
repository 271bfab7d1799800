"""compose.pg.yaml (the cloud state in the official postgres image) parses and wires every
RoadMap role to that database and the router; no Docker needed (`docker compose -f
compose.pg.yaml config` says the same where Docker is installed)."""

import pytest

from tests.conftest import REPO


@pytest.fixture(scope="module")
def services():
    yaml = pytest.importorskip("yaml")
    return yaml.safe_load((REPO / "compose.pg.yaml").read_text())["services"]


def test_compose_pg_runs_the_official_images(services):
    assert services["postgres"]["image"].startswith("postgres:")
    assert services["zenoh-router"]["image"].startswith("eclipse/zenoh:1.10")
    assert "pg_isready" in " ".join(services["postgres"]["healthcheck"]["test"])
    assert any(v.endswith(":/var/lib/postgresql/data") for v in services["postgres"]["volumes"])


def test_compose_pg_workers_and_tile_servers_use_the_database(services):
    workers = [s for s in services if s.startswith("worker-")]
    assert len(workers) >= 2
    ids = [services[w]["command"][services[w]["command"].index("--id") + 1] for w in workers]
    assert len(set(ids)) == len(ids)  # each worker its own name (leases are by owner)
    for name in [*workers, "tileserver", "vehicle"]:
        env = services[name]["environment"]
        assert env["ROADMAP_MERGER__STORE"].startswith("postgresql://")
        assert "@postgres:5432/" in env["ROADMAP_MERGER__STORE"]
        assert env["ROADMAP_GRID__ROUTING"] == "region"
        assert env["ROADMAP_BUS__CONNECT"] == '["tcp/zenoh-router:7447"]'
    for name in [*workers, "tileserver"]:
        assert services[name]["command"][0] in ("worker", "tileserver")
        assert services[name]["depends_on"]["postgres"]["condition"] == "service_healthy"
        assert "healthcheck" in services[name] or name == "tileserver"
