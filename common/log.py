"""Logging set-up for entry points only; libraries just call logging.getLogger(__name__)."""

import logging
import os
import sys

FORMAT = "%(asctime)s %(levelname)-5s %(name)s: %(message)s"


def configure_logging(level: str | int | None = None) -> None:
    """Configure the root logger once, for a CLI or node main (env ROADMAP_LOG_LEVEL wins)."""
    level = os.environ.get("ROADMAP_LOG_LEVEL", level or "INFO")
    if isinstance(level, str):
        level = level.upper()
    logging.basicConfig(level=level, format=FORMAT, stream=sys.stderr, force=True)
