"""The Zenoh key space (DESIGN.md: Key space): every key is built and parsed here and nowhere else.

Tile routing: a merger shard declares one queryable with complete=True on
`roadmap/tile/<tx>/<ty>` for every tile it holds data for (declared when a tile gets its first
patch, and on start-up for every stored tile). A tile query therefore reaches only its owner,
never every shard, and a `get` on a tile nobody holds answers with no reply at once. The routing
state grows with the tiles a shard holds, not with the number of shards. Ingest goes to the shard
by name (`roadmap/ingest/s<k>`): the vehicle computes the owner with common.grid.owner_of_tile.

Region routing (grid.routing = "region": the PostgreSQL workers, services/merger/worker.py):
ingest goes to `roadmap/region/<rx>/<ry>/ingest`, the region computed from the tile
(common.grid.region_of_tile), so a vehicle needs no shard count. The worker holding a region's
lease declares that key complete (one queryable per held region), and each worker declares the
non-complete fallback `roadmap/region/*/*/ingest`: Zenoh's BEST_MATCHING routes a query to the
complete holder when there is one (verified on 1.10.2) and only otherwise to every fallback,
where the worker that rendezvous hashing over the live workers picks claims the unheld region
and the others drop the query. Tiles keep their plain key `roadmap/tile/<tx>/<ty>` (the region
is a pure function of it): the holder declares one complete queryable per tile it holds, and
read-only tile servers (services/merger/tileserver.py) declare `roadmap/tile/*/*` complete and
answer from the stored tiles; a get still reaches ONE queryable (the holder's exact key wins),
never every worker, and the tiles stay readable while a region's writer is being replaced.

The read path that scales: a get with the default target reaches one queryable, and Zenoh picks
the same tile server every time, so a second server on `roadmap/tile/*/*` is only a standby.
Each tile server therefore also declares its own `roadmap/tileserver/<id>/tile/*/*` (complete),
and the localizer's tile client (services/localizer/tiles.py) spreads its reads itself: it
follows the tile servers' liveliness tokens `roadmap/alive/tileserver/<id>`, sends each tile
query to the server that rendezvous hashing over (client, tile) picks, and falls back to the
next server, then to the plain `roadmap/tile/<tx>/<ty>`, when none is alive or the chosen one
gives no reply. On its own key a server answers a tile it does not have (or not newer than
`?since=`) with a delete reply, so "no such tile" and "no answer" differ.

Liveliness tokens `roadmap/alive/<role>/<id>`: merger (s<k>), vehicle and localizer (their
vehicle id) and viewer; `roadmap status` reads them all with `alive_all()` and every stats
queryable with `stats_all()`, no shard count needed."""

from common.errors import CodecError

PREFIX = "roadmap"


def ingest(shard: int) -> str:
    return f"{PREFIX}/ingest/s{shard}"


def region_ingest(rx: int, ry: int) -> str:
    return f"{PREFIX}/region/{rx}/{ry}/ingest"


REGION_INGEST_ALL = f"{PREFIX}/region/*/*/ingest"


def parse_region_ingest(key: str) -> tuple[int, int]:
    parts = str(key).split("/")
    if len(parts) != 5 or parts[:2] != [PREFIX, "region"] or parts[4] != "ingest":
        raise CodecError(f"expected key {PREFIX}/region/<rx>/<ry>/ingest, got {key!r}")
    try:
        return int(parts[2]), int(parts[3])
    except ValueError as exc:
        raise CodecError(f"region key needs integer chunks, got {key!r}") from exc


TILE_ALL = f"{PREFIX}/tile/*/*"


def tile(tx: int, ty: int) -> str:
    return f"{PREFIX}/tile/{tx}/{ty}"


def tileserver_tile(server: str, tx: int, ty: int) -> str:
    """A tile on one tile server's own key: `roadmap/tileserver/<id>/tile/<tx>/<ty>`."""
    return f"{PREFIX}/tileserver/{server}/tile/{tx}/{ty}"


