"""A private PostgreSQL server in a temporary folder (initdb + pg_ctl), for the tests and the
benchmarks: unix socket only (no TCP listener), its own port number, stopped on close.

Finds the binaries on PATH or under /usr/lib/postgresql/<ver>/bin (Debian's package). initdb
refuses to run as root, so as root the server runs as the `postgres` OS user (created by the
Debian package) through runuser; `PgUnavailable` says what is missing otherwise."""

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path

from common.errors import RoadmapError

SERVER_OPTIONS = ("-c listen_addresses='' -c fsync=off -c full_page_writes=off "
                  "-c max_connections=200 -c shared_buffers=64MB")


class PgUnavailable(RoadmapError):
    """No PostgreSQL binaries, or no way to run them here."""


def find_bin_dir() -> Path:
    found = shutil.which("initdb")
    if found:
        return Path(os.path.realpath(found)).parent
    candidates = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"),
                        key=lambda p: int(p.split("/")[4]) if p.split("/")[4].isdigit() else 0)
    if candidates:
        return Path(candidates[-1]).parent
    raise PgUnavailable("PostgreSQL server binaries (initdb, pg_ctl) not found on PATH or under "
                        "/usr/lib/postgresql/*/bin: apt-get install postgresql")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LocalPostgres:
    """initdb into a temp folder, pg_ctl start on a free port; `url(db)`, `create_database`,
    `restart`, `stop`."""

    def __init__(self, base: str | None = None, *, options: str = SERVER_OPTIONS):
        self.bin = find_bin_dir()
        self.user = None
        if os.geteuid() == 0:
            try:
                pwd.getpwnam("postgres")
            except KeyError as exc:
                raise PgUnavailable("running as root and there is no `postgres` OS user to run "
                                    "initdb as (apt-get install postgresql creates it)") from exc
            self.user = "postgres"
        self.dir = Path(tempfile.mkdtemp(prefix="roadmap-pg-", dir=base))
        self.data, self.log = self.dir / "data", self.dir / "server.log"
        self.port, self.options = _free_port(), options
        if self.user:
            os.chmod(self.dir, 0o755)
            shutil.chown(self.dir, self.user)
        self._run("initdb", "-D", str(self.data), "-A", "trust", "-U", "postgres", "-E", "UTF8",
                  "--no-sync", timeout=120)
        self.start()

    def _run(self, tool: str, *args: str, timeout: float = 60) -> None:
        argv = [str(self.bin / tool), *args]
        if self.user:
            argv = ["runuser", "-u", self.user, "--", *argv]
        res = subprocess.run(argv, capture_output=True, text=True, timeout=timeout,
                             stdin=subprocess.DEVNULL, cwd=self.dir)
        if res.returncode != 0:
            raise PgUnavailable(f"{tool} failed ({res.returncode}): {res.stderr[-2000:]}"
                                f"{self._log_tail()}")

    def _log_tail(self) -> str:
        try:
            return "\nserver log:\n" + self.log.read_text()[-2000:]
        except OSError:
            return ""

    def start(self) -> None:
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.log), "-w", "-t", "60", "-o",
                  f"-p {self.port} -k {self.dir} {self.options}", "start", timeout=90)

    def stop(self, mode: str = "fast") -> None:
        self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "stop", timeout=90)

    def restart(self, down_s: float = 0.0) -> None:
        """Stop (fast: open connections are cut), stay down down_s, start again."""
        self.stop()
        time.sleep(down_s)
        self.start()

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://postgres@/{database}?host={self.dir}&port={self.port}"

    def create_database(self, name: str) -> str:
        import psycopg

        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}"')
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def close(self) -> None:
        try:
            self.stop("immediate")
        except (PgUnavailable, subprocess.TimeoutExpired):
            pass
        shutil.rmtree(self.dir, ignore_errors=True)


def main() -> int:
    """`python -m services.merger.pglocal [--db NAME]`: a private server until Ctrl-C (or
    SIGTERM); prints the database's postgresql:// URL on stdout, for `roadmap demo --store`."""
    import argparse
    import signal
    import sys

    parser = argparse.ArgumentParser(prog="python -m services.merger.pglocal")
    parser.add_argument("--db", default="roadmap", help="database to create (default roadmap)")
    args = parser.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    server = LocalPostgres()
    try:
        sys.stdout.write(server.create_database(args.db) + "\n")
        sys.stdout.flush()
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        return 0
    finally:
        server.close()


if __name__ == "__main__":
    raise SystemExit(main())
