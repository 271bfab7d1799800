"""Tiles -> map features in the world's local ENU frame (metres): the contour codec's own shapes
(common.contours.decode_shapes), one feature per shape, each with its class, tile and the tile's
version. Cell (col, row) of tile (tx, ty) has its centre at x = 51.2 tx + 0.1 (col + 0.5),
y = 51.2 ty + 0.1 (row + 0.5); polygon rings run through the centres of the border cells."""

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from common.classes import MARKINGS, Cls
from common.contours import (
    CODEC,
    LEGACY_CODECS,
    RAW_CODEC,
    ShapeKind,
    decode_raw,
    decode_shapes,
    encode_tile,
)
from common.errors import CodecError, ExportError
from common.grid import CELL_M, TileId, tile_origin_m
from common.messages import Tile


@dataclass(frozen=True)
class MapFeature:
    """A polygon (rings_xy_m: outer ring, then holes) or a centre line of thin paint
    (rings_xy_m: [vertices], painted width_m wide), in world metres."""

    cls: Cls
    kind: ShapeKind
    rings_xy_m: list[np.ndarray]
    tile: TileId
    version: int
    width_m: float = 0.0


def tile_features(tile: Tile, classes: Iterable[int] = MARKINGS) -> list[MapFeature]:
    """The shapes of one tile's classes in `classes`, in world metres."""
    wanted = {int(c) for c in classes}
    x0, y0 = tile_origin_m(tile.tile)
    offset = np.array([x0, y0]) + 0.5 * CELL_M
    out = []
    for shape in decode_shapes(_contour_bytes(tile)):
        if shape.cls not in wanted:
            continue
        rings = [offset + ring * CELL_M for ring in shape.rings]
        out.append(MapFeature(Cls(shape.cls), shape.kind, rings, tuple(tile.tile),
                              int(tile.version), shape.width_cells * CELL_M))
    return out


def map_features(tiles: Iterable[Tile], classes: Iterable[int] = MARKINGS) -> list[MapFeature]:
    classes = tuple(classes)
    return [f for t in sorted(tiles, key=lambda t: tuple(t.tile))
            for f in tile_features(t, classes)]


def _contour_bytes(tile: Tile) -> bytes:
    """The tile as contour bytes; a raw/1 tile (the uncompressed map) is traced first."""
    try:
        if tile.codec in (CODEC, *LEGACY_CODECS):
            return tile.data
        if tile.codec == RAW_CODEC:
            return encode_tile(decode_raw(tile.data))
    except CodecError as exc:
        raise ExportError(f"tile {tile.tile}: {exc}") from exc
    raise ExportError(f"tile {tile.tile}: unknown tile codec {tile.codec!r}")


def classes_named(names: Iterable[str]) -> tuple[Cls, ...]:
    """Report names ("lane_line", ...) -> classes; ExportError on an unknown name."""
    by_name = {c.name.lower(): c for c in Cls if c != Cls.NONE}
    try:
        return tuple(by_name[n] for n in names)
    except KeyError as exc:
        raise ExportError(f"unknown class {exc.args[0]!r} (known: {', '.join(by_name)})") from None
