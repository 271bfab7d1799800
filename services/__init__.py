"""RoadMap services: each a pure core object plus a thin Zenoh node."""

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())