def tileserver_tile_all(server: str) -> str:
    return f"{PREFIX}/tileserver/{server}/tile/*/*"


def parse_tileserver_tile(key: str) -> tuple[str, tuple[int, int]]:
    """`roadmap/tileserver/<id>/tile/<tx>/<ty>` -> (id, (tx, ty))."""
    parts = str(key).split("/")
    if len(parts) != 6 or parts[:2] != [PREFIX, "tileserver"] or parts[3] != "tile":
        raise CodecError(f"expected key {PREFIX}/tileserver/<id>/tile/<tx>/<ty>, got {key!r}")
    try:
        return parts[2], (int(parts[4]), int(parts[5]))
    except ValueError as exc:
        raise CodecError(f"tile key needs integer chunks, got {key!r}") from exc


def tile_update(tx: int, ty: int) -> str:
    return f"{PREFIX}/tile-update/{tx}/{ty}"


TILE_UPDATE_ALL = f"{PREFIX}/tile-update/*/*"


def tile_params(since: int | None = None, codec: str | None = None) -> str:
    """A tile query's parameters: `?since=<v>` (no sample when the tile is not newer than v)
    and `?codec=raw` (the raw/1 copy), `;`-joined; "" for neither."""
    params = [] if since is None else [f"since={int(since)}"]
    if codec is not None:
        params.append(f"codec={codec}")
    return "?" + ";".join(params) if params else ""


def tile_selector(tx: int, ty: int, since: int | None = None) -> str:
    """A tile query's selector: `roadmap/tile/<tx>/<ty>`, with `?since=<v>`."""
    return tile(tx, ty) + tile_params(since=since)


def pose(vehicle: str) -> str:
    return f"{PREFIX}/pose/{vehicle}"


POSE_ALL = f"{PREFIX}/pose/*"


def stats(role: str, ident: str) -> str:
    return f"{PREFIX}/stats/{role}/{ident}"


def stats_all(role: str | None = None) -> str:
    """Every stats queryable of a role (`roadmap/stats/<role>/*`), or of every role."""
    return f"{PREFIX}/stats/{role}/*" if role else f"{PREFIX}/stats/*/*"


def alive(role: str, ident: str) -> str:
    return f"{PREFIX}/alive/{role}/{ident}"


def alive_all(role: str | None = None) -> str:
    """Every liveliness token of a role (`roadmap/alive/<role>/*`), or of every role."""
    return f"{PREFIX}/alive/{role}/*" if role else f"{PREFIX}/alive/*/*"


def _chunks(key: str, head: str, n: int) -> list[str]:
    parts = str(key).split("/")
    if len(parts) != n + 2 or parts[0] != PREFIX or parts[1] != head:
        raise CodecError(f"expected key {PREFIX}/{head}/ + {n} chunks, got {key!r}")
    return parts[2:]


def parse_tile(key: str) -> tuple[int, int]:
    """`roadmap/tile/<tx>/<ty>` or `roadmap/tile-update/<tx>/<ty>` -> (tx, ty)."""
    head = str(key).split("/")[1] if "/" in str(key) else ""
    tx, ty = _chunks(key, head if head in ("tile", "tile-update") else "tile", 2)
    try:
        return int(tx), int(ty)
    except ValueError as exc:
        raise CodecError(f"tile key needs integer chunks, got {key!r}") from exc


def parse_ingest(key: str) -> int:
    (chunk,) = _chunks(key, "ingest", 1)
    if not chunk.startswith("s") or not chunk[1:].isdigit():
        raise CodecError(f"ingest key needs s<shard>, got {key!r}")
    return int(chunk[1:])


def parse_alive(key: str) -> tuple[str, str]:
    role, ident = _chunks(key, "alive", 2)
    return role, ident


def parse_stats(key: str) -> tuple[str, str]:
    role, ident = _chunks(key, "stats", 2)
    return role, ident


def parse_pose(key: str) -> str:
    (vehicle,) = _chunks(key, "pose", 1)
    return vehicle
