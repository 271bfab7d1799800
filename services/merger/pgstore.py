"""The cloud's durable state in PostgreSQL (merger.store = "postgresql://..."): the patch log,
the compressed (and raw) tiles with their versions, and the region leases with fencing epochs.

`RegionStore` is the store interface of services/merger/store.py (save_patches, load_patches,
save_tiles, load_tiles, close) for ONE region held by ONE worker at ONE lease epoch: a
DurableShard runs on it unchanged, so the contract stays "ack only after commit". Every write
transaction first locks the region's lease row and checks, in SQL, that this worker still holds
it at its epoch (`SELECT ... FOR UPDATE`); a worker that was paused and lost the lease (a new
owner bumped the epoch) gets `Fenced` and its transaction rolls back. A takeover bumps the epoch
under that same row lock and only then replays the region's patches, so it sees every patch an
old owner committed, and no old owner commits after it. Patches go in with
`INSERT ... ON CONFLICT DO NOTHING` (idempotent by patch id), batched by psycopg's executemany
(pipeline mode). SQL used, kept portable to the PostgreSQL-wire distributed engines
(deploy/README.md): tables keyed by region first, INSERT ... ON CONFLICT, UPDATE ... RETURNING,
SELECT ... FOR UPDATE, now() + interval; the schema set-up alone takes pg_advisory_xact_lock."""

import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np

from common.contours import encode_raw
from common.errors import RoadmapError
from common.grid import RegionId, region_of_tile
from common.messages import GridPatch
from services.merger.store import stored_form, stored_patch

logger = logging.getLogger(__name__)

SCHEMA = """
CREATE TABLE IF NOT EXISTS patches (
    rx INTEGER NOT NULL, ry INTEGER NOT NULL, patch_id TEXT NOT NULL,
    tx INTEGER NOT NULL, ty INTEGER NOT NULL, vehicle TEXT NOT NULL, traversal TEXT NOT NULL,
    t_first_ns BIGINT NOT NULL, t_last_ns BIGINT NOT NULL,
    packed BYTEA NOT NULL, packed_n INTEGER NOT NULL,  -- common.codec.pack_cells_votes
    epoch BIGINT NOT NULL,                            -- the writer's lease epoch (forensics)
    form TEXT,                                        -- NULL: cells, "sparse/1": its payload
    PRIMARY KEY (rx, ry, patch_id)                    -- a patch id has one tile: one region
);
ALTER TABLE patches ADD COLUMN IF NOT EXISTS form TEXT;  -- a store from before sparse/1
CREATE TABLE IF NOT EXISTS tiles (
    rx INTEGER NOT NULL, ry INTEGER NOT NULL, tx INTEGER NOT NULL, ty INTEGER NOT NULL,
    version BIGINT NOT NULL, codec TEXT NOT NULL, data BYTEA NOT NULL,
    raw BYTEA NOT NULL,                               -- raw/1 of the same labels and version
    PRIMARY KEY (rx, ry, tx, ty)
);
CREATE TABLE IF NOT EXISTS leases (
    rx INTEGER NOT NULL, ry INTEGER NOT NULL, owner TEXT, epoch BIGINT NOT NULL,
    expires_at TIMESTAMPTZ NOT NULL, PRIMARY KEY (rx, ry)
);
"""
SCHEMA_LOCK = 0x524D4150  # "RMAP": one schema set-up at a time

GUARD = "SELECT 1 FROM leases WHERE rx = %s AND ry = %s AND owner = %s AND epoch = %s FOR UPDATE"
INSERT_PATCH = ("INSERT INTO patches VALUES (%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s,%s) "
                "ON CONFLICT (rx, ry, patch_id) DO NOTHING")
