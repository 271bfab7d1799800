"""Class-aware point-to-map ICP on SE(2) (paper eq. 4).

The frame's semantic points (vehicle frame, metres) are matched to the nearest map cell of the
same class; Gauss-Newton with Huber weights and a shrinking correspondence gate estimates
T_world_vehicle = (x, y, yaw). The covariance is the inverse information matrix scaled by the
residuals; directions the geometry does not constrain (lane lines only: along the road) are
detected from the information matrix's eigenvalues, left out of the update and inflated.

The distance to the nearest cell is zero for every point on a marking, so that cost is flat over
a marking's width (a 0.15 m lane line: poses 0.1 m and 1 deg apart score the same). When the map
offers a likelihood field (`field(points, slots)`: each class's mask blurred by a Gaussian, with
its gradient), a few Gauss-Newton iterations on 1 - field refine the pose to the markings'
centres, and the pose's information comes from that smooth cost."""

import math
from dataclasses import dataclass, field

import numpy as np

from common.config import LocalizerConfig
from common.geometry import wrap_angle
from common.grid import CELL_M

DEGENERATE_VARIANCE = 25.0  # (5 m)^2 / (5 rad)^2-ish: "no information" in that direction


@dataclass(frozen=True)
class IcpResult:
    pose: np.ndarray  # (x, y, yaw) T_world_vehicle
    cov: np.ndarray  # 3x3 over (x, y, yaw)
    inliers: int
    points: int
    rmse_m: float
    degenerate: bool
    weak_direction: np.ndarray  # unit 3-vector of the least constrained direction
    info_eigs: np.ndarray  # eigenvalues of the (normalized) information matrix, ascending
    iterations: int
    attitude: np.ndarray = field(default_factory=lambda: np.zeros(0))  # camera (pitch, roll) rad
    information: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))  # of the points only

    @property
    def inlier_ratio(self) -> float:
        return self.inliers / max(self.points, 1)


def _jacobian(dx, dy, rx, ry, c, s, jac_v) -> np.ndarray:
    """Rows d residual / d (x, y, yaw[, attitude...]) of a residual whose gradient w.r.t. the
    world point is (dx, dy): (dx, dy)^T [[1, 0, -ry], [0, 1, rx]], plus (dx, dy)^T R d point /
    d attitude for jac_v (N, 2, k); (rx, ry) is the point rotated by the pose's yaw (c, s)."""
    cols = [dx, dy, rx * dy - ry * dx]
    if jac_v is not None:
        for k in range(jac_v.shape[2]):
            jx = c * jac_v[:, 0, k] - s * jac_v[:, 1, k]
            jy = s * jac_v[:, 0, k] + c * jac_v[:, 1, k]
            cols.append(dx * jx + dy * jy)
    return np.stack(cols, axis=1)


def _robust_weights(err_m: np.ndarray, huber_m: float) -> np.ndarray:
    w = np.ones_like(err_m)
    big = err_m > huber_m
    w[big] = huber_m / err_m[big]
    return w


@dataclass(frozen=True)
class IpmNoise:
    """How far a ground point from inverse perspective mapping may be off: one pixel of label
    noise moves a point at range r (from the camera) by r^2 / (f h) along the viewing ray and
    by r / f across it (f focal length in pixels, h camera height). Residuals along the ray of
    far points weigh less: sigma0^2 / (sigma0^2 + that error along the residual's direction)."""

    along_per_m2: float  # sigma_px / (f h)
    across_per_m: float  # sigma_px / f
    camera_xy: tuple[float, float]  # camera position in the vehicle frame
    sigma0_m: float

    @classmethod
    def from_camera(cls, camera, sigma_px: float, sigma0_m: float) -> "IpmNoise":
        f, h = float(camera.K[0, 0]), float(camera.T_vehicle_camera[2, 3])
        xy = camera.T_vehicle_camera[:2, 3]
        return cls(sigma_px / (f * h), sigma_px / f, (float(xy[0]), float(xy[1])), sigma0_m)

    def weights(self, pts_v: np.ndarray, nx: np.ndarray, ny: np.ndarray, c: float, s: float):
        """Per-point weights for residual directions (nx, ny) in the world (pose yaw c, s)."""
        dx, dy = pts_v[:, 0] - self.camera_xy[0], pts_v[:, 1] - self.camera_xy[1]
        r = np.maximum(np.hypot(dx, dy), 1e-6)
        nvx, nvy = c * nx + s * ny, -s * nx + c * ny  # direction in the vehicle frame
        along = (nvx * dx + nvy * dy) / r  # its components along and across the ray
        across = (-nvx * dy + nvy * dx) / r
        var = (along * self.along_per_m2 * r * r) ** 2 + (across * self.across_per_m * r) ** 2
        return self.sigma0_m**2 / (self.sigma0_m**2 + var)


