"""Minimal OSM XML reader for Lanelet2 maps: nodes (lat/lon), ways (node refs + tags) and
relations (members + tags). Pure parsing, no geometry."""

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

from common.errors import WorldError


@dataclass
class OsmMap:
    nodes: dict[int, tuple[float, float]] = field(default_factory=dict)  # id -> (lat, lon)
    ways: dict[int, tuple[list[int], dict]] = field(default_factory=dict)  # id -> (refs, tags)
    relations: dict[int, tuple[list[tuple[str, int, str]], dict]] = field(default_factory=dict)


def read_osm(path) -> OsmMap:
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise WorldError(f"cannot read OSM file {path}: {exc}") from exc
    osm = OsmMap()
    for el in root:
        tags = {t.get("k"): t.get("v") for t in el.findall("tag")}
        if el.tag == "node":
            osm.nodes[int(el.get("id"))] = (float(el.get("lat")), float(el.get("lon")))
        elif el.tag == "way":
            osm.ways[int(el.get("id"))] = ([int(n.get("ref")) for n in el.findall("nd")], tags)
        elif el.tag == "relation":
            members = [
                (m.get("type"), int(m.get("ref")), m.get("role")) for m in el.findall("member")
            ]
            osm.relations[int(el.get("id"))] = (members, tags)
    if not osm.nodes:
        raise WorldError(f"{path}: no nodes")
    return osm
