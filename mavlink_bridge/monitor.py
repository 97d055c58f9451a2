"""GNSS monitor: receiver solutions + autopilot EKF flags + our vision fixes → GnssStatus.

Pieces, each with one job:
- ``sample_from_gps_raw``: GPS_RAW_INT / GPS2_RAW → GnssSample (units decoded, "unknown" sentinels
  mapped to NaN / 255).
- ``assess_sample``: the per-sample verdict (no fix, low satellites, HDOP, h_acc, stale).
- ``SpoofDetector``: persistent GNSS/vision disagreement beyond their combined uncertainty
  (beyond the papers: spoofed receivers report perfect fixes, only an independent source shows it).
- ``JammingDetector``: fix-type flapping between a 3D fix and no fix (ArduPilot SITL under jamming
  flips 1↔6, docs/AUTOPILOTS.md).
- ``GnssMonitor``: keeps the latest of each and produces the verdict.
"""
from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from gis.geodesy import LocalFrame, msl_to_ellipsoid
from gis.types import GlobalFix
from mavlink_bridge.config import SwitchingConfig
from mavlink_bridge.types import GnssQuality, GnssSample, GnssStatus, GpsFixType

log = logging.getLogger(__name__)

#: ArduPilot EKF_STATUS_REPORT flag bit 15 (GPS_GLITCHING), see docs/AUTOPILOTS.md.
EKF_STATUS_GPS_GLITCH = 32768
#: PX4 ESTIMATOR_STATUS flag ESTIMATOR_GPS_GLITCH (MAVLink common ESTIMATOR_STATUS_FLAGS).
ESTIMATOR_GPS_GLITCH = 1024
#: How long a glitch flag counts after the last report that raised it.
GLITCH_HOLD_S = 2.0


#: alt_ellipsoid further than this from alt (MSL) + EGM96 means the autopilot's receiver uses
#: another geoid (ArduPilot SITL reports alt_ellipsoid = alt: no geoid at all; 47.8 m off at Zurich)
GEOID_DISAGREE_M = 5.0
_geoid_warned = False


def sample_from_gps_raw(msg, t_s: float) -> GnssSample:
    """Decode GPS_RAW_INT or GPS2_RAW (both carry the same fields) into a GnssSample.

    The ellipsoidal height is alt (MSL) + the EGM96 geoid, the model our fixes go back through as
    MSL (GPS_INPUT, GLOBAL_POSITION_SENSOR, the EKF origin), so a height round-trips to the
    autopilot unchanged whatever geoid its receiver uses; alt_ellipsoid is only compared with it,
    and a disagreement beyond GEOID_DISAGREE_M is logged once.

    MAVLink sentinels: eph/epv UINT16_MAX = unknown (PX4 also reports 10000 on loss),
    alt_ellipsoid 0 = not sent, h_acc/v_acc 0 = not sent (mm), vel UINT16_MAX, cog UINT16_MAX.
    Velocity is ground speed along the course: (vn, ve, NaN) — GPS_RAW_INT carries no vertical speed.
    """
    fix = GpsFixType(min(int(msg.fix_type), int(GpsFixType.RTK_FIXED)))
    eph = math.nan if msg.eph in (65535, 10000) else msg.eph / 100.0
    epv = math.nan if msg.epv in (65535, 10000) else msg.epv / 100.0
    h_acc_mm = getattr(msg, "h_acc", 0)
    v_acc_mm = getattr(msg, "v_acc", 0)
    alt_ell_mm = getattr(msg, "alt_ellipsoid", 0)
    vel = None
    if msg.vel != 65535 and msg.cog != 65535:
        v = msg.vel / 100.0
        cog = math.radians(msg.cog / 100.0)
        vel = (v * math.cos(cog), v * math.sin(cog), math.nan)
    lat, lon, alt_msl = msg.lat * 1e-7, msg.lon * 1e-7, msg.alt / 1000.0
    h_ell = float(msl_to_ellipsoid(lat, lon, alt_msl)) if fix >= GpsFixType.FIX_3D else math.nan
    _check_geoid(h_ell, alt_ell_mm / 1000.0 if alt_ell_mm else math.nan)
    return GnssSample(
        t_s=t_s,
        fix_type=fix,
        lat_deg=lat,
        lon_deg=lon,
        alt_msl_m=alt_msl,
        h_ellipsoid_m=h_ell,
        eph=eph,
        epv=epv,
        h_acc_m=h_acc_mm / 1000.0 if h_acc_mm else math.nan,
        v_acc_m=v_acc_mm / 1000.0 if v_acc_mm else math.nan,
        satellites=int(msg.satellites_visible),
        vel_ned_mps=vel,
        cog_deg=None if msg.cog == 65535 else msg.cog / 100.0,
    )


