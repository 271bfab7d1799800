"""What the viewer shows, kept in one thread-safe object fed by any source (live fleet or files):
the newest version of each tile, rendered on demand to a PNG in the map palette (north up, no
data transparent), the localizers' latest poses, each shard's counters and who is alive."""

import math
import threading
import time

import cv2
import numpy as np

from common.classes import COLORS_RGB, NAMES, Cls
from common.contours import CODEC, LEGACY_CODECS, RAW_CODEC, decode_raw, decode_tile
from common.errors import CodecError
from common.grid import TILE_M, TileId
from common.messages import Pose, Tile

POSE_STALE_S = 5.0  # a pose older than this is drawn as stale
POSE_FORGET_S = 120.0  # ... and dropped after this
HIDDEN_COUNTERS = ("tile_list",)  # long; the page gets the tiles on their own


def render_png(labels: np.ndarray) -> bytes:
    """(512, 512) labels (row = north) -> RGBA PNG, north up, class 0 transparent."""
    rgba = np.zeros((*labels.shape, 4), np.uint8)
    rgba[..., :3] = COLORS_RGB[np.clip(labels, 0, len(COLORS_RGB) - 1)]
    rgba[..., 3] = np.where(labels > 0, 255, 0)
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgba[::-1], cv2.COLOR_RGBA2BGRA))
    if not ok:
        raise CodecError("could not encode a tile PNG")
    return png.tobytes()


def tile_labels(tile: Tile) -> np.ndarray:
    if tile.codec in (CODEC, *LEGACY_CODECS):
        return decode_tile(tile.data)
    if tile.codec == RAW_CODEC:
        return decode_raw(tile.data)
    raise CodecError(f"tile {tile.tile}: unknown codec {tile.codec!r}")


class ViewerState:
    def __init__(self, source: str, clock=time.monotonic):
        self.source = source
        self.clock = clock
        self.lock = threading.Lock()
        self.tiles: dict[TileId, Tile] = {}
        self.received: dict[TileId, float] = {}
        self.owners: dict[TileId, str] = {}
        self.pngs: dict[TileId, tuple[int, bytes]] = {}  # tile -> (version, png)
        self.poses: dict[str, tuple[Pose, float]] = {}
        self.stats: dict[str, dict] = {}
        self.alive: dict[str, list[str]] = {}
        self.updates = 0

    # -- inputs ----------------------------------------------------------------------------------

    def put_tile(self, tile: Tile, shard: str | None = None) -> bool:
        """Keep the tile if it is newer than the one held; True when it was."""
        key = tuple(tile.tile)
        with self.lock:
            if shard:
                self.owners[key] = shard
            held = self.tiles.get(key)
            if held is not None and held.version >= tile.version:
                return False
            self.tiles[key] = tile
            self.received[key] = self.clock()
            self.updates += 1
            return True

    def put_pose(self, pose: Pose) -> None:
        with self.lock:
            self.poses[pose.vehicle] = (pose, self.clock())

    def put_stats(self, stats: dict[str, dict], owners: dict[TileId, str]) -> None:
        with self.lock:
            self.stats = {k: dict(v) for k, v in stats.items()}
            self.owners.update(owners)

    def put_alive(self, alive: dict[str, list[str]]) -> None:
        with self.lock:
            self.alive = dict(alive)

    # -- outputs ---------------------------------------------------------------------------------

    def versions(self) -> dict[TileId, int]:
        with self.lock:
            return {t: m.version for t, m in self.tiles.items()}

    def png(self, tile: TileId) -> bytes | None:
        """The tile's PNG (rendered once per version), None when no such tile."""
        with self.lock:
            msg = self.tiles.get(tile)
            cached = self.pngs.get(tile)
        if msg is None:
            return None
        if cached is not None and cached[0] == msg.version:
            return cached[1]
        png = render_png(tile_labels(msg))
        with self.lock:
            self.pngs[tile] = (msg.version, png)
        return png

    def snapshot(self) -> dict:
        """The page's whole state: tiles with versions and shards, poses, shards, classes."""
        now = self.clock()
        with self.lock:
            self.poses = {v: (p, t) for v, (p, t) in self.poses.items()
                          if now - t <= POSE_FORGET_S}
            tiles = [{"tx": t[0], "ty": t[1], "version": m.version,
                      "shard": self.owners.get(t)} for t, m in sorted(self.tiles.items())]
            poses = [_pose_json(p, now - t) for _, (p, t) in sorted(self.poses.items())]
            shards = {k: _visible(v) for k, v in sorted(self.stats.items())}
            alive = dict(self.alive)
            updates = self.updates
        return {"source": self.source, "tile_m": TILE_M, "tiles": tiles, "poses": poses,
                "shards": shards, "alive": alive, "updates": updates,
                "classes": [{"id": int(c), "name": NAMES[c], "rgb": COLORS_RGB[c].tolist()}
                            for c in Cls if c != Cls.NONE]}

    def tile_info(self, tile: TileId) -> dict | None:
        """A clicked tile: its version, codec, size, age and its shard's counters."""
        now = self.clock()
        with self.lock:
            msg = self.tiles.get(tile)
            if msg is None:
                return None
            shard = self.owners.get(tile)
            return {"tile": list(tile), "version": msg.version, "codec": msg.codec,
                    "bytes": len(msg.data), "shard": shard,
                    "received_s_ago": round(now - self.received.get(tile, now), 1),
                    "shard_stats": _visible(self.stats.get(shard, {})) if shard else {}}


def _visible(counters: dict) -> dict:
    return {k: v for k, v in counters.items() if k not in HIDDEN_COUNTERS}


def _pose_json(p: Pose, age_s: float) -> dict:
    cov = np.asarray(p.cov, float)
    sigma = math.sqrt(max(float(cov[0, 0]), float(cov[1, 1]), 0.0))
    return {"vehicle": p.vehicle, "x": round(p.x, 3), "y": round(p.y, 3),
            "yaw": round(p.yaw, 4), "ok": bool(p.ok), "sigma_m": round(sigma, 3),
            "t_ns": int(p.t_ns), "age_s": round(age_s, 2), "stale": age_s > POSE_STALE_S}
