"""GlobalFix → the MAVLink message each autopilot actually fuses (docs/AUTOPILOTS.md).

One function per message; each returns a pymavlink message (encoded by the caller's link).
- ArduPilot: GPS_INPUT (GPSx_TYPE=14), or ODOMETRY (LOCAL_FRD/BODY_FRD) / VISION_POSITION_ESTIMATE
  in NED metres from the EKF origin (ExternalNav, EK3_SRCn_POSXY=6).
- PX4: ODOMETRY (LOCAL_NED, estimator VISION) / VISION_POSITION_ESTIMATE in NED from the EKF's
  GPS_GLOBAL_ORIGIN, GLOBAL_POSITION_SENSOR (aux global position), HIL_GPS. PX4 has no GPS_INPUT
  handler, so GPS_INPUT is refused for the px4 profile (``check_profile``).
"""
from __future__ import annotations

import math
import time

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from gis.geodesy import LocalFrame
from gis.types import GlobalFix
from mavlink_bridge.config import MavlinkConfig

#: Which outputs each autopilot fuses (docs/AUTOPILOTS.md).
SUPPORTED_OUTPUTS = {
    "ardupilot": ("gps_input", "odometry", "vision_position_estimate"),
    "px4": ("odometry", "vision_position_estimate", "global_position_sensor", "hil_gps"),
}
#: Outputs expressed in the EKF's local NED frame: they need the EKF origin first.
LOCAL_OUTPUTS = ("odometry", "vision_position_estimate")

#: GPS epoch (1980-01-06) in Unix seconds and the GPS−UTC leap-second offset (since 2017).
GPS_EPOCH_UNIX_S = 315964800
GPS_LEAP_S = 18
_NAN21 = [math.nan] * 21


def check_profile(cfg: MavlinkConfig) -> None:
    """Refuse an output the selected autopilot ignores (e.g. GPS_INPUT to PX4) with a clear error."""
    if cfg.output not in SUPPORTED_OUTPUTS[cfg.autopilot]:
        raise ValueError(
            f"mavlink.output={cfg.output!r} is not fused by {cfg.autopilot} "
            f"(use one of {', '.join(SUPPORTED_OUTPUTS[cfg.autopilot])}; see docs/AUTOPILOTS.md)"
        )


def trustworthy(fix: GlobalFix, cfg: MavlinkConfig) -> bool:
    """Finite position and an accuracy the EKF's pre-use checks accept."""
    return (
        bool(np.all(np.isfinite(fix.p_ecef_m)))
        and math.isfinite(fix.h_msl_m)
        and math.isfinite(fix.h_acc_m)
        and math.isfinite(fix.v_acc_m)
        and 0 < fix.h_acc_m <= cfg.max_fix_h_acc_m
    )


