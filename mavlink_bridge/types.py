"""Values that cross the mavlink_bridge/ boundary.

GnssSample mirrors what GPS_RAW_INT carries (plus the ellipsoid height GPS_RAW_INT offers as
``alt_ellipsoid``); the GNSS simulator produces it and the monitor decodes it from the wire.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass


class GpsFixType(enum.IntEnum):
    """MAVLink GPS_FIX_TYPE."""

    NO_GPS = 0
    NO_FIX = 1
    FIX_2D = 2
    FIX_3D = 3
    DGPS = 4
    RTK_FLOAT = 5
    RTK_FIXED = 6


@dataclass(frozen=True)
class GnssSample:
    """One receiver solution.

    t_s: monotonic seconds; lat_deg/lon_deg WGS-84; alt_msl_m (EGM96) and h_ellipsoid_m;
    eph/epv: HDOP/VDOP (dimensionless, as GPS_RAW_INT), h_acc_m/v_acc_m: 1-σ accuracies;
    vel_ned_mps: (vn, ve, vd) m/s or None; satellites: visible satellites (255 = unknown).
    """

    t_s: float
    fix_type: GpsFixType
    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    h_ellipsoid_m: float
    eph: float
    epv: float
    h_acc_m: float
    v_acc_m: float
    satellites: int
    vel_ned_mps: tuple[float, float, float] | None = None
    cog_deg: float | None = None


def no_fix_sample(t_s: float, satellites: int = 0) -> GnssSample:
    """A receiver report without a position (GPS_RAW_INT during a dropout or jamming): fix_type
    NO_FIX, lat/lon/heights 0 (as gnss.csv writes them), HDOP/VDOP 99.99 and accuracies 100 m."""
    return GnssSample(float(t_s), GpsFixType.NO_FIX, 0.0, 0.0, 0.0, 0.0, 99.99, 99.99, 100.0, 100.0, int(satellites))


class GnssQuality(enum.Enum):
    GOOD = "good"            # trusted: we stand by
    DEGRADED = "degraded"    # usable but poor (few satellites, large eph)
    LOST = "lost"            # no fix / stale
    UNTRUSTED = "untrusted"  # fix looks fine but disagrees with vision (spoofing) or glitch flags


@dataclass(frozen=True)
class GnssStatus:
    """Verdict of the GNSS monitor at time t_s with human-readable reasons."""

    t_s: float
    quality: GnssQuality
    reasons: tuple[str, ...]
    sample: GnssSample | None = None

    @property
    def trusted(self) -> bool:
        return self.quality is GnssQuality.GOOD


@dataclass(frozen=True)
class VehicleAttitude:
    """The autopilot's attitude (ATTITUDE): body FRD in the local NED frame, radians; t_s: when we
    received it (bridge clock). baro_alt_m: the barometric altitude, metres, from the latest
    ALTITUDE.altitude_monotonic (PX4) or SCALED_PRESSURE (ArduPilot, as pressure altitude) received
    within 0.5 s, else None; only its changes are meaningful (the offset is learned from GNSS)."""

    t_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    baro_alt_m: float | None = None
