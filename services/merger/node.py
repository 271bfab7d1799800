"""`roadmap merger --shard I --shards N [--store PATH]`: one tile merger shard on Zenoh.

Ingest (`roadmap/ingest/s<I>`, complete): admitted on the RX thread before anything is
decoded (services/merger/throttle.py: an oversized payload is answered with an error ack at
once; a client over its rate gets its `throttled` ack merger.throttle_delay_s later, so a sender
that ignores the backoff still waits), then a bounded queue (merger.ingest_queue; full, it holds
the RX thread back: backpressure) drained by the main loop, which wakes as a query arrives and
takes the queries waiting together (up to merger.ingest_group), stores their new patches in one
transaction (group commit: one fsync), applies them and then replies each its IngestAck; a
flush thread recomputes and recompresses changed tiles meanwhile. Tiles
(`roadmap/tile/<tx>/<ty>`, one complete queryable per held tile) and stats
(`roadmap/stats/merger/s<I>`) are enqueued by cheap RX-thread callbacks and answered by a serve
thread from the cached compressed tiles. Changed tiles are recompressed once ingest has been
quiet for `merger.debounce_s` (at the latest `merger.debounce_max_s` after a change, while
batches keep coming) and published on `roadmap/tile-update/<tx>/<ty>`. Liveliness token
`roadmap/alive/merger/s<I>` once recovery is done. Runs until SIGTERM/SIGINT."""

import collections
import logging
import queue
import threading
import time

import cv2

from common import codec, keys
from common.bus import Callback, ZError, open_session, stop_event
from common.config import MergerConfig, RoadmapConfig
from common.contours import CODEC
from common.errors import CodecError, ConfigError
from common.grid import owner_of_tile
from common.messages import ACCEPTED, THROTTLED, IngestAck, Stats, Tile
from services.merger.durable import DurableShard
from services.merger.shard import MergerShard, TileCodecCache
from services.merger.store import ShardStore
from services.merger.throttle import IngestGuard, NoThrottle, get_ingest_guard

logger = logging.getLogger(__name__)

IDLE_WAIT_S = 0.1  # the main loop's longest wait for an ingest query (then it checks stop)
GROUP_BYTES = 32 << 20  # payload bytes of the ingest queries taken into one group commit


def get_durable_shard(shard: int, shards: int, store_path: str, cfg: RoadmapConfig) -> DurableShard:
    """Build the shard core + store for shard `shard` of `shards` and replay the store."""
    if not 0 <= shard < shards:
        raise ConfigError(f"--shard must be in [0, {shards}), got {shard}")
    shard_map = cfg.grid.shard_map if cfg.grid.shards == shards else {}

    def owns(tile) -> bool:
        return owner_of_tile(tile, shards, shard_map) == shard

    store = ShardStore(store_path, synchronous=cfg.merger.sqlite_synchronous)
    stored = store.check_meta("shard", f"{shard}/{shards}")
    if stored != f"{shard}/{shards}":
        store.close()
        raise ConfigError(f"store {store_path} belongs to shard {stored}, not {shard}/{shards}")
    durable = DurableShard(MergerShard.from_config(cfg.merger, owns), store, ident=f"s{shard}",
                           cache=TileCodecCache())
    n = durable.recover()
    logger.info("shard %d/%d: recovered %d patches, %d tiles from %s",
                shard, shards, n, len(durable.tiles()), store_path)
    return durable


