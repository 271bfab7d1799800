"""A small process supervisor for the local fleet: router, merger shards, vehicles, localizer.

Every role runs as its own OS process (`python -m services.cli ...`, so no console script is
needed on PATH), logging into OUT/logs/<name>.log. The supervisor can SIGKILL and restart a
process, and always stops everything on exit (SIGTERM, wait, then SIGKILL), also on Ctrl-C and
on errors. It never opens a Zenoh session itself: children are started with fork+exec
(subprocess), never a bare fork (ZENOH.md P2)."""

import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from common.bus import free_tcp_port, wait_for_tcp
from common.errors import RoadmapError, TransportError
from services.demo.secure import fleet_scheme

logger = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[2]
TERM_GRACE_S = 8.0


class ProcessError(RoadmapError):
    """A supervised process failed (exit code, timeout) or could not start."""


@dataclass
class Proc:
    name: str
    argv: list[str]
    log_path: Path
    popen: subprocess.Popen | None = None
    starts: int = 0
    started_at: float = 0.0
    history: list[dict] = field(default_factory=list)

    @property
    def pid(self) -> int | None:
        return self.popen.pid if self.popen else None

    def poll(self) -> int | None:
        return None if self.popen is None else self.popen.poll()

    def running(self) -> bool:
        return self.popen is not None and self.popen.poll() is None

    def log_tail(self, n_chars: int = 2000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-n_chars:]
        except OSError:
            return ""


def cli_argv(*args: str) -> list[str]:
    """argv running `roadmap <args>` with this interpreter."""
    return [sys.executable, "-m", "services.cli", *args]


