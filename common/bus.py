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

from common import security
from common.config import BusConfig
from common.errors import ConfigError, TransportError

logger = logging.getLogger(__name__)


def make_zenoh_config(bus: BusConfig, role: str | None = None) -> zenoh.Config:
    """The zenoh.Config of a process; with bus.tls_dir, mutual TLS with `role`'s certificate
    (a router also enforces the role ACL: common/security.py)."""
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
    if bus.max_message_bytes > 0:
        conf.insert_json5("transport/link/rx/max_message_size", str(int(bus.max_message_bytes)))
    if bus.tls_dir:
        _secure(conf, bus, role)
    return conf


def _secure(conf: zenoh.Config, bus: BusConfig, role: str | None) -> None:
    if role is None:
        raise ConfigError("bus.tls_dir is set: this process needs a role for its certificate")
    router = bus.mode == "router"
    check_secure_endpoints(bus.listen or bus.connect[:1] if router else bus.connect + bus.listen)
    for key, value in security.tls_settings(bus.tls_dir, role, listen=router or bool(bus.listen)
                                            ).items():
        conf.insert_json5(key, json.dumps(value))
    if router:
        conf.insert_json5("access_control", json.dumps(security.acl_config()))


def check_secure_endpoints(endpoints) -> None:
    """On a secure bus every endpoint is tls/: a tcp/ one would bypass mutual TLS and the ACL."""
    if any(not e.startswith("tls/") for e in endpoints):
        raise ConfigError(f"bus.tls_dir is set: endpoints must be tls/HOST:PORT, got "
                          f"{list(endpoints)}")


@contextlib.contextmanager
def open_session(bus: BusConfig, role: str | None = None,
                 connect_timeout_s: float | None = None):
    """`with open_session(cfg.bus, "merger") as session:` -- always closed, even on exceptions.
    `role` picks the certificate on a secure bus (bus.tls_dir; common.security.ROLES).

    Nodes wait for their router however long it takes; a one-shot tool (status, export) gives
    connect_timeout_s and gets a TransportError when no router answers within it."""
    conf = make_zenoh_config(bus, role)
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


def run_router(listen: list[str], stop: threading.Event, peers: list[str] | None = None,
               tls_dir: str = "") -> None:
    """A Zenoh router inside this Python process (no zenohd on PyPI; ZENOH.md 0); with
    tls_dir, over mutual TLS and enforcing the role ACL."""
    bus = BusConfig(mode="router", listen=listen, connect=[], tls_dir=tls_dir)
    conf = make_zenoh_config(bus, "router")
    if peers:
        if tls_dir:
            check_secure_endpoints(peers)
        conf.insert_json5("connect/endpoints", json.dumps(peers))
    session = zenoh.open(conf)
    try:
        logger.info("router listening on %s%s", listen,
                    " (mutual TLS, role ACL)" if tls_dir else "")
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
