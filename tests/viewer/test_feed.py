"""The viewer's live feed over a real local router: liveliness as processes come and go."""

import time

import pytest

from common import keys
from common.bus import open_session
from common.config import BusConfig
from services.viewer import feed as feed_module
from services.viewer.feed import LiveFeed
from services.viewer.state import ViewerState

pytestmark = pytest.mark.integration


def _until(condition, timeout_s: float = 5.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.05)
    return False


def test_a_process_gone_while_the_liveliness_snapshot_is_taken_shows_gone(router, monkeypatch):
    """The refresher's snapshot lists a vehicle's token; the vehicle drops it before the
    snapshot is applied. The drop, seen by the subscriber meanwhile, wins over the stale
    snapshot (it showed the vehicle alive until the next refresh)."""
    bus = BusConfig(connect=[router])
    with open_session(bus) as viewer, open_session(bus) as vehicle:
        state = ViewerState(source="test")
        feed = LiveFeed(viewer, state, ident="t", stats_every_s=60.0, timeout_s=0.5)
        token = vehicle.liveliness().declare_token(keys.alive("vehicle", "v9"))
        assert _until(lambda: "v9" in state.snapshot()["alive"].get("vehicle", []))
        real_alive = feed_module.fleet.alive

        def snapshot_then_drop(session, timeout_s):
            listed = real_alive(session, timeout_s)
            token.undeclare()  # the vehicle goes while the snapshot is on its way
            assert _until(lambda: not state.snapshot()["alive"].get("vehicle"))
            return listed

        monkeypatch.setattr(feed_module.fleet, "alive", snapshot_then_drop)
        try:
            feed.refresh()
        finally:
            feed.close()
        assert "v9" not in state.snapshot()["alive"].get("vehicle", [])
