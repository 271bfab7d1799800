"""Tile access for the localizer: which tiles to hold (around the car and ahead of it), decoding of
the Tile messages ("contour/2", legacy "contour/1", or "raw/1"), and the Zenoh client that fetches
and follows them.

`tiles_needed`, `decode_tile_message` and `server_order` are pure; `TileSource` (where a tile
query goes) and `TileClient` are the thin transport adapters and take an open session (from
common.bus.open_session). A tile that fails to decode, or that names another tile than the key it
came on, is rejected (counted, logged) and the last good version stays in the cache: hostile or
corrupt input never replaces the map.

Reads spread over the read-only tile servers with no configuration (common/keys.py): the client
follows their liveliness tokens and asks, for each tile, the one that rendezvous hashing over
(client, tile) ranks first, on that server's own key; the next one when it gives no reply (it is
then skipped for `suspect_s`, or until its token comes back), and last the plain tile key (a
worker holding the tile, or one tile server); with no tile server alive, only the plain key."""

import hashlib
import logging
import math
import threading
import time
from collections import Counter

import numpy as np

from common import codec, keys
from common.config import BusConfig, LocalizerConfig
from common.contours import CODEC, LEGACY_CODECS, RAW_CODEC, decode_raw, decode_tile
from common.errors import CodecError, TransportError
from common.grid import TileId, tiles_around
from common.messages import Tile

logger = logging.getLogger(__name__)


def tiles_needed(
    x_m: float, y_m: float, heading_rad: float | None, *, radius_m: float, ahead_m: float
) -> list[TileId]:
    """Tiles within radius of the car, then those along the direction of travel (nearest first)."""
    out = tiles_around(x_m, y_m, radius_m)
    if heading_rad is not None and ahead_m > 0:
        for d in np.arange(radius_m, radius_m + ahead_m + 1e-9, radius_m / 2):
            ax, ay = x_m + d * math.cos(heading_rad), y_m + d * math.sin(heading_rad)
            out += [t for t in tiles_around(ax, ay, radius_m / 2) if t not in out]
    return out


def decode_tile_message(msg: Tile) -> np.ndarray:
    """Tile message -> (512, 512) uint8 labels."""
    if msg.codec == CODEC or msg.codec in LEGACY_CODECS:  # decode_tile reads both
        return decode_tile(msg.data)
    if msg.codec == RAW_CODEC:
        return decode_raw(msg.data)
    raise CodecError(
        f"tile {msg.tile}: unknown codec {msg.codec!r} (expected {CODEC} or {RAW_CODEC})"
    )


def server_order(client_id: str, tile: TileId, servers) -> list[str]:
    """The tile servers in the order a client asks them for a tile: rendezvous (highest random
    weight) hashing over (client, tile, server). Different clients, and one client's different
    tiles, spread evenly over the servers; a server joining or leaving moves only its share.
    Weights: blake2b, stable across processes (never the salted built-in hash) and, unlike a bare
    crc32, not affine in the server name."""
    base = f"{client_id}/{int(tile[0])}/{int(tile[1])}/"
    return sorted(servers, key=lambda s: (_weight(base + s), s), reverse=True)


def _weight(text: str) -> int:
    return int.from_bytes(hashlib.blake2b(text.encode(), digest_size=8).digest(), "big")


