"""Semantic classes of road-surface paint (uint8 on the wire and in rasters) and their colours."""

import enum

import numpy as np


class Cls(enum.IntEnum):
    NONE = 0
    ROAD = 1
    LANE_LINE = 2
    STOP_LINE = 3
    CROSSWALK = 4
    GROUND_SIGN = 5


NUM_CLASSES = 6
MARKINGS = (Cls.LANE_LINE, Cls.STOP_LINE, Cls.CROSSWALK, Cls.GROUND_SIGN)
# Report names, as in DESIGN.md's report contract.
NAMES = {c: c.name.lower() for c in Cls}

# Paper-like palette (RGB): dark road, white lane lines, red stop lines, blue crosswalks,
# yellow ground signs, on black.
COLORS_RGB = np.array(
    [
        [0, 0, 0],
        [70, 70, 70],
        [255, 255, 255],
        [230, 40, 40],
        [40, 120, 255],
        [255, 210, 0],
    ],
    dtype=np.uint8,
)


def colorize(labels: np.ndarray) -> np.ndarray:
    """Class raster (H, W) uint8 -> RGB image (H, W, 3) in the map palette."""
    return COLORS_RGB[np.clip(labels, 0, NUM_CLASSES - 1)]
