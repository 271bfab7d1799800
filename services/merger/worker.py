"""`roadmap worker --id W --store postgresql://...`: a tile merger worker that holds regions by
lease in PostgreSQL (services/merger/pgstore.py), so workers scale out, fail over and rebalance.

Each held region is its own DurableShard (MergerShard + RegionStore at the lease's epoch), so a
region moves between workers whole: released by one, claimed and replayed from the stored patch
log by the next. Which worker should hold a region is rendezvous hashing over the live workers
(liveliness `roadmap/alive/merger/<id>`, common.grid.owner_among), unless merger.region_owners
names a live worker for it. A control tick
(merger.lease_renew_s) renews this worker's leases in one statement, releases the regions that a
live peer should now hold (after persisting their tiles), and claims the regions it should hold
whose lease is free, expired, or held by a worker that is no longer alive. A region nobody holds
yet is claimed on its first ingest, which reaches every worker's fallback queryable
(common/keys.py).
Ingest `roadmap/region/<rx>/<ry>/ingest` (complete, per held region): group commit per region,
ack after commit; a fenced write (the lease moved on) acks nothing and drops the region. Tiles
`roadmap/tile/<tx>/<ty>` (complete, per held tile) answer from memory, or from the database for
a tile of a region this worker does not hold; stats `roadmap/stats/merger/<id>`."""

import hashlib
import json
import logging
import queue
import threading
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from common import codec, keys
from common.bus import Callback, SampleKind, ZError, open_session, stop_event
from common.config import RoadmapConfig
from common.errors import CodecError, ConfigError, RoadmapError
from common.grid import RegionId, owner_among, region_of_tile
from common.messages import ACCEPTED, IngestAck, Stats, Tile
from services.merger.durable import DurableShard
from services.merger.pgstore import (
    Fenced,
    Leases,
    PgDatabase,
    RegionStore,
    StoreUnavailable,
    read_tile,
    wait_for_database,
)
from services.merger.shard import MergerShard, TileCodecCache

logger = logging.getLogger(__name__)

IDLE_WAIT_S = 0.1
GROUP_BYTES = 32 << 20
STEAL_GRACE_S = 1.5  # after start, before a lease of a worker we do not see alive is taken
SUMMED = ("patches_applied", "duplicates", "cell_votes", "traversals_retired",
          "traversals_revived", "tiles", "traversals_held", "cells", "errors")


@dataclass
class Holder:
    """One region held at one lease epoch."""

    region: RegionId
    epoch: int
    durable: DurableShard
    previous_owner: str | None
    replayed: int
    replay_s: float
    serving_at: float  # unix time the region started serving here