class TileSource:
    """Where a tile query goes: the live tile servers (liveliness `roadmap/alive/tileserver/*`)
    in server_order, then the plain key `roadmap/tile/<tx>/<ty>`. A server that gives no reply
    (timeout, or its link dropped) costs one timeout: it is skipped for `suspect_s` or until its
    liveliness token is declared again; losing the token removes it at once."""

    def __init__(self, session, *, client_id: str | None = None,
                 timeout_s: float = BusConfig.query_timeout_s, suspect_s: float = 10.0):
        from common.bus import Callback

        self.session, self.timeout_s, self.suspect_s = session, timeout_s, suspect_s
        self.client_id = client_id or str(session.info.zid())
        self.answered: Counter = Counter()  # tile queries answered, per server ("" = plain key)
        self.no_reply = 0  # tile-server queries that got no reply (the server then skipped)
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self._suspect_until: dict[str, float] = {}
        self._sub = session.liveliness().declare_subscriber(
            keys.alive_all("tileserver"), Callback(self._on_token, indirect=False), history=True)

    def live(self) -> list[str]:
        """The tile servers alive and not skipped now (sorted)."""
        now = time.monotonic()
        with self._lock:
            return sorted(s for s in self._alive if self._suspect_until.get(s, 0.0) <= now)

    def get(self, tile: TileId, params: str = "") -> list[bytes]:
        """The Tile payloads a tile query got (params: keys.tile_params); [] = none."""
        for server in server_order(self.client_id, tile, self.live()):
            answered, payloads = self._ask(keys.tileserver_tile(server, *tile) + params)
            if answered:
                self._count(server)
                return payloads
            self._skip(server)
        answered, payloads = self._ask(keys.tile(*tile) + params)
        if answered:
            self._count("")
        return payloads

    def _ask(self, selector: str) -> tuple[bool, list[bytes]]:
        """(anyone answered, the payloads of its Tile replies): a delete reply is an answer
        without a tile; an error reply other than the timeout is an answer, logged."""
        from common.bus import SampleKind

        try:
            replies = list(self.session.get(selector, timeout=self.timeout_s))
        except Exception as exc:  # zenoh raises its own ZError
            raise TransportError(f"get {selector}: {exc}") from exc
        answered, payloads = False, []
        for reply in replies:
            if reply.ok is not None:
                answered = True
                if reply.ok.kind != SampleKind.DELETE:
                    payloads.append(reply.ok.payload.to_bytes())
                continue
            err = reply.err.payload.to_bytes()
            if err != b"Timeout":
                answered = True
                logger.warning("get %s: error reply %r", selector, err[:200])
        return answered, payloads

    def _count(self, server: str) -> None:
        with self._lock:
            self.answered[server] += 1

    def _skip(self, server: str) -> None:
        logger.warning("tile server %s gave no reply; skipping it for %.0f s", server,
                       self.suspect_s)
        with self._lock:
            self.no_reply += 1
            self._suspect_until[server] = time.monotonic() + self.suspect_s

    def _on_token(self, sample) -> None:  # on the RX thread: tiny, never blocks
        from common.bus import SampleKind

        try:
            _, ident = keys.parse_alive(str(sample.key_expr))
        except CodecError:
            return
        with self._lock:
            self._suspect_until.pop(ident, None)
            if sample.kind == SampleKind.DELETE:
                self._alive.discard(ident)
            else:
                self._alive.add(ident)

    def close(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None


class TileClient:
    """Fetches tiles by Zenoh `get` on tile keys; follows roadmap/tile-update/*/*."""

    def __init__(
        self,
        session,
        cache,
        *,
        codec_name: str = LocalizerConfig.map_codec,
        timeout_s: float = BusConfig.query_timeout_s,
        retry_missing_s: float = 5.0,
        follow_updates: bool = True,
        on_tile=None,
        client_id: str | None = None,
    ):
        """on_tile(msg): called with every Tile message stored in the cache (fetched or an
        update), e.g. to record the map the car received. client_id: what the tile servers are
        chosen by (default: the session's Zenoh id, one per car process)."""
        from common.bus import FifoChannel

        if codec_name not in ("contour", "raw"):
            raise CodecError(f"localizer.map_codec must be 'contour' or 'raw', got {codec_name!r}")
        self.session, self.cache = session, cache
        self.params = keys.tile_params(codec="raw" if codec_name == "raw" else None)
        self.source = TileSource(session, client_id=client_id, timeout_s=timeout_s)
        self.timeout_s, self.retry_missing_s = timeout_s, retry_missing_s
        self.on_tile = on_tile
        self._missing: dict[TileId, float] = {}
        self.fetched = self.missing = self.updates = self.rejected = 0
        self.bytes = 0
        self.decode_ms: list[float] = []
        self._sub = (
            session.declare_subscriber(keys.TILE_UPDATE_ALL, FifoChannel(256))
            if follow_updates
            else None
        )

    def ensure(self, tiles: list[TileId]) -> int:
        """Fetch the tiles not cached yet (skipping recently missing ones); returns how many."""
        now = time.monotonic()
        got = 0
        for tile in tiles:
            if tile in self.cache:
                self.cache.touch(tile)
                continue
            if now - self._missing.get(tile, -1e9) < self.retry_missing_s:
                continue
            got += self.fetch(tile)
        return got

    def fetch(self, tile: TileId) -> bool:
        """One tile query (a tile server, else the tile's holder); False if nobody has it."""
        for payload in self.source.get(tile, self.params):
            try:
                self._store(payload, tile)
            except CodecError as exc:
                self._reject(tile, exc)
                continue
            self.fetched += 1
            return True
        self._missing[tile] = time.monotonic()
        self.missing += 1
        return False

    def poll_updates(self) -> int:
        """Apply pending tile-update publications for tiles we hold; returns how many applied."""
        if self._sub is None:
            return 0
        applied = 0
        while (sample := self._sub.try_recv()) is not None:
            try:
                tile = keys.parse_tile(str(sample.key_expr))
            except CodecError:
                continue
            if tile not in self.cache:
                continue
            try:
                if self.params:  # raw map wanted: the update is contour coded, fetch raw instead
                    applied += self.fetch(tile)
                else:
                    applied += self._store(sample.payload.to_bytes(), tile)
            except CodecError as exc:
                self._reject(tile, exc)
        self.updates += applied
        return applied

    def _store(self, payload: bytes, tile: TileId) -> bool:
        """Decode a Tile that came on `tile`'s key and cache it if newer; CodecError (cache
        untouched) when it does not decode or names another tile."""
        msg = codec.decode(payload, expect=Tile)
        if tuple(msg.tile) != tuple(tile):
            raise CodecError(f"a Tile for {tuple(msg.tile)} on the key of tile {tuple(tile)}")
        old = self.cache.version(msg.tile)
        if old is not None and msg.version <= old:
            return False
        t0 = time.perf_counter()
        labels = decode_tile_message(msg)
        self.decode_ms.append((time.perf_counter() - t0) * 1e3)
        self.bytes += len(msg.data)
        self.cache.put(msg.tile, msg.version, labels)
        if self.on_tile is not None:
            self.on_tile(msg)
        return True

    def _reject(self, tile: TileId, exc: CodecError) -> None:
        self.rejected += 1
        kept = self.cache.version(tile)
        logger.warning("tile %s rejected (%s); %s", tile, exc,
                       f"keeping version {kept}" if kept is not None else "none cached")

    def close(self) -> None:
        self.source.close()
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
