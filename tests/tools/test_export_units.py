"""Export on synthetic tiles, no processes: the codec's shapes in world metres, the Lanelet2
lines (a dashed line cut by a tile border chained into one dashed linestring, a solid one joined
again, widths to thin / thick), stop lines, crossings; GeoJSON rings; the CLI's errors."""

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from common.classes import Cls
from common.contours import ShapeKind, decode_shapes, decode_tile, encode_tile
from common.errors import ExportError
from common.grid import TILE_CELLS
from common.messages import Tile
from services.export.command import export_map
from services.export.features import map_features
from services.export.geojson import to_geojson
from services.export.lines import strip_centreline
from tests.conftest import roadmap

ORIGIN = (49.0, 8.4)


def _world_raster() -> np.ndarray:
    """Two tiles side by side (x 0-102.4 m, y 0-51.2 m), 0.1 m cells, row = north."""
    r = np.zeros((TILE_CELLS, 2 * TILE_CELLS), np.uint8)
    r[200:340, :] = Cls.ROAD
    for x0 in range(42, 900, 90):  # dashes 3 m long, 6 m apart, one across x = 51.2 m
        r[250, x0 : x0 + 30] = Cls.LANE_LINE  # 1 cell: 0.1 m wide (thin)
    r[300:303, 50:990] = Cls.LANE_LINE  # solid, 0.3 m wide (thick), across the border
    r[205:245, 700:703] = Cls.STOP_LINE  # 4 m long, 0.3 m wide
    for k in range(6):  # a crossing: stripes 0.5 m wide, 3 m long (along the road), 0.5 m gaps
        r[210 + 10 * k : 215 + 10 * k, 300:330] = Cls.CROSSWALK
    return r


def _tiles(raster: np.ndarray, versions=(4, 7)) -> list[Tile]:
    return [Tile(tile=(k, 0), version=v, codec="contour/2",
                 data=encode_tile(np.ascontiguousarray(raster[:, k * 512 : (k + 1) * 512])))
            for k, v in enumerate(versions)]


def test_shapes_are_the_tiles_cells_in_world_metres():
    tiles = _tiles(_world_raster())
    features = map_features(tiles)
    assert {f.tile: f.version for f in features} == {(0, 0): 4, (1, 0): 7}
    solid = [f for f in features if f.kind == ShapeKind.LINE and f.cls == Cls.LANE_LINE
             and f.width_m > 0.25]
    assert len(solid) == 2  # cut by the tile border
    for f in solid:
        assert np.allclose(f.rings_xy_m[0][:, 1], 30.15, atol=0.06)  # rows 300-302: y 30.0-30.3
        assert f.width_m == pytest.approx(0.3, abs=0.06)
    # every line's cells, drawn back, are the decoded tile's cells
    for t in tiles:
        labels = decode_tile(t.data)
        shapes = decode_shapes(t.data)
        assert {s.cls for s in shapes} == set(np.unique(labels)) - {0}


def _ways(osm_text: str) -> list[dict]:
    root = ET.fromstring(osm_text)
    nodes = {n.get("id"): (float(n.get("lat")), float(n.get("lon"))) for n in root.iter("node")}
    out = []
    for w in root.iter("way"):
        tags = {t.get("k"): t.get("v") for t in w.findall("tag")}
        tags["_nodes"] = [nodes[nd.get("ref")] for nd in w.findall("nd")]
        out.append(tags)
    return out


def test_lanelet2_chains_dashes_joins_cut_lines_and_tags_widths():
    ways = _ways(export_map(_tiles(_world_raster()), ORIGIN, "lanelet2"))
    lanes = [w for w in ways if w["type"] in ("line_thin", "line_thick")]
    by_kind = sorted((w["type"], w["subtype"]) for w in lanes)
    assert by_kind == [("line_thick", "solid"), ("line_thin", "dashed")], by_kind
    dashed = next(w for w in lanes if w["subtype"] == "dashed")
    assert dashed["roadmap:tile_versions"] == "0,0:4;1,0:7"  # the chain spans both tiles
    lon = [p[1] for p in dashed["_nodes"]]
    span_m = (max(lon) - min(lon)) * np.pi / 180 * 6378137 * np.cos(np.radians(49.0))
    assert span_m == pytest.approx(84.0, abs=1.0)  # the first dash's start to the last's end
    thick = next(w for w in lanes if w["subtype"] == "solid")
    assert float(thick["width"]) == pytest.approx(0.3, abs=0.06)
    assert float(dashed["width"]) < 0.2
    (stop,) = [w for w in ways if w["type"] == "stop_line"]
    assert len(stop["_nodes"]) >= 2
    zebra = [w for w in ways if w["type"] == "zebra_marking"]
    assert len(zebra) == 2
    root = ET.fromstring(export_map(_tiles(_world_raster()), ORIGIN, "lanelet2"))
    (rel,) = root.iter("relation")
    assert {t.get("k"): t.get("v") for t in rel.findall("tag")}["subtype"] == "crosswalk"
    # the crosswalk lanelet's left bound lies left of the direction both bounds run
    nodes = {n.get("id"): (float(n.get("lon")), float(n.get("lat"))) for n in root.iter("node")}
    bounds = {}
    for m in rel.findall("member"):
        way = next(w for w in root.iter("way") if w.get("id") == m.get("ref"))
        bounds[m.get("role")] = np.array([nodes[nd.get("ref")] for nd in way.findall("nd")])
    direction = bounds["left"][-1] - bounds["left"][0]
    assert np.dot(direction, bounds["right"][-1] - bounds["right"][0]) > 0
    side = bounds["left"].mean(axis=0) - bounds["right"].mean(axis=0)
    assert direction[0] * side[1] - direction[1] * side[0] > 0  # left: counter-clockwise side


