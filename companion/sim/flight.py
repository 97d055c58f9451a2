"""Multicopter-like trajectories with exact kinematics: survey lawn-mower, orbit, loops.

A path is a polyline of ENU waypoints, corner-rounded, then flown with a speed profile limited by
cruise speed, longitudinal and lateral acceleration (v ≤ sqrt(a_lat/κ)), smoothed in time so
acceleration is continuous. Attitude follows a multicopter: the thrust axis (body −z) tilts to
produce acceleration against gravity and linear drag; heading follows the path (or looks at a
point for orbits).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d

G_MPS2 = 9.80665


@dataclass(frozen=True)
class FlightSpec:
    """kind: survey | orbit | loop | line. Distances in metres, ENU; altitude above origin height."""

    kind: str = "loop"
    speed_mps: float = 7.0
    altitude_m: float = 80.0
    size_m: float = 240.0          # side of the survey area / loop, or orbit diameter
    row_spacing_m: float = 60.0    # survey rows
    laps: float = 1.25             # loop / orbit repetitions (revisits for loop closing)
    center_enu: tuple[float, float] = (0.0, 0.0)
    heading_deg: float = 0.0       # rotation of the pattern (clockwise from north)
    a_max_mps2: float = 2.0
    a_lat_max_mps2: float = 2.5
    drag_per_s: float = 0.06       # linear drag coefficient (tilt at cruise speed)
    look_at: tuple[float, float, float] | None = None  # yaw towards this ENU point (orbit)

    def __post_init__(self):
        if self.kind not in ("survey", "orbit", "loop", "line"):
            raise ValueError(f"FlightSpec.kind must be survey|orbit|loop|line, got {self.kind!r}")
        if not 0.5 <= self.speed_mps <= 30:
            raise ValueError(f"FlightSpec.speed_mps must be in [0.5, 30], got {self.speed_mps}")
        if not 5 <= self.altitude_m <= 500:
            raise ValueError(f"FlightSpec.altitude_m must be in [5, 500], got {self.altitude_m}")


def waypoints(spec: FlightSpec) -> np.ndarray:
    """(N, 3) ENU waypoints of the pattern."""
    s, h = spec.size_m, spec.altitude_m
    if spec.kind == "survey":
        n_rows = max(2, int(round(s / spec.row_spacing_m)) + 1)
        ys = np.linspace(-s / 2, s / 2, n_rows)
        pts = []
        for i, y in enumerate(ys):
            xs = (-s / 2, s / 2) if i % 2 == 0 else (s / 2, -s / 2)
            pts += [(xs[0], y), (xs[1], y)]
        xy = np.array(pts)
    elif spec.kind == "orbit":
        a = np.linspace(0, 2 * np.pi * spec.laps, int(72 * spec.laps) + 1)
        xy = (s / 2) * np.stack([np.cos(a), np.sin(a)], 1)
    elif spec.kind == "loop":
        sq = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * s / 2
        n = int(np.ceil(4 * spec.laps)) + 1
        xy = np.array([sq[i % 4] for i in range(n)], float)
    else:
        xy = np.array([[-s / 2, 0.0], [s / 2, 0.0]])
    th = np.radians(spec.heading_deg)
    R = np.array([[np.cos(th), np.sin(th)], [-np.sin(th), np.cos(th)]])  # clockwise from north
    xy = xy @ R.T + np.asarray(spec.center_enu)
    return np.c_[xy, np.full(len(xy), h)]


@dataclass
class Trajectory:
    """Kinematics on a fine time grid; ``state(t)`` interpolates (C2 splines)."""

    t_s: np.ndarray
    p_enu: CubicSpline
    yaw_ned_rad: CubicSpline     # heading, clockwise from north, unwrapped
    spec: FlightSpec

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1])

    def state(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(p_enu (N,3), v_enu (N,3), a_enu (N,3), R_enu_body (N,3,3)) at times t (clamped)."""
        t = np.clip(np.atleast_1d(np.asarray(t, float)), 0, self.duration_s)
        p, v, a = self.p_enu(t), self.p_enu(t, 1), self.p_enu(t, 2)
        return p, v, a, self._attitude(v, a, self.yaw_ned_rad(t))

    def _attitude(self, v, a, yaw) -> np.ndarray:
        # specific thrust = a + g·up + drag·v ; body z (down) = −thrust direction
        f = a + np.array([0, 0, G_MPS2]) + self.spec.drag_per_s * v
        zb = -f / np.linalg.norm(f, axis=1, keepdims=True)
        h = np.stack([np.sin(yaw), np.cos(yaw), np.zeros_like(yaw)], 1)  # heading in ENU
        xb = h - np.einsum("ij,ij->i", h, zb)[:, None] * zb
        xb /= np.linalg.norm(xb, axis=1, keepdims=True)
        yb = np.cross(zb, xb)
        return np.stack([xb, yb, zb], axis=2)


