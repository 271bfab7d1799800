"""Pose graph of the mapping vehicle (paper eq. 2-3): Pose2 nodes, odometry and GNSS factors, ISAM2.

The only module that imports gtsam. Speaks numpy: poses are (x, y, yaw) arrays in the world ENU
frame (metres, radians); node keys are integers (frame indices)."""

import logging

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

logger = logging.getLogger(__name__)

PRIOR_SIGMAS = np.array([0.5, 0.5, 0.2])  # m, m, rad: first pose, before GNSS pins it down
ODOM_SIGMA_FLOOR = np.array([0.002, 0.001, 0.0001])  # m, m, rad per odometry step
ODOM_SIGMA_PER_M = np.array([0.01, 0.002, 0.0002])  # m/m, m/m, rad/m: grows with distance
GNSS_HUBER_K = 3.0  # robust kernel width in sigmas (outlier fixes near the outage edges)
RELIN_THRESHOLD = 0.01  # ISAM2 relinearization threshold (m / rad)
EXTRA_ITERATIONS_AFTER_GAP = 3  # extra ISAM2 updates after a large correction (GNSS returns)


def odometry_sigmas(distance_m: float) -> np.ndarray:
    """Between-factor sigmas (x, y, yaw) for one odometry step of `distance_m` metres."""
    return ODOM_SIGMA_FLOOR + ODOM_SIGMA_PER_M * abs(distance_m)


class PoseGraph:
    """Incremental Pose2 graph: collects factors and initial values; `optimize()` sends only
    the new ones to ISAM2."""

    def __init__(self, relinearize_threshold: float = RELIN_THRESHOLD):
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(relinearize_threshold)
        params.enablePartialRelinearizationCheck = True  # check only cliques that changed
        params.relinearizeSkip = 1
        self._isam = gtsam.ISAM2(params)
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._keys: set[int] = set()
        self._large_correction = False

    def __contains__(self, key: int) -> bool:
        return key in self._keys

    def add_node(self, key: int, initial_pose) -> None:
        """A new pose variable with its initial guess (e.g. the odometry prediction)."""
        if key in self._keys:
            return
        self._new_values.insert(X(key), _pose2(initial_pose))
        self._keys.add(key)

    def add_prior(self, key: int, pose, sigmas=PRIOR_SIGMAS) -> None:
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, float))
        self._new_factors.add(gtsam.PriorFactorPose2(X(key), _pose2(pose), noise))

    def add_odometry(self, i: int, j: int, delta, sigmas=None) -> None:
        """BetweenFactorPose2: pose j seen from pose i is `delta` (dx, dy, dyaw) in i's frame."""
        delta = np.asarray(delta, float)
        if sigmas is None:
            sigmas = odometry_sigmas(float(np.hypot(delta[0], delta[1])))
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, float))
        self._new_factors.add(gtsam.BetweenFactorPose2(X(i), X(j), _pose2(delta), noise))

    def add_gnss(self, key: int, xy_m, sigma_m: float) -> None:
        """Unary position factor: translation of pose `key` is `xy_m` (world) with `sigma_m`.

        PoseTranslationPrior2D compares only the translation (its Jacobian is [R 0]), so the
        yaw is left free and the residual is exactly the world position error. A PriorFactorPose2
        with a 1e3 rad yaw sigma needs an arbitrary yaw and couples it through Logmap; measured on
        the 300 m outage drive rotated by 0 / 1.5 / 2.8 rad it was as fast and 0.008-0.011 m
        outage error vs 0.012 m here, but this factor's result is invariant to the rotation."""
        base = gtsam.noiseModel.Isotropic.Sigma(2, float(sigma_m))
        robust = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(GNSS_HUBER_K), base
        )
        self._new_factors.add(
            gtsam.PoseTranslationPrior2D(X(key), np.asarray(xy_m, float).reshape(2), robust)
        )

    def mark_large_correction(self) -> None:
        """Ask the next optimize() to iterate a few extra times (e.g. GNSS back after an outage)."""
        self._large_correction = True

    def optimize(self, iterations: int = 1) -> None:
        """ISAM2 update with only the factors and values added since the last call, then
        `iterations - 1` more relinearizing steps (more after a marked large correction)."""
        self._isam.update(self._new_factors, self._new_values)
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        extra = iterations - 1 + (EXTRA_ITERATIONS_AFTER_GAP if self._large_correction else 0)
        for _ in range(extra):
            self._isam.update()
        self._large_correction = False

    def estimate(self, key: int) -> np.ndarray:
        """Current optimized (x, y, yaw) of one node (call optimize() first)."""
        p = self._isam.calculateEstimatePose2(X(key))
        return np.array([p.x(), p.y(), p.theta()])

    def estimates(self, keys=None) -> dict[int, np.ndarray]:
        """Optimized poses of the given keys (all nodes when None)."""
        if keys is None:
            values = self._isam.calculateEstimate()
            keys = sorted(self._keys)
            poses = [values.atPose2(X(k)) for k in keys]
            return {
                k: np.array([p.x(), p.y(), p.theta()]) for k, p in zip(keys, poses, strict=True)
            }
        return {k: self.estimate(k) for k in keys}


def _pose2(pose) -> "gtsam.Pose2":
    x, y, yaw = (float(v) for v in pose)
    return gtsam.Pose2(x, y, yaw)