UPSERT_TILE = """INSERT INTO tiles VALUES (%s,%s,%s,%s,%s,%s,%s,%s)
ON CONFLICT (rx, ry, tx, ty) DO UPDATE SET version = EXCLUDED.version, codec = EXCLUDED.codec,
    data = EXCLUDED.data, raw = EXCLUDED.raw WHERE tiles.version <= EXCLUDED.version"""


class StoreUnavailable(RoadmapError):
    """PostgreSQL cannot be reached (or the connection broke): nothing was committed."""


class Fenced(RoadmapError):
    """This worker no longer holds the region's lease at its epoch: the write was refused."""


def _psycopg():
    try:
        import psycopg
    except ImportError as exc:  # the optional extra
        raise RoadmapError("merger.store = postgresql://... needs psycopg 3: "
                           "pip install 'roadmap[postgres]'") from exc
    return psycopg


class PgDatabase:
    """One connection (opened lazily, reopened after a failure) and a lock: one transaction at a
    time. Connection errors become StoreUnavailable; the next call connects again."""

    def __init__(self, url: str, *, name: str = "roadmap", connect_timeout_s: float = 2.0):
        self.url, self.name, self.connect_timeout_s = url, name, connect_timeout_s
        self.lock = threading.RLock()
        self._conn = None

    def _connection(self):
        psycopg = _psycopg()
        if self._conn is None or self._conn.closed or self._conn.broken:
            try:
                self._conn = psycopg.connect(self.url, autocommit=True, application_name=self.name,
                                             connect_timeout=max(1, round(self.connect_timeout_s)))
            except psycopg.OperationalError as exc:
                self._conn = None
                raise StoreUnavailable(f"cannot connect to {_redact(self.url)}: {exc}") from exc
        return self._conn

    @contextmanager
    def transaction(self):
        """A cursor inside BEGIN ... COMMIT (ROLLBACK on any exception)."""
        psycopg = _psycopg()
        with self.lock:
            conn = self._connection()
            try:
                with conn.transaction(), conn.cursor() as cur:
                    yield cur
            except (psycopg.OperationalError, psycopg.InterfaceError) as exc:
                self.close()
                raise StoreUnavailable(f"{_redact(self.url)}: {exc}") from exc

    def stream(self, sql: str, params, itersize: int = 512) -> Iterator[tuple]:
        """Rows of a query through a server-side cursor (not all in memory at once)."""
        psycopg = _psycopg()
        with self.lock:
            conn = self._connection()
            try:
                with conn.transaction(), conn.cursor(name=f"stream_{id(self)}") as cur:
                    cur.itersize = itersize
                    cur.execute(sql, params)
                    yield from cur
            except (psycopg.OperationalError, psycopg.InterfaceError) as exc:
                self.close()
                raise StoreUnavailable(f"{_redact(self.url)}: {exc}") from exc

    def create_schema(self) -> None:
        with self.transaction() as cur:
            cur.execute("SELECT pg_advisory_xact_lock(%s)", (SCHEMA_LOCK,))
            for statement in filter(str.strip, SCHEMA.split(";")):
                cur.execute(statement)

    def close(self) -> None:
        with self.lock:
            if self._conn is not None:
                try:
                    self._conn.close()
                except Exception:  # noqa: BLE001 - closing a broken connection
                    pass
                self._conn = None


def _redact(url: str) -> str:
    """The URL without its password (for messages and logs)."""
    if "@" not in url or "://" not in url:
        return url
    scheme, rest = url.split("://", 1)
    cred, host = rest.rsplit("@", 1)
    return f"{scheme}://{cred.split(':', 1)[0]}@{host}"


# -- leases ------------------------------------------------------------------------------------


