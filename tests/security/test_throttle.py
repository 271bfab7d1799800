"""The merger's ingest admission (services/merger/throttle.py), pure: size limit before decode,
a token bucket per client that stops a flooding vehicle without starving the others."""

import pytest

from common.config import MergerConfig
from common.errors import ConfigError
from common.messages import THROTTLED
from services.merger.throttle import (
    ClientThrottle,
    IngestGuard,
    NoThrottle,
    TokenBucket,
    get_ingest_guard,
)


def test_bucket_allows_its_burst_then_its_rate():
    b = TokenBucket(rate_per_s=10.0, burst=5.0, now_s=0.0)
    assert [b.take(1, 0.0) for _ in range(6)] == [True] * 5 + [False]
    assert b.take(1, 0.1) and not b.take(1, 0.1)  # 0.1 s at 10/s: one more
    assert b.take(5, 10.0) and not b.take(1, 10.0)  # refills up to the burst only


def test_bucket_ignores_a_clock_that_steps_back():
    b = TokenBucket(rate_per_s=1.0, burst=1.0, now_s=100.0)
    assert b.take(1, 100.0)
    assert not b.take(1, 50.0) and not b.take(1, 100.5)
    assert b.take(1, 101.0)


def test_a_flooding_client_does_not_starve_the_others():
    t = ClientThrottle(rate_per_s=10.0, burst=20.0)
    flood = [t.allow("flooder", now_s=i * 0.001) for i in range(1000)]  # 1000 in one second
    assert sum(flood) <= 20 + 10  # its burst, plus what one second refills
    normal = [t.allow(f"veh-{k}", now_s=0.5 + i * 0.2) for i in range(5) for k in range(3)]
    assert all(normal)  # three vehicles at 5/s each: never refused


def test_forgotten_clients_are_bounded():
    t = ClientThrottle(rate_per_s=1.0, burst=1.0, max_clients=3)
    for k in range(10):
        t.allow(f"veh-{k}", now_s=0.0)
    assert list(t.buckets) == ["veh-7", "veh-8", "veh-9"]


def test_guard_refuses_oversize_before_rate_and_costs_by_size():
    g = IngestGuard(max_bytes=1000, throttle=ClientThrottle(rate_per_s=1.0, burst=4.0),
                    token_bytes=100)
    assert "max_ingest_bytes" in g.refusal("v", size=1001, now_s=0.0)
    assert g.refusal("v", size=250, now_s=0.0) is None  # 3 tokens of 4
    assert g.refusal("v", size=100, now_s=0.0) is None  # the 4th
    assert g.refusal("v", size=1, now_s=0.0).startswith(THROTTLED)
    assert g.counters == {"refused_oversize": 1, "throttled": 1}


def test_a_request_larger_than_the_burst_can_still_pass():
    g = IngestGuard(max_bytes=10**6, throttle=ClientThrottle(rate_per_s=1.0, burst=2.0),
                    token_bytes=100)
    assert g.refusal("v", size=10_000, now_s=0.0) is None  # 100 tokens, capped at the burst


def test_factory_picks_no_throttle_when_rate_is_off():
    assert isinstance(get_ingest_guard(MergerConfig(ingest_rate_per_s=0)).throttle, NoThrottle)
    guard = get_ingest_guard(MergerConfig())
    assert isinstance(guard.throttle, ClientThrottle)
    assert guard.max_bytes == MergerConfig().max_ingest_bytes


def test_throttle_rejects_nonsense_settings():
    with pytest.raises(ConfigError):
        ClientThrottle(rate_per_s=0.0, burst=1.0)
