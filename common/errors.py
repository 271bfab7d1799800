"""The exception hierarchy; the CLI maps every RoadmapError to a one-line message and exit 1."""


class RoadmapError(Exception):
    """Root of every error this project raises on purpose."""


class ConfigError(RoadmapError):
    """A config file, env override or option is malformed or contradictory."""


class CodecError(RoadmapError):
    """A wire message or compressed tile does not match the expected format."""


class TileError(RoadmapError):
    """A tile or cell index is out of range or not owned here."""


class DriveLogError(RoadmapError):
    """A drive log on disk is missing files or has inconsistent streams."""


class WorldError(RoadmapError):
    """A world source (procedural, Lanelet2, Argoverse 2) cannot be built."""


class TransportError(RoadmapError):
    """Zenoh could not be reached or answered with an error."""


class ExportError(RoadmapError):
    """A map or trajectory cannot be exported (no tiles, no origin, an unknown tile codec)."""