class Leases:
    """Region leases on a PgDatabase: list, claim (compare-and-set on the epoch), renew, release.
    Expiry is judged by the database's clock (now()), never by a worker's."""

    def __init__(self, db: PgDatabase, owner: str, lease_s: float):
        self.db, self.owner, self.lease_s = db, owner, float(lease_s)

    def all(self) -> dict[RegionId, tuple[str | None, int, bool]]:
        """region -> (owner, epoch, valid = not expired)."""
        with self.db.transaction() as cur:
            cur.execute("SELECT rx, ry, owner, epoch, expires_at > now() FROM leases")
            return {(rx, ry): (owner, int(epoch), bool(valid))
                    for rx, ry, owner, epoch, valid in cur.fetchall()}

    def claim(self, region: RegionId, seen_epoch: int | None) -> int | None:
        """Take a region: a new one (no lease yet, seen_epoch None) or one whose lease we saw at
        seen_epoch; returns the new epoch, or None when someone else changed it meanwhile."""
        rx, ry = region
        with self.db.transaction() as cur:
            if seen_epoch is None:
                cur.execute("INSERT INTO leases VALUES (%s, %s, %s, 1, now() + %s * interval "
                            "'1 second') ON CONFLICT (rx, ry) DO NOTHING RETURNING epoch",
                            (rx, ry, self.owner, self.lease_s))
            else:
                cur.execute("UPDATE leases SET owner = %s, epoch = epoch + 1, expires_at = now() "
                            "+ %s * interval '1 second' WHERE rx = %s AND ry = %s AND epoch = %s "
                            "RETURNING epoch", (self.owner, self.lease_s, rx, ry, seen_epoch))
            row = cur.fetchone()
        return None if row is None else int(row[0])

    def renew(self, held: dict[RegionId, int]) -> set[RegionId]:
        """Extend the leases we hold at their epochs (one statement); returns those still ours.
        An expired lease nobody took is still ours: its epoch is unchanged, so nobody wrote."""
        if not held:
            return set()
        regions = list(held)
        with self.db.transaction() as cur:
            cur.execute(
                "UPDATE leases SET expires_at = now() + %s * interval '1 second' "
                "WHERE owner = %s AND (rx, ry, epoch) IN "
                "(SELECT * FROM unnest(%s::int[], %s::int[], %s::bigint[])) RETURNING rx, ry",
                (self.lease_s, self.owner, [r[0] for r in regions], [r[1] for r in regions],
                 [held[r] for r in regions]))
            return {(rx, ry) for rx, ry in cur.fetchall()}

    def release(self, region: RegionId, epoch: int) -> bool:
        """Hand a region back (owner NULL, expired now) so the next owner need not wait."""
        with self.db.transaction() as cur:
            cur.execute("UPDATE leases SET owner = NULL, expires_at = now() WHERE rx = %s AND "
                        "ry = %s AND owner = %s AND epoch = %s", (*region, self.owner, epoch))
            return cur.rowcount == 1


# -- one region's store (the ShardStore interface) ---------------------------------------------


