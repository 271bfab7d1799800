"""Where tiles are read from besides a running fleet (services/fleet.py): a demo's output folder,
a folder of shard stores (`*.sqlite`), one store, or a `tiles.npz` the demo fetched; and the
geodetic origin of the world those tiles are in."""

import json
import logging
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from common.errors import ExportError
from common.grid import TileId
from common.messages import Tile

logger = logging.getLogger(__name__)


@dataclass
class StoredMap:
    """Tiles on disk: each tile's newest compressed form, its shard where known, and one summary
    row per shard store read ({path, shard, patches, tiles})."""

    tiles: list[Tile]
    owners: dict[TileId, str] = field(default_factory=dict)
    stores: list[dict] = field(default_factory=list)


def read_folder(path: str | Path) -> StoredMap:
    """A demo's output folder (its shard stores, else run/tiles.npz), a folder of `*.sqlite`
    shard stores, one store, or a tiles.npz."""
    path = Path(path)
    if path.is_file():
        return _read_npz(path) if path.suffix == ".npz" else _read_stores([path])
    if not path.is_dir():
        raise ExportError(f"{path}: no such folder or file")
    stores = sorted(path.glob("*.sqlite")) or sorted(path.glob("run/*.sqlite"))
    if stores:
        return _read_stores(stores)
    for npz in (path / "tiles.npz", path / "run" / "tiles.npz"):
        if npz.is_file():
            return _read_npz(npz)
    raise ExportError(f"{path}: no shard stores (*.sqlite, run/*.sqlite) and no tiles.npz")


def _read_stores(paths: list[Path]) -> StoredMap:
    from services.merger.store import ShardStore

    out = StoredMap(tiles=[])
    for p in paths:
        try:
            store = ShardStore.read_only(p)
        except (OSError, ValueError) as exc:
            raise ExportError(f"cannot open shard store {p}: {exc}") from exc
        try:
            shard = store.meta("shard")  # "k/N"
            ident = f"s{shard.split('/')[0]}" if shard else p.stem
            rows = store.load_tiles()
            out.stores.append({"path": str(p), "shard": ident, "of": shard,
                               "patches": store.count_patches(), "tiles": len(rows)})
        except Exception as exc:  # sqlite3.Error: not a store, or a damaged one
            raise ExportError(f"{p}: not a readable shard store ({exc})") from exc
        finally:
            store.close()
        for tile, version, codec_name, data in rows:
            out.tiles.append(Tile(tile=tuple(tile), version=int(version), codec=codec_name,
                                  data=data))
            out.owners[tuple(tile)] = ident
    return out


def _read_npz(path: Path) -> StoredMap:
    from services.demo.fetch import load_tiles

    try:
        t = load_tiles(path)
    except (OSError, ValueError, KeyError) as exc:
        raise ExportError(f"{path}: not a tiles.npz of roadmap demo ({exc})") from exc
    codec_name = t["codecs"][0] if len(t["codecs"]) == 1 else "contour/2"
    tiles = [Tile(tile=tile, version=int(v), codec=codec_name, data=data)
             for tile, v, data in zip(t["tiles"], t["versions"], t["compressed"], strict=True)]
    return StoredMap(tiles=tiles)


def origin_latlon(cfg, folder: str | Path | None = None) -> tuple[float, float]:
    """The world's geodetic origin: config world.origin_lat_deg/lon_deg, else the folder's
    config.toml, else the world its drive logs name (drives/*/*/log.json)."""
    w = cfg.world
    if w.origin_lat_deg is not None:
        return float(w.origin_lat_deg), float(w.origin_lon_deg)
    if folder is not None:
        root = Path(folder)
        root = root.parent.parent if root.is_file() and root.parent.name == "run" else root
        found = _origin_in_config(root / "config.toml") or _origin_in_logs(root)
        if found:
            return found
    raise ExportError("no geodetic origin: set world.origin_lat_deg and world.origin_lon_deg "
                      "(--set or the config file), or export a demo's output folder (its drive "
                      "logs name their world's origin)")


def _origin_in_config(path: Path) -> tuple[float, float] | None:
    try:
        world = tomllib.loads(path.read_text()).get("world", {})
    except (OSError, tomllib.TOMLDecodeError):
        return None
    lat, lon = world.get("origin_lat_deg"), world.get("origin_lon_deg")
    if isinstance(lat, int | float) and isinstance(lon, int | float):
        return float(lat), float(lon)
    return None


def _origin_in_logs(root: Path) -> tuple[float, float] | None:
    origins = set()
    for log in sorted(root.glob("drives/**/log.json")):
        try:
            world = json.loads(log.read_text())["world"]
            origins.add((float(world["origin_lat"]), float(world["origin_lon"])))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    if len(origins) > 1:
        raise ExportError(f"{root}: its drive logs name different origins {sorted(origins)}: "
                          "set world.origin_lat_deg and world.origin_lon_deg")
    return origins.pop() if origins else None
