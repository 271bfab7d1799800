"""A MergerShard made durable: ingest = validate -> store the new patches in one transaction ->
apply -> ack; flush = recompute dirty tiles -> recompress -> persist changed tiles. Transport-free
and thread-safe (one lock), so the node only adapts Zenoh to it."""

import logging
import threading

from common import codec
from common.contours import CODEC, LEGACY_CODECS, RAW_CODEC, encode_raw
from common.errors import CodecError, TileError
from common.messages import IngestAck, IngestBatch, SparseBatch, Stats, Tile
from common.sparse import expand_patch
from services.merger.shard import MergerShard, TileCodecCache, TileId
from services.merger.store import ShardStore

logger = logging.getLogger(__name__)

RECOVERY_CHUNK = 512
RECOVERY_FLUSH_EVERY = 16  # chunks: labels are recomputed (and old traversals retired) as the
# replay goes, so a restart after months of traversals never holds them all at once


def grid_batch(msg) -> IngestBatch:
    """An ingest payload's batch as GridPatches: an IngestBatch as it is, a SparseBatch's
    patches expanded (common.sparse.expand_patch). CodecError for anything else."""
    if isinstance(msg, IngestBatch):
        return msg
    if isinstance(msg, SparseBatch):
        return IngestBatch([expand_patch(p) for p in msg.patches])
    raise CodecError(f"expected an IngestBatch or SparseBatch, got {type(msg).__name__}")


class DurableShard:
    def __init__(self, shard: MergerShard, store: ShardStore, *, ident: str,
                 cache: TileCodecCache | None = None):
        self.shard = shard
        self.store = store
        self.ident = ident
        self.cache = cache or TileCodecCache()
        self.lock = threading.RLock()
        self.flush_lock = threading.Lock()
        self.errors = 0
        self._changed: dict[TileId, Tile] = {}  # changed since take_changed(), for publication

    def recover(self) -> int:
        """Replay the stored patches and tile versions; returns the number of patches replayed."""
        with self.lock:
            for tile, version, codec_name, data in self.store.load_tiles():
                # a tile stored by an older codec keeps its version (so versions never go
                # back); replaying the patches below re-encodes it and bumps the version
                if codec_name == self.cache.codec or codec_name in LEGACY_CODECS:
                    self.cache.restore(tile, version, data)
            chunk, n = [], 0
            for p in self.store.load_patches():
                chunk.append(p)
                if len(chunk) >= RECOVERY_CHUNK:
                    n += self._replay(chunk)
                    chunk = []
                    if n % (RECOVERY_CHUNK * RECOVERY_FLUSH_EVERY) == 0:
                        self.shard.flush(keep_dirty=True)
            n += self._replay(chunk)
        self.flush()  # lock order: flush_lock before the state lock
        return n

    def _replay(self, patches) -> int:
        self.shard.apply_batch(patches)
        return len(patches)

    def ingest(self, payload: bytes) -> IngestAck:
        """Strictly decode a batch, persist its new patches, apply them, return the ack. Any bad
        input yields IngestAck(error=...) and leaves the state untouched."""
        return self.ingest_many([payload])[0]

    def ingest_many(self, payloads: list[bytes]) -> list[IngestAck]:
        """Group commit: the acks of several batches (queries waiting together), whose new
        patches are stored in ONE transaction (one fsync) before any of them is applied or
        acked. Each batch is checked on its own: a bad one gets its error ack and adds nothing.
        A failing store raises (no ack at all, nothing applied): the senders retry."""
        acks: list[IngestAck | None] = [None] * len(payloads)
        decoded = []
        for i, payload in enumerate(payloads):  # outside the lock: flushes go on meanwhile
            try:
                decoded.append((i, grid_batch(codec.decode(payload))))
            except CodecError as exc:
                acks[i] = self._error(f"bad IngestBatch: {exc}")
        with self.lock:
            checked, new, new_ids = [], [], set()
            for i, batch in decoded:
                try:
                    fresh = self.shard.check_batch(batch.patches)
                except TileError as exc:
                    acks[i] = self._error(str(exc))
                    continue
                fresh = [p for p in fresh if p.patch_id not in new_ids]  # an earlier batch's
                new_ids.update(p.patch_id for p in fresh)
                new += fresh
                checked.append((i, batch))
            if new:
                self.store.save_patches(new)  # durable before any ack (raises -> no ack)
            for i, batch in checked:
                acks[i] = IngestAck(results=self.shard.apply_checked(batch.patches))
        return acks

    def _error(self, message: str) -> IngestAck:
        with self.lock:
            self.errors += 1
        logger.warning("%s: refused batch: %s", self.ident, message)
        return IngestAck(error=message)

    def flush(self) -> list[Tile]:
        """Recompute dirty tiles; returns the Tiles whose compressed form changed (persisted).

        The state lock is held per tile for the label recomputation only; compression runs
        outside it, so ingest goes on while a flush compresses (one flush at a time)."""
        with self.flush_lock:
            with self.lock:
                dirty = self.shard.dirty_tiles()
            tiles = []
            for t in dirty:
                with self.lock:
                    self.shard.flush([t])
                    labels = self.shard.labels(t)  # a new array per flush: a stable snapshot
                data = self.cache.encode(labels)
                with self.lock:
                    if self.cache.put(t, data):
                        tiles.append(self.tile(t))
            with self.lock:
                if tiles:
                    self.store.save_tiles([(t.tile, t.version, t.codec, t.data) for t in tiles])
                self._changed.update((t.tile, t) for t in tiles)
            return tiles

    def take_changed(self) -> list[Tile]:
        """Tiles changed by any flush since the last call (latest version of each)."""
        with self.lock:
            out, self._changed = list(self._changed.values()), {}
            return out

    def has_dirty(self) -> bool:
        with self.lock:
            return bool(self.shard.dirty_tiles())

    def tiles(self) -> list[TileId]:
        with self.lock:
            return [t for t in self.shard.tiles() if self.cache.get(t) is not None]

    def tile(self, tile: TileId) -> Tile | None:
        with self.lock:
            entry = self.cache.get(tile)
        if entry is None:
            return None
        return Tile(tile=tuple(tile), version=entry[0], codec=CODEC, data=entry[1])

    def raw_tile(self, tile: TileId) -> Tile | None:
        with self.lock:
            entry = self.cache.get(tile)
            if entry is None:
                return None
            labels = self.shard.labels(tile).copy()
        return Tile(tile=tuple(tile), version=entry[0], codec=RAW_CODEC, data=encode_raw(labels))

    def stats(self) -> Stats:
        """Counters after a flush, so the digest covers every acked patch."""
        self.flush()  # before taking the state lock: flush takes flush_lock, then the state lock
        with self.lock:
            counters = {**self.shard.stats(), "errors": self.errors}
        return Stats(role="merger", ident=self.ident, counters=counters)
