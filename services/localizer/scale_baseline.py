"""The wheel-odometry scale from along-road fixes a baseline apart.

A filter that learns the scale from each match's pull cannot tell a pull that corrects a wrong
along-road start from one that corrects the wheel: both move the position along the road, and
a start 0.3-4 m off read as scale swung it 3-5 % wrong in a few seconds (held-out town:3 s461,
Karlsruhe s492), with a sigma of 0.07-0.3 %. Two fixes of the along-road position far apart say
how far the car went, whatever the start: the distance between them over the distance the
wheels counted is the scale, to (their sigmas) / (the baseline), 0.1-0.2 % over 100 m.

The fixes must be the matches' own, not the filter's posterior, which leans on the odometry
the scale is to correct: `prior_free` takes the prior back out of a match made with the
filter's prediction as its prior."""

import math

import numpy as np


def prior_free(post_xy: np.ndarray, prior_xy: np.ndarray, prior_cov: np.ndarray,
               information: np.ndarray, along: np.ndarray) -> tuple[np.ndarray, float]:
    """The along-road position the match alone measured, and its sigma: along the unit
    vector `along`, z = post + (I_prior / I_match) (post - prior), the Gaussian MAP undone
    (I: information along it; prior_cov, information: 2x2 over the position)."""
    i_match = float(along @ information @ along)
    i_prior = 1.0 / max(float(along @ prior_cov @ along), 1e-12)
    shift = float(along @ (np.asarray(post_xy, float) - prior_xy))
    z = np.asarray(post_xy, float) + along * (i_prior / i_match) * shift
    return z, 1.0 / math.sqrt(i_match)


class ScaleBaselines:
    """Pairs of along-road fixes (`fix`) at least `baseline_m` of wheel travel apart, each
    giving the scale (distance between the fixes / the wheels' distance) and its sigma (the
    fixes' sigmas, each at least `floor_m`, over the wheels' distance). Consecutive pairs share
    a fix; `restart` forgets the last one (a filter restarted elsewhere)."""

    def __init__(self, baseline_m: float, floor_m: float = 0.05):
        self.baseline_m, self.floor_m = baseline_m, floor_m
        self.anchor: tuple[np.ndarray, np.ndarray, float] | None = None

    def restart(self) -> None:
        self.anchor = None

    def fix(self, wheel_xy: np.ndarray, fixed_xy: np.ndarray,
            sigma_m: float) -> tuple[float, float] | None:
        """A fix of the position `fixed_xy` (world) with its sigma, where the unscaled wheel
        odometry read `wheel_xy` (its own frame); (scale, sigma) once a baseline is complete."""
        here = (np.asarray(wheel_xy, float), np.asarray(fixed_xy, float),
                max(float(sigma_m), self.floor_m))
        if self.anchor is None:
            self.anchor = here
            return None
        wheels_m = float(np.hypot(*(here[0] - self.anchor[0])))
        if wheels_m < self.baseline_m:
            return None
        scale = float(np.hypot(*(here[1] - self.anchor[1]))) / wheels_m
        sigma = math.hypot(here[2], self.anchor[2]) / wheels_m
        self.anchor = here
        return scale, sigma
