"""EKF over the planar pose (x, y, yaw) in the world frame plus the wheel-odometry scale factor,
the gyro bias and the camera's yaw mounting error (filterpy's ExtendedKalmanFilter).

The pose's yaw is the heading the camera sees (what ICP measures); the car moves along that
heading minus the camera yaw offset. A miscalibrated camera (0.2 deg is common) thus shows as
ICP lateral corrections that keep pointing one way as the car drives, and the filter learns the
offset from them; `vehicle_pose` is the car's own heading.

Predict from wheel speed (m/s, times the estimated scale) and gyro yaw rate (rad/s); update
with an ICP pose (its 3x3
covariance) or a consumer GNSS position. Every update is gated by the Mahalanobis distance of its
innovation (chi-square); angle residuals are wrapped. `ok` is the integrity flag: False when the
position uncertainty grows past a bound, too many updates in a row were rejected, or the gyro
bias estimate ran past GYRO_BIAS_LIMIT_SIGMAS of its prior (a wrong match's pull, not the
gyro's; a reset forgets such a bias).

With `freeze_scale_on_reset` the odometry scale is frozen at each reset: measurements move
the pose (and the other states) but not the scale until it thaws: when the caller says so
(`scale_frozen = False`, the Localizer at its first trusted pose) or a match pins the
along-road position to within `scale_thaw_sigma_m` (`along_road_fixed`). A frozen scale keeps
its variance, and the position the uncertainty that variance adds as the car drives."""

import math
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from common.config import LocalizerConfig
from common.geometry import wrap_angle

CHI2_99 = {2: 9.21, 3: 11.34}
SCALE_LIMIT = 0.05  # wheel odometry scale error beyond +-5 % is a filter fault, not a car
# a gyro bias estimate beyond this many sigma of its prior is the filter's fault too: a start
# on the wrong paint turns the heading frame after frame, and the filter reads the turn as bias
# (held-out Karlsruhe s513: -0.8 deg/s, ok 8.9 m off; true biases here are 0.05 deg/s or less,
# no estimate on a right track went past 0.26 deg/s over 97 drives: docs/RESULTS.md)
GYRO_BIAS_LIMIT_SIGMAS = 3.0


def _clamp_scale(scale: float) -> float:
    """The odometry scale within +-SCALE_LIMIT of 1: every update that moves it clamps it."""
    return min(max(float(scale), 1.0 - SCALE_LIMIT), 1.0 + SCALE_LIMIT)


def shift_consistency(shift: np.ndarray, expected_cov: np.ndarray) -> tuple[float, int]:
    """(squared Mahalanobis distance, degrees of freedom) of a posterior's shift from its prior.

    For a consistent filter the shift a measurement causes has the covariance prior minus
    posterior (the variance the measurement removed): its squared distance under that
    covariance is chi-square with as many degrees of freedom as the measurement observed (the
    pseudo-inverse drops the directions it left unobserved, lane lines' along-road one). A
    shift far beyond it says the filter's covariance was too small for where the matches put
    the pose."""
    w, v = np.linalg.eigh(0.5 * (expected_cov + expected_cov.T))
    seen = w > 1e-8  # variance removed, m^2 (a tenth of a millimetre)
    z = v.T @ np.asarray(shift, float)
    return float(np.sum(z[seen] ** 2 / w[seen])), int(seen.sum())


@dataclass(frozen=True)
class MatchBias:
    """What successive ICP matches share of their error: the map's error of the marking they
    all see, the camera's pitch and height error that moves it along the road. Matches of one
    crosswalk over 15 frames are one fix, not 15; summed as independent, they shrank the
    filter's along-road sigma to centimetres and read the start's offset as odometry scale
    (3.4 % wrong in 8 frames on Karlsruhe s492).

    A state (x, y, yaw) added to each match's pose, a first-order Gauss-Markov process over the
    distance driven: stationary sigma `sigma_m` (and `yaw_sigma_rad`), correlation length
    `length_m`. The filter's own pose is then known only to within that shared error while one
    marking is in view, and the odometry scale learns from fixes `length_m` or more apart."""

    sigma_m: float = LocalizerConfig.match_bias_sigma_m
    yaw_sigma_rad: float = math.radians(LocalizerConfig.match_bias_yaw_deg)
    length_m: float = LocalizerConfig.match_bias_length_m

    @property
    def on(self) -> bool:
        return self.sigma_m > 0 or self.yaw_sigma_rad > 0

    @property
    def variances(self) -> np.ndarray:
        return np.array([self.sigma_m**2, self.sigma_m**2, self.yaw_sigma_rad**2])

    def decay(self, distance_m: float) -> float:
        """The share of the shared error still shared after driving distance_m."""
        return math.exp(-abs(distance_m) / max(self.length_m, 1e-6))


