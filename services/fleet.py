"""What any client can ask a running fleet over Zenoh, with no shard count or config: the stats
of every process that serves them (`roadmap/stats/<role>/<id>`), the liveliness tokens
(`roadmap/alive/<role>/<id>`), the tiles the shards list in their stats and the tiles themselves.
Used by `roadmap export`, `roadmap viewer` and `roadmap status`; the callers own the session."""

import logging

from common import codec, keys
from common.bus import ConsolidationMode
from common.errors import CodecError
from common.grid import TileId
from common.messages import Stats, Tile

logger = logging.getLogger(__name__)


def all_stats(session, timeout_s: float, role: str | None = None) -> dict[tuple[str, str], dict]:
    """{(role, id): counters} of every stats queryable that answered (of one role, or all)."""
    out = {}
    replies = session.get(keys.stats_all(role), timeout=timeout_s,
                          consolidation=ConsolidationMode.NONE)
    for reply in replies:
        if reply.ok is None:
            logger.debug("stats: error reply %s", reply.err.payload.to_bytes()[:200])
            continue
        try:
            msg = codec.decode(reply.ok.payload.to_bytes(), expect=Stats)
            out[keys.parse_stats(str(reply.ok.key_expr))] = dict(msg.counters)
        except CodecError as exc:
            logger.warning("stats %s: %s", reply.ok.key_expr, exc)
    return out


def shard_stats(session, timeout_s: float) -> dict[str, dict]:
    """{"s<k>": counters} of every merger shard that answered."""
    return {ident: c for (_, ident), c in all_stats(session, timeout_s, "merger").items()}


def alive(session, timeout_s: float) -> dict[str, list[str]]:
    """{role: sorted ids} of the liveliness tokens visible through the router now."""
    out: dict[str, set[str]] = {}
    for reply in session.liveliness().get(keys.alive_all(), timeout=timeout_s):
        if reply.ok is None:
            continue
        try:
            role, ident = keys.parse_alive(str(reply.ok.key_expr))
        except CodecError:
            continue
        out.setdefault(role, set()).add(ident)
    return {role: sorted(ids) for role, ids in sorted(out.items())}


def tile_list(counters: dict) -> list[TileId]:
    """A shard's counters["tile_list"] ("tx,ty;tx,ty") -> [(tx, ty)]."""
    tiles = []
    for item in str((counters or {}).get("tile_list", "")).split(";"):
        if item.strip():
            tx, ty = item.split(",")
            tiles.append((int(tx), int(ty)))
    return tiles


def tile_owners(stats: dict[str, dict]) -> dict[TileId, str]:
    """{tile: shard id} from the shards' tile lists."""
    return {t: ident for ident, counters in stats.items() for t in tile_list(counters)}


def get_tile(session, tile: TileId, timeout_s: float, since: int | None = None) -> Tile | None:
    """The compressed tile from its owner; None when nobody holds it or it is not newer than
    `since`."""
    for reply in session.get(keys.tile_selector(*tile, since=since), timeout=timeout_s):
        if reply.ok is not None:
            return codec.decode(reply.ok.payload.to_bytes(), expect=Tile)
    return None


def fleet_tiles(session, timeout_s: float) -> tuple[list[Tile], dict[TileId, str]]:
    """Every tile the shards list, compressed, and each tile's shard."""
    owners = tile_owners(shard_stats(session, timeout_s))
    tiles = []
    for tile in sorted(owners):
        msg = get_tile(session, tile, timeout_s)
        if msg is None:
            logger.warning("tile %s: listed by %s but not served", tile, owners[tile])
            continue
        tiles.append(msg)
    return tiles, owners
