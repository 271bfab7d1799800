"""The GNSS as an integrity monitor of the map-matched pose.

Map matching can lock onto the wrong road: a parallel carriageway 10 m over looks like the
right one to ICP, and its covariance says centimetres. The consumer GNSS, whose fixes the filter
only gates once it is sure of itself, still knows where the car is to a few metres. The
residuals of the last fixes (fix minus filter pose, both at the fix's time) averaged: their
white noise averages out, the receiver's slowly varying bias does not, and a mean beyond
`alert_sigmas` times the fixes' reported sigma is not a bias any receiver claims."""

from collections import deque

import numpy as np

from common.config import LocalizerConfig


class GnssCheck:
    def __init__(
        self,
        fixes: int = LocalizerConfig.gnss_check_fixes,
        alert_sigmas: float = LocalizerConfig.gnss_alert_sigmas,
    ):
        """fixes: the window of fixes averaged (a test needs half of it);
        alert_sigmas: the mean residual's bound in reported sigmas (0: never disagrees)."""
        self.alert_sigmas = alert_sigmas
        self.residuals: deque = deque(maxlen=max(int(fixes), 1))  # (dx, dy, reported sigma)

    def add(self, fix_xy: np.ndarray, pose_xy: np.ndarray, sigma_m: float) -> None:
        dx, dy = np.asarray(fix_xy, float) - np.asarray(pose_xy, float)
        self.residuals.append((dx, dy, float(sigma_m)))

    def reset(self) -> None:
        """A new start: the residuals of the old pose say nothing about the new one."""
        self.residuals.clear()

    @property
    def mean_residual_m(self) -> float:
        if not self.residuals:
            return 0.0
        r = np.asarray(self.residuals)
        return float(np.hypot(*r[:, :2].mean(axis=0)))

    @property
    def heard(self) -> bool:
        """Half a window of fixes since the (re)start: enough to tell (or the check is off)."""
        return self.alert_sigmas <= 0 or 2 * len(self.residuals) >= self.residuals.maxlen

    @property
    def disagrees(self) -> bool:
        """The mean residual of at least half a window beyond alert_sigmas x the mean
        reported sigma."""
        if self.alert_sigmas <= 0 or not self.heard:
            return False
        sigma = float(np.asarray(self.residuals)[:, 2].mean())
        return self.mean_residual_m > self.alert_sigmas * sigma