def _resample(poly: np.ndarray, step_m: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = np.r_[0, np.cumsum(seg)]
    q = np.arange(0, s[-1], step_m)
    return np.stack([np.interp(q, s, poly[:, k]) for k in range(3)], 1)


def make_trajectory(spec: FlightSpec, start_hover_s: float = 1.0) -> Trajectory:
    step = 0.5
    p = _resample(waypoints(spec), step)
    corner_m = max(6.0, min(30.0, spec.speed_mps ** 2 / spec.a_lat_max_mps2))
    if spec.kind != "orbit":
        p = gaussian_filter1d(p, sigma=corner_m / step / 2, axis=0, mode="nearest")
    ds = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.r_[0, np.cumsum(ds)]
    # curvature-limited speed, then forward/backward acceleration passes
    d1 = np.gradient(p, s, axis=0)
    d2 = np.gradient(d1, s, axis=0)
    kappa = np.linalg.norm(np.cross(d1, d2), axis=1) / np.maximum(np.linalg.norm(d1, axis=1) ** 3, 1e-9)
    vmax = np.minimum(spec.speed_mps, np.sqrt(spec.a_lat_max_mps2 / np.maximum(kappa, 1e-9)))
    v = vmax.copy()
    v[0] = v[-1] = 0.0
    for i in range(1, len(v)):
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * spec.a_max_mps2 * ds[i - 1]))
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * spec.a_max_mps2 * ds[i]))
    t_of_s = np.r_[0, np.cumsum(ds / np.maximum(0.5 * (v[1:] + v[:-1]), 0.05))]
    # uniform time grid, jerk-smoothed speed (Gaussian, 0.7 s), re-integrated along the path
    dt = 0.02
    tg = np.arange(0, t_of_s[-1], dt)
    vg = gaussian_filter1d(np.gradient(np.interp(tg, t_of_s, s), dt), 0.7 / dt, mode="nearest")
    sg = np.r_[0, np.cumsum(0.5 * (vg[1:] + vg[:-1]) * dt)]
    sg *= s[-1] / sg[-1]
    n_hover = int(start_hover_s / dt)
    sg = np.r_[np.zeros(n_hover), sg]
    tg = np.arange(len(sg)) * dt
    pos = np.stack([np.interp(sg, s, p[:, k]) for k in range(3)], 1)
    if spec.look_at is not None:
        d = np.asarray(spec.look_at[:2]) - pos[:, :2]
    else:
        tang = np.stack([np.interp(sg, s, d1[:, k]) for k in range(2)], 1)
        d = tang
    yaw = np.unwrap(np.arctan2(d[:, 0], d[:, 1]))
    # smooth the sampled kinematics so the splines' derivatives are well behaved
    pos = gaussian_filter1d(pos, 0.3 / dt, axis=0, mode="nearest")
    yaw = gaussian_filter1d(yaw, 0.5 / dt, mode="nearest")
    return Trajectory(tg, CubicSpline(tg, pos), CubicSpline(tg, yaw), spec)
