"""Integrity checks of the fusion (beyond the papers): does GNSS move as visual odometry says we
move (GnssConsistency: spoofing), is the SLAM map's scale still the one the alignment assumed
(SlamSpeedCheck: GNSS Doppler ground speed against the globalised track), and how far the GNSS fits
walked over a window (walk_from_m: the floor under a fix's σ while GNSS is trusted,
companion.fusion.sigma.walk_floor)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from gis.geodesy import R_ecef_enu, ecef_to_geodetic
from gis.sim3 import Sim3
from gis.types import Alignment

WALK_WINDOW_S = 10.0     # GNSS fits this far apart bound an undetected walk-off (companion.fusion.sigma.walk_floor)


def walk_from_m(fits: Iterable[Alignment], newest: Alignment, c_slam: np.ndarray,
                window_s: float = WALK_WINDOW_S) -> tuple[float, Alignment] | None:
    """How far (horizontally, metres) the newest GNSS fit puts the camera at ``c_slam`` (SLAM frame)
    from where the newest of ``fits`` at least ``window_s`` older than it puts it (same SLAM map),
    and that older fit; None without one. Two fits ``window_s`` apart, compared through the SLAM
    track, differ by what the receiver walked meanwhile, plus the older fit's own error carried
    that far (its extrapolated rotation and scale: ~3 m 20 s into the demo's clean flight) and the
    receiver's wander (Localizer._walk_floor). Beyond the papers."""
    old = None
    for a in fits:
        if (a.map_id, a.reset_counter) == (newest.map_id, newest.reset_counter) and a.t_s <= newest.t_s - window_s:
            if old is None or a.t_s > old.t_s:
                old = a
    if old is None:
        return None
    c = np.asarray(c_slam, float).reshape(1, 3)
    p_new = newest.T_ecef_slam.apply(c)[0]
    lat, lon, _ = ecef_to_geodetic(p_new)
    d = R_ecef_enu(float(lat), float(lon)).T @ (p_new - old.T_ecef_slam.apply(c)[0])
    return float(np.hypot(d[0], d[1])), old


@dataclass
class GnssConsistency:
    """Does GNSS move like visual odometry says we move? (beyond the papers; spoofing, issue 6)

    Innovation ν = horizontal GNSS position − the current alignment's prediction from the SLAM
    pose. Its slowly varying part (receiver bias, alignment error) is tracked by an exponential
    mean with time constant ``ema_s``; a sample more than ``gate_m`` from that mean is kept out of
    the alignment fits, and ``persist_s`` of such samples flags GNSS as inconsistent (a drifting or
    jumping spoofer) until it agrees again for as long. The mean is not updated while samples
    disagree, so a slow walk-off cannot drag it along. Defaults from a Monte Carlo with the
    simulator's standalone-receiver model (Gauss–Markov 2.7 m, τ 20 s + 0.7 m white): no false
    flag in 1 h of clean GNSS; a 10 m jump is flagged after persist_s, a 1 m/s walk-off after ~11 s
    (median). After a GNSS gap longer than ``reset_gap_s`` the mean restarts (vision drifted
    meanwhile; only the bridge's absolute test applies to the first samples).
    """

    gate_m: float = 5.0
    ema_s: float = 5.0
    persist_s: float = 2.0
    reset_gap_s: float = 2.0
    inconsistent: bool = False
    last_dev_m: float = 0.0
    _mean: np.ndarray | None = None
    _since: float | None = None
    _last_t: float | None = None

    def update(self, t_s: float, nu_en_m: np.ndarray) -> bool:
        """Feed one innovation (east, north metres); True when the sample may be used for fits."""
        nu = np.asarray(nu_en_m, float)[:2]
        if self._mean is None or self._last_t is None or t_s - self._last_t > self.reset_gap_s:
            self._mean, self._since, self.inconsistent = nu.copy(), None, False
        dt = t_s - self._last_t if self._last_t is not None else 0.0
        self._last_t = t_s
        self.last_dev_m = float(np.linalg.norm(nu - self._mean))
        agrees = self.last_dev_m <= self.gate_m
        if agrees != (not self.inconsistent):  # evidence against the current verdict
            self._since = t_s if self._since is None else self._since
            if t_s - self._since >= self.persist_s:
                self.inconsistent, self._since = not agrees, None
        else:
            self._since = None
        if agrees and not self.inconsistent:
            self._mean += min(1.0, max(dt, 0.0) / self.ema_s) * (nu - self._mean)
        return agrees and not self.inconsistent

    def offset_m(self, now_s: float, max_age_s: float) -> float | None:
        """|mean innovation| (horizontal metres) while innovations keep coming (the newest at most
        ``max_age_s`` before ``now_s``), else None."""
        if self._mean is None or self._last_t is None or now_s - self._last_t > max_age_s:
            return None
        return float(np.hypot(self._mean[0], self._mean[1]))

    def shift(self, d_en_m: np.ndarray) -> None:
        """The alignment changed: predictions moved by −d, so innovations move by +d."""
        if self._mean is not None:
            self._mean += np.asarray(d_en_m, float)[:2]

    def reset(self) -> None:
        self._mean, self._since, self._last_t, self.inconsistent = None, None, None, False


@dataclass
class SlamSpeedCheck:
    """Is the SLAM map's scale still the one the alignment assumed? (integrity; beyond the papers)

    Monocular SLAM can lose its scale in a turn (the map shrinks 2–4× within seconds). Positions
    then drift at metres per second while the alignment's covariance still claims a metre — the
    worst failure a position source can have. While GNSS is available, its Doppler ground speed
    is an independent yardstick: the horizontal speed of the globalised SLAM track over
    ``window_s`` must match it within ``max_ratio_error`` whenever the vehicle moves faster than
    ``min_speed_mps``. A spoofer walking the position off at ≤ 1–2 m/s barely changes the ratio;
    a scale collapse changes it by tens of percent. Any mismatch withholds fixes at once
    (``suspect``); ``persist_s`` of it → ``broken`` (the alignment is dropped).

    The window keeps SLAM-frame positions and takes the displacement under the alignment of the
    latest sample: while GNSS is good a new alignment is adopted every few seconds, and the
    globalised positions of one window under two alignments differ by the change between them,
    which is not motion. The speed is the length of the component-wise median of the frame-to-frame
    horizontal velocities, not the window's end-to-end displacement: local mapping moves the map,
    and the tracked camera with it, by metres in one frame (bundle adjustment, loop closures; 3–9 m
    in a `loop` flight's second lap), which read as scale breaks (ratios 0.08–1.35) and dropped the
    alignment just before GNSS was lost, so no fix came for the rest of the flight
    (docs/BENCHMARKS.md, "Long `loop` denials on this machine"). A jump is one step of ~10; a scale
    break shrinks or stretches every step.
    """

    window_s: float = 1.0
    min_speed_mps: float = 3.0
    max_ratio_error: float = 0.3
    persist_s: float = 0.5
    broken: bool = False
    last_ratio: float = 1.0
    _hist: list[tuple[float, np.ndarray, float]] = field(default_factory=list)  # (t, camera centre in the SLAM frame, GNSS speed)
    _since: float | None = None

    def update(self, t_s: float, c_slam: np.ndarray, T_ecef_slam: Sim3, R_ecef_enu_: np.ndarray,
               gnss_speed_mps: float | None) -> bool:
        """Feed the SLAM camera centre, the current alignment and the GNSS ground speed; returns
        ``broken``."""
        if gnss_speed_mps is None or not math.isfinite(gnss_speed_mps):
            self._hist.clear()  # compare only over spans with GNSS speed throughout
            return self.broken
        if self._hist and t_s - self._hist[-1][0] > self.window_s:
            self._hist.clear()  # GNSS speed came back after a gap: a new span
        self._hist.append((t_s, np.asarray(c_slam, float), float(gnss_speed_mps)))
        while len(self._hist) > 2 and self._hist[1][0] <= t_s - self.window_s:
            self._hist.pop(0)
        t0 = self._hist[0][0]
        if t_s - t0 < 0.5 * self.window_s:
            return self.broken
        t = np.array([h[0] for h in self._hist])
        p_enu = T_ecef_slam.apply(np.array([h[1] for h in self._hist])) @ R_ecef_enu_  # rows: ENU axes, ECEF origin
        dt = np.diff(t)
        steps = dt > 0
        v_step = np.diff(p_enu[:, :2], axis=0)[steps] / dt[steps, None]
        v_vis = float(np.linalg.norm(np.median(v_step, axis=0)))
        v_gnss = float(np.mean([v for _, _, v in self._hist[1:]]))  # the same span's mean ground speed
        if max(v_vis, v_gnss) < self.min_speed_mps:
            self._since = None
            return self.broken
        self.last_ratio = v_vis / max(v_gnss, 1e-3)
        if abs(self.last_ratio - 1.0) > self.max_ratio_error:
            self._since = t_s if self._since is None else self._since
            if t_s - self._since >= self.persist_s:
                self.broken = True
        else:
            self._since = None
        return self.broken

    @property
    def suspect(self) -> bool:
        """Mismatch seen (not yet persistent) or broken: fixes are withheld meanwhile."""
        return self.broken or self._since is not None

    def reset(self) -> None:
        self._hist.clear()
        self._since, self.broken, self.last_ratio = None, False, 1.0

    def open_since(self, t_s: float) -> float | None:
        """When a mismatch that GNSS ground speed stopped coming for (a loss mid-check, ``window_s``
        or more before ``t_s``) was first seen; else None. Nothing here can settle it any more:
        fixes stay withheld (``suspect``) until ``settle`` with another test of the scale."""
        if self._since is None or self.broken or (self._hist and t_s - self._hist[-1][0] < self.window_s):
            return None
        return self._since

    def settle(self) -> None:
        """Another test of the scale passed after the open mismatch began (``open_since``)."""
        self._hist.clear()
        self._since, self.last_ratio = None, 1.0
