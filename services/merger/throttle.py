"""Admission of ingest queries before anything is decoded: a size limit and a token bucket per
client (the vehicle id the query carries as its attachment), so one vehicle that floods ingest
is answered `throttled` at once while the others' batches keep flowing.

Pure: the caller passes the time (monotonic seconds) and the payload size; no clocks, no I/O."""

from collections import OrderedDict
from dataclasses import dataclass, field

from common.errors import ConfigError
from common.messages import THROTTLED


class TokenBucket:
    """`rate_per_s` tokens a second up to `burst`; a request takes `cost` tokens or is refused."""

    def __init__(self, rate_per_s: float, burst: float, now_s: float):
        self.rate_per_s, self.burst = float(rate_per_s), float(burst)
        self.tokens, self.last_s = float(burst), float(now_s)

    def take(self, cost: float, now_s: float) -> bool:
        elapsed = max(0.0, now_s - self.last_s)  # a clock that steps back refills nothing
        self.tokens = min(self.burst, self.tokens + elapsed * self.rate_per_s)
        self.last_s = max(self.last_s, now_s)
        if self.tokens < cost:
            return False
        self.tokens -= cost
        return True


class ClientThrottle:
    """One TokenBucket per client id, at most max_clients of them (least recently seen ones
    forgotten: a forgotten client starts again with a full bucket)."""

    def __init__(self, *, rate_per_s: float, burst: float, max_clients: int = 4096):
        if rate_per_s <= 0 or burst < 1 or max_clients < 1:
            raise ConfigError("merger.ingest_rate_per_s must be > 0 (or <= 0: off), "
                              "ingest_burst >= 1, ingest_clients >= 1")
        self.rate_per_s, self.burst, self.max_clients = rate_per_s, burst, int(max_clients)
        self.buckets: OrderedDict[str, TokenBucket] = OrderedDict()

    def allow(self, client: str, now_s: float, cost: float = 1.0) -> bool:
        bucket = self.buckets.get(client)
        if bucket is None:
            bucket = self.buckets[client] = TokenBucket(self.rate_per_s, self.burst, now_s)
            if len(self.buckets) > self.max_clients:
                self.buckets.popitem(last=False)
        self.buckets.move_to_end(client)
        # a request never costs more than a full bucket: else it could never pass
        return bucket.take(min(cost, self.burst), now_s)


class NoThrottle:
    """merger.ingest_rate_per_s <= 0: every request passes."""

    def allow(self, client: str, now_s: float, cost: float = 1.0) -> bool:
        return True


@dataclass
class IngestGuard:
    """Refuses an ingest query before it is decoded: too large (max_bytes), or its client out
    of tokens (a request costs one token per started token_bytes of payload)."""

    max_bytes: int
    throttle: ClientThrottle | NoThrottle
    token_bytes: int = 256 << 10
    counters: dict = field(default_factory=lambda: {"refused_oversize": 0, "throttled": 0})

    def refusal(self, client: str, size: int, now_s: float) -> str | None:
        """None to admit the query, else the error its IngestAck carries."""
        if size > self.max_bytes:
            self.counters["refused_oversize"] += 1
            return (f"ingest payload of {size} bytes exceeds merger.max_ingest_bytes "
                    f"({self.max_bytes}): send smaller batches")
        cost = max(1, -(-size // self.token_bytes))
        if not self.throttle.allow(client, now_s, cost):
            self.counters["throttled"] += 1
            return f"{THROTTLED}: client {client!r} is over its ingest rate, retry later"
        return None


def get_ingest_guard(merger_cfg) -> IngestGuard:
    m = merger_cfg
    throttle = (ClientThrottle(rate_per_s=m.ingest_rate_per_s, burst=m.ingest_burst,
                               max_clients=m.ingest_clients)
                if m.ingest_rate_per_s > 0 else NoThrottle())
    return IngestGuard(max_bytes=m.max_ingest_bytes, throttle=throttle,
                       token_bytes=m.ingest_token_bytes)