class Supervisor:
    """Starts named processes, kills/restarts them, and stops them all in `close()`.

    Use as a context manager: `with Supervisor(out / "logs") as sup: ...`."""

    def __init__(self, log_dir: Path, env: dict[str, str] | None = None,
                 config: Path | None = None):
        self.log_dir = Path(log_dir)
        self.config = config  # passed to every client as --config (one effective config)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.procs: dict[str, Proc] = {}
        self.env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
        self.router_endpoint: str | None = None
        self._t0 = time.monotonic()

    # -- lifecycle ---------------------------------------------------------------------------

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def start(self, name: str, argv: list[str]) -> Proc:
        """Start (or restart) the process `name`; its output appends to logs/<name>.log."""
        proc = self.procs.get(name) or Proc(name, list(argv), self.log_dir / f"{name}.log")
        if proc.running():
            raise ProcessError(f"{name} is already running (pid {proc.pid})")
        proc.argv = list(argv)
        with open(proc.log_path, "ab") as log:
            log.write(f"\n=== start #{proc.starts + 1}: {' '.join(argv)}\n".encode())
            log.flush()
            proc.popen = subprocess.Popen(
                argv, cwd=REPO, env=self.env, stdin=subprocess.DEVNULL, stdout=log,
                stderr=subprocess.STDOUT, start_new_session=True,
            )
        proc.starts += 1
        proc.started_at = time.monotonic()
        proc.history.append({"event": "start", "t_s": self.elapsed(), "pid": proc.pid})
        self.procs[name] = proc
        logger.debug("started %s (pid %s)", name, proc.pid)
        return proc

    def kill(self, name: str) -> None:
        """SIGKILL, no grace: the crash the delivery contract must survive."""
        proc = self.procs[name]
        if proc.running():
            os.killpg(proc.popen.pid, signal.SIGKILL)
            proc.popen.wait()
        proc.history.append({"event": "SIGKILL", "t_s": self.elapsed()})
        logger.info("killed %s (SIGKILL)", name)

    def restart(self, name: str) -> Proc:
        return self.start(name, self.procs[name].argv)

    def stop(self, name: str, grace_s: float = TERM_GRACE_S) -> int | None:
        """SIGTERM, wait up to grace_s, then SIGKILL; returns the exit code."""
        proc = self.procs.get(name)
        if proc is None or proc.popen is None:
            return None
        if proc.running():
            self._signal(proc, signal.SIGTERM)
            try:
                proc.popen.wait(grace_s)
            except subprocess.TimeoutExpired:
                logger.warning("%s ignored SIGTERM for %.0f s: SIGKILL", name, grace_s)
                self._signal(proc, signal.SIGKILL)
                proc.popen.wait()
        return proc.popen.returncode

    def close(self) -> None:
        """Stop every process: clients first, the router last (so clients close cleanly)."""
        names = [n for n in self.procs if n != "router"]
        names += ["router"] if "router" in self.procs else []
        running = [n for n in names if self.procs[n].running()]
        for n in running:
            if n != "router":
                self._signal(self.procs[n], signal.SIGTERM)
        deadline = time.monotonic() + TERM_GRACE_S
        for n in running:
            if n == "router":
                continue
            self._wait_or_kill(self.procs[n], deadline)
        if "router" in running:
            self.stop("router")

    def _wait_or_kill(self, proc: Proc, deadline: float) -> None:
        try:
            proc.popen.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            logger.warning("%s ignored SIGTERM: SIGKILL", proc.name)
            self._signal(proc, signal.SIGKILL)
            proc.popen.wait()

    @staticmethod
    def _signal(proc: Proc, sig: int) -> None:
        try:
            os.killpg(proc.popen.pid, sig)
        except ProcessLookupError:
            pass

    def elapsed(self) -> float:
        return round(time.monotonic() - self._t0, 3)

    # -- waiting -----------------------------------------------------------------------------

    def wait(self, name: str, timeout_s: float) -> int:
        """Wait for a process to exit; raise ProcessError on timeout or a non-zero exit."""
        proc = self.procs[name]
        try:
            rc = proc.popen.wait(timeout_s)
        except subprocess.TimeoutExpired as exc:
            raise ProcessError(f"{name} did not finish within {timeout_s:.0f} s; "
                               f"log {proc.log_path}:\n{proc.log_tail()}") from exc
        if rc != 0:
            raise ProcessError(f"{name} exited with {rc}; log {proc.log_path}:\n{proc.log_tail()}")
        return rc

    def check_alive(self, names: list[str]) -> None:
        """Raise if one of the long-running processes died unexpectedly."""
        for n in names:
            proc = self.procs[n]
            if not proc.running():
                raise ProcessError(f"{n} died with exit code {proc.poll()}; log {proc.log_path}:\n"
                                   f"{proc.log_tail()}")

    # -- roles -------------------------------------------------------------------------------

    def start_router(self, endpoint: str | None = None, timeout_s: float = 20.0) -> str:
        """A local Zenoh router on `endpoint` (default: a free loopback port, tls/ for a secure
        fleet); returns it."""
        if endpoint is None:
            endpoint = f"{fleet_scheme(self.env)}/127.0.0.1:{free_tcp_port()}"
        host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
        self.start("router", cli_argv("router", "--listen", endpoint))
        if not wait_for_tcp(host.strip("[]") if host not in ("[::]", "0.0.0.0") else "127.0.0.1",
                            int(port), timeout_s):
            raise TransportError(f"router did not listen on {endpoint} within {timeout_s:.0f} s:\n"
                                 f"{self.procs['router'].log_tail()}")
        self.router_endpoint = endpoint
        return endpoint

    def _client_args(self) -> list[str]:
        if self.router_endpoint is None:
            raise ProcessError("start the router first")
        config = ["--config", str(self.config)] if self.config else []
        return [*config, "--connect", self.router_endpoint]

    def start_merger(self, shard: int, shards: int, store: Path, extra: list[str] = ()) -> Proc:
        return self.start(f"merger-s{shard}", cli_argv(
            "merger", "--shard", str(shard), "--shards", str(shards), "--store", str(store),
            *self._client_args(), *extra))

    def start_vehicle(self, name: str, log: Path, vehicle_id: str, state: Path,
                      extra: list[str] = ()) -> Proc:
        return self.start(name, cli_argv(
            "vehicle", "--log", str(log), "--id", vehicle_id, "--state", str(state),
            *self._client_args(), *extra))

    def start_localizer(self, name: str, log: Path, out: Path, extra: list[str] = ()) -> Proc:
        return self.start(name, cli_argv(
            "localize", "--log", str(log), "--out", str(out), *self._client_args(), *extra))

    def start_viewer(self, port: int, extra: list[str] = ()) -> Proc:
        """`roadmap viewer` on 127.0.0.1:port, a client of the fleet's router."""
        return self.start("viewer", cli_argv("viewer", "--port", str(port),
                                             *self._client_args(), *extra))

    def history(self) -> dict[str, list[dict]]:
        return {n: p.history for n, p in self.procs.items()}
