"""The ground-truth segmenter of simulated drive logs: true labels with realistic errors, so that
mapping and localization can be tested and ablated without the model."""

from dataclasses import dataclass

import cv2
import numpy as np

from common.classes import Cls
from common.segmentation.base import Segmenter


@dataclass
class GroundTruthSegmenter(Segmenter):
    """True labels with realistic errors: ragged boundaries, missed blobs and spurious blobs.

    boundary_flip: probability that a pixel on a class boundary takes its neighbour's class;
    miss_rate: expected fraction of marking area dropped as blobs per frame;
    spurious_per_frame: expected number of small false marking blobs on the road per frame."""

    boundary_flip: float = 0.3
    miss_rate: float = 0.03
    spurious_per_frame: float = 0.5
    seed: int = 0
    name: str = "ground-truth+corruption"

    def __post_init__(self):
        self._rng = np.random.default_rng(self.seed)

    def segment(self, image_rgb=None, labels_true=None) -> np.ndarray:
        if labels_true is None:
            raise ValueError("GroundTruthSegmenter needs the true label image of the frame")
        labels = labels_true.copy()
        self._ragged_boundaries(labels, labels_true)
        self._drop_blobs(labels)
        self._add_spurious(labels)
        return labels

    def _ragged_boundaries(self, labels, truth):
        if self.boundary_flip <= 0:
            return
        shifted = np.roll(truth, self._rng.choice([-1, 1]), axis=int(self._rng.integers(2)))
        edge = shifted != truth
        flip = edge & (self._rng.random(truth.shape) < self.boundary_flip)
        labels[flip] = shifted[flip]

    def _drop_blobs(self, labels):
        marking = labels >= Cls.LANE_LINE
        area = int(marking.sum())
        if area == 0 or self.miss_rate <= 0:
            return
        h, w = labels.shape
        ys, xs = np.nonzero(marking)
        n = self._rng.poisson(self.miss_rate * area / 150.0)
        for i in self._rng.integers(0, len(ys), n):
            r = int(self._rng.integers(3, 9))
            y0, y1 = max(ys[i] - r, 0), min(ys[i] + r, h)
            x0, x1 = max(xs[i] - r, 0), min(xs[i] + r, w)
            window = labels[y0:y1, x0:x1]
            window[window >= Cls.LANE_LINE] = Cls.ROAD

    def _add_spurious(self, labels):
        road = np.argwhere(labels == Cls.ROAD)
        if len(road) == 0:
            return
        for _ in range(self._rng.poisson(self.spurious_per_frame)):
            y, x = road[self._rng.integers(len(road))]
            cls = int(self._rng.choice([Cls.LANE_LINE, Cls.GROUND_SIGN, Cls.STOP_LINE]))
            axes = (int(self._rng.integers(1, 4)), int(self._rng.integers(1, 6)))
            cv2.ellipse(labels, (int(x), int(y)), axes, float(self._rng.uniform(0, 180)), 0, 360,
                        cls, -1)
