"""The demo's own error (services/demo: run.py, report.py)."""

from common.errors import RoadmapError


class DemoError(RoadmapError):
    """The demo cannot run (a service missing or failing); the message names which."""