def test_crossing_edges_run_across_the_stripes_at_their_ends():
    ways = _ways(export_map(_tiles(_world_raster()), ORIGIN, "lanelet2"))
    lat0, lon0 = ORIGIN
    for w in (w for w in ways if w["type"] == "zebra_marking"):
        (a_lat, a_lon), (b_lat, b_lon) = w["_nodes"]
        xa = (a_lon - lon0) * np.pi / 180 * 6378137 * np.cos(np.radians(lat0))
        xb = (b_lon - lon0) * np.pi / 180 * 6378137 * np.cos(np.radians(lat0))
        assert xa == pytest.approx(xb, abs=0.05)  # the walking direction is north here
        assert min(abs(xa - 30.0), abs(xa - 33.0)) < 0.15  # stripes span x 30.0-33.0 m


def test_geojson_rings_are_closed_and_oriented():
    raster = _world_raster()
    raster[100:104, 100:104] = Cls.GROUND_SIGN  # a 4-cell square: a polygon
    raster[120, 150] = Cls.GROUND_SIGN  # one cell: a ring with no area -> the cell's outline
    doc = to_geojson(map_features(_tiles(raster)), ORIGIN)
    polys = [f for f in doc["features"] if f["geometry"]["type"] == "Polygon"]
    assert len(polys) >= 2
    for f in polys:
        for k, ring in enumerate(f["geometry"]["coordinates"]):
            a = np.asarray(ring)
            area = 0.5 * np.sum(a[:-1, 0] * a[1:, 1] - a[1:, 0] * a[:-1, 1])
            assert ring[0] == ring[-1] and len(ring) >= 4 and (area > 0) == (k == 0)


def test_strip_centreline_of_a_bent_strip():
    # an L-shaped strip 0.2 m wide: the centre line follows the bend
    outline = np.array([[0, 0], [10, 0], [10, 10], [9.8, 10], [9.8, 0.2], [0, 0.2]], float)
    centre, width = strip_centreline(outline)
    assert width == pytest.approx(0.2, abs=0.05)
    assert np.hypot(*(centre[0] - [0, 0.1])) < 0.2 and np.hypot(*(centre[-1] - [9.9, 10])) < 0.2


def test_export_errors_are_one_line(tmp_path):
    with pytest.raises(ExportError):
        export_map([], ORIGIN, "geojson")
    res = roadmap("export", "--format", "geojson", "--from", tmp_path, "--out", tmp_path / "x")
    assert res.returncode == 1 and "no shard stores" in res.stderr
    assert res.stderr.strip().count("\n") == 0


def test_export_without_an_origin_says_how_to_give_one(tmp_path):
    np.savez(tmp_path / "tiles.npz", tiles=np.zeros((1, 2), np.int64),
             versions=np.ones(1, np.int64), raw_versions=np.ones(1, np.int64),
             raw=np.zeros((1, 512, 512), np.uint8),
             blob=np.frombuffer(encode_tile(_world_raster()[:, :512].copy()), np.uint8),
             offsets=np.array([0, len(encode_tile(_world_raster()[:, :512].copy()))]),
             codecs=np.array(json.dumps(["contour/2"])))
    res = roadmap("export", "--format", "geojson", "--from", tmp_path / "tiles.npz",
                  "--out", tmp_path / "x.geojson")
    assert res.returncode == 1 and "world.origin_lat_deg" in res.stderr, res.stderr
    res = roadmap("export", "--format", "lanelet2", "--from", tmp_path / "tiles.npz",
                  "--set", "world.origin_lat_deg=49.0", "--set", "world.origin_lon_deg=8.4",
                  "--out", tmp_path / "x.osm")
    assert res.returncode == 0, res.stderr
    assert ET.parse(tmp_path / "x.osm").getroot().tag == "osm"


def test_status_and_export_say_when_no_router_answers(tmp_path):
    from common.bus import free_tcp_port

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"  # nobody listens here
    for args in (("status", "--connect", endpoint),
                 ("export", "--format", "geojson", "--connect", endpoint, "--out",
                  tmp_path / "x.geojson")):
        res = roadmap(*args, timeout=30)
        assert res.returncode == 1 and "no Zenoh router answers" in res.stderr, res.stderr