@dataclass
class RegionTable:
    """The regions this worker holds: claim (lease compare-and-set, then replay), renew, release,
    drop. Transport-free: the node declares and undeclares queryables from what it returns."""

    ident: str
    write_db: PgDatabase
    control_db: PgDatabase
    lease_s: float
    merger_cfg: object
    held: dict[RegionId, Holder] = field(default_factory=dict)
    region_owners: dict[str, str] = field(default_factory=dict)  # merger.region_owners
    counters: dict[str, int] = field(default_factory=lambda: {
        "claims": 0, "released": 0, "lost": 0, "fenced": 0, "store_errors": 0})
    log: list[dict] = field(default_factory=list)

    def __post_init__(self):
        self.leases = Leases(self.control_db, self.ident, self.lease_s)
        self.lock = threading.RLock()

    def owner(self, region: RegionId, everyone: set[str]) -> str | None:
        """Who should hold a region: its merger.region_owners worker while alive, else the
        rendezvous winner among the live workers."""
        pinned = self.region_owners.get(f"{region[0]},{region[1]}")
        if pinned is not None and pinned in everyone:
            return pinned
        return owner_among(region, sorted(everyone))

    def get(self, region: RegionId) -> Holder | None:
        with self.lock:
            return self.held.get(tuple(region))

    def holders(self) -> list[Holder]:
        with self.lock:
            return [self.held[r] for r in sorted(self.held)]

    # -- the control tick ------------------------------------------------------------------------

    def tick(self, members: set[str], steal_dead: bool) -> tuple[list[Holder], list[RegionId]]:
        """Renew, release, claim; returns (regions gained, regions lost or released)."""
        everyone = set(members) | {self.ident}
        leases = self.leases.all()
        with self.lock:
            epochs = {r: h.epoch for r, h in self.held.items()}
        kept = self.leases.renew(epochs)
        gone = [r for r in epochs if r not in kept]
        for r in gone:
            self.drop(r, "lost")
        for r in sorted(kept):
            if self.owner(r, everyone) != self.ident:
                self.release(r)
                gone.append(r)
        gained = []
        for r, (owner, epoch, valid) in sorted(leases.items()):
            if self.get(r) is None and self._should_claim(r, owner, valid, everyone, steal_dead):
                holder = self.claim(r, epoch, owner)
                if holder is not None:
                    gained.append(holder)
        return gained, gone

    def _should_claim(self, region, owner, valid, everyone, steal_dead) -> bool:
        if self.owner(region, everyone) != self.ident:
            return False
        return (owner is None or not valid or owner == self.ident
                or (steal_dead and owner not in everyone))

    def claim_on_ingest(self, region: RegionId, members: set[str], steal_dead: bool
                        ) -> Holder | None:
        """A region this worker does not hold got an ingest on the fallback queryable: claim it
        if it is ours by rendezvous and free (never leased, expired, or its owner is gone)."""
        everyone = set(members) | {self.ident}
        if self.owner(region, everyone) != self.ident:
            return None
        lease = self.leases.all().get(tuple(region))
        if lease is None:
            return self.claim(region, None, None)
        owner, epoch, valid = lease
        if self._should_claim(region, owner, valid, everyone, steal_dead):
            return self.claim(region, epoch, owner)
        return None

    def claim(self, region: RegionId, seen_epoch: int | None, previous: str | None
              ) -> Holder | None:
        """Take the lease (epoch + 1) and rebuild the region from its stored patches."""
        with self.lock:
            if region in self.held:
                return self.held[region]
            epoch = self.leases.claim(region, seen_epoch)
            if epoch is None:
                return None
            t0 = time.monotonic()
            store = RegionStore(self.write_db, self.control_db, region, owner=self.ident,
                                epoch=epoch)
            shard = MergerShard.from_config(
                self.merger_cfg, lambda tile, r=tuple(region): region_of_tile(tile) == r)
            store.labels_of = shard.labels
            durable = DurableShard(shard, store, ident=f"{self.ident}/r{region[0]}_{region[1]}",
                                   cache=TileCodecCache())
            n = durable.recover()
            refresh_raw(durable, durable.tiles())
            holder = Holder(tuple(region), epoch, durable, previous, n,
                            round(time.monotonic() - t0, 3), time.time())
            self.held[tuple(region)] = holder
            self.counters["claims"] += 1
            self.log.append({"region": list(region), "epoch": epoch, "from": previous,
                             "replayed": n, "replay_s": holder.replay_s,
                             "serving_at": holder.serving_at})
        logger.info("%s: holds region %s at epoch %d (from %s, replayed %d patches in %.2f s)",
                    self.ident, region, epoch, previous, n, holder.replay_s)
        return holder

    def release(self, region: RegionId) -> None:
        """Persist the region's tiles and hand its lease back (another worker should hold it)."""
        with self.lock:
            holder = self.held.pop(tuple(region), None)
        if holder is None:
            return
        try:
            with holder.durable.lock:
                dirty = holder.durable.shard.dirty_tiles()
            holder.durable.flush()
            refresh_raw(holder.durable, dirty)
            self.leases.release(region, holder.epoch)
        except RoadmapError as exc:  # fenced or no database: the lease expires by itself
            logger.warning("%s: release of %s: %s", self.ident, region, exc)
        self.counters["released"] += 1
        logger.info("%s: released region %s (epoch %d)", self.ident, region, holder.epoch)

    def drop(self, region: RegionId, why: str) -> None:
        """Forget a region whose lease moved on (fenced / not renewed)."""
        with self.lock:
            holder = self.held.pop(tuple(region), None)
        if holder is not None:
            self.counters[why] = self.counters.get(why, 0) + 1
            logger.warning("%s: lost region %s (epoch %d): %s", self.ident, region,
                           holder.epoch, why)

    # -- reads -----------------------------------------------------------------------------------

    def stats(self) -> dict:
        """Counters summed over the held regions, the digest over all their tiles (the same as
        one MergerShard holding them all), and the lease log (takeover times)."""
        holders = self.holders()
        per = [h.durable.stats().counters for h in holders]
        out = {k: sum(int(c.get(k, 0)) for c in per) for k in SUMMED}
        out.update({k: int(v) for k, v in self.counters.items()})
        tiles = sorted(((t, h) for h in holders for t in h.durable.shard.tiles()),
                       key=lambda item: item[0])
        digest = hashlib.sha256()
        for t, h in tiles:
            digest.update(np.asarray(t, dtype="<i8").tobytes())
            with h.durable.lock:
                digest.update(h.durable.shard.labels(t).tobytes())
        out["digest"] = digest.hexdigest()
        out["tile_list"] = ";".join(f"{tx},{ty}" for (tx, ty), _ in tiles)
        out["regions"] = ";".join(f"{h.region[0]},{h.region[1]}@{h.epoch}" for h in holders)
        out["lease_log"] = json.dumps(self.log[-200:])
        return out