class MergerNode:
    def __init__(self, session, durable: DurableShard, *, shard: int,
                 debounce_s: float = MergerConfig.debounce_s,
                 debounce_max_s: float = MergerConfig.debounce_max_s,
                 ingest_queue: int = MergerConfig.ingest_queue,
                 ingest_group: int = MergerConfig.ingest_group,
                 guard: IngestGuard | None = None,
                 throttle_delay_s: float = MergerConfig.throttle_delay_s):
        self.session = session
        self.guard = guard or IngestGuard(max_bytes=codec.MAX_MESSAGE_BYTES, throttle=NoThrottle())
        self._guard_lock = threading.Lock()
        self.throttle_delay_s = throttle_delay_s
        self.held_max = max(1, int(ingest_queue))  # throttled queries held back, at most
        self._held: collections.deque = collections.deque()  # (release time, query, reply)
        self.durable = durable
        self.shard = shard
        self.debounce_s = debounce_s
        self.ingest_group = max(1, int(ingest_group))
        self.debounce_max_s = max(debounce_s, debounce_max_s)
        self._last_ingest = 0.0  # monotonic time of the last ingest group
        self._changed_since: float | None = None  # first ingest not yet flushed
        self._publish_lock = threading.Lock()
        self.serve_queue: queue.Queue = queue.Queue()
        self.ingest_queue: queue.Queue = queue.Queue(maxsize=max(1, int(ingest_queue)))
        self.tile_queryables = {}
        self.ingest = session.declare_queryable(
            keys.ingest(shard), Callback(self._admit, indirect=False), complete=True)
        self.stats_q = session.declare_queryable(keys.stats("merger", f"s{shard}"),
                                                 self._enqueue_callback(stats=True), complete=True)
        for tile in durable.tiles():
            self._declare_tile(tile)
        self.token = session.liveliness().declare_token(keys.alive("merger", f"s{shard}"))
        self.serving = threading.Thread(target=self._serve_loop, name="merger-serve", daemon=True)
        self.flushing = threading.Thread(target=self._flush_loop, name="merger-flush", daemon=True)
        self._stop = threading.Event()

    def _enqueue_callback(self, stats: bool = False):
        """Queries go to the serve thread tagged with the queryable that took them: a wildcard
        (`roadmap/stats/**`) names no shard, so its key cannot tell."""
        return Callback(lambda query: self.serve_queue.put((stats, query)), indirect=False)

    def _declare_tile(self, tile) -> None:
        if tile not in self.tile_queryables:
            self.tile_queryables[tile] = self.session.declare_queryable(
                keys.tile(*tile), self._enqueue_callback(), complete=True)

    def _admit(self, query) -> None:
        """RX thread: answer an oversized query at once and hold a throttled one's answer for
        throttle_delay_s (neither is decoded nor queued); queue the others for the main loop."""
        size = sum(len(z) for z in (query.payload, query.attachment) if z is not None)
        client = _client_id(query) if size <= self.guard.max_bytes else ""
        with self._guard_lock:
            refusal = self.guard.refusal(client, size, time.monotonic())
        if refusal is None:
            self.ingest_queue.put(query)
            return
        reply = codec.encode(IngestAck(error=refusal))
        if (refusal.startswith(THROTTLED) and self.throttle_delay_s > 0
                and len(self._held) < self.held_max):
            self._held.append((time.monotonic() + self.throttle_delay_s, query, reply))
            return
        with query:
            query.reply(query.key_expr, reply)

    def _release_held(self, now_s: float) -> None:
        """Answer the held throttled queries that are due (all of them at `now_s` = inf)."""
        while self._held and self._held[0][0] <= now_s:
            _, query, reply = self._held.popleft()
            with query:
                query.reply(query.key_expr, reply)

    # -- main loop: ingest + debounced flush ---------------------------------------------------

    def run(self, stop: threading.Event) -> None:
        """Ingest on this thread; serve and flush on their own threads until `stop`."""
        self.serving.start()
        self.flushing.start()
        try:
            while not stop.is_set():
                group = self._waiting_ingest(IDLE_WAIT_S)
                if group:
                    self._handle_ingest(group)
                self._release_held(time.monotonic())
        finally:
            self._release_held(float("inf"))
            self._stop.set()
            self.flushing.join(timeout=30.0)
            self.serving.join(timeout=2.0)
            self._flush_and_publish()
            self._undeclare()

    def _flush_loop(self) -> None:
        """Debounced recompression: once ingest has been quiet for debounce_s, or, while batches
        keep coming, once the oldest unpublished change is debounce_max_s old (a burst is
        merged and compressed once, not every debounce_s); never busier than half the time
        (waits at least as long as the last flush took), so ingest keeps flowing."""
        pause = self.debounce_s
        while not self._stop.wait(pause):
            now = time.monotonic()
            since = self._changed_since
            if since is None:
                continue
            quiet = now - self._last_ingest >= self.debounce_s
            if not quiet and now - since < self.debounce_max_s:
                pause = min(self.debounce_s, since + self.debounce_max_s - now)
                continue
            self._changed_since = None  # changes from here on wait for the next flush
            try:
                self._flush_and_publish()
            except Exception:  # keep flushing later; the data is safe in the store
                logger.exception("flush failed")
                self._changed_since = since
            pause = max(self.debounce_s, time.monotonic() - now)

    def _waiting_ingest(self, timeout_s: float) -> list:
        """The next ingest query (waiting up to timeout_s for one: woken as it arrives, not by
        polling, since a shard with few requests in flight would otherwise idle between them)
        and those waiting behind it (at most ingest_group in all, ~GROUP_BYTES)."""
        group, size = [], 0
        while len(group) < self.ingest_group and size < GROUP_BYTES:
            try:
                query = (self.ingest_queue.get_nowait() if group
                         else self.ingest_queue.get(timeout=timeout_s))
            except queue.Empty:
                break
            group.append(query)
            size += len(query.payload) if query.payload is not None else 0
        return group

    def _handle_ingest(self, group: list) -> None:
        """One group commit for the waiting batches, then each its ack (DESIGN: an ack means
        stored)."""
        payloads = [q.payload.to_bytes() if q.payload is not None else b"" for q in group]
        try:
            acks = self.durable.ingest_many(payloads)
        except Exception as exc:  # e.g. the store failed: no ack, the vehicles retry
            logger.exception("ingest failed")
            acks = [IngestAck(error=f"shard failed to store the batch: {exc}")] * len(group)
        self._last_ingest = time.monotonic()
        accepted = any(ACCEPTED in ack.results.values() for ack in acks)
        if accepted and self._changed_since is None:
            self._changed_since = self._last_ingest
        for query, ack in zip(group, acks, strict=True):
            with query:
                query.reply(query.key_expr, codec.encode(ack))

    def _flush_and_publish(self) -> None:
        self.durable.flush()
        self._publish_changed()

    def _publish_changed(self) -> None:
        """Declare the queryables of new tiles and publish the changed ones (any thread)."""
        with self._publish_lock:
            for tile in self.durable.take_changed():
                self._declare_tile(tile.tile)
                self.session.put(keys.tile_update(*tile.tile), codec.encode(tile))

    def _undeclare(self) -> None:
        for entity in [self.token, self.ingest, self.stats_q, *self.tile_queryables.values()]:
            try:
                entity.undeclare()
            except ZError as exc:  # the session may already be closing
                logger.debug("undeclare: %s", exc)

    # -- serve thread: tiles and stats ---------------------------------------------------------

    def _serve_loop(self) -> None:
        while not self._stop.is_set():
            try:
                stats, query = self.serve_queue.get(timeout=0.1)
            except queue.Empty:
                continue
            with query:
                try:
                    self._serve(query, stats)
                except Exception as exc:  # a bad query must never end the serve thread
                    logger.warning("query %s failed: %s", query.selector, exc)
                    query.reply_err(str(exc).encode())

    def _serve(self, query, stats: bool = False) -> None:
        key = str(query.key_expr)
        if stats:  # its own key, also to roadmap/stats/** or roadmap/stats/merger/*
            own = keys.stats("merger", f"s{self.shard}")
            query.reply(own, codec.encode(self._stats()))  # stats flush first
            self._publish_changed()  # so every tile the stats list answers its queries now
            return
        tile = keys.parse_tile(key)
        since, want = _tile_selector(query.parameters)
        msg: Tile | None = (self.durable.raw_tile(tile) if want == "raw"
                            else self.durable.tile(tile))
        if msg is None:
            query.reply_del(key)
        elif since is None or msg.version > since:
            query.reply(key, codec.encode(msg))

    def _stats(self) -> Stats:
        stats = self.durable.stats()
        with self._guard_lock:
            counters = {**stats.counters, **self.guard.counters}
        return Stats(role=stats.role, ident=stats.ident, counters=counters)


