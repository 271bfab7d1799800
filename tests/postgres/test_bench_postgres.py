"""bench.json `postgres` (services/bench/postgres.py), run small on the private server: real
workers, tile servers and router. Checks the section's shape and counts, never its timings."""

import pytest

pytestmark = [pytest.mark.integration, pytest.mark.postgres, pytest.mark.timeout(400)]


def test_postgres_section_small(pg_url):
    from services.bench.postgres import postgres_section

    s = postgres_section(pg_url, regions=4, traversals=1, workers=(1, 2), reads=40, window=4,
                         rounds=1)
    assert set(s["ingest"]) == {"1_workers", "2_workers"}
    for run in s["ingest"].values():
        assert run["per_s"] > 0 and run["patches"] == s["patches"]
        assert run["patches_applied"] == s["patches"]  # each patch applied once
    assert s["ingest_ratio_to_1_worker"]["1_workers"] == 1.0
    assert s["ingest_ratio_to_1_worker"]["2_workers"] > 0
    assert 1 <= sum(s["ingest"]["2_workers"]["regions_per_worker"].values()) <= s["regions"]
    assert s["takeover"]["takeover_s"] >= 0 and s["takeover"]["regions_moved"] >= 1
    for k in ("1_tile_servers", "2_tile_servers"):
        r = s["reads"][k]
        assert r["answered"] == r["queries"] == 40  # every tile read from the database
        assert sum(r["served_per_server"].values()) == 40  # warm-up reads not counted
        assert r["answered_by"] == r["served_per_server"] and r["no_reply"] == 0
        assert abs(sum(r["share_per_server"].values()) - 1.0) < 1e-6
        assert set(r["cpu_s"]) - {"postgres"} == {"bench_client", "router", "rest_of_machine",
                                                  *r["served_per_server"]}
    assert min(s["reads"]["2_tile_servers"]["served_per_server"].values()) > 0  # both serve
    assert s["reads_ratio_2_to_1"] > 0
    assert s["sqlite_1_shard"]["per_s"] > 0 and s["postgres_1_worker_vs_sqlite_1_shard"] > 0


def test_postgres_bench_skips_without_server_binaries(monkeypatch):
    pytest.importorskip("psycopg")
    from services.bench import postgres
    from services.merger import pglocal

    def missing():
        raise pglocal.PgUnavailable("initdb not found (test)")

    monkeypatch.setattr(pglocal, "find_bin_dir", missing)
    section = postgres.run(quick=True)["postgres"]
    assert set(section) == {"skipped"} and "initdb not found" in section["skipped"]