def h_ellipsoid_of(sample: GnssSample) -> float:
    """Ellipsoidal height of a solution: GPS_RAW_INT's alt_ellipsoid is optional, else MSL + EGM96."""
    if math.isfinite(sample.h_ellipsoid_m):
        return sample.h_ellipsoid_m
    return float(msl_to_ellipsoid(sample.lat_deg, sample.lon_deg, sample.alt_msl_m))


def h_acc_of(sample: GnssSample, uere_m: float = 2.0) -> float:
    """1-σ horizontal accuracy: the receiver's h_acc, else HDOP × a nominal range error."""
    if math.isfinite(sample.h_acc_m) and sample.h_acc_m > 0:
        return sample.h_acc_m
    if math.isfinite(sample.eph):
        return sample.eph * uere_m
    return math.inf


def assess_sample(sample: GnssSample | None, now_s: float, cfg: SwitchingConfig) -> tuple[GnssQuality, list[str]]:
    """Verdict of one receiver solution on its own (no cross-checks)."""
    if sample is None:
        return GnssQuality.LOST, ["no GNSS data received"]
    age = now_s - sample.t_s
    if age > cfg.stale_after_s:
        return GnssQuality.LOST, [f"GNSS data stale ({age:.1f} s > {cfg.stale_after_s:g} s)"]
    if sample.fix_type < GpsFixType.FIX_3D:
        return GnssQuality.LOST, [f"no 3D fix (fix_type {int(sample.fix_type)})"]
    reasons = []
    if sample.satellites != 255 and sample.satellites < cfg.min_satellites:
        reasons.append(f"{sample.satellites} satellites < {cfg.min_satellites}")
    if not math.isfinite(sample.eph) or sample.eph > cfg.max_eph:
        reasons.append(f"HDOP {sample.eph:.2f} > {cfg.max_eph:g}")
    if math.isfinite(sample.h_acc_m) and sample.h_acc_m > cfg.max_h_acc_m:
        reasons.append(f"h_acc {sample.h_acc_m:.1f} m > {cfg.max_h_acc_m:g} m")
    return (GnssQuality.DEGRADED, reasons) if reasons else (GnssQuality.GOOD, [])


@dataclass
class SpoofDetector:
    """GNSS vs vision disagreement test.

    Normalised horizontal distance d/σ with σ = sqrt(h_acc_gnss² + h_acc_vision²), the vision fix
    propagated to the GNSS time with its velocity. Disagreement (> spoof_sigma) persisting
    spoof_persist_s flags spoofing; agreement persisting as long clears it. A fix that is not
    ``anchored`` (our SLAM track jumped and nothing re-anchored it yet) is no reference: the test
    pauses and its verdict holds. In a `terraslam sitl` flight, GNSS good, the track jumped 5.3 m,
    no GNSS fit re-anchored it for 14 s while the map's scale broke (15 %), and the test took the
    good GNSS for spoofed; the takeover put ArduPilot on our fixes and its EKF failsafed.
    """

    cfg: SwitchingConfig
    spoofed: bool = False
    last_sigma: float = math.nan
    _since_s: float | None = None  # start of the current run of evidence against the current verdict

    def update(self, sample: GnssSample, fix: GlobalFix, uere_m: float) -> None:
        dt = sample.t_s - fix.t_s
        if abs(dt) > self.cfg.spoof_max_dt_s or sample.fix_type < GpsFixType.FIX_3D or not fix.anchored:
            return
        frame = LocalFrame(fix.lat_deg, fix.lon_deg, fix.h_ellipsoid_m)
        h = sample.h_ellipsoid_m if math.isfinite(sample.h_ellipsoid_m) else fix.h_ellipsoid_m
        d_ned = frame.geodetic_to_ned(sample.lat_deg, sample.lon_deg, h)
        if fix.v_ned_mps is not None:
            d_ned = d_ned - np.asarray(fix.v_ned_mps, float) * dt
        sigma = math.hypot(h_acc_of(sample, uere_m), fix.h_acc_m)
        self.last_sigma = float(np.hypot(d_ned[0], d_ned[1]) / sigma) if sigma > 0 else math.inf
        disagree = self.last_sigma > self.cfg.spoof_sigma
        if disagree == self.spoofed:
            self._since_s = None
            return
        if self._since_s is None:
            self._since_s = sample.t_s
        if sample.t_s - self._since_s >= self.cfg.spoof_persist_s:
            self.spoofed = disagree
            self._since_s = None


