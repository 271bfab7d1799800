"""A private PostgreSQL server for the tests of the PostgreSQL store (services/merger/pglocal.py):
one per test session, a fresh database per test; skipped, saying why, where the server binaries
or psycopg are missing (`.ci/run` installs both)."""

import re

import pytest


@pytest.fixture(scope="session")
def pg_server():
    pytest.importorskip("psycopg", reason="PostgreSQL tests need psycopg 3: pip install "
                        "'roadmap[postgres]'")
    from services.merger.pglocal import LocalPostgres, PgUnavailable

    try:
        server = LocalPostgres()
    except PgUnavailable as exc:
        pytest.skip(f"no private PostgreSQL server here: {exc}")
    yield server
    server.close()


@pytest.fixture
def pg_url(pg_server, request) -> str:
    """postgresql:// URL of a new, empty database for this test."""
    name = "t_" + re.sub(r"[^a-z0-9_]", "_", request.node.name.lower())[:50]
    return pg_server.create_database(name)