# -- the Zenoh node ----------------------------------------------------------------------------


class WorkerNode:
    def __init__(self, session, table: RegionTable, read_db: PgDatabase, *, ident: str,
                 renew_s: float, debounce_s: float, debounce_max_s: float, ingest_queue: int,
                 ingest_group: int):
        self.session, self.table, self.read_db, self.ident = session, table, read_db, ident
        self.renew_s, self.debounce_s = renew_s, debounce_s
        self.debounce_max_s = max(debounce_s, debounce_max_s)
        self.ingest_group = max(1, int(ingest_group))
        self.ingest_queue: queue.Queue = queue.Queue(maxsize=max(1, int(ingest_queue)))
        self.serve_queue: queue.Queue = queue.Queue()
        self.members: set[str] = set()
        self.started = time.monotonic()
        self.errors = 0
        self._decl_lock = threading.RLock()
        self._region_q: dict[RegionId, object] = {}
        self._tile_q: dict[tuple, object] = {}
        self._last_ingest, self._changed_since = 0.0, None
        self._stop = threading.Event()
        enqueue = Callback(self.ingest_queue.put, indirect=False)
        self.fallback = session.declare_queryable(keys.REGION_INGEST_ALL, enqueue, complete=False)
        self.stats_q = session.declare_queryable(keys.stats("merger", ident),
                                                 Callback(self.serve_queue.put, indirect=False),
                                                 complete=True)
        self.live = session.liveliness().declare_subscriber(keys.alive_all("merger"),
                                                            self._on_alive, history=True)
        self.token = session.liveliness().declare_token(keys.alive("merger", ident))
        self.threads = [threading.Thread(target=fn, name=f"worker-{fn.__name__}", daemon=True)
                        for fn in (self._control_loop, self._flush_loop, self._serve_loop)]

    def _on_alive(self, sample) -> None:
        _, ident = keys.parse_alive(str(sample.key_expr))
        if sample.kind == SampleKind.DELETE:
            self.members.discard(ident)
        else:
            self.members.add(ident)

    def _steal_dead(self) -> bool:
        return time.monotonic() - self.started > STEAL_GRACE_S

    # -- declarations ----------------------------------------------------------------------------

    def _gain(self, holder: Holder) -> None:
        with self._decl_lock:
            if holder.region not in self._region_q:
                self._region_q[holder.region] = self.session.declare_queryable(
                    keys.region_ingest(*holder.region),
                    Callback(self.ingest_queue.put, indirect=False), complete=True)
            for tile in holder.durable.tiles():
                self._declare_tile(tile)

    def _declare_tile(self, tile) -> None:
        with self._decl_lock:
            if tile not in self._tile_q:
                self._tile_q[tile] = self.session.declare_queryable(
                    keys.tile(*tile), Callback(self.serve_queue.put, indirect=False),
                    complete=True)

    def _lose(self, region: RegionId) -> None:
        with self._decl_lock:
            entities = [self._region_q.pop(tuple(region), None)]
            entities += [self._tile_q.pop(t) for t in list(self._tile_q)
                         if region_of_tile(t) == tuple(region)]
        _undeclare([e for e in entities if e is not None])

    # -- threads ---------------------------------------------------------------------------------

    def run(self, stop: threading.Event) -> None:
        for t in self.threads:
            t.start()
        try:
            while not stop.is_set():
                group = self._waiting_ingest(IDLE_WAIT_S)
                if group:
                    self._handle_ingest(group)
        finally:
            self._stop.set()
            for t in self.threads:
                t.join(timeout=10.0)
            self._flush_and_publish()
            for holder in self.table.holders():  # a clean stop hands the regions over now
                self.table.release(holder.region)
            _undeclare([self.token, self.live, self.fallback, self.stats_q,
                        *self._region_q.values(), *self._tile_q.values()])

    def _control_loop(self) -> None:
        while not self._stop.wait(self.renew_s):
            try:
                gained, gone = self.table.tick(self.members, self._steal_dead())
            except StoreUnavailable as exc:
                self.table.counters["store_errors"] += 1
                logger.warning("%s: lease tick: %s", self.ident, exc)
                continue
            except Exception:  # keep ticking: the leases are what keeps the regions served
                logger.exception("lease tick failed")
                continue
            for region in gone:
                self._lose(region)
            for holder in gained:
                self._gain(holder)

    def _waiting_ingest(self, timeout_s: float) -> list:
        group, size = [], 0
        while len(group) < self.ingest_group and size < GROUP_BYTES:
            try:
                q = self.ingest_queue.get_nowait() if group else self.ingest_queue.get(
                    timeout=timeout_s)
            except queue.Empty:
                break
            group.append(q)
            size += len(q.payload) if q.payload is not None else 0
        return group

    def _handle_ingest(self, group: list) -> None:
        """Per region: one group commit, then the acks; queries for a region this worker does
        not hold (and cannot claim) are dropped unanswered (the holder answers, or the vehicle
        retries)."""
        by_region: dict[RegionId, list] = {}
        for q in group:
            try:
                region = keys.parse_region_ingest(str(q.key_expr))
            except CodecError as exc:
                with q:
                    q.reply(q.key_expr, codec.encode(IngestAck(error=str(exc))))
                continue
            by_region.setdefault(region, []).append(q)
        for region, queries in by_region.items():
            holder = self._holder_for_ingest(region)
            if holder is None:
                for q in queries:
                    q.drop()
                continue
            self._ingest_region(holder, queries)

    def _holder_for_ingest(self, region: RegionId) -> Holder | None:
        holder = self.table.get(region)
        if holder is not None:
            return holder
        try:
            holder = self.table.claim_on_ingest(region, self.members, self._steal_dead())
        except StoreUnavailable as exc:
            logger.warning("%s: claim of %s: %s", self.ident, region, exc)
            return None
        if holder is not None:
            self._gain(holder)
        return holder

    def _ingest_region(self, holder: Holder, queries: list) -> None:
        payloads = [q.payload.to_bytes() if q.payload is not None else b"" for q in queries]
        try:
            acks = holder.durable.ingest_many(payloads)
        except Fenced as exc:  # the lease moved on: no ack; the vehicles resend to the holder
            self.table.counters["fenced"] += 1
            logger.warning("%s: %s", self.ident, exc)
            self.table.drop(holder.region, "lost")
            self._lose(holder.region)
            for q in queries:
                q.drop()
            return
        except Exception as exc:  # e.g. the database is down: an error ack, the vehicles retry
            self.table.counters["store_errors"] += 1
            logger.warning("%s: ingest failed: %s", self.ident, exc)
            acks = [IngestAck(error=f"worker failed to store the batch: {exc}")] * len(queries)
        self._last_ingest = time.monotonic()
        if any(ACCEPTED in a.results.values() for a in acks) and self._changed_since is None:
            self._changed_since = self._last_ingest
        for q, ack in zip(queries, acks, strict=True):
            with q:
                q.reply(q.key_expr, codec.encode(ack))

    def _flush_loop(self) -> None:
        """Debounced recompression (as services/merger/node.py): once ingest is quiet for
        debounce_s, or the oldest unpublished change is debounce_max_s old."""
        while not self._stop.wait(self.debounce_s / 2):
            since = self._changed_since
            if since is None:
                continue
            now = time.monotonic()
            if now - self._last_ingest < self.debounce_s and now - since < self.debounce_max_s:
                continue
            self._changed_since = None
            try:
                self._flush_and_publish()
            except Exception:  # the data is safe in the store; flush again later
                logger.exception("flush failed")
                self._changed_since = since

    def _flush_and_publish(self) -> None:
        for holder in self.table.holders():
            try:
                with holder.durable.lock:
                    dirty = holder.durable.shard.dirty_tiles()
                holder.durable.flush()
                refresh_raw(holder.durable, dirty)
            except Fenced as exc:
                logger.warning("%s: %s", self.ident, exc)
                self.table.drop(holder.region, "lost")
                self._lose(holder.region)
                continue
            for tile in holder.durable.take_changed():
                if self.table.get(holder.region) is holder:
                    self._declare_tile(tile.tile)
                self.session.put(keys.tile_update(*tile.tile), codec.encode(tile))

    def _serve_loop(self) -> None:
        while not self._stop.is_set():
            try:
                q = self.serve_queue.get(timeout=0.1)
            except queue.Empty:
                continue
            with q:
                try:
                    self._serve(q)
                except Exception as exc:  # a bad query must never end the serve thread
                    logger.warning("query %s failed: %s", q.selector, exc)
                    q.reply_err(str(exc).encode())

    def _serve(self, q) -> None:
        key = str(q.key_expr)
        if key == keys.stats("merger", self.ident):
            self._flush_and_publish()  # first: stored raw copies and tile queryables current
            counters = {**self.table.stats(), "worker_errors": self.errors}
            q.reply(key, codec.encode(Stats(role="merger", ident=self.ident, counters=counters)))
            return
        tile = keys.parse_tile(key)
        msg = tile_message(self.table, self.read_db, tile, q.parameters)
        if msg is not None and msg is not False:  # no such tile: no reply, as with no queryable
            q.reply(key, codec.encode(msg))


