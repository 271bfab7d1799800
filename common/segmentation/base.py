"""The segmenter interface: camera image (and, in simulation, the true labels) -> class image
(H, W) uint8 in our classes (common.classes)."""


import numpy as np


class Segmenter:
    name = "segmenter"

    def segment(self, image_rgb: np.ndarray | None, labels_true: np.ndarray | None = None):
        raise NotImplementedError
