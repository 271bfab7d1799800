"""A real ingest shard stand-in for the vehicle tests: acks IngestBatches and SparseBatches
after a durable SQLite write.

`python -m tests.vehicle.ingest_peer --connect EP --db PATH [--shard 0] [--delay S]` declares
`roadmap/ingest/s<shard>` (complete) and the liveliness token `roadmap/alive/merger/s<shard>`;
each patch id is applied (inserted) once, later copies are acked as duplicate."""

import argparse
import sqlite3
import time

from common import codec, keys
from common.bus import FifoChannel, ZError, open_session, stop_event
from common.config import BusConfig
from common.messages import ACCEPTED, DUPLICATE, IngestAck
from services.merger.durable import grid_batch


def serve(connect: str, db_path: str, shard: int, delay_s: float) -> None:
    db = sqlite3.connect(db_path, isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("CREATE TABLE IF NOT EXISTS applied (patch_id TEXT PRIMARY KEY, cells INTEGER)")
    db.execute("CREATE TABLE IF NOT EXISTS received (patch_id TEXT, status TEXT)")
    stop = stop_event()
    with open_session(BusConfig(connect=[connect])) as session:
        q = session.declare_queryable(keys.ingest(shard), FifoChannel(64), complete=True)
        token = session.liveliness().declare_token(keys.alive("merger", f"s{shard}"))
        while not stop.is_set():
            try:
                query = q.try_recv()
            except ZError:
                break
            if query is None:
                time.sleep(0.01)
                continue
            with query:
                batch = grid_batch(codec.decode(query.payload.to_bytes()))
                time.sleep(delay_s)
                results = {}
                db.execute("BEGIN IMMEDIATE")
                for p in batch.patches:
                    cur = db.execute(
                        "INSERT OR IGNORE INTO applied VALUES (?, ?)", (p.patch_id, len(p.cells))
                    )
                    results[p.patch_id] = ACCEPTED if cur.rowcount == 1 else DUPLICATE
                    db.execute(
                        "INSERT INTO received VALUES (?, ?)", (p.patch_id, results[p.patch_id])
                    )
                db.execute("COMMIT")
                query.reply(query.key_expr, codec.encode(IngestAck(results=results)))
        token.undeclare()
        q.undeclare()


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--connect", required=True)
    ap.add_argument("--db", required=True)
    ap.add_argument("--shard", type=int, default=0)
    ap.add_argument("--delay", type=float, default=0.0)
    a = ap.parse_args()
    serve(a.connect, a.db, a.shard, a.delay)