def _normal_equations(pts_v, jac_v, nearest, pose, gate_m, huber_m, ipm=None):
    """Distance of points (vehicle frame) placed at pose to their nearest map cells (0.1 m squares).

    The residual is the scalar distance to the cell's square, so points already on a map cell of
    their class add no information: the Hessian comes from the points that are off the map, and
    steps are full Gauss-Newton steps (point-to-point with dense cells would crawl). With
    jac_v (N, 2, k) = d point / d camera attitude, the attitude gets k extra columns."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rx = c * pts_v[:, 0] - s * pts_v[:, 1]
    ry = s * pts_v[:, 0] + c * pts_v[:, 1]
    ex = rx + pose[0] - nearest[:, 0]
    ey = ry + pose[1] - nearest[:, 1]
    half = 0.5 * CELL_M
    ex = np.sign(ex) * np.maximum(np.abs(ex) - half, 0.0)
    ey = np.sign(ey) * np.maximum(np.abs(ey) - half, 0.0)
    err = np.hypot(ex, ey)
    inl = err < gate_m
    on = err > 1e-9
    nx = np.where(on, ex / np.where(on, err, 1.0), 0.0)
    ny = np.where(on, ey / np.where(on, err, 1.0), 0.0)
    w = _robust_weights(err, huber_m) * inl
    if ipm is not None:
        w = w * ipm.weights(pts_v, nx, ny, c, s)
    J = _jacobian(nx, ny, rx, ry, c, s, jac_v)
    H = (J * w[:, None]).T @ J
    g = J.T @ (w * err)
    return H, g, err, inl, w


class Icp:
    """Point-to-map ICP against a map exposing `nearest(points_world, slots)`.

    Optionally also estimates the camera's pitch and roll offset of the frame (vibration,
    calibration error): IPM points move with the attitude by their jacobians (common.camera
    perturbed), so far points are not mistaken for a longitudinal shift."""

    def __init__(
        self,
        *,
        iterations: int = LocalizerConfig.icp_iterations,
        gate_start_m: float = LocalizerConfig.icp_gate_start_m,
        gate_end_m: float = LocalizerConfig.icp_gate_end_m,
        huber_m: float = LocalizerConfig.icp_huber_m,
        yaw_lever_m: float = 8.0,
        degenerate_ratio: float = 1e-3,
        cov_scale: float = LocalizerConfig.icp_cov_scale,
        point_sigma_m: float = 0.05,
        probe_m: float = 0.1,
        attitude_sigma_rad: float = math.radians(LocalizerConfig.attitude_sigma_deg),
        min_sigma_m: float = 0.01,
        min_sigma_yaw_rad: float = 0.001,
        min_points: int = 30,
        refine_iterations: int = LocalizerConfig.icp_refine_iterations,
        field_sigma: float = 0.1,
        field_min: float = 0.02,
        field_slots: tuple = (1, 2),  # lane line, stop line
        ipm: IpmNoise | None = None,
    ):
        self.iterations = iterations
        self.gate_start_m, self.gate_end_m = gate_start_m, gate_end_m
        self.huber_m = huber_m
        self.yaw_lever_m = yaw_lever_m  # yaw in "metres at this lever" when comparing eigenvalues
        self.degenerate_ratio = degenerate_ratio
        self.cov_scale = cov_scale  # neighbouring points are correlated: n points != n samples
        self.point_sigma_m = point_sigma_m  # distance noise of one point at the probe poses
        self.probe_m = probe_m
        # the points are correlated (cov_scale of them count as one): weigh the prior alike, or
        # 700 points of one crosswalk drag the pitch degrees away
        self.attitude_prior = (point_sigma_m / attitude_sigma_rad) ** 2 * cov_scale
        self.min_sigma_m, self.min_sigma_yaw_rad = min_sigma_m, min_sigma_yaw_rad
        self.min_points = min_points
        self.refine_iterations = refine_iterations
        self.field_sigma = field_sigma  # noise of one point's field residual (1 - field)
        self.field_min = field_min  # points where the field is below this have no match
        self.field_slots = np.asarray(field_slots)  # class slots refined on the field
        self.ipm = ipm  # range-dependent weights of the frame's points (None: all alike)

    def register(
        self,
        points_v: np.ndarray,
        slots: np.ndarray,
        pose0: np.ndarray,
        local_map,
        jacobians: np.ndarray | None = None,
        prior_cov: np.ndarray | None = None,
        gate_start_m: float | None = None,
    ):
        """Align points (N, 2) of class slots (N,) to the map from an initial pose; None if too few.

        jacobians: optional (N, 2, k) derivatives of the points w.r.t. camera pitch and roll.
        prior_cov: optional 3x3 covariance of pose0 (the filter's prediction): a prior that keeps
        directions the points hardly constrain (the flat bottom of the cost) where they were.
        gate_start_m: correspondence gate of the first iteration (tracking: small, so the
        match cannot jump to the next dash)."""
        g0 = self.gate_start_m if gate_start_m is None else gate_start_m
        pose = np.asarray(pose0, dtype=np.float64).copy()
        if len(points_v) < self.min_points:
            return None
        pts0 = np.asarray(points_v, dtype=np.float64)
        jac = None if jacobians is None else np.asarray(jacobians, dtype=np.float64)
        att = np.zeros(0 if jac is None else jac.shape[2])
        scale = np.array([1.0, 1.0, self.yaw_lever_m])  # information in comparable units
        prior = (
            None
            if prior_cov is None
            else (self.point_sigma_m**2 * self.cov_scale * np.linalg.inv(prior_cov))
        )
        pose_prior = pose.copy()
        solved = self._nearest_iterations(pts0, jac, slots, pose, att, local_map, g0, scale,
                                          prior, pose_prior)
        if solved is None:
            return None
        pose, att, it = solved
        refined = None
        if self.refine_iterations and hasattr(local_map, "field"):
            # lines only: a blurred area (road, an arrow, a crosswalk stripe cut off by the ROI)
            # pulls the points along its visible edges inwards, a bias as large as the blur
            # (measured: 0.58 m along a crosswalk); a line is seen across its whole width
            thin = np.where(np.isin(slots, self.field_slots), slots, -1)
            refined = self._refine(pts0, jac, thin, pose, att, local_map, scale, prior, pose_prior)
        if refined is not None:
            pose, att, H_field = refined
        return self._result(
            _moved(pts0, jac, att),
            jac,
            slots,
            pose,
            local_map,
            scale,
            it + 1,
            att,
            None if refined is None else H_field,
        )

    def _nearest_iterations(self, pts0, jac, slots, pose, att, local_map, g0, scale, prior,
                            pose_prior):
        """Gauss-Newton on nearest map cells with a shrinking gate: (pose, attitude, the last
        iteration's index), or None when too few points stay inliers."""
        it = 0
        for it in range(self.iterations):
            gate = g0 + (self.gate_end_m - g0) * it / max(self.iterations - 1, 1)
            pts = _moved(pts0, jac, att)
            nearest, valid = local_map.nearest(_to_world(pts, pose), slots)
            H, g, err, inl, w = _normal_equations(
                pts[valid],
                None if jac is None else jac[valid],
                nearest[valid],
                pose,
                gate,
                self.huber_m,
                self.ipm,
            )
            if inl.sum() < self.min_points:
                return None
            _add_prior(H, g, pose, pose_prior, prior)
            step, d_att = self._step(H, g, att, scale)
            pose = pose + step
            pose[2] = float(wrap_angle(pose[2]))
            att = att + d_att
            if np.abs(step[:2]).max() < 1e-4 and abs(step[2]) < 1e-5 and it >= 2:
                break
        return pose, att, it

    def _refine(self, pts0, jac, slots, pose, att, local_map, scale, prior, pose_prior):
        """Gauss-Newton on the likelihood field from the nearest-cell optimum: (pose, attitude,
        pose information in distance units) or None when too few points reach the field.

        1 - field is not zero at a ridge, so plain Gauss-Newton overshoots across thin markings:
        every step is halved until the cost (with the priors) goes down."""
        pose, att = pose.copy(), att.copy()
        to_dist = (self.point_sigma_m / self.field_sigma) ** 2  # field units -> metres units

        def cost(pose, att):
            value, _, valid = local_map.field(_to_world(_moved(pts0, jac, att), pose), slots)
            c = float(((1.0 - value[valid]) ** 2).sum()) * to_dist
            c += self.attitude_prior * float(att @ att)
            if prior is not None:
                delta = _pose_delta(pose, pose_prior)
                c += float(delta @ prior @ delta)
            return c

        current = cost(pose, att)
        for _ in range(self.refine_iterations):
            H, g, n = _field_equations(
                _moved(pts0, jac, att), jac, slots, pose, local_map, self.field_min, self.ipm
            )
            if n < self.min_points:
                return None
            H, g = H * to_dist, g * to_dist
            _add_prior(H, g, pose, pose_prior, prior)
            step, d_att = self._step(H, g, att, scale)
            for _halving in range(5):
                trial = pose + step
                trial[2] = float(wrap_angle(trial[2]))
                c = cost(trial, att + d_att)
                if c < current:
                    break
                step, d_att = 0.5 * step, 0.5 * d_att
            else:
                break
            pose, att, current = trial, att + d_att, c
            if np.abs(step[:2]).max() < 1e-4 and abs(step[2]) < 1e-5:
                break
        H, _, n = _field_equations(
            _moved(pts0, jac, att), jac, slots, pose, local_map, self.field_min, self.ipm
        )
        if n < self.min_points:
            return None
        return pose, att, H * to_dist

    def _step(self, H, g, att, scale):
        """Pose step in the constrained directions (attitude eliminated), then the attitude step."""
        if len(att) == 0:
            return _constrained_step(H, g, scale, self.degenerate_ratio), att
        Hpp, Hpa, Haa = H[:3, :3], H[:3, 3:], H[3:, 3:] + self.attitude_prior * np.eye(len(att))
        gp, ga = g[:3], g[3:] + self.attitude_prior * att
        Haa_inv = np.linalg.inv(Haa)
        step = _constrained_step(
            Hpp - Hpa @ Haa_inv @ Hpa.T, gp - Hpa @ Haa_inv @ ga, scale, self.degenerate_ratio
        )
        return step, -Haa_inv @ (ga + Hpa.T @ step)

    def _pose_information(self, H, n_att):
        if n_att == 0:
            return H
        Haa = H[3:, 3:] + self.attitude_prior * np.eye(n_att)
        return H[:3, :3] - H[:3, 3:] @ np.linalg.solve(Haa, H[3:, :3])

    def _result(
        self, pts, jac, slots, pose, local_map, scale, iterations, att, H_field=None
    ) -> IcpResult:
        nearest, valid = local_map.nearest(_to_world(pts, pose), slots)
        _, _, err, inl, w = _normal_equations(
            pts[valid], None, nearest[valid], pose, self.gate_end_m, self.huber_m, self.ipm
        )
        if H_field is None:
            H_field = self._smoothed_information(pts, jac, slots, pose, local_map, scale)
        H = self._pose_information(H_field, len(att))
        cov, inflation, eigs, weak, degenerate, info = _covariance(
            H, scale, self.degenerate_ratio
        )
        cov = cov * self.point_sigma_m**2 * self.cov_scale + inflation
        info = info / (self.point_sigma_m**2 * self.cov_scale)
        cov[0, 0] += self.min_sigma_m**2
        cov[1, 1] += self.min_sigma_m**2
        cov[2, 2] += self.min_sigma_yaw_rad**2
        n = int(inl.sum())
        rmse = float(np.sqrt(np.mean(err[inl] ** 2))) if n else float("inf")
        return IcpResult(
            pose, cov, n, len(pts), rmse, degenerate, weak, eigs, iterations, att, info
        )

    def _smoothed_information(self, pts, jac, slots, pose, local_map, scale):
        """Information matrix averaged over poses a probe step away in each direction.

        At the optimum most points sit on their map cells (zero distance, no gradient); the
        curvature of the cost just around the optimum is what constrains the pose."""
        H = 0.0
        for k in range(3):
            for sign in (-1.0, 1.0):
                probe = pose.copy()
                probe[k] += sign * self.probe_m / scale[k]
                nearest, valid = local_map.nearest(_to_world(pts, probe), slots)
                Hk, *_ = _normal_equations(
                    pts[valid],
                    None if jac is None else jac[valid],
                    nearest[valid],
                    probe,
                    self.gate_end_m,
                    self.huber_m,
                    self.ipm,
                )
                H = H + Hk / 6.0
        return H


def _field_equations(pts_v, jac_v, slots, pose, local_map, field_min, ipm=None):
    """Normal equations of the residuals 1 - field(point) over (pose, attitude); (H, g, points
    that reach the field)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rx = c * pts_v[:, 0] - s * pts_v[:, 1]
    ry = s * pts_v[:, 0] + c * pts_v[:, 1]
    value, grad, valid = local_map.field(np.stack([rx + pose[0], ry + pose[1]], axis=1), slots)
    use = valid & (value > field_min)
    r = np.where(use, 1.0 - value, 0.0)
    gx, gy = np.where(use, -grad[:, 0], 0.0), np.where(use, -grad[:, 1], 0.0)
    J = _jacobian(gx, gy, rx, ry, c, s, jac_v)
    if ipm is None:
        return J.T @ J, J.T @ r, int(use.sum())
    norm = np.maximum(np.hypot(gx, gy), 1e-12)
    w = ipm.weights(pts_v, gx / norm, gy / norm, c, s)
    return (J * w[:, None]).T @ J, J.T @ (w * r), int(use.sum())


def _pose_delta(pose, pose_prior) -> np.ndarray:
    delta = pose - pose_prior
    delta[2] = float(wrap_angle(delta[2]))
    return delta


def _add_prior(H, g, pose, pose_prior, prior) -> None:
    """Add the pose prior (information `prior` about pose_prior, or None) to H and g in place."""
    if prior is not None:
        H[:3, :3] += prior
        g[:3] += prior @ _pose_delta(pose, pose_prior)


def _moved(pts0, jac, att):
    return pts0 if jac is None or len(att) == 0 else pts0 + jac @ att


def _to_world(pts_v: np.ndarray, pose: np.ndarray) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.stack(
        [c * pts_v[:, 0] - s * pts_v[:, 1] + pose[0], s * pts_v[:, 0] + c * pts_v[:, 1] + pose[1]],
        axis=1,
    )


def _scaled_eig(H: np.ndarray, scale: np.ndarray):
    Hs = H / np.outer(scale, scale)  # information over (x, y, lever * yaw)
    eigs, vecs = np.linalg.eigh(Hs)
    return eigs, vecs


def _constrained_step(H, g, scale, ratio):
    """Gauss-Newton step solved only in the well-constrained eigen-directions."""
    eigs, vecs = _scaled_eig(H, scale)
    top = max(eigs[-1], 1e-12)
    gs = g / scale
    step_s = np.zeros(3)
    for k in range(3):
        if eigs[k] > ratio * top:
            step_s -= vecs[:, k] * (vecs[:, k] @ gs) / eigs[k]
    return step_s / scale


def _covariance(H, scale, ratio):
    """Inverse information (unit variance), plus an inflation for unconstrained directions, and
    the information with those directions removed.

    The removal is done on the eigen-decomposition in scaled coordinates: pinv of the finite
    covariance is NOT it (pinv does not commute with the scaling; its null direction is
    scale * v instead of v / scale, so a lane-line-only match, weak along the road, passed on a
    confident mix of the along-road position and yaw, and the filter's along-road sigma
    collapsed from 0.4 m to 0.5 mm on the first frame after initialization)."""
    eigs, vecs = _scaled_eig(H, scale)
    top = max(eigs[-1], 1e-12)
    var = np.empty(3)
    degenerate = False
    for k in range(3):
        if eigs[k] > ratio * top:
            var[k] = 1.0 / eigs[k]
        else:
            var[k] = np.inf
            degenerate = True
    cov_s = (vecs * np.where(np.isinf(var), 0.0, var)) @ vecs.T
    cov = cov_s / np.outer(scale, scale)
    weak = vecs[:, 0] / scale
    weak = weak / max(np.linalg.norm(weak), 1e-12)
    inflation = np.zeros((3, 3))
    for k in np.flatnonzero(np.isinf(var)):
        v = vecs[:, k] / scale
        inflation += DEGENERATE_VARIANCE * np.outer(v, v) / max(v @ v, 1e-12)
    kept = np.where(np.isinf(var), 0.0, eigs)
    info = (vecs * kept) @ vecs.T * np.outer(scale, scale)
    return cov, inflation, eigs / top, weak, degenerate, info
