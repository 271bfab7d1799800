"""Sources that fill a ViewerState: a live fleet over Zenoh (tile-update and pose subscriptions,
plus a refresher thread that lists the shards' tiles and counters, catches up on any tile newer
than the one held, and reads the liveliness tokens; a liveliness subscription shows a process
that comes and goes between two refreshes), or the tiles of a demo's folder on disk."""

import logging
import threading

from common import codec, keys
from common.bus import Callback, SampleKind, ZError
from common.errors import CodecError
from common.messages import Pose, Tile
from services import fleet
from services.viewer.state import ViewerState

logger = logging.getLogger(__name__)


class LiveFeed:
    """Subscriptions are cheap callbacks on the session's RX thread (decode, store); the tile
    PNGs are rendered later, by the page's requests."""

    def __init__(self, session, state: ViewerState, *, ident: str, stats_every_s: float,
                 timeout_s: float):
        self.session, self.state = session, state
        self.stats_every_s, self.timeout_s = stats_every_s, timeout_s
        self._stop = threading.Event()
        self.tile_sub = session.declare_subscriber(
            keys.TILE_UPDATE_ALL, Callback(self._on_tile, indirect=False))
        self.pose_sub = session.declare_subscriber(
            keys.POSE_ALL, Callback(self._on_pose, indirect=False))
        self.token = session.liveliness().declare_token(keys.alive("viewer", ident))
        # tokens as they come and go (a small demo's vehicle lives 2 s, under one refresh)
        self._alive_lock = threading.Lock()
        self._alive: dict[str, set[str]] = {}
        # events that arrive while a liveliness snapshot is in flight, replayed onto it (None:
        # no snapshot in flight): a token dropped then would else show alive till the next one
        self._journal: list[tuple[bool, str, str]] | None = None
        self.alive_sub = session.liveliness().declare_subscriber(
            keys.alive_all(), self._on_alive, history=True)
        self.thread = threading.Thread(target=self._refresh_loop, name="viewer-refresh",
                                       daemon=True)

    def start(self) -> "LiveFeed":
        self.thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self.thread.is_alive():  # (never started: a feed refreshed by hand)
            self.thread.join(timeout=10.0)
        for entity in (self.token, self.tile_sub, self.pose_sub, self.alive_sub):
            try:
                entity.undeclare()
            except ZError as exc:
                logger.debug("undeclare: %s", exc)

    def _on_tile(self, sample) -> None:
        try:
            self.state.put_tile(codec.decode(sample.payload.to_bytes(), expect=Tile))
        except CodecError as exc:
            logger.warning("tile update %s: %s", sample.key_expr, exc)

    def _on_alive(self, sample) -> None:
        try:
            role, ident = keys.parse_alive(str(sample.key_expr))
        except CodecError:
            return
        event = (sample.kind != SampleKind.DELETE, role, ident)
        with self._alive_lock:
            if self._journal is not None:
                self._journal.append(event)
            self._apply_alive([event])

    def _apply_alive(self, events) -> None:
        """(alive, role, ident) events onto the held set, and the set into the state; under
        the lock."""
        for up, role, ident in events:
            ids = self._alive.setdefault(role, set())
            if up:
                ids.add(ident)
            else:
                ids.discard(ident)
        self.state.put_alive({r: sorted(i) for r, i in sorted(self._alive.items()) if i})

    def _on_pose(self, sample) -> None:
        try:
            self.state.put_pose(codec.decode(sample.payload.to_bytes(), expect=Pose))
        except CodecError as exc:
            logger.warning("pose %s: %s", sample.key_expr, exc)

    def _refresh_loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.refresh()
            except (ZError, CodecError) as exc:  # the router away, a bad reply: try again
                logger.warning("refresh: %s", exc)
            self._stop.wait(self.stats_every_s)

    def refresh_stats(self) -> dict:
        """The shards' counters and tile lists now (also for a clicked tile's panel)."""
        stats = fleet.shard_stats(self.session, self.timeout_s)
        owners = fleet.tile_owners(stats)
        self.state.put_stats(stats, owners)
        return owners

    def refresh(self) -> None:
        """Shards' counters and tile lists, liveliness, and every listed tile the state lacks
        or holds an older version of (a publication missed, or sent before the viewer)."""
        owners = self.refresh_stats()
        with self._alive_lock:
            self._journal = []
        alive = None
        try:
            alive = fleet.alive(self.session, self.timeout_s)  # settles missed events
        finally:
            with self._alive_lock:
                journal, self._journal = self._journal, None
                if alive is not None:
                    self._alive = {role: set(ids) for role, ids in alive.items()}
                    self._apply_alive(journal)  # what changed while it was taken
        held = self.state.versions()
        for tile, shard in sorted(owners.items()):
            if self._stop.is_set():
                return
            msg = fleet.get_tile(self.session, tile, self.timeout_s, since=held.get(tile))
            if msg is not None:
                self.state.put_tile(msg, shard)


def load_folder(state: ViewerState, path) -> None:
    """The tiles of a demo's output folder, shard stores or tiles.npz, once."""
    from services.export.sources import read_folder

    stored = read_folder(path)
    for tile in stored.tiles:
        state.put_tile(tile, stored.owners.get(tuple(tile.tile)))
    state.put_stats({row["shard"]: {"patches": row["patches"], "tiles": row["tiles"],
                                    "store": row["path"]} for row in stored.stores},
                    stored.owners)
