"""`roadmap demo --viewer [PORT]`: the viewer as one more process of the demo's fleet, up from
the moment the shards are until the demo ends (the Supervisor stops it with the rest)."""

import logging
import time
import urllib.request

logger = logging.getLogger("roadmap.demo")

READY_TIMEOUT_S = 20.0


def start_viewer(sup, port: int | None) -> str | None:
    """Start the viewer under `sup` on 127.0.0.1:port (None: no viewer); returns its URL once
    it answers."""
    if port is None:
        return None
    sup.start_viewer(port)
    url = f"http://127.0.0.1:{port}/"
    deadline = time.monotonic() + READY_TIMEOUT_S
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(url + "api/state", timeout=1.0):
                logger.info("viewer: %s (up until the demo ends)", url)
                return url
        except OSError:
            sup.check_alive(["viewer"])
            time.sleep(0.2)
    logger.warning("viewer: no answer on %s after %.0f s; see logs/viewer.log", url,
                   READY_TIMEOUT_S)
    return url
