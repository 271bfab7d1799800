"""`roadmap export` on the Karlsruhe demo's output: the GeoJSON passes a GeoJSON schema and
RFC 7946's rules, each feature names its class, tile and the tile's version; the Lanelet2 OSM
loads with the `lanelet2` package, its linestrings counted by type; and the exported lines lie on
the source HD map's lines (within 0.2 m), checked both in our frame and in Lanelet2's own."""

import json
import xml.etree.ElementTree as ET
from collections import Counter

import numpy as np
import pytest

from common.classes import MARKINGS, NAMES
from common.geometry import latlon_to_local_m
from services.export.features import map_features
from services.export.sources import read_folder
from services.sim.osm import read_osm
from tests.tools.conftest import roadmap_ok

pytestmark = [pytest.mark.integration, pytest.mark.shared_data]

LANE_TYPES = ("line_thin", "line_thick")
STEP_M = 0.25  # exported lines are checked at points this far apart along them


@pytest.fixture(scope="module")
def exported(karlsruhe_demo, tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    roadmap_ok("export", "--format", "geojson", "--from", karlsruhe_demo.out,
               "--out", d / "map.geojson")
    roadmap_ok("export", "--format", "lanelet2", "--from", karlsruhe_demo.out,
               "--out", d / "map.osm")
    return d, json.loads((d / "map.geojson").read_text())


def _densified(xy: np.ndarray, step_m: float = STEP_M) -> np.ndarray:
    out = [xy[:1]]
    for a, b in zip(xy[:-1], xy[1:], strict=True):
        n = max(int(np.ceil(np.linalg.norm(b - a) / step_m)), 1)
        out.append(a + (b - a) * (np.arange(1, n + 1)[:, None] / n))
    return np.concatenate(out)


def _distances(points: np.ndarray, lines: list[np.ndarray]) -> np.ndarray:
    """Distance of each point to the nearest segment of any of the polylines."""
    a = np.concatenate([p[:-1] for p in lines])
    b = np.concatenate([p[1:] for p in lines])
    best = np.full(len(points), np.inf)
    for k in range(0, len(points), 512):
        q = points[k : k + 512, None, :]
        ab = b - a
        t = np.clip(((q - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0.0, 1.0)
        d = np.linalg.norm(q - (a + t[..., None] * ab), axis=-1).min(axis=1)
        best[k : k + 512] = d
    return best


def _source_lines(osm_path, origin, types) -> list[np.ndarray]:
    """The HD map's ways of `types` in metres about `origin` (the world loader's projection)."""
    osm = read_osm(osm_path)
    out = []
    for refs, tags in osm.ways.values():
        if tags.get("type") in types:
            ll = np.array([osm.nodes[r] for r in refs if r in osm.nodes])
            if len(ll) >= 2:
                out.append(np.stack(latlon_to_local_m(ll[:, 0], ll[:, 1], *origin), axis=1))
    return out


def _origin(doc: dict) -> tuple[float, float]:
    return doc["roadmap"]["origin_lat_deg"], doc["roadmap"]["origin_lon_deg"]


def _to_m(positions, origin) -> np.ndarray:
    ll = np.asarray(positions, float)
    return np.stack(latlon_to_local_m(ll[:, 1], ll[:, 0], *origin), axis=1)


def _signed_area(ring: np.ndarray) -> float:
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def test_geojson_passes_the_schema_and_rfc7946(exported, karlsruhe_demo):
    """Schema: geojson-pydantic's models (RFC 7946) both as a JSON Schema (jsonschema) and as
    the validating models; then the RFC's rules a schema cannot state."""
    jsonschema = pytest.importorskip("jsonschema")
    models = pytest.importorskip("geojson_pydantic", reason="needs geojson-pydantic (.[test])")
    _, doc = exported
    jsonschema.validate(doc, models.FeatureCollection.model_json_schema())
    models.FeatureCollection.model_validate(doc)
    assert doc["features"]
    for f in doc["features"]:
        g = f["geometry"]
        rings = [g["coordinates"]] if g["type"] == "LineString" else g["coordinates"]
        for ring in rings:
            a = np.asarray(ring)
            assert np.all(np.abs(a[:, 0]) <= 180) and np.all(np.abs(a[:, 1]) <= 90)
            assert 8.3 < a[:, 0].min() and a[:, 0].max() < 8.5  # Karlsruhe: lon ~8.4
            assert 48.9 < a[:, 1].min() and a[:, 1].max() < 49.1  # lat ~49.0
        if g["type"] == "Polygon":
            for k, ring in enumerate(g["coordinates"]):
                assert ring[0] == ring[-1] and len(ring) >= 4  # closed linear rings
                area = _signed_area(np.asarray(ring))
                assert area > 0 if k == 0 else area < 0  # right-hand rule (RFC 7946 3.1.6)


def test_every_feature_carries_its_class_tile_and_tile_version(exported, karlsruhe_demo):
    _, doc = exported
    stored = read_folder(karlsruhe_demo.out)
    versions = {tuple(t.tile): t.version for t in stored.tiles}
    names = {NAMES[c] for c in MARKINGS}
    kinds = Counter()
    for f in doc["features"]:
        p = f["properties"]
        assert p["class"] in names and p["tile_version"] == versions[tuple(p["tile"])], p
        kinds[(p["class"], f["geometry"]["type"])] += 1
        if f["geometry"]["type"] == "LineString":
            assert 0.05 <= p["width_m"] <= 0.6, p  # thin paint: a line with its width
    # thin paint as lines (the codec's centre polylines), areas as polygons
    assert kinds[("lane_line", "LineString")] >= 10, kinds
    assert kinds[("crosswalk", "LineString")] + kinds[("crosswalk", "Polygon")] >= 5, kinds
    assert kinds[("stop_line", "LineString")] >= 1, kinds
    assert {t for t in map(tuple, doc["roadmap"]["tiles"])} == set(versions)


def test_geojson_positions_return_to_the_map_metres(exported, karlsruhe_demo):
    """WGS84 and back: each position within 1 cm of the codec's shape in the world frame."""
    _, doc = exported
    features = map_features(read_folder(karlsruhe_demo.out).tiles)
    assert len(features) == len(doc["features"])
    worst = 0.0
    for f, g in zip(features, doc["features"], strict=True):
        if g["geometry"]["type"] == "LineString":
            back, orig = _to_m(g["geometry"]["coordinates"], _origin(doc)), f.rings_xy_m[0]
            worst = max(worst, float(np.abs(back - orig).max()))
    assert worst < 0.01


def test_geojson_lines_lie_on_the_source_map(exported, karlsruhe_demo):
    """The demo's lane lines (LineStrings) against the Lanelet2 map's line_thin / line_thick
    ways they were painted from, at a point every 0.25 m along every exported line."""
    _, doc = exported
    origin = _origin(doc)
    source = _source_lines(karlsruhe_demo.osm, origin, LANE_TYPES)
    lines = [_to_m(f["geometry"]["coordinates"], origin) for f in doc["features"]
             if f["properties"]["class"] == "lane_line"
             and f["geometry"]["type"] == "LineString"]
    pts = np.concatenate([_densified(line) for line in lines])
    d = _distances(pts, source)
    length = sum(float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) for p in lines)
    print(f"geojson lane lines: {length:.0f} m, distance to the source lines median "  # noqa: T201
          f"{np.median(d):.3f} p95 {np.percentile(d, 95):.3f} max {d.max():.3f} m")
    assert length > 50.0
    assert np.percentile(d, 95) <= 0.2 and np.median(d) <= 0.1
    stops = [_to_m(f["geometry"]["coordinates"], origin) for f in doc["features"]
             if f["properties"]["class"] == "stop_line"
             and f["geometry"]["type"] == "LineString"]
    ds = _distances(np.concatenate([_densified(s) for s in stops]),
                    _source_lines(karlsruhe_demo.osm, origin, ("stop_line",)))
    # stop lines run across the road: the mapping's along-road error lands on them whole
    assert np.median(ds) <= 0.25, np.median(ds)


def _lanelet2_linestrings(path, origin):
    lanelet2 = pytest.importorskip("lanelet2", reason="needs the lanelet2 package (.[test])")
    from lanelet2.io import Origin
    from lanelet2.projection import LocalCartesianProjector

    lanelet_map = lanelet2.io.load(str(path), LocalCartesianProjector(Origin(*origin)))
    return lanelet_map


def _attr(prim, key: str) -> str:
    return prim.attributes[key] if key in prim.attributes else ""


def test_lanelet2_osm_loads_with_lanelet2(exported, karlsruhe_demo):
    """lanelet2.io.load reads the export; its linestrings, counted by type and subtype, are
    the ways the file holds, tagged as Lanelet2's LinestringTagging.md says."""
    d, doc = exported
    lanelet_map = _lanelet2_linestrings(d / "map.osm", _origin(doc))
    loaded = Counter((_attr(ls, "type"), _attr(ls, "subtype"))
                     for ls in lanelet_map.lineStringLayer)
    root = ET.parse(d / "map.osm").getroot()
    ways = [{t.get("k"): t.get("v") for t in w.findall("tag")} for w in root.iter("way")]
    in_file = Counter((w["type"], w.get("subtype", "")) for w in ways if w.get("area") != "yes")
    print(f"lanelet2 linestrings by type: {dict(loaded)}")  # noqa: T201
    assert loaded == in_file
    lane = {k: n for k, n in loaded.items() if k[0] in LANE_TYPES}
    assert set(k[1] for k in lane) <= {"solid", "dashed"}
    assert sum(lane.values()) >= 3 and sum(n for k, n in lane.items() if k[1] == "dashed") >= 1
    assert loaded[("stop_line", "")] >= 1
    assert loaded[("zebra_marking", "")] >= 2 and loaded[("zebra_marking", "")] % 2 == 0
    crosswalks = [ll for ll in lanelet_map.laneletLayer if _attr(ll, "subtype") == "crosswalk"]
    assert 2 * len(crosswalks) == loaded[("zebra_marking", "")]
    for w in ways:
        assert w["roadmap:class"] in {NAMES[c] for c in MARKINGS} and w["roadmap:tile_versions"]
        if w["type"] in LANE_TYPES + ("stop_line",):
            assert 0.05 <= float(w["width"]) <= 0.6


def test_lanelet2_lines_lie_on_the_source_map_in_lanelet2s_frame(exported, karlsruhe_demo):
    """Both maps loaded by lanelet2 with one LocalCartesianProjector (its ENU frame, not ours):
    the exported lane lines within 0.2 m of the source's, and tagged like the source line
    they lie on (thin / thick, solid / dashed) for most of their length."""
    d, doc = exported
    origin = _origin(doc)
    ours = _lanelet2_linestrings(d / "map.osm", origin)
    source = _lanelet2_linestrings(karlsruhe_demo.osm, origin)

    def lines(m, types):
        return [(np.array([[p.x, p.y] for p in ls]), _attr(ls, "type"), _attr(ls, "subtype"))
                for ls in m.lineStringLayer if _attr(ls, "type") in types and len(ls) >= 2]

    src = lines(source, LANE_TYPES)
    exp = lines(ours, LANE_TYPES)
    pts = np.concatenate([_densified(xy) for xy, _, _ in exp])
    dist = _distances(pts, [xy for xy, _, _ in src])
    print(f"lanelet2 lane lines: distance to the source lines median {np.median(dist):.3f} "  # noqa: T201
          f"p95 {np.percentile(dist, 95):.3f} max {dist.max():.3f} m")
    assert np.percentile(dist, 95) <= 0.2 and np.median(dist) <= 0.1
    same_type = same_style = total = 0.0
    for xy, typ, sub in exp:
        near = min(src, key=lambda s: float(np.median(_distances(_densified(xy), [s[0]]))))
        length = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum())
        total += length
        same_type += length * (typ == near[1])
        same_style += length * (sub == {"solid_solid": "solid"}.get(near[2], near[2]))
    print(f"tagged like the source line: type {same_type / total:.2f}, "  # noqa: T201
          f"solid/dashed {same_style / total:.2f} of {total:.0f} m")
    assert same_type / total >= 0.8 and same_style / total >= 0.8


def test_stores_and_the_fetched_npz_export_the_same(karlsruhe_demo, tmp_path):
    for name, src in (("dir", karlsruhe_demo.out), ("store", karlsruhe_demo.out / "run" /
                                                    "merger-s0.sqlite"),
                      ("npz", karlsruhe_demo.out / "run" / "tiles.npz")):
        (tmp_path / name).mkdir()
        roadmap_ok("export", "--format", "geojson", "--from", src,
                   "--out", tmp_path / name / "map.geojson")
    texts = {n: (tmp_path / n / "map.geojson").read_text() for n in ("dir", "store", "npz")}
    assert texts["dir"] == texts["store"] == texts["npz"]
