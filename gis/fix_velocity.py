"""The velocity a fix reports: a least-squares fit to the last second of SLAM positions.

Why a fit and not the fix-to-fix difference: SLAM positions jitter by about 0.1 m from frame to
frame (80 m above the simulated city, ``terraslam sitl``), so a 10-Hz difference is off by
1.5–2.5 m/s on average, and by tens of m/s at a SLAM jump. ArduPilot fuses GPS_INPUT velocity with
the speed accuracy we report (floored at EK3_VELNE_M_NSE); with the difference's claimed 0.2 m/s,
its EKF variance failsafe landed the vehicle 10–50 s into a denial.

Model (per NED axis, times t relative to the newest position):

    p(t) = c_k + v·t + ½·a·t²

a constant acceleration over the window, and one offset c_k per *segment*: a SLAM jump moves the
track, not the vehicle, so a position that falls outside the fit's prediction by more than
BREAK_SIGMAS starts a new segment and the velocity stays continuous across the jump (the newest
segment's offset absorbs it). The velocity at the newest time is v, its variance per axis
s²·(AᵀA)⁻¹ᵥᵥ with s² the axis's residual variance (ordinary least squares); the largest axis's
standard deviation is reported, as a receiver reports one speed accuracy. Without enough positions
for a residual (MIN_DOF) there is no velocity: better none than one whose error nobody knows.

Written by hand: a 3-parameter-plus-offsets linear least-squares fit (numpy.linalg.lstsq); no kept
library offers the segment offsets and the prediction gate together.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

WINDOW_S = 1.0          # the fit takes the positions of the last second...
MIN_POSES = 8           # ...or, at a low frame rate, the last this many
MAX_WINDOW_S = 3.0      # ...but none older than this (a constant acceleration stops being a model)
MIN_DOF = 3             # residual degrees of freedom needed for a velocity (a quadratic fit: ≥ 6 positions)
BREAK_SIGMAS = 5.0      # a position this many σ of prediction from the fit starts a new segment


@dataclass(frozen=True)
class VelocityFit:
    """NED velocity at the newest position (m/s) and its 1-σ (m/s, the largest axis's)."""

    v_ned_mps: np.ndarray
    sigma_mps: float


def window_start(t_s: np.ndarray) -> int:
    """Index of the oldest of the times ``t_s`` (ascending, newest last) the fit takes."""
    age = t_s[-1] - np.asarray(t_s, float)
    recent = int(np.argmax(age <= WINDOW_S))
    start = min(recent, max(len(age) - MIN_POSES, 0))
    return max(start, int(np.argmax(age <= MAX_WINDOW_S)))


def _design(t_s: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """Columns: one offset per segment, then t and ½t²."""
    segs = np.unique(segment)
    offsets = (segment[:, None] == segs[None, :]).astype(float)
    return np.hstack([offsets, t_s[:, None], 0.5 * t_s[:, None] ** 2])


def _solve(t_s: np.ndarray, p_ned_m: np.ndarray, segment: np.ndarray):
    """(coefficients (k, 3), (AᵀA)⁻¹, residual variance per axis (3,)) or None without MIN_DOF."""
    A = _design(t_s, segment)
    dof = len(t_s) - A.shape[1]
    if dof < MIN_DOF:
        return None
    x, _, rank, _ = np.linalg.lstsq(A, p_ned_m, rcond=None)
    if rank < A.shape[1]:
        return None
    r = p_ned_m - A @ x
    return x, np.linalg.inv(A.T @ A), np.sum(r * r, axis=0) / dof


def breaks(t_s: np.ndarray, p_ned_m: np.ndarray, segment: np.ndarray, t_new_s: float, p_new_ned_m: np.ndarray) -> bool:
    """Does the new position fall outside the earlier positions' fit (BREAK_SIGMAS of its
    prediction error on some axis), so that it starts a new segment? False without a fit."""
    sol = _solve(t_s - t_new_s, p_ned_m, segment)
    if sol is None:
        return False
    x, C, s2 = sol
    row = np.zeros(x.shape[0])
    row[list(np.unique(segment)).index(segment[-1])] = 1.0  # continues the newest segment, at t = 0
    innovation = p_new_ned_m - row @ x
    var = s2 * (1.0 + row @ C @ row)
    return bool(np.any(innovation ** 2 > BREAK_SIGMAS ** 2 * np.maximum(var, 1e-12)))


def fit_velocity(t_s: np.ndarray, p_ned_m: np.ndarray, segment: np.ndarray) -> VelocityFit | None:
    """The velocity at the newest of the positions ``p_ned_m`` (N, 3; NED metres about any point)
    taken at ``t_s`` (N,), ``segment`` (N,) the segment of each (module doc); None without MIN_DOF."""
    t_s = np.asarray(t_s, float)
    sol = _solve(t_s - t_s[-1], np.asarray(p_ned_m, float), np.asarray(segment))
    if sol is None:
        return None
    x, C, s2 = sol
    k = x.shape[0] - 2  # the t column
    return VelocityFit(x[k].copy(), float(np.sqrt(np.max(s2) * C[k, k])))
