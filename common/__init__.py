"""RoadMap common library: transport-free conventions shared by every process."""

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())
