"""Map features -> a GeoJSON FeatureCollection (RFC 7946): WGS84 [lon, lat] positions about the
world's origin (common.geometry.local_m_to_latlon, the projection the world's loader used, so a
position converts back to the same metres). Thin paint is a LineString with its painted width;
areas are Polygons (exterior ring counter-clockwise, holes clockwise, rings closed). Every
feature carries its class, the tile it came from and that tile's version."""

import numpy as np

from common.classes import Cls
from common.contours import ShapeKind
from common.geometry import local_m_to_latlon
from common.grid import CELL_M
from services.export.features import MapFeature

DECIMALS = 8  # degrees: ~1 mm


def to_geojson(features: list[MapFeature], origin_latlon: tuple[float, float], *,
               name: str = "roadmap") -> dict:
    lat0, lon0 = origin_latlon
    out = [_feature(i, f, lat0, lon0) for i, f in enumerate(features)]
    out = [f for f in out if f is not None]
    doc = {"type": "FeatureCollection", "name": name, "features": out,
           "roadmap": {"origin_lat_deg": lat0, "origin_lon_deg": lon0,
                       "frame": "local ENU metres about the origin, equirectangular "
                                "(common.geometry.latlon_to_local_m)",
                       "cell_m": CELL_M,
                       "tiles": sorted({tuple(f.tile) for f in features})}}
    if out:
        doc["bbox"] = _bbox(out)
    return doc


def _feature(i: int, f: MapFeature, lat0: float, lon0: float) -> dict | None:
    props = {"class": Cls(f.cls).name.lower(), "class_id": int(f.cls),
             "tile": [int(f.tile[0]), int(f.tile[1])], "tile_version": int(f.version),
             "shape": f.kind.value}
    if f.kind == ShapeKind.LINE:
        line = _dedupe(f.rings_xy_m[0])
        if len(line) < 2:
            return None
        geometry = {"type": "LineString", "coordinates": _positions(line, lat0, lon0)}
        props["width_m"] = round(float(f.width_m), 3)
    else:
        rings = [_ring(r, outer=k == 0) for k, r in enumerate(f.rings_xy_m)]
        geometry = {"type": "Polygon",
                    "coordinates": [_positions(r, lat0, lon0) for r in rings]}
    return {"type": "Feature", "id": i, "geometry": geometry, "properties": props}


def _positions(xy: np.ndarray, lat0: float, lon0: float) -> list[list[float]]:
    lat, lon = local_m_to_latlon(xy[:, 0], xy[:, 1], lat0, lon0)
    return [[round(float(a), DECIMALS), round(float(b), DECIMALS)] for a, b in zip(lon, lat,
                                                                                  strict=True)]


def _dedupe(xy: np.ndarray) -> np.ndarray:
    keep = np.ones(len(xy), dtype=bool)
    keep[1:] = np.any(np.abs(np.diff(xy, axis=0)) > 1e-9, axis=1)
    return xy[keep]


def _ring(xy: np.ndarray, *, outer: bool) -> np.ndarray:
    """A closed linear ring of >= 4 positions, oriented by the right-hand rule. A ring that
    encloses no area (one or two cells, or cells in a row) becomes the outline of those cells."""
    xy = _dedupe(np.asarray(xy, dtype=float))
    if len(xy) > 1 and np.allclose(xy[0], xy[-1]):
        xy = xy[:-1]
    if len(xy) < 3 or abs(_signed_area(xy)) < 1e-9:
        lo, hi = xy.min(axis=0) - CELL_M / 2, xy.max(axis=0) + CELL_M / 2
        xy = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    if (_signed_area(xy) > 0) != outer:
        xy = xy[::-1]
    return np.concatenate([xy, xy[:1]])


def _signed_area(xy: np.ndarray) -> float:
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _bbox(features: list[dict]) -> list[float]:
    pts = []
    for f in features:
        c = f["geometry"]["coordinates"]
        pts += c if f["geometry"]["type"] == "LineString" else [p for ring in c for p in ring]
    a = np.array(pts)
    return [float(a[:, 0].min()), float(a[:, 1].min()), float(a[:, 0].max()),
            float(a[:, 1].max())]
