"""Queries the demo needs (shard stats, every tile compressed and raw), run in a child process.

The demo process supervises children with fork+exec and must never hold a Zenoh session while
it forks (ZENOH.md P2), so its queries run here: `python -m services.demo.fetch --connect EP
stats --shards K` prints the shards' counters as JSON; `... tiles --shards K --out FILE.npz`
saves every tile (compressed bytes, raw labels, versions) to one npz (no pickle)."""

import argparse
import json
import logging
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np

from common import codec, keys
from common.errors import CodecError, TransportError
from common.grid import TILE_CELLS
from common.messages import Stats, Tile

logger = logging.getLogger(__name__)

RAW_SELECTOR = "?codec=raw"


# -- inside the child: pure query helpers over an open session -----------------------------------


def query_one(session, selector: str, timeout_s: float):
    """Payload bytes of the first ok reply, or None when nobody answered."""
    for reply in session.get(selector, timeout=timeout_s):
        if reply.ok is not None:
            return reply.ok.payload.to_bytes()
        logger.debug("%s: error reply %s", selector, reply.err.payload.to_bytes()[:200])
    return None


def shard_stats(session, shards: int, timeout_s: float) -> dict[str, dict]:
    """{"s<i>": counters or None} for every shard."""
    out = {}
    for i in range(shards):
        data = query_one(session, keys.stats("merger", f"s{i}"), timeout_s)
        out[f"s{i}"] = None if data is None else dict(codec.decode(data, expect=Stats).counters)
    return out


def parse_tile_list(text: str) -> list[tuple[int, int]]:
    """The merger's counters["tile_list"]: "tx,ty;tx,ty"."""
    tiles = []
    for item in str(text or "").split(";"):
        if item.strip():
            tx, ty = item.split(",")
            tiles.append((int(tx), int(ty)))
    return tiles


def list_tiles(session, stats: dict[str, dict], timeout_s: float) -> list[tuple[int, int]]:
    tiles = set()
    for counters in stats.values():
        tiles.update(parse_tile_list((counters or {}).get("tile_list", "")))
    if not tiles:  # no listing in the stats: ask every tile queryable (demo scale only)
        for reply in session.get(keys.tile("*", "*"), timeout=timeout_s):
            if reply.ok is not None:
                tiles.add(keys.parse_tile(str(reply.ok.key_expr)))
    return sorted(tiles)


def fetch_tile(session, tile: tuple[int, int], timeout_s: float, tries: int = 3):
    """(compressed Tile, raw labels (512, 512) uint8) of one tile."""
    for attempt in range(tries):
        comp = query_one(session, keys.tile(*tile), timeout_s)
        raw = query_one(session, keys.tile(*tile) + RAW_SELECTOR, timeout_s)
        if comp is not None and raw is not None:
            break
        time.sleep(0.2 * (attempt + 1))
    else:
        raise TransportError(f"tile {tile}: no reply from its shard")
    comp_tile = codec.decode(comp, expect=Tile)
    raw_tile = codec.decode(raw, expect=Tile)
    try:
        labels = np.frombuffer(zlib.decompress(raw_tile.data), np.uint8)
    except zlib.error as exc:
        raise CodecError(f"tile {tile}: raw/1 data is not zlib ({exc})") from exc
    if labels.size != TILE_CELLS * TILE_CELLS:
        raise CodecError(f"tile {tile}: raw/1 holds {labels.size} cells, expected 512x512")
    return comp_tile, raw_tile, labels.reshape(TILE_CELLS, TILE_CELLS)


def save_tiles(path: Path, fetched: list) -> None:
    """npz: tiles (N,2), versions (N,), raw (N,512,512), blob + offsets of the compressed data."""
    blobs = [t.data for t, _, _ in fetched]
    offsets = np.cumsum([0] + [len(b) for b in blobs]).astype(np.int64)
    np.savez(
        path,
        tiles=np.array([t.tile for t, _, _ in fetched], np.int64).reshape(-1, 2),
        versions=np.array([t.version for t, _, _ in fetched], np.int64),
        raw_versions=np.array([r.version for _, r, _ in fetched], np.int64),
        raw=np.array([lab for _, _, lab in fetched], np.uint8).reshape(-1, TILE_CELLS, TILE_CELLS),
        blob=np.frombuffer(b"".join(blobs), np.uint8),
        offsets=offsets,
        codecs=np.array(json.dumps(sorted({t.codec for t, _, _ in fetched}))),
    )


def load_tiles(path: Path) -> dict:
    """Inverse of save_tiles: {tiles: [(tx, ty)], compressed: [bytes], raw: array, versions}."""
    with np.load(path) as z:
        blob, offsets = z["blob"].tobytes(), z["offsets"]
        return {
            "tiles": [tuple(int(v) for v in t) for t in z["tiles"]],
            "compressed": [blob[offsets[i] : offsets[i + 1]] for i in range(len(offsets) - 1)],
            "raw": z["raw"],
            "versions": z["versions"].tolist(),
            "codecs": json.loads(str(z["codecs"])),
        }


def _main(argv: list[str] | None = None) -> int:
    from common.bus import open_session
    from common.config import load_config
    from common.log import configure_logging

    p = argparse.ArgumentParser(prog="python -m services.demo.fetch")
    p.add_argument("--connect", required=True)
    p.add_argument("--timeout", type=float, default=5.0)
    p.add_argument("what", choices=["stats", "tiles"])
    p.add_argument("--shards", type=int, required=True)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    configure_logging("WARNING")
    # the environment's bus settings (a secure fleet's ROADMAP_BUS__TLS_DIR) with this router;
    # stats as a monitor, tiles as a localizer: the roles the ACL gives those keys
    bus = load_config(sets=[f'bus.connect=["{args.connect}"]']).bus
    with open_session(bus, "monitor") as session:
        time.sleep(0.2)  # let the router's routing table reach this new session
        stats = shard_stats(session, args.shards, args.timeout)
    if args.what == "tiles":
        with open_session(bus, "localizer") as session:
            time.sleep(0.2)
            tiles = list_tiles(session, stats, args.timeout)
            save_tiles(Path(args.out), [fetch_tile(session, t, args.timeout) for t in tiles])
    sys.stdout.write(json.dumps(stats) + "\n")
    return 0


# -- in the demo process: run the child ----------------------------------------------------------


def run_fetch(endpoint: str, what: str, shards: int, out: Path | None = None,
              timeout_s: float = 120.0) -> dict:
    """Run this module in a child process; returns the shards' stats."""
    argv = [sys.executable, "-m", "services.demo.fetch", "--connect", endpoint, what,
            "--shards", str(shards)] + (["--out", str(out)] if out else [])
    try:
        res = subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s,
                             stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired as exc:
        raise TransportError(f"fetching {what} from the shards timed out "
                             f"({timeout_s:.0f} s)") from exc
    if res.returncode != 0:
        raise TransportError(f"fetching {what} from the shards failed:\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


if __name__ == "__main__":
    sys.exit(_main())