@dataclass
class JammingDetector:
    """Counts transitions between a usable fix (≥ 3D) and none within a sliding window."""

    cfg: SwitchingConfig
    _last_ok: bool | None = None
    _flips: deque = field(default_factory=deque)

    def update(self, sample: GnssSample) -> None:
        ok = sample.fix_type >= GpsFixType.FIX_3D
        if self._last_ok is not None and ok != self._last_ok:
            self._flips.append(sample.t_s)
        self._last_ok = ok
        while self._flips and sample.t_s - self._flips[0] > self.cfg.jamming_window_s:
            self._flips.popleft()

    def jammed(self, now_s: float) -> bool:
        recent = [t for t in self._flips if now_s - t <= self.cfg.jamming_window_s]
        return len(recent) >= self.cfg.jamming_flips


def _check_geoid(h_ell_egm96_m: float, h_ell_reported_m: float) -> None:
    global _geoid_warned
    if not _geoid_warned and abs(h_ell_egm96_m - h_ell_reported_m) > GEOID_DISAGREE_M:
        _geoid_warned = True
        log.warning("the autopilot's GNSS reports an ellipsoidal height %.1f m from its MSL altitude + EGM96 "
                    "(its receiver uses another geoid, or none as in ArduPilot SITL): heights are taken from "
                    "its MSL altitude, which our fixes return to", h_ell_reported_m - h_ell_egm96_m)


@dataclass
class GnssMonitor:
    """Latest receiver sample + EKF glitch flags + spoofing/jamming detectors → GnssStatus."""

    cfg: SwitchingConfig
    uere_m: float = 2.0
    sample: GnssSample | None = None
    _glitch_t_s: float | None = None
    fix: GlobalFix | None = None  # our latest vision fix
    vision_check: str | None = None  # why the pipeline's GNSS-vs-visual-odometry test distrusts GNSS, or None
    spoof: SpoofDetector = field(init=False)
    jamming: JammingDetector = field(init=False)

    def __post_init__(self) -> None:
        self.spoof = SpoofDetector(self.cfg)
        self.jamming = JammingDetector(self.cfg)

    def on_sample(self, sample: GnssSample) -> None:
        self.sample = sample
        self.jamming.update(sample)
        if self.fix is not None:
            self.spoof.update(sample, self.fix, self.uere_m)

    def on_fix(self, fix: GlobalFix | None) -> None:
        """Our latest vision fix (None: tracking lost; the spoofing test pauses, its verdict holds)."""
        self.fix = fix

    def on_vision_check(self, reason: str | None) -> None:
        """The pipeline's verdict (companion.pipeline.GnssConsistency): None = GNSS moves as vision
        says; a reason = GNSS walked or jumped away from visual odometry."""
        self.vision_check = reason

    def on_ekf_flags(self, glitch: bool, t_s: float) -> None:
        if glitch:
            self._glitch_t_s = t_s

    def status(self, now_s: float) -> GnssStatus:
        quality, reasons = assess_sample(self.sample, now_s, self.cfg)
        if quality is not GnssQuality.LOST:
            untrusted = []
            if self.spoof.spoofed:
                untrusted.append(f"GNSS disagrees with vision ({self.spoof.last_sigma:.1f} sigma > {self.cfg.spoof_sigma:g}): spoofing suspected")
            if self.vision_check is not None:
                untrusted.append(self.vision_check)
            if self._glitch_t_s is not None and now_s - self._glitch_t_s <= GLITCH_HOLD_S:
                untrusted.append("autopilot EKF reports GPS glitch")
            if self.jamming.jammed(now_s):
                untrusted.append("fix flapping between 3D and no fix: jamming suspected")
            if untrusted:
                quality, reasons = GnssQuality.UNTRUSTED, untrusted + reasons
        elif self.jamming.jammed(now_s):
            reasons.append("fix flapping: jamming suspected")
        return GnssStatus(t_s=now_s, quality=quality, reasons=tuple(reasons), sample=self.sample)
