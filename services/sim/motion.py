"""Vehicle motion along a route: a lateral offset in the lane that varies per drive, a speed
profile limited by curvature (lateral acceleration) and by acceleration/braking limits, and the
resulting true trajectory sampled at any rate. Local ENU metres, seconds, radians."""

import math
from dataclasses import dataclass

import numpy as np

from services.sim import paint

A_LAT_MAX = 2.0  # m/s^2, comfortable cornering
A_ACC = 1.2  # m/s^2
A_BRAKE = 2.0  # m/s^2
V_START = 2.0  # m/s: starts rolling
MIN_TURN_RADIUS_M = 5.0


@dataclass
class Trajectory:
    """True motion as a function of time: sampled densely, interpolated on demand."""

    t_s: np.ndarray  # (N,) from 0
    xy: np.ndarray  # (N, 2)
    yaw: np.ndarray  # (N,) unwrapped
    speed: np.ndarray  # (N,) m/s
    yaw_rate: np.ndarray  # (N,) rad/s

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1])

    def poses(self, t_s: np.ndarray) -> np.ndarray:
        """(x, y, yaw) at times t (yaw wrapped to [-pi, pi))."""
        x = np.interp(t_s, self.t_s, self.xy[:, 0])
        y = np.interp(t_s, self.t_s, self.xy[:, 1])
        yaw = np.interp(t_s, self.t_s, self.yaw)
        return np.stack([x, y, (yaw + np.pi) % (2 * np.pi) - np.pi], axis=1)

    def at(self, t_s: np.ndarray, what: str) -> np.ndarray:
        return np.interp(t_s, self.t_s, getattr(self, what))


def driven_path(
    route: np.ndarray,
    rng,
    *,
    max_len_m: float | None,
    step_m: float = 0.5,
    offset_m: float = 0.0,
    wobble_m: float = 0.25,
) -> np.ndarray:
    """The path the car drives: the route shifted sideways by offset_m plus a slow wobble, then
    followed by a pure-pursuit driver whose curvature is limited to a car's turning circle."""
    line = paint.resample(paint.remove_cusps(route), step_m)
    if max_len_m is not None:
        line = line[: max(2, int(max_len_m / step_m) + 1)]
    s = np.arange(len(line)) * step_m
    wobble = sum(
        wobble_m / 2 * math.sqrt(1 / (k + 1)) * np.sin(2 * np.pi * s / lam + ph)
        for k, (lam, ph) in enumerate(
            zip(rng.uniform(60, 300, 3), rng.uniform(0, 6.3, 3), strict=False)
        )
    )
    line = line + (offset_m + wobble)[:, None] * paint.normals(line)
    return pure_pursuit(line, step_m=step_m)


def pure_pursuit(
    line: np.ndarray,
    *,
    step_m: float = 0.5,
    lookahead_m: float = 5.0,
    max_kappa: float = 1.0 / MIN_TURN_RADIUS_M,
) -> np.ndarray:
    """Positions (N, 2) every step_m of a kinematic car tracking `line` (points every step_m)."""
    if len(line) < 3:
        return line
    ahead = max(1, int(round(lookahead_m / step_m)))
    d0 = line[min(ahead, len(line) - 1)] - line[0]
    x, y, th = float(line[0, 0]), float(line[0, 1]), math.atan2(d0[1], d0[0])
    idx, out = 0, [(x, y)]
    for _ in range(3 * len(line)):
        window = line[idx : idx + 4 * ahead]
        idx += int(np.argmin(np.sum((window - (x, y)) ** 2, axis=1)))
        if idx >= len(line) - 2:
            break
        tx, ty = line[min(idx + ahead, len(line) - 1)]
        c, s_ = math.cos(th), math.sin(th)
        lx, ly = c * (tx - x) + s_ * (ty - y), -s_ * (tx - x) + c * (ty - y)
        kappa = max(-max_kappa, min(max_kappa, 2.0 * ly / max(lx * lx + ly * ly, 1e-6)))
        th_new = th + kappa * step_m
        if abs(kappa) > 1e-9:  # exact arc
            x += (math.sin(th_new) - math.sin(th)) / kappa
            y -= (math.cos(th_new) - math.cos(th)) / kappa
        else:
            x, y = x + step_m * c, y + step_m * s_
        th = th_new
        out.append((x, y))
    return np.array(out)


def speed_profile(
    s: np.ndarray, kappa: np.ndarray, rng, *, v_min: float = 8.0, v_max: float = 15.0
) -> np.ndarray:
    """Target speed per station: a cruise speed that drifts in [v_min, v_max], capped by
    sqrt(a_lat / kappa) in curves, then limited by acceleration and braking."""
    n = len(s)
    cruise = np.interp(
        s, np.linspace(0, s[-1], 8) if s[-1] > 0 else np.zeros(8), rng.uniform(v_min, v_max, 8)
    )
    v = np.minimum(cruise, np.sqrt(A_LAT_MAX / np.maximum(np.abs(kappa), 1e-6)))
    v[0] = V_START
    ds = np.diff(s)
    for i in range(1, n):  # acceleration limit, forward
        v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + 2 * A_ACC * ds[i - 1]))
    for i in range(n - 2, -1, -1):  # braking limit, backward
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2 * A_BRAKE * ds[i]))
    return np.maximum(v, 0.5)


def curvature(path: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(station s, unwrapped heading, curvature) of a polyline."""
    s = paint.arc_length(path)
    d = np.gradient(path, axis=0)
    yaw = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    kappa = np.gradient(yaw) / np.maximum(np.gradient(s), 1e-6)
    return s, yaw, kappa


def drive(
    route: np.ndarray,
    rng,
    *,
    max_len_m: float | None = None,
    offset_m: float = 0.0,
    rate_hz: float = 100.0,
) -> Trajectory:
    """Drive a route: path, speed profile, then time-sample it at rate_hz."""
    path = driven_path(route, rng, max_len_m=max_len_m, offset_m=offset_m)
    s, yaw, kappa = curvature(path)
    v = speed_profile(s, kappa, rng)
    # time at each station: trapezoid of ds / v
    t = np.concatenate([[0.0], np.cumsum(2 * np.diff(s) / (v[1:] + v[:-1]))])
    ts = np.arange(0.0, t[-1], 1.0 / rate_hz)
    si = np.interp(ts, t, s)
    xy = np.stack([np.interp(si, s, path[:, 0]), np.interp(si, s, path[:, 1])], axis=1)
    yaw_t = np.interp(si, s, yaw)
    speed = np.interp(ts, t, v)
    return Trajectory(ts, xy, yaw_t, speed, np.gradient(yaw_t, ts))
