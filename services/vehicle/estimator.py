"""Vehicle pose estimation for mapping: wheel speed + gyro odometry and GNSS into the pose graph.

Consumes time-stamped sensor samples (ns) and frame times; produces, in frame order, the frames
whose optimized pose is settled (x, y, yaw in the world ENU frame, metres / radians). Odometry
scale and gyro bias are calibrated online from the GNSS-good part of the drive, so a GNSS outage
is bridged by calibrated odometry and then smoothed when GNSS returns."""

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from common.config import VehicleConfig
from common.geometry import se2_compose, wrap_angle
from services.vehicle.pose_graph import PoseGraph

logger = logging.getLogger(__name__)

NS = 1e-9
GAP_S = 2.0  # a GNSS silence longer than this is an outage (large correction when it ends)
COVERED_S = 0.6  # a node is GNSS-covered when a good fix lies within this time
MIN_SCALE_CHORD_M = 20.0  # calibration windows shorter than this give no scale evidence


def integrate_odometry(
    t0_ns, t1_ns, odom_t_ns, speed_mps, imu_t_ns, yaw_rate_rps, *, scale=1.0, gyro_bias_rps=0.0
):
    """Dead-reckon from t0 to t1: (delta (dx, dy, dyaw) in the start frame, distance_m).

    Speed and yaw rate are linearly interpolated onto the union of sample times and integrated
    with the midpoint heading; speed is multiplied by `scale`, `gyro_bias_rps` is subtracted."""
    inner = lambda t: t[(t > t0_ns) & (t < t1_ns)]  # noqa: E731
    grid = np.unique(np.concatenate([[t0_ns, t1_ns], inner(odom_t_ns), inner(imu_t_ns)]))
    v = _interp(grid, odom_t_ns, speed_mps) * scale
    w = _interp(grid, imu_t_ns, yaw_rate_rps) - gyro_bias_rps
    dt = np.diff(grid) * NS
    ds = 0.5 * (v[1:] + v[:-1]) * dt
    dth = 0.5 * (w[1:] + w[:-1]) * dt
    th = np.concatenate([[0.0], np.cumsum(dth)])
    mid = 0.5 * (th[1:] + th[:-1])
    delta = np.array([np.sum(ds * np.cos(mid)), np.sum(ds * np.sin(mid)), th[-1]])
    return delta, float(np.sum(np.abs(ds)))


def _interp(t, ts, vs):
    if len(ts) == 0:
        return np.zeros(len(t))
    return np.interp(t.astype(np.float64), ts.astype(np.float64), vs)


def dead_reckon(start_pose, deltas) -> np.ndarray:
    """Chain SE2 deltas (N, 3) from start_pose -> poses (N + 1, 3)."""
    poses = [np.asarray(start_pose, float)]
    for d in deltas:
        poses.append(se2_compose(poses[-1], d))
    return np.array(poses)


def fit_rigid_2d(src_xy: np.ndarray, dst_xy: np.ndarray):
    """Least-squares rotation + translation with dst = R src + t -> (yaw, t)."""
    cs, cd = src_xy.mean(axis=0), dst_xy.mean(axis=0)
    a, b = src_xy - cs, dst_xy - cd
    yaw = math.atan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b))
    c, s = math.cos(yaw), math.sin(yaw)
    t = cd - np.array([[c, -s], [s, c]]) @ cs
    return yaw, t


class SampleBuffer:
    """Recent (t_ns, value) samples; old ones are trimmed as frames advance."""

    def __init__(self):
        self.t = np.zeros(0, np.int64)
        self.v = np.zeros(0, np.float64)

    def add(self, t_ns, values) -> None:
        self.t = np.concatenate([self.t, np.atleast_1d(np.asarray(t_ns, np.int64))])
        self.v = np.concatenate([self.v, np.atleast_1d(np.asarray(values, np.float64))])

    def trim_before(self, t_ns: int) -> None:
        keep = max(int(np.searchsorted(self.t, t_ns)) - 1, 0)  # keep one sample before t
        self.t, self.v = self.t[keep:], self.v[keep:]

    def at(self, t_ns: int) -> float:
        return float(_interp(np.array([t_ns]), self.t, self.v)[0])