def refresh_raw(durable: DurableShard, tiles) -> None:
    """Store the raw/1 copy of tiles whose labels were recomputed: DurableShard.flush persists
    only tiles whose compressed bytes changed, and labels can change where the contours do not,
    so the tile servers' raw copies would lag (same version, upserted again)."""
    with durable.lock:
        rows = [(m.tile, m.version, m.codec, m.data) for m in map(durable.tile, tiles) if m]
        if rows:
            durable.store.save_tiles(rows)


def tile_message(table: RegionTable | None, db: PgDatabase, tile, parameters):
    """The Tile for a query: from the holder's memory when this worker holds the region, else
    from the stored tiles; None: no such tile; False: not newer than ?since."""
    from services.merger.node import _tile_selector

    since, want = _tile_selector(parameters)
    holder = table.get(region_of_tile(tile)) if table is not None else None
    msg = None
    if holder is not None:
        msg = holder.durable.raw_tile(tile) if want == "raw" else holder.durable.tile(tile)
    if msg is None:
        row = read_tile(db, tile, raw=want == "raw")
        if row is not None:
            msg = Tile(tile=tuple(tile), version=row[0], codec=row[1], data=row[2])
    if msg is None:
        return None
    return msg if since is None or msg.version > since else False


def _undeclare(entities) -> None:
    for e in entities:
        try:
            e.undeclare()
        except ZError as exc:  # the session may already be closing
            logger.debug("undeclare: %s", exc)


