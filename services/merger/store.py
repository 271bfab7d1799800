"""The shard's durable store: SQLite in WAL mode, one file per shard (DESIGN.md: Delivery).

Holds every applied patch (id, tile, traversal, times, and its cells + votes as they came on the
wire, common.codec.pack_cells_votes, ~1 byte per cell, or a sparse patch's payload as it came,
`form` "sparse/1", replayed through common.sparse.expand_patch; rows written before packed
patches hold cells as uint32 and votes as uint8 where they fit, else uint16, and are still
read) and each tile's
compressed form with its version. The new patches of a batch, or
of a group of batches, are written in ONE transaction, committed (fsync'd with synchronous=FULL)
before the shard acks; on restart the shard replays the stored patches."""

import logging
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from common.classes import NUM_CLASSES
from common.codec import pack_cells_votes, unpack_cells_votes
from common.config import MergerConfig
from common.messages import GridPatch, SparsePatch
from common.sparse import FORM as SPARSE_FORM
from common.sparse import expand_patch

logger = logging.getLogger(__name__)

SCHEMA = """
CREATE TABLE IF NOT EXISTS patches (
    patch_id TEXT PRIMARY KEY, tx INTEGER NOT NULL, ty INTEGER NOT NULL,
    vehicle TEXT NOT NULL, traversal TEXT NOT NULL,
    t_first_ns INTEGER NOT NULL, t_last_ns INTEGER NOT NULL,
    cells BLOB NOT NULL, votes BLOB NOT NULL,
    packed_n INTEGER,  -- cells of the packed form in `cells` (votes empty); NULL: raw arrays
    form TEXT  -- NULL: cells (packed or raw); "sparse/1": the payload in `cells`
);
CREATE TABLE IF NOT EXISTS tiles (
    tx INTEGER NOT NULL, ty INTEGER NOT NULL, version INTEGER NOT NULL,
    codec TEXT NOT NULL, data BLOB NOT NULL, PRIMARY KEY (tx, ty)
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
"""


class ShardStore:
    """One SQLite file; not shared between threads without the caller's lock."""

    def __init__(self, path: str | Path, *,
                 synchronous: str = MergerConfig.sqlite_synchronous):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.db = sqlite3.connect(str(self.path), isolation_level=None, check_same_thread=False)
        self.db.execute("PRAGMA journal_mode=WAL")
        self.db.execute(f"PRAGMA synchronous={synchronous}")
        self.db.executescript(SCHEMA)
        columns = {row[1] for row in self.db.execute("PRAGMA table_info(patches)")}
        if "packed_n" not in columns:  # a store from before packed patches
            self.db.execute("ALTER TABLE patches ADD COLUMN packed_n INTEGER")
        if "form" not in columns:  # ... and from before sparse patches
            self.db.execute("ALTER TABLE patches ADD COLUMN form TEXT")

    @classmethod
    def read_only(cls, path: str | Path) -> "ShardStore":
        """An existing store opened for reading only (export, status, viewer of a demo's
        output): nothing written, a shard running on it undisturbed."""
        store = cls.__new__(cls)
        store.path = Path(path)
        if not store.path.is_file():
            raise FileNotFoundError(f"no shard store at {store.path}")
        store.db = sqlite3.connect(f"file:{store.path}?mode=ro", uri=True, isolation_level=None,
                                   check_same_thread=False)
        return store

    def close(self) -> None:
        self.db.close()

    def meta(self, key: str) -> str | None:
        row = self.db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else row[0]

    def check_meta(self, key: str, value: str) -> str | None:
        """Record a setting on first use; return the stored value (differs on a mismatch)."""
        row = self.db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        if row is None:
            self.db.execute("INSERT INTO meta (key, value) VALUES (?, ?)", (key, value))
            return value
        return row[0]

    def save_patches(self, patches: list[GridPatch]) -> None:
        """All of them in one committed transaction, or none (raises sqlite3.Error)."""
        rows = [
            (p.patch_id, int(p.tile[0]), int(p.tile[1]), p.vehicle, p.traversal,
             int(p.t_first_ns), int(p.t_last_ns), *stored_form(p))
            for p in patches
        ]
        with self._transaction():
            self.db.executemany("INSERT OR IGNORE INTO patches (patch_id, tx, ty, vehicle, "
                                "traversal, t_first_ns, t_last_ns, cells, votes, packed_n, form) "
                                "VALUES (?,?,?,?,?,?,?,?,?,?,?)", rows)

    def load_patches(self) -> Iterator[GridPatch]:
        cur = self.db.execute("SELECT patch_id, tx, ty, vehicle, traversal, t_first_ns, "
                              "t_last_ns, cells, votes, packed_n, form FROM patches ORDER BY rowid")
        for pid, tx, ty, vehicle, trav, t0, t1, cells, votes, packed_n, form in cur:
            if packed_n is None and form is None:  # a row from before packed patches
                c = np.frombuffer(cells, dtype="<u4")
                yield GridPatch(patch_id=pid, vehicle=vehicle, tile=(tx, ty), cells=c,
                                votes=_votes_from_blob(votes, len(c)), t_first_ns=t0,
                                t_last_ns=t1, traversal=trav)
                continue
            yield stored_patch(pid, vehicle, (tx, ty), t0, t1, trav, cells, packed_n, form)

    def count_patches(self) -> int:
        return int(self.db.execute("SELECT COUNT(*) FROM patches").fetchone()[0])

    def save_tiles(self, tiles: list[tuple[tuple[int, int], int, str, bytes]]) -> None:
        """[(tile, version, codec, data)] in one transaction."""
        rows = [(t[0], t[1], v, codec, data) for t, v, codec, data in tiles]
        with self._transaction():
            self.db.executemany("INSERT OR REPLACE INTO tiles VALUES (?,?,?,?,?)", rows)

    def load_tiles(self) -> list[tuple[tuple[int, int], int, str, bytes]]:
        cur = self.db.execute("SELECT tx, ty, version, codec, data FROM tiles ORDER BY tx, ty")
        return [((tx, ty), v, codec, bytes(data)) for tx, ty, v, codec, data in cur]

    def _transaction(self):
        return _Transaction(self.db)


