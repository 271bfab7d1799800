"""Map features -> a Lanelet2 map (OSM XML, lat/lon nodes about the world's origin), tagged as
Lanelet2's LinestringTagging.md says:

- lane lines: `type=line_thin` or `line_thick` (painted width from LINE_THICK_FROM_M),
  `subtype=solid` or `dashed`, `width`; lines the tile borders cut are joined again and the
  dashes of a line are chained into one linestring through them (services/export/lines.py);
- stop lines: `type=stop_line`, `width`;
- crosswalks: per crossing, its two edges along the walking direction as `type=zebra_marking`
  linestrings, and between them a lanelet `subtype=crosswalk`;
- ground signs (arrows, text): their outlines, `type=symbol`, `subtype=ground_sign`, `area=yes`
  (Lanelet2's `arrow` needs a direction the map does not know).

Thin paint the codec traced as a polygon becomes its strip's centre line; specks shorter than
MIN_LINE_M are left out. Every way carries `roadmap:class` and `roadmap:tile_versions`
("tx,ty:version;..." of the tiles it came from)."""

import xml.etree.ElementTree as ET

import numpy as np

from common.classes import Cls
from common.contours import ShapeKind
from common.geometry import local_m_to_latlon
from services.export.features import MapFeature
from services.export.lines import Piece, chain_dashes, join_pieces, strip_centreline

LINE_THICK_FROM_M = 0.2  # Lanelet2 maps: line_thin 0.12-0.15 m, line_thick 0.25-0.3 m
MIN_LINE_M = 1.0  # shorter pieces of line paint are specks or cut-off dash ends, not lines
LONE_DASH_M = 1.5  # a lone piece at least this long (and short enough to be one) is a dash
CROSSING_GAP_M = 1.5  # stripes of one crossing lie closer than this (stripe gaps 0.5 m)
DECIMALS = 10  # degrees


def to_osm(features: list[MapFeature], origin_latlon: tuple[float, float]) -> str:
    """The whole map as Lanelet2 OSM XML text."""
    doc = _OsmDoc(*origin_latlon)
    for piece in _lane_lines(features):
        kind = "line_thick" if piece.width_m >= LINE_THICK_FROM_M else "line_thin"
        dashed = piece.dashes > 1 or (piece.dashes == 1 and piece.length_m >= LONE_DASH_M)
        doc.way(piece.xy, {"type": kind, "subtype": "dashed" if dashed else "solid",
                           "width": f"{piece.width_m:.2f}"}, Cls.LANE_LINE, piece.tiles)
    for piece in _lines_of(features, Cls.STOP_LINE):
        doc.way(piece.xy, {"type": "stop_line", "width": f"{piece.width_m:.2f}"},
                Cls.STOP_LINE, piece.tiles)
    for left, right, tiles in _crossings(features):
        a = doc.way(left, {"type": "zebra_marking"}, Cls.CROSSWALK, tiles)
        b = doc.way(right, {"type": "zebra_marking"}, Cls.CROSSWALK, tiles)
        doc.lanelet(a, b, {"type": "lanelet", "subtype": "crosswalk", "one_way": "no",
                           "participant:pedestrian": "yes"})
    for f in features:
        if f.cls == Cls.GROUND_SIGN and f.kind == ShapeKind.POLYGON:
            doc.way(f.rings_xy_m[0], {"type": "symbol", "subtype": "ground_sign", "area": "yes"},
                    Cls.GROUND_SIGN, {f.tile: f.version}, closed=True)
    return doc.text()


def _pieces(features: list[MapFeature], cls: Cls) -> list[Piece]:
    """Every shape of a class as a line piece (strip polygons by their centre line)."""
    out = []
    for f in features:
        if f.cls != cls:
            continue
        if f.kind == ShapeKind.LINE:
            xy, width = f.rings_xy_m[0], f.width_m
        else:
            xy, width = strip_centreline(f.rings_xy_m[0])
            width += 0.1  # the outline runs through the border cells' centres
        out.append(Piece(np.asarray(xy, float), float(width), {f.tile: f.version}))
    return out


def _lines_of(features: list[MapFeature], cls: Cls) -> list[Piece]:
    return [p for p in join_pieces(_pieces(features, cls)) if p.length_m >= MIN_LINE_M]


def _lane_lines(features: list[MapFeature]) -> list[Piece]:
    return chain_dashes(_lines_of(features, Cls.LANE_LINE))


