"""The only module that imports zenoh: session configuration, the local router, stop signals.

Pitfalls handled here (ZENOH.md): multicast scouting is always off; clients wait for the router
(connect timeout -1) so start order never matters; shared memory is off by default (zenoh#2628);
sessions are closed in `finally` (a callback entity hangs the interpreter otherwise)."""

import contextlib
import json
import logging
import signal
import socket
import threading

import zenoh

from common.config import BusConfig
from common.errors import TransportError

logger = logging.getLogger(__name__)


def make_zenoh_config(bus: BusConfig) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(bus.mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if bus.mode == "router":
        conf.insert_json5("listen/endpoints", json.dumps(bus.listen or bus.connect[:1]))
        conf.insert_json5("connect/endpoints", json.dumps([]))
    else:
        conf.insert_json5("connect/endpoints", json.dumps(bus.connect))
        if bus.listen:
            conf.insert_json5("listen/endpoints", json.dumps(bus.listen))
        conf.insert_json5("connect/timeout_ms", "-1")
        conf.insert_json5("connect/exit_on_failure", "false")
    conf.insert_json5("transport/link/tx/lease", str(int(bus.lease_ms)))
    conf.insert_json5("transport/shared_memory/enabled", json.dumps(bool(bus.shared_memory)))
    return conf


@contextlib.contextmanager
def open_session(bus: BusConfig, connect_timeout_s: float | None = None):
    """`with open_session(cfg.bus) as session:` -- always closed, even on exceptions.

    Nodes wait for their router however long it takes; a one-shot tool (status, export) gives
    connect_timeout_s and gets a TransportError when no router answers within it."""
    conf = make_zenoh_config(bus)
    if connect_timeout_s is not None and bus.mode == "client":
        conf.insert_json5("connect/timeout_ms", str(int(connect_timeout_s * 1000)))
        conf.insert_json5("connect/exit_on_failure", "true")
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        raise TransportError(f"no Zenoh router answers at {', '.join(bus.connect)} "
                             f"({exc})") from exc
    try:
        yield session
    finally:
        session.close()


def stop_event() -> threading.Event:
    """An Event set by SIGTERM or SIGINT, so nodes leave their loop and close their session."""
    event = threading.Event()

    def _handler(signum, _frame):
        logger.info("signal %s: stopping", signum)
        event.set()

    signal.signal(signal.SIGTERM, _handler)
    signal.signal(signal.SIGINT, _handler)
    return event


def run_router(listen: list[str], stop: threading.Event, peers: list[str] | None = None) -> None:
    """A Zenoh router inside this Python process (no zenohd on PyPI; ZENOH.md 0)."""
    bus = BusConfig(mode="router", listen=listen, connect=[])
    conf = make_zenoh_config(bus)
    if peers:
        conf.insert_json5("connect/endpoints", json.dumps(peers))
    session = zenoh.open(conf)
    try:
        logger.info("router listening on %s", listen)
        stop.wait()
    finally:
        session.close()


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_tcp(host: str, port: int, timeout_s: float = 10.0) -> bool:
    import time

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError), socket.create_connection((host, port), timeout=0.2):
            return True
        time.sleep(0.05)
    return False


# Re-exported so nodes need no zenoh import of their own.
ZError = zenoh.ZError
FifoChannel = zenoh.handlers.FifoChannel
RingChannel = zenoh.handlers.RingChannel
SampleKind = zenoh.SampleKind
QueryTarget = zenoh.QueryTarget
ConsolidationMode = zenoh.ConsolidationMode
# Callback(fn, indirect=False): runs on the RX thread, no extra thread
Callback = zenoh.handlers.Callback