@dataclass
class Calibration:
    """Odometry scale and gyro bias, estimated from windows of GNSS-settled optimized poses."""

    scale: float = 1.0
    gyro_bias_rps: float = 0.0
    chord_opt_m: float = 0.0
    chord_raw_m: float = 0.0
    yaw_excess_rad: float = 0.0
    time_s: float = 0.0
    windows: int = 0

    def add_window(self, chord_opt_m, chord_raw_m, gyro_dyaw_rad, opt_dyaw_rad, dt_s) -> None:
        if chord_raw_m >= MIN_SCALE_CHORD_M:
            self.chord_opt_m += chord_opt_m
            self.chord_raw_m += chord_raw_m
            self.scale = self.chord_opt_m / self.chord_raw_m
        self.yaw_excess_rad += wrap_angle(gyro_dyaw_rad - opt_dyaw_rad)
        self.time_s += dt_s
        self.gyro_bias_rps = self.yaw_excess_rad / self.time_s
        self.windows += 1


@dataclass
class _Node:
    t_ns: int
    raw_delta: np.ndarray  # uncalibrated odometry from the previous node (scale 1, bias 0)
    delta: np.ndarray  # calibrated odometry from the previous node
    covered: bool = False
    precise: bool = False  # covered by a fix good enough to calibrate odometry with


