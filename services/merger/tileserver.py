"""`roadmap tileserver --id T --store postgresql://...`: a read-only tile server.

Declares `roadmap/tile/*/*` (complete) and answers every tile query from the stored compressed
tiles (and their raw/1 copies, `?codec=raw`; `?since=<v>` as the workers), so a region's tiles
stay readable while its writer is being replaced. A worker holding a tile declares its exact key,
which Zenoh prefers; without one, the query lands here (on one tile server only). For reads that
scale, it also declares its own `roadmap/tileserver/<id>/tile/*/*`, where the tile clients spread
their queries (services/localizer/tiles.py); there a missing tile (or one not newer than
`?since=`) gets a delete reply, so the client can tell "none" from "no answer". Several serve
threads, each with its own connection. Stats `roadmap/stats/tileserver/<id>` (served, of which
`direct` on its own key), liveliness `roadmap/alive/tileserver/<id>`."""

import logging
import queue
import threading

from common import codec, keys
from common.bus import Callback, open_session, stop_event
from common.config import RoadmapConfig
from common.errors import CodecError, ConfigError
from common.messages import Stats
from services.merger.pgstore import PgDatabase, wait_for_database
from services.merger.worker import _undeclare, tile_message, worker_ident

logger = logging.getLogger(__name__)


class TileServer:
    def __init__(self, session, url: str, *, ident: str, threads: int = 2):
        self.session, self.ident = session, ident
        self.queue: queue.Queue = queue.Queue(maxsize=1024)
        self.served = self.direct = self.missing = self.errors = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.dbs = [PgDatabase(url, name=f"roadmap-{ident}-{i}") for i in range(max(1, threads))]
        put = Callback(self.queue.put, indirect=False)
        self.entities = [
            session.declare_queryable(keys.TILE_ALL, put, complete=True),
            session.declare_queryable(keys.tileserver_tile_all(ident), put, complete=True),
            session.declare_queryable(keys.stats("tileserver", ident), put, complete=True),
            session.liveliness().declare_token(keys.alive("tileserver", ident)),
        ]
        self.threads = [threading.Thread(target=self._serve_loop, args=(db,), daemon=True,
                                         name=f"tiles-{i}") for i, db in enumerate(self.dbs)]

    def run(self, stop: threading.Event) -> None:
        for t in self.threads:
            t.start()
        try:
            stop.wait()
        finally:
            self._stop.set()
            for t in self.threads:
                t.join(timeout=5.0)
            _undeclare(self.entities)
            for db in self.dbs:
                db.close()

    def _serve_loop(self, db: PgDatabase) -> None:
        while not self._stop.is_set():
            try:
                q = self.queue.get(timeout=0.1)
            except queue.Empty:
                continue
            with q:
                try:
                    self._serve(q, db)
                except Exception as exc:  # a bad query (or no database) answers an error
                    with self._lock:
                        self.errors += 1
                    q.reply_err(str(exc).encode())

    def _serve(self, q, db: PgDatabase) -> None:
        key = str(q.key_expr)
        if key == keys.stats("tileserver", self.ident):
            counters = {"served": self.served, "direct": self.direct, "missing": self.missing,
                        "errors": self.errors}
            q.reply(key, codec.encode(Stats(role="tileserver", ident=self.ident,
                                            counters=counters)))
            return
        try:  # on its own key, or on roadmap/tile/<tx>/<ty>
            tile, direct = keys.parse_tileserver_tile(key)[1], True
        except CodecError:
            tile, direct = keys.parse_tile(key), False
        msg = tile_message(None, db, tile, q.parameters)
        with self._lock:
            self.served += msg is not None
            self.direct += direct and msg is not None
            self.missing += msg is None
        if msg is not None and msg is not False:
            q.reply(key, codec.encode(msg))
        elif direct:  # answered, nothing (newer) here: the client need not ask elsewhere
            q.reply_del(key)
        # on roadmap/tile/*/*: no reply, as with no queryable


def main(args, cfg: RoadmapConfig) -> int:
    url = args.store or cfg.merger.store
    if not url.startswith(("postgresql://", "postgres://")):
        raise ConfigError(f"roadmap tileserver needs --store postgresql://..., got {url!r}")
    stop = stop_event()
    wait_for_database(url).close()
    with open_session(cfg.bus) as session:
        server = TileServer(session, url, ident=worker_ident(args), threads=args.threads)
        logger.info("tile server %s serving", server.ident)
        server.run(stop)
    return 0