def _pose_residual(a, b):
    r = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    if r.shape[0] == 3:
        r[2] = float(wrap_angle(r[2]))
    return r


def _kalman_step(x, P, z, H, R, consider_scale: bool):
    """A linear update with innovation z (already z - H x) in the Joseph form; with
    consider_scale the odometry scale (state 3) keeps its estimate and variance (Schmidt)."""
    S = H @ P @ H.T + R
    gain = np.linalg.solve(S, H @ P).T
    if consider_scale:
        gain[3] = 0.0
    x = x + gain @ z
    x[2] = float(wrap_angle(x[2]))
    x[3] = _clamp_scale(x[3])
    keep = np.eye(len(P)) - gain @ H
    P = keep @ P @ keep.T + gain @ R @ gain.T
    return x, 0.5 * (P + P.T)


class _PlanarEKF(ExtendedKalmanFilter):
    """filterpy EKF whose prediction is the unicycle motion model."""

    def predict_x(self, u=None):
        v, w, dt, decay = u
        x = self.x.reshape(-1)
        w = w - x[4]
        yaw_mid = x[2] - x[5] + 0.5 * w * dt
        d = x[3] * v * dt
        x_new = np.array(
            [
                x[0] + d * math.cos(yaw_mid),
                x[1] + d * math.sin(yaw_mid),
                float(wrap_angle(x[2] + w * dt)),
                x[3],
                x[4],
                x[5],
                *(decay * x[6:]),  # the matches' shared error (MatchBias), when a state
            ]
        )
        self.x = x_new.reshape(self.x.shape)