def stored_patch(pid: str, vehicle: str, tile: tuple[int, int], t_first_ns: int, t_last_ns: int,
                 traversal: str, payload: bytes, packed_n: int, form: str | None) -> GridPatch:
    """The GridPatch of a stored row (stored_form's inverse): a sparse patch's payload expanded
    as the ingest did, else the packed cells + votes unpacked."""
    if form is not None:
        return expand_patch(SparsePatch(patch_id=pid, vehicle=vehicle, tile=tile,
                                        t_first_ns=t_first_ns, t_last_ns=t_last_ns,
                                        traversal=traversal, data=bytes(payload), form=form))
    cells, votes = unpack_cells_votes(bytes(payload), packed_n, f"stored patch {pid!r}")
    return GridPatch(patch_id=pid, vehicle=vehicle, tile=tile, cells=cells, votes=votes,
                     t_first_ns=t_first_ns, t_last_ns=t_last_ns, traversal=traversal)


def stored_form(p: GridPatch) -> tuple[bytes, bytes, int | None, str | None]:
    """(cells, votes, packed_n, form) of a patch's row: a sparse patch's payload as it came,
    else the packed cells + votes (as they came, or packed here)."""
    if p.sparse is not None:
        return bytes(p.sparse), b"", None, SPARSE_FORM
    packed = p.packed if p.packed is not None else pack_cells_votes(p.cells, p.votes)
    return packed, b"", len(p.cells), None


def _votes_from_blob(blob: bytes, n: int) -> np.ndarray:
    """Rows written before packed patches: uint8 counts when they all fitted, else uint16; the
    length tells which (n * 6 or n * 12 bytes)."""
    dtype = np.uint8 if len(blob) == n * NUM_CLASSES else np.dtype("<u2")
    return np.frombuffer(blob, dtype=dtype).reshape(n, NUM_CLASSES).astype(np.uint16)


class _Transaction:
    def __init__(self, db: sqlite3.Connection):
        self.db = db

    def __enter__(self):
        self.db.execute("BEGIN IMMEDIATE")

    def __exit__(self, exc_type, exc, tb):
        self.db.execute("COMMIT" if exc_type is None else "ROLLBACK")
        return False
