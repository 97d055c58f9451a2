"""Autopilot-side signals a real vehicle provides: attitude (ATTITUDE) and barometric altitude.

Attitude is the body FRD orientation in the local NED frame *at the vehicle* (what an autopilot
reports), from the truth with a constant bias per axis (AHRS misalignment; magnetometer heading
bias for yaw) plus white noise. Barometric altitude is relative to the take-off point, with
white noise and a random-walk drift (weather / temperature).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from companion.sim.types import AttitudeSample
from gis.geodesy import R_NED_ENU, LocalFrame, R_ecef_enu


@dataclass(frozen=True)
class AttitudeNoise:
    rate_hz: float = 50.0
    roll_pitch_sigma_deg: float = 0.15
    roll_pitch_bias_deg: float = 0.2
    yaw_sigma_deg: float = 0.5
    yaw_bias_deg: float = 1.5
    baro_sigma_m: float = 0.15
    baro_drift_m_per_sqrt_s: float = 0.02


def R_ned_body_at_vehicle(origin: LocalFrame, R_enu_body: np.ndarray, lat_deg, lon_deg) -> np.ndarray:
    """Body attitude in the NED frame at each vehicle position, (N, 3, 3)."""
    lat, lon = np.atleast_1d(lat_deg), np.atleast_1d(lon_deg)
    R_ecef_enuveh = np.stack([R_ecef_enu(a, b) for a, b in zip(lat, lon)])
    R = np.einsum("nji,jk,nkl->nil", R_ecef_enuveh, origin.R_ecef_enu, R_enu_body)
    return R_NED_ENU @ R


def simulate_attitude(origin: LocalFrame, t_s: np.ndarray, R_enu_body: np.ndarray, lat_deg, lon_deg,
                      h_ellipsoid_m: np.ndarray, h_home_ellipsoid_m: float, noise: AttitudeNoise = AttitudeNoise(),
                      seed: int = 0) -> list[AttitudeSample]:
    rng = np.random.default_rng(seed)
    ypr = Rotation.from_matrix(R_ned_body_at_vehicle(origin, R_enu_body, lat_deg, lon_deg)).as_euler("ZYX")
    n = len(t_s)
    rp_b = np.radians(rng.normal(0, noise.roll_pitch_bias_deg, 2))
    yaw_b = np.radians(rng.normal(0, noise.yaw_bias_deg))
    roll = ypr[:, 2] + rp_b[0] + np.radians(noise.roll_pitch_sigma_deg) * rng.standard_normal(n)
    pitch = ypr[:, 1] + rp_b[1] + np.radians(noise.roll_pitch_sigma_deg) * rng.standard_normal(n)
    yaw = ypr[:, 0] + yaw_b + np.radians(noise.yaw_sigma_deg) * rng.standard_normal(n)
    yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
    dt = np.diff(t_s, prepend=t_s[0])
    drift = np.cumsum(rng.standard_normal(n) * noise.baro_drift_m_per_sqrt_s * np.sqrt(dt))
    baro = h_ellipsoid_m - h_home_ellipsoid_m + drift + noise.baro_sigma_m * rng.standard_normal(n)
    return [AttitudeSample(float(t_s[i]), float(roll[i]), float(pitch[i]), float(yaw[i]), float(baro[i])) for i in range(n)]
