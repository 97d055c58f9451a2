"""A straight, level flight as GlobalFix (ours) and GnssSample (receiver) streams, for the benchmark,
the tests and demos that need the bridge without the full pipeline. Heights: ``h_msl_m`` EGM96."""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from gis.geodesy import LocalFrame, ecef_to_geodetic, ellipsoid_to_msl, msl_to_ellipsoid
from gis.types import AlignmentSource, GlobalFix
from mavlink_bridge.types import GnssSample, GpsFixType


@dataclass(frozen=True)
class Flight:
    """Start point (lat, lon, MSL height) and constant NED velocity."""

    lat0_deg: float = 47.3977
    lon0_deg: float = 8.5456
    h0_msl_m: float = 520.0
    v_ned_mps: tuple[float, float, float] = (5.0, 0.0, 0.0)

    @functools.cached_property
    def frame(self) -> LocalFrame:
        return LocalFrame(self.lat0_deg, self.lon0_deg, float(msl_to_ellipsoid(self.lat0_deg, self.lon0_deg, self.h0_msl_m)))

    def p_ned_m(self, t_rel_s: float) -> np.ndarray:
        return np.asarray(self.v_ned_mps, float) * t_rel_s

    def fix(self, t_s: float, t_rel_s: float, seq: int = 0, sigma_m: float = 0.5,
            offset_ned_m=(0.0, 0.0, 0.0), with_velocity: bool = True) -> GlobalFix:
        """Our vision fix at flight time ``t_rel_s`` stamped ``t_s`` (monotonic), 1-σ ``sigma_m``."""
        p_ecef = self.frame.ned_to_ecef(self.p_ned_m(t_rel_s) + np.asarray(offset_ned_m, float))
        lat, lon, h = (float(x) for x in ecef_to_geodetic(p_ecef))
        return GlobalFix(
            t_s=t_s, seq=seq, p_ecef_m=p_ecef, lat_deg=lat, lon_deg=lon, h_ellipsoid_m=h,
            h_msl_m=float(ellipsoid_to_msl(lat, lon, h)), cov_ned_m2=np.eye(3) * sigma_m**2,
            h_acc_m=sigma_m, v_acc_m=sigma_m, source=AlignmentSource.FINE,
            v_ned_mps=np.asarray(self.v_ned_mps, float) if with_velocity else None,
            speed_acc_mps=0.2 if with_velocity else None, yaw_deg=0.0,
        )

    def gnss(self, t_s: float, t_rel_s: float, fix_type: GpsFixType = GpsFixType.RTK_FIXED,
             satellites: int = 14, hdop: float = 0.8, h_acc_m: float = 1.0,
             offset_ned_m=(0.0, 0.0, 0.0)) -> GnssSample:
        """The receiver's solution (optionally displaced by ``offset_ned_m``: spoofing)."""
        lat, lon, h = (float(x) for x in self.frame.ned_to_geodetic(self.p_ned_m(t_rel_s) + np.asarray(offset_ned_m, float)))
        vn, ve, vd = self.v_ned_mps
        return GnssSample(
            t_s=t_s, fix_type=fix_type, lat_deg=lat, lon_deg=lon, alt_msl_m=float(ellipsoid_to_msl(lat, lon, h)),
            h_ellipsoid_m=h, eph=hdop, epv=hdop * 1.5, h_acc_m=h_acc_m, v_acc_m=1.5 * h_acc_m,
            satellites=satellites, vel_ned_mps=(vn, ve, vd), cog_deg=float(np.degrees(np.arctan2(ve, vn)) % 360),
        )

    def gnss_lost(self, t_s: float) -> GnssSample:
        """What PX4/ArduPilot report with no fix: fix 0, 0 satellites, unknown accuracies."""
        return GnssSample(t_s=t_s, fix_type=GpsFixType.NO_GPS, lat_deg=0.0, lon_deg=0.0, alt_msl_m=0.0,
                          h_ellipsoid_m=float("nan"), eph=float("nan"), epv=float("nan"),
                          h_acc_m=100.0, v_acc_m=100.0, satellites=0)