@dataclass
class PoseEstimator:
    """Frames -> settled optimized poses. One verb per input; `settled()` hands poses out in order.

    settle_lag_s: a frame is settled once a good GNSS fix at least this much later is in the graph
    (so an outage holds its frames until GNSS returns); max_wait_s: commit anyway after this long;
    calib_window_s: length of the windows that calibrate odometry scale and gyro bias;
    init_baseline_m: GNSS travel needed to fix the initial heading; calibrate: estimate scale/bias
    (only from windows covered by fixes with sigma <= calib_max_gnss_sigma_m, i.e. RTK)."""

    settle_lag_s: float = VehicleConfig.settle_lag_s
    max_wait_s: float = VehicleConfig.max_wait_s
    calib_window_s: float = VehicleConfig.calib_window_s
    init_baseline_m: float = 5.0
    calibrate: bool = True
    gnss_sigma_floor_m: float = 0.01
    calib_max_gnss_sigma_m: float = 0.2  # consumer GNSS is too coarse to calibrate with
    graph: PoseGraph = field(default_factory=PoseGraph)
    calibration: Calibration = field(default_factory=Calibration)

    def __post_init__(self):
        self._odom, self._imu = SampleBuffer(), SampleBuffer()
        self._nodes: list[_Node] = []
        self._pending_fixes: list[tuple[int, np.ndarray, float]] = []
        self._fixes: list[tuple[int, int, np.ndarray, float]] = []  # node, t, xy, sigma (pre-init)
        self._local: list[np.ndarray] = []  # dead-reckoned poses before initialization
        self._pred: np.ndarray | None = None  # latest predicted/optimized pose of the last node
        self._initialized = False
        self._last_fix_ns: int | None = None
        self._next_settle = 0
        self._calib_start = None

    # -- inputs ------------------------------------------------------------------------------

    def add_odometry(self, t_ns, speed_mps) -> None:
        self._odom.add(t_ns, speed_mps)

    def add_imu(self, t_ns, yaw_rate_rps) -> None:
        self._imu.add(t_ns, yaw_rate_rps)

    def add_gnss(self, t_ns: int, xy_m, sigma_m: float, ok: bool) -> None:
        """A GNSS fix; bad fixes (ok False) are ignored, as the paper uses only good RTK fixes."""
        if ok and np.all(np.isfinite(xy_m)) and np.isfinite(sigma_m) and sigma_m > 0:
            self._pending_fixes.append((int(t_ns), np.asarray(xy_m, float), float(sigma_m)))

    def add_frame(self, t_ns: int) -> int:
        """A camera frame at t_ns becomes pose node len(nodes); returns its index."""
        i = len(self._nodes)
        self._nodes.append(self._make_node(i, int(t_ns)))  # 1. odometry from the previous frame
        self._attach_fixes(i)  # 2. GNSS fixes up to this frame onto the nearest node
        if not self._initialized:
            self._try_initialize()  # 3. heading from the first GNSS baseline
        else:
            self._add_to_graph(i)
        if self._initialized:
            self.graph.optimize()  # 4. one incremental ISAM2 step with only the new factors
            self._pred = self.graph.estimate(i)
        self._odom.trim_before(t_ns - 10**9)
        self._imu.trim_before(t_ns - 10**9)
        return i

    # -- outputs -----------------------------------------------------------------------------

    def settled(self, flush: bool = False) -> list[tuple[int, np.ndarray]]:
        """(node, optimized pose) of every newly settled node, in order."""
        if not self._nodes:
            return []
        if flush and not self._initialized:
            self._initialize_without_gnss()
        if not self._initialized:
            return []
        last = len(self._nodes) - 1
        t_last = self._nodes[last].t_ns
        out = []
        while self._next_settle <= last:
            t = self._nodes[self._next_settle].t_ns
            fixed = (
                self._last_fix_ns is not None and self._last_fix_ns >= t + self.settle_lag_s / NS
            )
            if not (flush or fixed or (t_last - t) * NS > self.max_wait_s):
                break
            out.append(self._next_settle)
            self._next_settle += 1
        poses = [self.graph.estimate(i) for i in out]
        if self.calibrate and out:
            self._calibrate_upto(out[-1])
        return list(zip(out, poses, strict=True))

    def node_time_ns(self, i: int) -> int:
        return self._nodes[i].t_ns

    def covered(self, i: int) -> bool:
        return self._nodes[i].covered

    def raw_deltas(self) -> np.ndarray:
        return np.array([n.raw_delta for n in self._nodes])

    # -- steps -------------------------------------------------------------------------------

    def _make_node(self, i: int, t_ns: int) -> _Node:
        if i == 0:
            return _Node(t_ns, np.zeros(3), np.zeros(3))
        t0 = self._nodes[i - 1].t_ns
        args = (t0, t_ns, self._odom.t, self._odom.v, self._imu.t, self._imu.v)
        raw, _ = integrate_odometry(*args)
        cal = self.calibration
        delta, _ = integrate_odometry(*args, scale=cal.scale, gyro_bias_rps=cal.gyro_bias_rps)
        return _Node(t_ns, raw, delta)

    def _attach_fixes(self, i: int) -> None:
        t_i = self._nodes[i].t_ns
        keep = []
        for t_g, xy, sigma in self._pending_fixes:
            if t_g > t_i:
                keep.append((t_g, xy, sigma))
                continue
            k = i if i == 0 or (t_i - t_g) <= (t_g - self._nodes[i - 1].t_ns) else i - 1
            k = max(k, 0)
            if self._last_fix_ns is not None and (t_g - self._last_fix_ns) * NS > GAP_S:
                self.graph.mark_large_correction()
            self._last_fix_ns = t_g if self._last_fix_ns is None else max(self._last_fix_ns, t_g)
            self._fixes.append((k, t_g, xy, max(sigma, self.gnss_sigma_floor_m)))
            self._mark_covered(k, t_g, sigma <= self.calib_max_gnss_sigma_m)
        self._pending_fixes = keep
        if self._initialized:
            self._flush_fixes()

    def _mark_covered(self, k: int, t_g: int, precise: bool) -> None:
        for step in (-1, 1):
            j = k if step < 0 else k + 1
            while 0 <= j < len(self._nodes) and abs(self._nodes[j].t_ns - t_g) * NS <= COVERED_S:
                self._nodes[j].covered = True
                self._nodes[j].precise |= precise
                j += step

    def _fix_at_node(self, k: int, t_g: int, xy: np.ndarray, yaw_k: float) -> np.ndarray:
        """Move a fix taken at t_g to node k's time along the heading (speed x time offset)."""
        dt = (t_g - self._nodes[k].t_ns) * NS
        v = self._odom.at(t_g) * self.calibration.scale if len(self._odom.t) else 0.0
        return xy - v * dt * np.array([math.cos(yaw_k), math.sin(yaw_k)])

    def _flush_fixes(self) -> None:
        for k, t_g, xy, sigma in self._fixes:
            yaw_k = self._pred[2] if self._pred is not None else 0.0
            self.graph.add_gnss(k, self._fix_at_node(k, t_g, xy, yaw_k), sigma)
        self._fixes = []

    def _add_to_graph(self, i: int) -> None:
        pred = se2_compose(self._pred, self._nodes[i].delta)
        self.graph.add_node(i, pred)
        self.graph.add_odometry(i - 1, i, self._nodes[i].delta)

    def _try_initialize(self) -> None:
        """Align the dead-reckoned start with GNSS once the fixes span init_baseline_m (and ten
        fix sigmas, so consumer-GNSS noise of a standing car never fakes a heading)."""
        if len(self._fixes) < 2:
            return
        gxy = np.array([f[2] for f in self._fixes])
        baseline_m = max(self.init_baseline_m, 10.0 * max(f[3] for f in self._fixes))
        if np.max(np.linalg.norm(gxy - gxy[0], axis=1)) < baseline_m:
            return
        local = dead_reckon(np.zeros(3), [n.delta for n in self._nodes[1:]])
        src = np.array([local[f[0], :2] for f in self._fixes])
        yaw, t = fit_rigid_2d(src, gxy)
        start = np.array([t[0], t[1], yaw])
        self._insert_initial(
            dead_reckon(start, [n.delta for n in self._nodes[1:]]),
            position_sigma_m=max(f[3] for f in self._fixes) * 3.0,
        )

    def _initialize_without_gnss(self) -> None:
        logger.warning("no GNSS baseline in the whole log: poses are odometry from the origin")
        self._insert_initial(dead_reckon(np.zeros(3), [n.delta for n in self._nodes[1:]]), 1.0)

    def _insert_initial(self, poses: np.ndarray, position_sigma_m: float) -> None:
        self.graph.add_node(0, poses[0])
        self.graph.add_prior(0, poses[0], sigmas=[position_sigma_m, position_sigma_m, 0.1])
        for i in range(1, len(poses)):
            self.graph.add_node(i, poses[i])
            self.graph.add_odometry(i - 1, i, self._nodes[i].delta)
        self._initialized = True
        fixes, self._fixes = self._fixes, []
        for k, t_g, xy, sigma in fixes:
            self.graph.add_gnss(k, self._fix_at_node(k, t_g, xy, poses[k][2]), sigma)
        self.graph.optimize()
        self._pred = self.graph.estimate(len(poses) - 1)
        logger.info("pose graph initialized at %s with %d nodes", np.round(poses[0], 3), len(poses))

    def _calibrate_upto(self, j: int) -> None:
        """Close a calibration window ending at settled node j if the whole window had GNSS."""
        if self._calib_start is None or not self._nodes[j].precise:
            self._calib_start = j if self._nodes[j].precise else None
            return
        i = self._calib_start
        if not all(n.precise for n in self._nodes[i : j + 1]):
            self._calib_start = j
            return
        span_s = (self._nodes[j].t_ns - self._nodes[i].t_ns) * NS
        if span_s < self.calib_window_s:
            return
        raw = [n.raw_delta for n in self._nodes[i + 1 : j + 1]]
        bias = self.calibration.gyro_bias_rps
        debiased = [
            np.array(
                [
                    d[0],
                    d[1],
                    d[2] - bias * (self._nodes[i + 1 + k].t_ns - self._nodes[i + k].t_ns) * NS,
                ]
            )
            for k, d in enumerate(raw)
        ]
        chord_raw = float(np.linalg.norm(dead_reckon(np.zeros(3), debiased)[-1, :2]))
        pi, pj = self.graph.estimate(i), self.graph.estimate(j)
        self.calibration.add_window(
            chord_opt_m=float(np.linalg.norm(pj[:2] - pi[:2])),
            chord_raw_m=chord_raw,
            gyro_dyaw_rad=float(sum(d[2] for d in raw)),
            opt_dyaw_rad=float(pj[2] - pi[2]),
            dt_s=span_s,
        )
        logger.debug(
            "calibration: scale %.5f gyro bias %.5f deg/s",
            self.calibration.scale,
            math.degrees(self.calibration.gyro_bias_rps),
        )
        self._calib_start = j
