"""Tile access for the localizer: which tiles to hold (around the car and ahead of it), decoding of
the Tile messages ("contour/2", legacy "contour/1", or "raw/1"), and the Zenoh client that fetches
and follows them.

`tiles_needed` and `decode_tile_message` are pure; `TileClient` is the thin transport adapter and
takes an open session (from common.bus.open_session). A tile that fails to decode, or that names
another tile than the key it came on, is rejected (counted, logged) and the last good version
stays in the cache: hostile or corrupt input never replaces the map."""

import logging
import math
import time

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
    ):
        """on_tile(msg): called with every Tile message stored in the cache (fetched or an
        update), e.g. to record the map the car received."""
        from common.bus import FifoChannel

        if codec_name not in ("contour", "raw"):
            raise CodecError(f"localizer.map_codec must be 'contour' or 'raw', got {codec_name!r}")
        self.session, self.cache = session, cache
        self.params = "?codec=raw" if codec_name == "raw" else ""
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
        """One `get` of a tile from its owner shard; False if nobody holds it."""
        key = keys.tile(*tile) + self.params
        try:
            replies = list(self.session.get(key, timeout=self.timeout_s))
        except Exception as exc:  # zenoh raises its own ZError
            raise TransportError(f"get {key}: {exc}") from exc
        for reply in replies:
            if reply.ok is None:
                logger.warning("tile %s: error reply %r", tile, reply.err.payload.to_bytes()[:200])
                continue
            try:
                self._store(reply.ok.payload.to_bytes(), tile)
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
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