def worker_ident(args) -> str:
    import os
    import socket

    return args.id or f"{socket.gethostname()}-{os.getpid()}"


def main(args, cfg: RoadmapConfig) -> int:
    url = args.store or cfg.merger.store
    if not url.startswith(("postgresql://", "postgres://")):
        raise ConfigError(f"roadmap worker needs --store postgresql://... (or merger.store), "
                          f"got {url!r}")
    if cfg.merger.opencv_threads > 0:
        cv2.setNumThreads(cfg.merger.opencv_threads)
    ident = worker_ident(args)
    stop = stop_event()
    wait_for_database(url).close()
    m = cfg.merger
    dbs = [PgDatabase(url, name=f"roadmap-{ident}-{role}") for role in ("write", "ctl", "read")]
    table = RegionTable(ident=ident, write_db=dbs[0], control_db=dbs[1], lease_s=m.lease_s,
                        merger_cfg=m, region_owners=dict(m.region_owners))
    try:
        with open_session(cfg.bus) as session:
            node = WorkerNode(session, table, dbs[2], ident=ident, renew_s=m.lease_renew_s,
                              debounce_s=m.debounce_s, debounce_max_s=m.debounce_max_s,
                              ingest_queue=m.ingest_queue, ingest_group=m.ingest_group)
            logger.info("worker %s serving (store %s)", ident, url.split("@")[-1])
            node.run(stop)
    finally:
        for db in dbs:
            db.close()
    return 0
