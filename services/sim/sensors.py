"""Sensor models of the two vehicle profiles (DESIGN.md noise profiles): wheel odometry, gyro,
GNSS (RTK with outages in blocked zones, or consumer with a slowly varying bias), and camera
vibration and calibration error. Pure functions of a true Trajectory and a seeded generator."""

import math
from dataclasses import dataclass

import numpy as np

from common.world import World
from services.sim.motion import Trajectory

NS = 1_000_000_000
OUTAGE_SIGMA_M = 50.0


@dataclass(frozen=True)
class NoiseProfile:
    name: str
    gnss_hz: float
    gnss_sigma_m: float  # white noise per axis
    gnss_bias_m: float  # stationary std per axis of the Gauss-Markov bias (0: none)
    gnss_bias_tau_s: float
    gnss_reported_sigma_m: float
    gnss_outages: bool  # lose the fix in the world's blocked zones
    odom_hz: float = 50.0
    odom_scale_error: float = 0.005
    odom_noise_mps: float = 0.03
    gyro_hz: float = 100.0
    gyro_bias_dps: float = 0.02
    gyro_noise_dps: float = 0.05
    vibration_deg: float = 0.3
    calibration_error_deg: float = 0.1


PROFILES = {
    "mapping": NoiseProfile(
        "mapping",
        gnss_hz=10.0,
        gnss_sigma_m=0.02,
        gnss_bias_m=0.0,
        gnss_bias_tau_s=1.0,
        gnss_reported_sigma_m=0.02,
        gnss_outages=True,
    ),
    "production": NoiseProfile(
        "production",
        gnss_hz=5.0,
        gnss_sigma_m=0.4,
        gnss_bias_m=1.6,
        gnss_bias_tau_s=60.0,
        gnss_reported_sigma_m=2.5,
        gnss_outages=False,
        odom_scale_error=0.01,
        gyro_bias_dps=0.05,
        calibration_error_deg=0.2,
    ),
}


def signed(rng, magnitude: float) -> float:
    return float(magnitude if rng.random() < 0.5 else -magnitude)


def odometry(traj: Trajectory, p: NoiseProfile, rng):
    """Wheel odometry: forward speed with a scale error (magnitude p.odom_scale_error) + noise."""
    t = np.arange(0.0, traj.duration_s, 1.0 / p.odom_hz)
    scale = 1.0 + signed(rng, p.odom_scale_error)
    v = traj.at(t, "speed") * scale + rng.normal(0.0, p.odom_noise_mps, len(t))
    return t, np.maximum(v, 0.0), scale


def gyro(traj: Trajectory, p: NoiseProfile, rng):
    """Gyro z: yaw rate + constant bias (magnitude p.gyro_bias_dps) + white noise."""
    t = np.arange(0.0, traj.duration_s, 1.0 / p.gyro_hz)
    bias = math.radians(signed(rng, p.gyro_bias_dps))
    w = traj.at(t, "yaw_rate") + bias + rng.normal(0.0, math.radians(p.gyro_noise_dps), len(t))
    return t, w, bias


def gauss_markov(n: int, dt: float, sigma: float, tau_s: float, rng) -> np.ndarray:
    """First-order Gauss-Markov process (n, 2) with stationary std sigma and time constant tau."""
    out = np.zeros((n, 2))
    if sigma <= 0 or n == 0:
        return out
    a = math.exp(-dt / tau_s)
    q = sigma * math.sqrt(1 - a * a)
    out[0] = rng.normal(0, sigma, 2)
    e = rng.normal(0, q, (n, 2))
    for i in range(1, n):
        out[i] = a * out[i - 1] + e[i]
    return out


def gnss(traj: Trajectory, p: NoiseProfile, world: World, rng):
    """(t, xy, sigma, ok): fixes at p.gnss_hz; inside blocked zones (mapping) the fix is lost:
    ok False, sigma 50 m and xy a multipath-corrupted position that must not be used."""
    t = np.arange(0.0, traj.duration_s, 1.0 / p.gnss_hz)
    true = traj.poses(t)[:, :2]
    bias = gauss_markov(len(t), 1.0 / p.gnss_hz, p.gnss_bias_m, p.gnss_bias_tau_s, rng)
    xy = true + bias + rng.normal(0.0, p.gnss_sigma_m, (len(t), 2))
    sigma = np.full(len(t), p.gnss_reported_sigma_m)
    ok = np.ones(len(t), bool)
    if p.gnss_outages and world.gnss_blocked:
        ok = ~world.gnss_blocked_at(true)
        xy[~ok] += rng.normal(0.0, 15.0, (int((~ok).sum()), 2))
        sigma[~ok] = OUTAGE_SIGMA_M
    return t, xy, sigma, ok


def vibration(n: int, p: NoiseProfile, rng, corr: float = 0.6) -> np.ndarray:
    """(n, 2) pitch and roll (rad) per frame: AR(1) with stationary std p.vibration_deg."""
    sigma = math.radians(p.vibration_deg)
    out = np.zeros((n, 2))
    e = rng.normal(0.0, sigma * math.sqrt(1 - corr * corr), (n, 2))
    if n:
        out[0] = rng.normal(0.0, sigma, 2)
    for i in range(1, n):
        out[i] = corr * out[i - 1] + e[i]
    return out


def calibration_error(p: NoiseProfile, rng) -> np.ndarray:
    """(pitch, roll, yaw) error (rad) of total magnitude p.calibration_error_deg."""
    d = rng.normal(size=3)
    return math.radians(p.calibration_error_deg) * d / np.linalg.norm(d)
