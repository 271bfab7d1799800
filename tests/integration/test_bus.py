"""The bus helpers over a real local router process: query/reply and liveliness."""

import time

import pytest

from common.bus import open_session
from common.config import BusConfig

pytestmark = pytest.mark.integration


def test_query_reply_through_router(router):
    bus = BusConfig(connect=[router])
    with open_session(bus) as server, open_session(bus) as client:
        def on_query(query):
            with query:
                query.reply(query.key_expr, b"ack:" + query.payload.to_bytes())

        q = server.declare_queryable("roadmap/test/echo", on_query, complete=True)
        token = server.liveliness().declare_token("roadmap/alive/test/0")
        time.sleep(0.3)
        replies = list(client.get("roadmap/test/echo", payload=b"hi", timeout=3.0))
        tokens = client.liveliness().get("roadmap/alive/test/*", timeout=2.0)
        alive = [str(r.ok.key_expr) for r in tokens]
        token.undeclare()
        q.undeclare()
    assert [r.ok.payload.to_bytes() for r in replies if r.ok] == [b"ack:hi"]
    assert alive == ["roadmap/alive/test/0"]
