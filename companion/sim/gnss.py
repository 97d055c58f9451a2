"""GNSS receiver simulator: GPS_RAW_INT-like solutions at 5–10 Hz with scripted degradations.

Error model (per horizontal axis; vertical ×1.6): first-order Gauss–Markov (correlation time τ)
plus white noise, sized so the mean horizontal error matches the mode:
  standalone ≈ 3.5 m mean (TerraSLAM Table 1: "GPS … over 3 m"), DGPS ≈ 0.7 m (Table 1: 0.72 m).
For a 2-D Gaussian with per-axis σ the mean radial error is σ·sqrt(π/2) (Rayleigh mean).

Urban degradation follows the digital-twin paper §IV-A (satellite count and multipath as
functions of height): visible satellites N(h) = N_open·(1 − 0.6·exp(−h_agl/h_s)), and with
probability p(h) = 0.7·exp(−h_agl/h_s) a non-line-of-sight bias drawn from a two-component
Gaussian mixture (their GMM) persists for a few seconds. HDOP grows as satellites drop.

Scripted events (``GnssEvent``) override the base mode in [start_s, end_s): dropout (fix lost),
jamming (satellites fall, noise grows, fix flaps), spoof_drift (smooth drift with a perfect-looking
fix), spoof_jump (sudden offset, perfect-looking fix).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gis.geodesy import LocalFrame, ellipsoid_to_msl
from mavlink_bridge.types import GnssSample, GpsFixType, no_fix_sample

BASE_MODES = ("standalone", "dgps", "urban")
EVENT_MODES = ("dropout", "jamming", "spoof_drift", "spoof_jump", "standalone", "dgps", "urban")

#: mode → (per-axis Gauss–Markov σ m, white σ m, τ s, satellites, HDOP, fix type)
_MODE = {
    "standalone": (2.70, 0.70, 20.0, 12, 0.9, GpsFixType.FIX_3D),
    "dgps": (0.50, 0.25, 10.0, 15, 0.7, GpsFixType.DGPS),
    "urban": (2.70, 0.70, 20.0, 14, 0.9, GpsFixType.FIX_3D),
}
MEAN_H_ERROR_M = {m: math.hypot(g, w) * math.sqrt(math.pi / 2) for m, (g, w, *_r) in _MODE.items()}

#: NLOS multipath bias mixture (weights, mean m, σ m) — the digital-twin paper's GMM, §IV-A
_MP_W, _MP_MU, _MP_SIG = np.array([0.6, 0.4]), np.array([0.0, 8.0]), np.array([2.0, 4.0])


@dataclass(frozen=True)
class GnssEvent:
    """A scripted change: ``mode`` from start_s until end_s (None: to the end)."""

    mode: str
    start_s: float
    end_s: float | None = None
    drift_mps: float = 0.5          # spoof_drift speed
    jump_m: float = 40.0            # spoof_jump offset
    bearing_deg: float = 60.0       # spoof direction, clockwise from north
    ramp_s: float = 15.0            # jamming: time to full denial

    def __post_init__(self):
        if self.mode not in EVENT_MODES:
            raise ValueError(f"GNSS event mode must be one of {EVENT_MODES}, got {self.mode!r}")
        if self.end_s is not None and self.end_s <= self.start_s:
            raise ValueError(f"GNSS event {self.mode}: end_s {self.end_s} must be after start_s {self.start_s}")

    def active(self, t: np.ndarray) -> np.ndarray:
        return (t >= self.start_s) & (t < (np.inf if self.end_s is None else self.end_s))


@dataclass(frozen=True)
class GnssSpec:
    base: str = "standalone"
    rate_hz: float = 5.0
    events: tuple[GnssEvent, ...] = ()
    urban_scale_m: float = 25.0     # h_s of the urban model

    def __post_init__(self):
        if self.base not in BASE_MODES:
            raise ValueError(f"GnssSpec.base must be one of {BASE_MODES}, got {self.base!r}")
        if not 1.0 <= self.rate_hz <= 20.0:
            raise ValueError(f"GnssSpec.rate_hz must be in [1, 20], got {self.rate_hz}")


def parse_timeline(text: str) -> tuple[GnssEvent, ...]:
    """"dropout@60-90,spoof_drift@120" → events (times in seconds; open end when no '-END')."""
    events = []
    for item in filter(None, (s.strip() for s in text.split(","))):
        try:
            mode, span = item.split("@")
            a, _, b = span.partition("-")
            events.append(GnssEvent(mode.strip(), float(a), float(b) if b else None))
        except ValueError as e:
            raise ValueError(f"bad GNSS timeline item {item!r} (expected MODE@START[-END], e.g. dropout@60-90): {e}") from None
    return tuple(events)


def _gauss_markov(n: int, dt: float, tau: float, sigma: float, rng) -> np.ndarray:
    phi = math.exp(-dt / tau)
    q = sigma * math.sqrt(1 - phi * phi)
    w = rng.standard_normal(n) * q
    x = np.empty(n)
    x[0] = rng.standard_normal() * sigma
    for i in range(1, n):
        x[i] = phi * x[i - 1] + w[i]
    return x


def simulate_gnss(spec: GnssSpec, origin: LocalFrame, t_s: np.ndarray, p_enu: np.ndarray, v_enu: np.ndarray,
                  h_agl_m: np.ndarray, seed: int = 0) -> list[GnssSample]:
    """Receiver solutions at times t_s for the antenna at p_enu (ENU at origin) moving at v_enu."""
    rng = np.random.default_rng(seed)
    n = len(t_s)
    dt = 1.0 / spec.rate_hz
    g, w, tau, sats0, hdop0, fix0 = _MODE[spec.base]
    err = np.stack([_gauss_markov(n, dt, tau, g, rng) + rng.standard_normal(n) * w for _ in range(2)], 1)
    err_u = 1.6 * (_gauss_markov(n, dt, tau, g, rng) + rng.standard_normal(n) * w)
    sats = np.clip(sats0 + np.round(_gauss_markov(n, dt, 60.0, 1.2, rng)), 4, 24).astype(int)
    hdop = np.full(n, hdop0)
    fix = np.full(n, int(fix0))
    sigma_axis = math.hypot(g, w)
    h_acc = np.full(n, sigma_axis * math.sqrt(2))
    if spec.base == "urban":
        frac = 1 - 0.6 * np.exp(-np.maximum(h_agl_m, 0) / spec.urban_scale_m)
        sats = np.round(sats * frac).astype(int)
        hdop = hdop0 * np.sqrt(9.0 / np.maximum(sats - 3, 1))
        p_mp = 0.7 * np.exp(-np.maximum(h_agl_m, 0) / spec.urban_scale_m)
        # NLOS biases persist ~3 s: one draw per 3 s block
        block = (t_s // 3.0).astype(int)
        ub, inv = np.unique(block, return_inverse=True)
        comp = rng.choice(2, size=len(ub), p=_MP_W)
        mag = np.abs(rng.normal(_MP_MU[comp], _MP_SIG[comp]))
        ang = rng.uniform(0, 2 * np.pi, len(ub))
        mp = np.stack([np.sin(ang), np.cos(ang)], 1) * mag[:, None]
        gate = rng.random(len(ub))[inv] < p_mp
        err = err * (hdop / hdop0)[:, None] + mp[inv] * gate[:, None]
        err_u = err_u * (hdop / hdop0)
        h_acc = sigma_axis * math.sqrt(2) * hdop / hdop0
        fix = np.where(sats < 4, int(GpsFixType.NO_FIX), np.where(sats == 4, int(GpsFixType.FIX_2D), fix))
    vel_err = rng.standard_normal((n, 3)) * (0.1 if spec.base == "dgps" else 0.2)
    vel = v_enu + vel_err
    lost = np.zeros(n, bool)
    for ev in spec.events:
        m = ev.active(t_s)
        if not m.any():
            continue
        if ev.mode in _MODE:  # switch of the base quality, e.g. DGPS corrections lost
            g2, w2, _, s2, hd2, f2 = _MODE[ev.mode]
            err[m] *= math.hypot(g2, w2) / sigma_axis
            err_u[m] *= math.hypot(g2, w2) / sigma_axis
            sats[m], hdop[m], fix[m], h_acc[m] = s2, hd2, int(f2), math.hypot(g2, w2) * math.sqrt(2)
        elif ev.mode == "dropout":
            lost |= m
        elif ev.mode == "jamming":
            j = np.clip((t_s[m] - ev.start_s) / ev.ramp_s, 0, 1)
            sats[m] = np.round(sats[m] * (1 - j)).astype(int)
            err[m] *= (1 + 6 * j)[:, None]
            err_u[m] *= 1 + 6 * j
            hdop[m] = hdop[m] * (1 + 8 * j)
            h_acc[m] = h_acc[m] * (1 + 6 * j)
            flap = (rng.random(m.sum()) < j) | (sats[m] < 4)
            idx = np.flatnonzero(m)
            lost[idx[flap]] = True
        else:  # spoofing: a clean, confident solution that walks away from the truth
            b = math.radians(ev.bearing_deg)
            dirn = np.array([math.sin(b), math.cos(b)])
            off = (ev.drift_mps * (t_s[m] - ev.start_s)) if ev.mode == "spoof_drift" else np.full(m.sum(), ev.jump_m)
            err[m] = off[:, None] * dirn + rng.standard_normal((m.sum(), 2)) * 0.3
            err_u[m] = rng.standard_normal(m.sum()) * 0.5
            sats[m], hdop[m], fix[m], h_acc[m] = 14, 0.7, int(GpsFixType.FIX_3D), 1.5
            if ev.mode == "spoof_drift":
                vel[m, :2] += ev.drift_mps * dirn
    p = p_enu + np.c_[err, err_u]
    lat, lon, h = origin.enu_to_geodetic(p)
    msl = ellipsoid_to_msl(lat, lon, h)
    fix = np.where(sats < 4, int(GpsFixType.NO_FIX), fix)
    lost |= fix <= int(GpsFixType.NO_FIX)
    out = []
    for i in range(n):
        if lost[i]:
            out.append(no_fix_sample(t_s[i], min(sats[i], 3)))
            continue
        vn, ve, vd = float(vel[i, 1]), float(vel[i, 0]), float(-vel[i, 2])
        out.append(GnssSample(
            t_s=float(t_s[i]), fix_type=GpsFixType(int(fix[i])), lat_deg=float(lat[i]), lon_deg=float(lon[i]),
            alt_msl_m=float(msl[i]), h_ellipsoid_m=float(h[i]), eph=float(round(hdop[i], 2)),
            epv=float(round(hdop[i] * 1.4, 2)), h_acc_m=float(h_acc[i]), v_acc_m=float(h_acc[i] * 1.6),
            satellites=int(sats[i]), vel_ned_mps=(vn, ve, vd),
            cog_deg=float(math.degrees(math.atan2(ve, vn)) % 360.0),
        ))
    return out