class PoseFilter:
    """(x, y, yaw, odometry scale, gyro bias, camera yaw) EKF, plus the matches' shared error
    (x, y, yaw) with `match_bias`, with gating and an integrity flag; numpy in and out."""

    def __init__(
        self,
        *,
        speed_sigma_rel: float = LocalizerConfig.speed_sigma_rel,
        speed_sigma_mps: float = 0.05,
        yaw_rate_sigma_rps: float = math.radians(LocalizerConfig.yaw_rate_sigma_dps),
        gate_prob_chi2: dict | None = None,
        max_position_sigma_m: float = LocalizerConfig.max_position_sigma_m,
        max_rejections: int = 20,
        scale_sigma0: float = LocalizerConfig.scale_sigma0,
        scale_walk_per_s: float = LocalizerConfig.scale_walk_per_s,
        gyro_bias_sigma0_rps: float = math.radians(0.1),
        gyro_bias_walk_rps: float = math.radians(0.002),
        camera_yaw_sigma0_rad: float = math.radians(0.3),
        freeze_scale_on_reset: bool = LocalizerConfig.scale_frozen_at_start,
        scale_thaw_sigma_m: float = LocalizerConfig.scale_thaw_fix_sigma_m,
        consistency_chi2: float = LocalizerConfig.integrity_consistency_chi2,
        scale_skips_inconsistent: bool = LocalizerConfig.scale_skips_inconsistent,
        frozen_scale_considered: bool = LocalizerConfig.scale_frozen_considered,
        inflate_after: int = 3,
        inflate_m: float = 0.15,
        inflate_yaw_rad: float = math.radians(0.3),
        match_bias: MatchBias = MatchBias(),
    ):
        self.speed_sigma_rel = speed_sigma_rel
        self.speed_sigma_mps = speed_sigma_mps
        self.yaw_rate_sigma_rps = yaw_rate_sigma_rps
        self.chi2 = gate_prob_chi2 or CHI2_99
        self.max_position_sigma_m = max_position_sigma_m
        self.max_rejections = max_rejections
        self.scale_sigma0, self.scale_walk_per_s = scale_sigma0, scale_walk_per_s
        self.inflate_after, self.inflate_m, self.inflate_yaw_rad = (
            inflate_after,
            inflate_m,
            inflate_yaw_rad,
        )
        self.inflations = 0
        self.pose_rejections = 0
        self.gnss_rejections = 0
        self.gyro_bias_sigma0, self.gyro_bias_walk = gyro_bias_sigma0_rps, gyro_bias_walk_rps
        self.camera_yaw_sigma0 = camera_yaw_sigma0_rad
        self.match_bias, self.dim = match_bias, 9 if match_bias.on else 6
        self.ekf = _PlanarEKF(dim_x=self.dim, dim_z=3)
        self.ekf.x = np.eye(self.dim, 1, -3)  # the scale 1, all else 0
        self.initialized = False
        self.rejections = 0
        self.last_nis = 0.0
        # the last accepted posterior's position shift against what the covariance expects of
        # it (squared Mahalanobis distance, degrees of freedom; shift_consistency), and the
        # distance beyond which the filter is inconsistent (0: never)
        self.last_shift_d2: tuple[float, int] = (0.0, 0)
        self.consistency_chi2 = consistency_chi2
        # ... and whether such a shift moves the odometry scale (False: it does, as any other)
        self.scale_skips_inconsistent = scale_skips_inconsistent
        # a frozen scale keeps its covariance with the pose (False: dropped at each update)
        self.frozen_scale_considered = frozen_scale_considered
        self.freeze_scale_on_reset, self.scale_thaw_sigma_m = (freeze_scale_on_reset,
                                                               scale_thaw_sigma_m)
        self.scale_frozen = False
        self.scale_restarts = 0

    # -- state ------------------------------------------------------------------------------

    def reset(self, pose: np.ndarray, cov: np.ndarray, scale: float | None = None) -> None:
        """Start from a pose and its 3x3 covariance; the odometry scale is kept across resets."""
        scale = float(self.ekf.x[3, 0]) if scale is None else float(scale)
        bias = 0.0 if self.gyro_bias_faulty else float(self.ekf.x[4, 0])
        cam = float(self.ekf.x[5, 0])
        x = np.zeros(self.dim)  # the matches' shared error, if a state, starts unknown
        x[:6] = [*np.asarray(pose, dtype=float)[:3], scale, bias, cam]
        self.ekf.x = x.reshape(-1, 1)
        self.ekf.P = np.zeros((self.dim, self.dim))
        self.ekf.P[:3, :3] = np.asarray(cov, dtype=float)
        self.ekf.P[3, 3] = self.scale_sigma0**2
        self.ekf.P[4, 4] = self.gyro_bias_sigma0**2
        self.ekf.P[5, 5] = self.camera_yaw_sigma0**2
        self.ekf.P[6:, 6:] = np.diag(self.match_bias.variances[: self.dim - 6])
        self.initialized = True
        self.rejections = 0
        self.scale_frozen = self.freeze_scale_on_reset

    @property
    def pose(self) -> np.ndarray:
        return self.ekf.x.reshape(-1)[:3].copy()

    @property
    def match_pose(self) -> np.ndarray:
        """Where the next match is expected: the pose plus the matches' shared error."""
        return self._match_h() @ self.ekf.x.reshape(-1)

    @property
    def match_cov(self) -> np.ndarray:
        """The covariance of match_pose: ICP's prior."""
        H = self._match_h()
        return H @ self.ekf.P @ H.T

    def _match_h(self) -> np.ndarray:
        """A match's pose as a function of the state: the pose, plus the shared error."""
        H = np.eye(3, self.dim)
        if self.dim > 6:
            H[:, 6:9] = np.eye(3)
        return H

    @property
    def vehicle_pose(self) -> np.ndarray:
        """(x, y, yaw) of the car: the camera-frame heading minus the camera yaw offset."""
        x = self.ekf.x.reshape(-1)
        return np.array([x[0], x[1], float(wrap_angle(x[2] - x[5]))])

    @property
    def camera_yaw_rad(self) -> float:
        return float(self.ekf.x[5, 0])

    @property
    def cov(self) -> np.ndarray:
        return self.ekf.P[:3, :3].copy()

    @property
    def odometry_scale(self) -> float:
        return float(self.ekf.x[3, 0])

    @property
    def shift_inconsistent(self) -> bool:
        """The last accepted posterior moved the position beyond `consistency_chi2`."""
        return 0 < self.consistency_chi2 < self.last_shift_d2[0]

    @property
    def scale_sigma(self) -> float:
        return float(math.sqrt(max(self.ekf.P[3, 3], 0.0)))

    @property
    def gyro_bias_rps(self) -> float:
        return float(self.ekf.x[4, 0])

    @property
    def gyro_bias_faulty(self) -> bool:
        return abs(self.gyro_bias_rps) > GYRO_BIAS_LIMIT_SIGMAS * self.gyro_bias_sigma0

    @property
    def position_sigma_m(self) -> float:
        return float(math.sqrt(max(np.linalg.eigvalsh(self.ekf.P[:2, :2])[-1], 0.0)))

    @property
    def ok(self) -> bool:
        return (
            self.initialized
            and self.position_sigma_m <= self.max_position_sigma_m
            and self.rejections < self.max_rejections
            and not self.gyro_bias_faulty
        )

    # -- verbs ------------------------------------------------------------------------------

    def predict(self, speed_mps: float, yaw_rate_rps: float, dt_s: float) -> None:
        if not self.initialized or dt_s <= 0:
            return
        _, _, yaw, k, b, cam = self.ekf.x.reshape(-1)[:6]
        yaw_mid = yaw - cam + 0.5 * (yaw_rate_rps - b) * dt_s
        c, s = math.cos(yaw_mid), math.sin(yaw_mid)
        d = k * speed_mps * dt_s
        h = 0.5 * dt_s
        # Jacobians of the motion model w.r.t. the state (x, y, yaw, scale, gyro bias, camera
        # yaw) and the inputs (v, w)
        self.ekf.F = np.array(
            [
                [1.0, 0.0, -d * s, speed_mps * dt_s * c, d * s * h, d * s],
                [0.0, 1.0, d * c, speed_mps * dt_s * s, -d * c * h, -d * c],
                [0.0, 0.0, 1.0, 0.0, -dt_s, 0.0],
                [0.0, 0.0, 0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 0.0, 0.0, 1.0, 0.0],
                [0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            ]
        )
        G = np.array(
            [
                [k * dt_s * c, -d * s * h],
                [k * dt_s * s, d * c * h],
                [0.0, dt_s],
                [0.0, 0.0],
                [0.0, 0.0],
                [0.0, 0.0],
            ]
        )
        sv = self.speed_sigma_rel * abs(speed_mps) + self.speed_sigma_mps
        Q = G @ np.diag([sv**2, self.yaw_rate_sigma_rps**2]) @ G.T
        Q[3, 3] = self.scale_walk_per_s**2 * dt_s
        Q[4, 4] = self.gyro_bias_walk**2 * dt_s
        Q[5, 5] = math.radians(0.001) ** 2 * dt_s  # the mount may settle, slowly
        decay = self.match_bias.decay(d)
        if self.dim > 6:  # the matches' shared error fades as the car drives past its marking
            self.ekf.F = np.pad(self.ekf.F, ((0, 3), (0, 3)))
            self.ekf.F[6:, 6:] = decay * np.eye(3)
            Q = np.pad(Q, ((0, 3), (0, 3)))
            Q[6:, 6:] = np.diag(self.match_bias.variances * (1.0 - decay**2))
        self.ekf.Q = Q
        self.ekf.predict(u=(speed_mps, yaw_rate_rps, dt_s, decay))

    def update_pose(self, pose: np.ndarray, cov: np.ndarray) -> bool:
        """ICP pose measurement; False if gated out."""
        return self._update(np.asarray(pose, float), np.eye(3, self.dim), np.asarray(cov, float))

    def update_posterior(
        self, pose: np.ndarray, information: np.ndarray, gate_chi2: float = 16.27,
        consider_scale: bool = False,
    ) -> bool:
        """Accept a pose already fused with this filter's prediction (ICP with the prediction as
        its prior) together with the information its measurements added (3x3 over the pose).

        The pose block becomes (P^-1 + information)^-1; the odometry scale follows the pose through
        its prior correlation (it is observed only through the pose). Gated by the shift of the
        pose relative to the prediction's covariance. With `consider_scale` the scale's estimate
        and variance stand, as for a frozen scale (information that is no measurement of the
        wheel: a hold of the along-road position at the prediction)."""
        if not self.initialized:
            return False
        considered = (self.scale_frozen and self.frozen_scale_considered) or consider_scale
        if not considered:
            self._decouple_frozen_scale()
        if self.dim > 6:
            return self._shared_error_posterior(pose, information, gate_chi2, considered)
        P = self.ekf.P
        Ppp = P[:3, :3]
        shift = _pose_residual(pose, self.ekf.x.reshape(-1)[:3])
        if not self._shift_passes(shift, Ppp, gate_chi2):
            return False
        Ppp_post = np.linalg.inv(np.linalg.inv(Ppp) + information)
        Ppp_post = 0.5 * (Ppp_post + Ppp_post.T)
        self.last_shift_d2 = shift_consistency(shift[:2], (Ppp - Ppp_post)[:2, :2])
        if self.scale_skips_inconsistent and self.shift_inconsistent:
            self._decouple_scale()  # a pull the covariance cannot explain is not the wheel's
        K = P[3:, :3] @ np.linalg.inv(Ppp)  # regression of the scale on the pose
        x = self.ekf.x.reshape(-1).copy()
        x[3:] = x[3:] + (K * [[0.0], [1.0], [1.0]] if considered else K) @ shift
        x[:3] = np.asarray(pose, float)
        x[2] = float(wrap_angle(x[2]))
        x[3] = _clamp_scale(x[3])
        P_new = np.empty_like(P)
        P_new[:3, :3] = Ppp_post
        P_new[3:, :3] = K @ Ppp_post
        P_new[:3, 3:] = P_new[3:, :3].T
        P_new[3:, 3:] = P[3:, 3:] - K @ P[:3, 3:] + K @ Ppp_post @ K.T
        if considered:  # the scale's own variance and its covariance with the others stand
            gain = np.eye(3) - Ppp_post @ np.linalg.inv(Ppp)  # of the pose, shift = gain @ z
            P_new[3, 3] = P[3, 3]
            P_new[3, 4:] = P_new[4:, 3] = P[3, 4:] - P[3, :3] @ gain.T @ K[1:].T
        self.ekf.x = x.reshape(-1, 1)
        self.ekf.P = P_new
        self._restart_faulty_scale()
        return True

    def _shift_passes(self, shift: np.ndarray, cov: np.ndarray, gate_chi2: float) -> bool:
        """The gate of update_posterior: the fused pose's shift against its prior's covariance
        (counting rejections)."""
        self.last_nis = float(shift @ np.linalg.solve(cov, shift))
        if self.last_nis > gate_chi2:
            self.rejections += 1
            return False
        self.rejections = 0
        return True

    def _shared_error_posterior(self, pose, information, gate_chi2: float,
                                considered: bool) -> bool:
        """update_posterior where a match observes the pose plus the matches' shared error
        (MatchBias), and ICP had match_pose and match_cov as its prior.

        ICP's pose is the prior fused with its points: (S^-1 + I) shift = I (z - prior), with S
        the prior's covariance and I the points' information. That is a measurement z of the
        match along the directions I observes (its eigenvectors), each with variance 1 / its
        eigenvalue, and a Kalman update of the whole state with it splits the shift between the
        pose (and, through their covariance, the scale and the rest) and the shared error."""
        x, H = self.ekf.x.reshape(-1), self._match_h()
        S = H @ self.ekf.P @ H.T
        shift = _pose_residual(pose, H @ x)
        if not self._shift_passes(shift, S, gate_chi2):
            return False
        info = 0.5 * (information + information.T)
        w, V = np.linalg.eigh(info)
        seen = w > 1e-9 * max(float(w[-1]), 1e-300)
        V, w = V[:, seen], w[seen]
        z = V.T @ (np.linalg.solve(S, shift) + info @ shift) / w
        Hz, R = V.T @ H, np.diag(1.0 / w)
        P_prior = self.ekf.P.copy()
        x_new, P_new = _kalman_step(x, P_prior, z, Hz, R, considered)
        self.last_shift_d2 = shift_consistency(x_new[:2] - x[:2], (P_prior - P_new)[:2, :2])
        if self.scale_skips_inconsistent and self.shift_inconsistent:
            self._decouple_scale()  # a pull the covariance cannot explain is not the wheel's
            x_new, P_new = _kalman_step(x, self.ekf.P, z, Hz, R, considered)
        self.ekf.x, self.ekf.P = x_new.reshape(-1, 1), P_new
        self._restart_faulty_scale()
        return True

    def update_position(self, xy: np.ndarray, sigma_m: float, min_sigma_m: float = 0.0) -> bool:
        """GNSS position measurement (isotropic sigma); False if gated out. A filter whose
        position sigma is already below min_sigma_m only gates the fix (counting rejections):
        fixes whose error is a slow bias must not average the filter's sigma below that bias."""
        H = np.eye(2, self.dim)
        z, R = np.asarray(xy, float), np.eye(2) * sigma_m**2
        if self.initialized and self.position_sigma_m < min_sigma_m:
            return self._gate(z, H, R)
        return self._update(z, H, R)

    def _inflate(self) -> None:
        """Pose measurements keep disagreeing with the filter: doubt the filter, not them."""
        self.ekf.P[:3, :3] += np.diag(
            [self.inflate_m**2, self.inflate_m**2, self.inflate_yaw_rad**2]
        )
        self.inflations += 1

    def innovation(self, z: np.ndarray, H: np.ndarray, R: np.ndarray):
        """(innovation, its covariance, squared Mahalanobis distance) of a linear measurement."""
        y = _pose_residual(z, H @ self.ekf.x.reshape(-1))
        S = H @ self.ekf.P @ H.T + R
        return y, S, float(y @ np.linalg.solve(S, y))

    def _gate(self, z, H, R) -> bool:
        """The chi-square gate alone, with its rejection counts; True if the fix passes."""
        _, _, d2 = self.innovation(z, H, R)
        self.last_nis = d2
        if d2 > self.chi2[len(z)]:
            self.rejections += 1
            self.gnss_rejections += 1
            return False
        self.rejections = 0
        self.gnss_rejections = 0
        return True

    def along_road_fixed(self, sigma_m: float) -> None:
        """An accepted match alone knew the along-road position to within sigma_m."""
        if sigma_m <= self.scale_thaw_sigma_m:
            self.scale_frozen = False

    def _considered_update(self, z, H, R) -> None:
        """A linear update that leaves the frozen scale's estimate and variance as they are
        but keeps its covariance with the rest of the state right (the Schmidt-Kalman "consider"
        form, Joseph-stabilized): the drift its error builds stays known, for the match that
        thaws it to learn from."""
        y, _, _ = self.innovation(z, H, R)
        x, self.ekf.P = _kalman_step(self.ekf.x.reshape(-1), self.ekf.P, y, H, R, True)
        self.ekf.x = x.reshape(-1, 1)

    def _restart_faulty_scale(self) -> None:
        """An update that drove the scale to SCALE_LIMIT read a pull as the wheel's: a start off
        along the road, pulled back by fixes its too small covariance called sure (held-out
        Karlsruhe s462: 0.95 against a true 0.990; 25 s of dead reckoning later, 2.9 m off). The
        scale starts again from its prior, as at a reset, uncorrelated with the rest."""
        if abs(self.odometry_scale - 1.0) < SCALE_LIMIT - 1e-9:
            return
        self._decouple_scale()
        self.ekf.x[3, 0], self.ekf.P[3, 3] = 1.0, self.scale_sigma0**2
        self.scale_frozen = self.freeze_scale_on_reset
        self.scale_restarts += 1

    def _decouple_frozen_scale(self) -> None:
        """A frozen scale learns nothing from the next measurement."""
        if self.scale_frozen:
            self._decouple_scale()

    def _decouple_scale(self) -> None:
        """The scale's correlation with the rest of the state (what the motion since the last
        measurement built) dropped, its variance kept: the next measurement moves it not."""
        P = self.ekf.P
        P[3, :3] = P[:3, 3] = 0.0
        P[3, 4:] = P[4:, 3] = 0.0

    def _update(self, z, H, R) -> bool:
        if not self.initialized:
            return False
        considered = self.scale_frozen and self.frozen_scale_considered
        if not considered:
            self._decouple_frozen_scale()
        _, _, d2 = self.innovation(z, H, R)
        self.last_nis = d2
        pose = len(z) == 3
        if d2 > self.chi2[len(z)]:
            self.rejections += 1
            self.pose_rejections += pose
            self.gnss_rejections += not pose
            if pose and self.pose_rejections % self.inflate_after == 0:
                self._inflate()
            return False
        self.rejections = 0
        self.pose_rejections = 0 if pose else self.pose_rejections
        self.gnss_rejections = self.gnss_rejections if pose else 0
        if considered:
            self._considered_update(z, H, R)
        else:
            self.ekf.update(
                z.reshape(-1, 1),
                lambda _x: H,
                lambda x: H @ x,
                R=R,
                residual=lambda a, b: _pose_residual(a.reshape(-1), b.reshape(-1)).reshape(-1, 1),
            )
            self.ekf.x[2, 0] = float(wrap_angle(self.ekf.x[2, 0]))
            self.ekf.x[3, 0] = _clamp_scale(self.ekf.x[3, 0])
        self._restart_faulty_scale()
        return True
