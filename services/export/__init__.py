"""Map export (`roadmap export`): the merged map's tiles -> WGS84 vector features, written as
GeoJSON (RFC 7946) or as a Lanelet2 OSM map; tiles read from a running fleet or from disk."""