def _client_id(query) -> str:
    """The sender's vehicle id (the query's attachment, as the vehicle's uploader sets it), ""
    when there is none. Self-declared: deploy/README.md says what that does and does not stop."""
    attachment = query.attachment
    if attachment is None:
        return ""
    return attachment.to_bytes()[:codec.MAX_ID_CHARS].decode("utf-8", "replace")


def _tile_selector(parameters) -> tuple[int | None, str]:
    """`?since=<v>` and `?codec=raw|contour` -> (since, codec); CodecError on anything else."""
    since_text = parameters.get("since")
    want = parameters.get("codec") or "contour"
    try:
        since = int(since_text) if since_text not in (None, "") else None
    except ValueError as exc:
        raise CodecError(f"since must be an integer version, got {since_text!r}") from exc
    if want not in ("raw", "contour", CODEC):
        raise CodecError(f"codec must be raw or contour, got {want!r}")
    return since, "raw" if want == "raw" else "contour"


def main(args, cfg: RoadmapConfig) -> int:
    if cfg.merger.opencv_threads > 0:
        cv2.setNumThreads(cfg.merger.opencv_threads)
    stop = stop_event()
    store_path = args.store or f"merger-s{args.shard}.sqlite"
    durable = get_durable_shard(args.shard, args.shards, store_path, cfg)
    try:
        with open_session(cfg.bus, "merger") as session:
            node = MergerNode(session, durable, shard=args.shard,
                              debounce_s=cfg.merger.debounce_s,
                              debounce_max_s=cfg.merger.debounce_max_s,
                              ingest_queue=cfg.merger.ingest_queue,
                              ingest_group=cfg.merger.ingest_group,
                              guard=get_ingest_guard(cfg.merger),
                              throttle_delay_s=cfg.merger.throttle_delay_s)
            logger.info("merger s%d/%d serving", args.shard, args.shards)
            node.run(stop)
    finally:
        durable.store.close()
    return 0
