"""`roadmap export --format geojson|lanelet2 --out FILE [--from DIR | --connect EP]`: the map in
WGS84, from a running fleet (every tile the shards list) or from disk (a demo's output folder,
shard stores, a tiles.npz)."""

import json
import logging
import sys
from pathlib import Path

from common.classes import MARKINGS, Cls
from common.errors import ExportError
from common.messages import Tile
from services.export.features import classes_named, map_features
from services.export.geojson import to_geojson
from services.export.lanelet2 import to_osm
from services.export.sources import origin_latlon, read_folder

logger = logging.getLogger(__name__)

CONNECT_TIMEOUT_S = 5.0  # no router within this: a one-line error, not a wait

FORMATS = ("geojson", "lanelet2")


def export_map(tiles: list[Tile], origin_latlon: tuple[float, float], fmt: str, *,
               classes=MARKINGS, name: str = "roadmap") -> str:
    """Tiles -> the text of a GeoJSON FeatureCollection or a Lanelet2 OSM map."""
    if fmt not in FORMATS:
        raise ExportError(f"unknown export format {fmt!r} ({', '.join(FORMATS)})")
    if not tiles:
        raise ExportError("no tiles to export")
    features = map_features(tiles, classes)
    if fmt == "geojson":
        return json.dumps(to_geojson(features, origin_latlon, name=name), separators=(",", ":"))
    return to_osm(features, origin_latlon)


def load_tiles(args, cfg) -> tuple[list[Tile], str]:
    """The tiles to export and where they came from (a folder, or the router's endpoint)."""
    if args.from_dir:
        if args.connect:
            raise ExportError("give --from DIR or --connect ENDPOINT, not both")
        return read_folder(args.from_dir).tiles, str(args.from_dir)
    from common.bus import open_session
    from services.fleet import fleet_tiles

    with open_session(cfg.bus, connect_timeout_s=CONNECT_TIMEOUT_S) as session:
        tiles, _ = fleet_tiles(session, cfg.bus.query_timeout_s)
    return tiles, ",".join(cfg.bus.connect)


def export_command(args, cfg) -> int:
    tiles, source = load_tiles(args, cfg)
    origin = origin_latlon(cfg, args.from_dir)
    classes = classes_named(args.classes.split(",")) if args.classes else MARKINGS
    if args.road:
        classes = (Cls.ROAD, *classes)
    text = export_map(tiles, origin, args.format, classes=classes, name=Path(args.out).stem)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    sys.stdout.write(f"{out}: {args.format}, {len(tiles)} tiles from {source}, origin "
                     f"{origin[0]:.7f}, {origin[1]:.7f}\n")
    return 0