class RegionStore:
    """The patches and tiles of one region, written only while `owner` holds it at `epoch`."""

    def __init__(self, write_db: PgDatabase, read_db: PgDatabase, region: RegionId, *,
                 owner: str, epoch: int, labels_of: Callable[[tuple], np.ndarray] | None = None):
        self.write_db, self.read_db = write_db, read_db
        self.region, self.owner, self.epoch = tuple(region), owner, int(epoch)
        self.labels_of = labels_of  # the shard's labels of a tile: the raw/1 copy of save_tiles

    def close(self) -> None:
        """The connections belong to the worker."""

    def _guard(self, cur) -> None:
        cur.execute(GUARD, (*self.region, self.owner, self.epoch))
        if cur.fetchone() is None:
            raise Fenced(f"region {self.region}: lease epoch {self.epoch} of {self.owner} is "
                         f"no longer current")

    def save_patches(self, patches: list[GridPatch]) -> None:
        """All of them in one committed transaction (after the fence check), or none."""
        rows = []
        for p in patches:
            if region_of_tile(tuple(p.tile)) != self.region:
                raise Fenced(f"patch {p.patch_id!r}: tile {tuple(p.tile)} is outside region "
                             f"{self.region}")
            payload, _, n, form = stored_form(p)
            rows.append((*self.region, p.patch_id, int(p.tile[0]), int(p.tile[1]), p.vehicle,
                         p.traversal, int(p.t_first_ns), int(p.t_last_ns), payload, n or 0,
                         self.epoch, form))
        with self.write_db.transaction() as cur:
            self._guard(cur)
            cur.executemany(INSERT_PATCH, rows)

    def load_patches(self) -> Iterator[GridPatch]:
        """The region's patches, for a replay (order is irrelevant: the map is a function of the
        set; sorted by id for a stable log)."""
        sql = (f"SELECT {PATCH_COLUMNS} FROM patches WHERE rx = %s AND ry = %s "
               "ORDER BY patch_id")
        for row in self.read_db.stream(sql, self.region):
            yield _patch_of_row(*row)

    def count_patches(self) -> int:
        with self.read_db.transaction() as cur:
            cur.execute("SELECT COUNT(*) FROM patches WHERE rx = %s AND ry = %s", self.region)
            return int(cur.fetchone()[0])

    def save_tiles(self, tiles: list[tuple[tuple[int, int], int, str, bytes]]) -> None:
        """[(tile, version, codec, data)] and each tile's raw/1 copy, in one fenced transaction."""
        rows = [(*self.region, int(t[0]), int(t[1]), int(v), codec, data,
                 encode_raw(self.labels_of(t)) if self.labels_of else b"")
                for t, v, codec, data in tiles]
        with self.write_db.transaction() as cur:
            self._guard(cur)
            cur.executemany(UPSERT_TILE, rows)

    def load_tiles(self) -> list[tuple[tuple[int, int], int, str, bytes]]:
        with self.read_db.transaction() as cur:
            cur.execute("SELECT tx, ty, version, codec, data FROM tiles WHERE rx = %s AND ry = %s "
                        "ORDER BY tx, ty", self.region)
            return [((tx, ty), int(v), codec, bytes(data)) for tx, ty, v, codec, data in cur]


# -- reads for the tile servers and the tests --------------------------------------------------


def read_tile(db: PgDatabase, tile: tuple[int, int], raw: bool = False
              ) -> tuple[int, str, bytes] | None:
    """(version, codec, data) of a stored tile (its raw/1 copy with raw=True), or None."""
    rx, ry = region_of_tile(tuple(tile))
    with db.transaction() as cur:
        cur.execute("SELECT version, codec, data, raw FROM tiles WHERE rx = %s AND ry = %s AND "
                    "tx = %s AND ty = %s", (rx, ry, int(tile[0]), int(tile[1])))
        row = cur.fetchone()
    if row is None:
        return None
    version, codec_name, data, raw_data = row
    return (int(version), "raw/1", bytes(raw_data)) if raw else (int(version), codec_name,
                                                                  bytes(data))


def all_patches(db: PgDatabase) -> Iterator[GridPatch]:
    """Every stored patch (a replay of the whole map: tests, benchmarks)."""
    for row in db.stream(f"SELECT {PATCH_COLUMNS} FROM patches ORDER BY patch_id", ()):
        yield _patch_of_row(*row)


PATCH_COLUMNS = ("patch_id, vehicle, tx, ty, t_first_ns, t_last_ns, traversal, packed, packed_n, "
                 "form")


def _patch_of_row(pid, vehicle, tx, ty, t0, t1, trav, packed, n, form) -> GridPatch:
    return stored_patch(pid, vehicle, (tx, ty), t0, t1, trav, packed, n, form)


def wait_for_database(url: str, timeout_s: float = 30.0) -> PgDatabase:
    """A PgDatabase with the schema in place, once the server answers (a worker starting
    beside a database that is still starting)."""
    db = PgDatabase(url, name="roadmap-schema")
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            db.create_schema()
            return db
        except StoreUnavailable:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)