def _crossings(features: list[MapFeature]):
    """[(left edge, right edge, tiles)] per crossing: stripes grouped by proximity; the edges
    run across the stripes (the walking direction) at both ends of the stripes."""
    stripes = [p for p in join_pieces(_pieces(features, Cls.CROSSWALK)) if p.length_m > 0.2]
    out = []
    for group in _groups(stripes, CROSSING_GAP_M):
        pts = np.concatenate([stripes[k].xy for k in group])
        along = _mean_axis([stripes[k].xy for k in group])  # stripes run along the traffic
        walk = np.array([-along[1], along[0]])
        c = pts.mean(axis=0)
        u, w = (pts - c) @ along, (pts - c) @ walk
        half = 0.5 * float(np.mean([stripes[k].width_m for k in group]))  # round line caps
        w0, w1 = w.min() - half, w.max() + half
        edges = [np.stack([c + u0 * along + w0 * walk, c + u0 * along + w1 * walk])
                 for u0 in (u.min() - half, u.max() + half)]
        tiles = {t: v for k in group for t, v in stripes[k].tiles.items()}
        # both edges run along +walk; left of it lies -along (walk is along turned +90 deg)
        out.append((edges[0], edges[1], tiles))
    return out


def _mean_axis(polylines: list[np.ndarray]) -> np.ndarray:
    """Length-weighted mean direction of polylines (sign-free, as a doubled angle)."""
    acc = np.zeros(2)
    for xy in polylines:
        d = xy[-1] - xy[0]
        a = np.arctan2(d[1], d[0])
        acc += np.linalg.norm(d) * np.array([np.cos(2 * a), np.sin(2 * a)])
    a = 0.5 * np.arctan2(acc[1], acc[0])
    return np.array([np.cos(a), np.sin(a)])


def _groups(pieces: list[Piece], gap_m: float) -> list[list[int]]:
    """Connected groups of pieces whose vertices come within gap_m (union-find)."""
    parent = list(range(len(pieces)))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    dense = [_densified(p.xy, gap_m / 2) for p in pieces]
    for i in range(len(pieces)):
        for j in range(i + 1, len(pieces)):
            if find(i) != find(j) and _min_dist(dense[i], dense[j]) <= gap_m:
                parent[find(i)] = find(j)
    groups: dict[int, list[int]] = {}
    for i in range(len(pieces)):
        groups.setdefault(find(i), []).append(i)
    return list(groups.values())


def _densified(xy: np.ndarray, step_m: float) -> np.ndarray:
    out = [xy[:1]]
    for a, b in zip(xy[:-1], xy[1:], strict=True):
        n = max(int(np.ceil(np.linalg.norm(b - a) / step_m)), 1)
        out.append(a + (b - a) * (np.arange(1, n + 1)[:, None] / n))
    return np.concatenate(out)


def _min_dist(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.min(np.linalg.norm(a[:, None] - b[None], axis=2)))


class _OsmDoc:
    """OSM XML under construction: positive ids in order, one node per vertex."""

    def __init__(self, lat0: float, lon0: float):
        self.lat0, self.lon0 = lat0, lon0
        self.root = ET.Element("osm", version="0.6", generator="roadmap export")
        self.ways: list[ET.Element] = []
        self.relations: list[ET.Element] = []
        self.next_id = 1

    def _id(self) -> int:
        self.next_id += 1
        return self.next_id - 1

    def way(self, xy: np.ndarray, tags: dict, cls: Cls, tiles: dict, closed: bool = False) -> int:
        lat, lon = local_m_to_latlon(xy[:, 0], xy[:, 1], self.lat0, self.lon0)
        refs = []
        for a, b in zip(lat, lon, strict=True):
            refs.append(self._id())
            ET.SubElement(self.root, "node", id=str(refs[-1]), visible="true", version="1",
                          lat=f"{a:.{DECIMALS}f}", lon=f"{b:.{DECIMALS}f}")
        if closed:
            refs.append(refs[0])
        way = ET.Element("way", id=str(self._id()), visible="true", version="1")
        for r in refs:
            ET.SubElement(way, "nd", ref=str(r))
        versions = ";".join(f"{tx},{ty}:{v}" for (tx, ty), v in sorted(tiles.items()))
        for k, v in {**tags, "roadmap:class": cls.name.lower(),
                     "roadmap:tile_versions": versions}.items():
            ET.SubElement(way, "tag", k=k, v=str(v))
        self.ways.append(way)
        return int(way.get("id"))

    def lanelet(self, left: int, right: int, tags: dict) -> None:
        rel = ET.Element("relation", id=str(self._id()), visible="true", version="1")
        for role, ref in (("left", left), ("right", right)):
            ET.SubElement(rel, "member", type="way", ref=str(ref), role=role)
        for k, v in tags.items():
            ET.SubElement(rel, "tag", k=k, v=v)
        self.relations.append(rel)

    def text(self) -> str:
        self.root.extend(self.ways + self.relations)  # OSM order: nodes, ways, relations
        ET.indent(self.root, space=" ")
        return ET.tostring(self.root, encoding="unicode", xml_declaration=True) + "\n"