def _gps_week(unix_s: float) -> tuple[int, int]:
    gps_s = unix_s - GPS_EPOCH_UNIX_S + GPS_LEAP_S
    week = int(gps_s // (7 * 86400))
    return week, int((gps_s - week * 7 * 86400) * 1000)


def gps_input(mav: mavlink.MAVLink, fix: GlobalFix | None, cfg: MavlinkConfig, unix_s: float | None = None):
    """ArduPilot GPS_INPUT. ``fix`` None or untrustworthy → fix_type NO_FIX, 0 satellites.

    A fix without a velocity (or its accuracy) is not sent (None): ArduPilot's MAVLink GPS keeps
    the previous message's velocity and speed accuracy when the ignore flags are set, and its EKF
    fuses GPS velocity whenever EK3_SRCn_VELXY is GPS, so a flagged message would be fused with a
    stale velocity."""
    week, week_ms = _gps_week(time.time() if unix_s is None else unix_s)
    if fix is None or not trustworthy(fix, cfg):
        return mav.gps_input_encode(0, cfg.gps_id, 0, week_ms, week, 1, 0, 0, 0.0, 99.99, 99.99,
                                    0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0)
    if fix.v_ned_mps is None or fix.speed_acc_mps is None:
        return None
    vn, ve, vd = (float(v) for v in fix.v_ned_mps)
    # HDOP/VDOP are dimensionless; we have no satellite geometry, so express our 1-σ accuracy in the
    # same units with a nominal range error (h_acc 5 m → HDOP 2.5, both EKF3 pre-use limits).
    hdop = min(max(fix.h_acc_m / cfg.uere_m, 0.5), 99.99)
    vdop = min(max(fix.v_acc_m / cfg.uere_m, 0.5), 99.99)
    yaw_cdeg = 0 if fix.yaw_deg is None else (round(fix.yaw_deg * 100) % 36000 or 36000)  # 0 = none, 36000 = north
    return mav.gps_input_encode(
        int(fix.t_s * 1e6), cfg.gps_id, 0, week_ms, week, 3,
        round(fix.lat_deg * 1e7), round(fix.lon_deg * 1e7), float(fix.h_msl_m),
        hdop, vdop, vn, ve, vd, float(fix.speed_acc_mps), float(fix.h_acc_m), float(fix.v_acc_m),
        cfg.reported_satellites, yaw_cdeg,
    )


def _pose_covariance(cov_ned_m2: np.ndarray) -> list[float]:
    """Upper triangle (21) of the 6×6 [x y z roll pitch yaw] covariance: position block, angles NaN
    (unknown → the EKF uses its noise parameters)."""
    c = _NAN21.copy()
    c[0], c[1], c[2] = cov_ned_m2[0, 0], cov_ned_m2[0, 1], cov_ned_m2[0, 2]
    c[6], c[7], c[11] = cov_ned_m2[1, 1], cov_ned_m2[1, 2], cov_ned_m2[2, 2]
    return [float(v) for v in c]


def _q_and_R(fix: GlobalFix, q_fallback: np.ndarray | None) -> tuple[list[float], np.ndarray | None]:
    q = fix.q_ned_body if fix.q_ned_body is not None else q_fallback
    if q is None:
        return [math.nan, 0.0, 0.0, 0.0], None
    w, x, y, z = (float(v) for v in q)
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
    return [w, x, y, z], R


def odometry(mav, fix: GlobalFix, origin: LocalFrame, cfg: MavlinkConfig, q_fallback: np.ndarray | None = None):
    """ODOMETRY in the EKF origin's NED frame.

    PX4: frame LOCAL_NED, velocity in LOCAL_NED (child frame), estimator_type VISION.
    ArduPilot: only frame LOCAL_FRD with child BODY_FRD is accepted; velocity rotated into the body
    with the fix attitude (or the autopilot's ATTITUDE as fallback), NaN when no attitude is known.
    """
    p = origin.ecef_to_ned(fix.p_ecef_m)
    q, R_ned_body = _q_and_R(fix, q_fallback)
    v = np.full(3, math.nan) if fix.v_ned_mps is None else np.asarray(fix.v_ned_mps, float)
    if cfg.autopilot == "ardupilot":
        frame, child = mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD
        v = R_ned_body.T @ v if R_ned_body is not None else np.full(3, math.nan)
    else:
        frame, child = mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_NED
    vel_cov = _NAN21.copy()
    if fix.speed_acc_mps is not None:
        vel_cov[0] = vel_cov[6] = vel_cov[11] = float(fix.speed_acc_mps) ** 2
    return mav.odometry_encode(
        int(fix.t_s * 1e6), frame, child, float(p[0]), float(p[1]), float(p[2]), q,
        float(v[0]), float(v[1]), float(v[2]), math.nan, math.nan, math.nan,
        _pose_covariance(fix.cov_ned_m2), vel_cov, fix.reset_counter % 256,
        mavlink.MAV_ESTIMATOR_TYPE_VISION, 100,
    )


def vision_position_estimate(mav, fix: GlobalFix, origin: LocalFrame, q_fallback: np.ndarray | None = None):
    """VISION_POSITION_ESTIMATE (NED from the EKF origin, Euler angles from the attitude)."""
    p = origin.ecef_to_ned(fix.p_ecef_m)
    _, R = _q_and_R(fix, q_fallback)
    if R is None:
        roll = pitch = yaw = math.nan
    else:  # ZYX Euler angles of R_ned_body
        roll = math.atan2(R[2, 1], R[2, 2])
        pitch = -math.asin(max(-1.0, min(1.0, R[2, 0])))
        yaw = math.atan2(R[1, 0], R[0, 0])
    return mav.vision_position_estimate_encode(
        int(fix.t_s * 1e6), float(p[0]), float(p[1]), float(p[2]), roll, pitch, yaw,
        _pose_covariance(fix.cov_ned_m2), fix.reset_counter % 256,
    )


def global_position_sensor(mav, fix: GlobalFix, cfg: MavlinkConfig, now_s: float):
    """PX4 aux global position (EKF2_AGP0_ID = cfg.agp_id); only horizontal position is fused."""
    return mav.global_position_sensor_encode(
        cfg.target_system, cfg.target_component, cfg.agp_id, int(fix.t_s * 1e6),
        max(0, int((now_s - fix.t_s) * 1e6)), mavlink.GLOBAL_POSITION_SRC_VISION, 0,
        round(fix.lat_deg * 1e7), round(fix.lon_deg * 1e7), float(fix.h_ellipsoid_m), float(fix.h_msl_m),
        float(fix.h_acc_m), float(fix.v_acc_m),
    )


def hil_gps(mav, fix: GlobalFix, cfg: MavlinkConfig):
    """PX4 HIL_GPS (MAV_USEHILGPS=1; sent with the vehicle's system id). eph/epv are read as cm.

    PX4 always takes HIL_GPS velocity as valid, so a fix without velocity is not sent (None).
    """
    if fix.v_ned_mps is None:
        return None
    v = np.asarray(fix.v_ned_mps, float)
    speed = math.hypot(v[0], v[1])
    cog = round(math.degrees(math.atan2(v[1], v[0])) % 360 * 100) if speed > 0.1 else 65535
    return mav.hil_gps_encode(
        int(fix.t_s * 1e6), 3, round(fix.lat_deg * 1e7), round(fix.lon_deg * 1e7), round(fix.h_msl_m * 1000),
        min(65534, round(fix.h_acc_m * 100)), min(65534, round(fix.v_acc_m * 100)), round(speed * 100),
        round(v[0] * 100), round(v[1] * 100), round(v[2] * 100), cog, cfg.reported_satellites, 0, 0,
    )
