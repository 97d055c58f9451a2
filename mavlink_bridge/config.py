"""Config sections ``mavlink`` and ``switching`` (validated; unknown keys are errors)."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator


class MavlinkConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    connect: str = Field("udpout:127.0.0.1:14540", description="pymavlink URL: serial device (/dev/ttyTHS1), udpin:/udpout:HOST:PORT or tcp:HOST:PORT")
    baud: int = Field(921600, gt=0, description="serial baud rate")
    autopilot: Literal["ardupilot", "px4"] = Field("ardupilot", description="autopilot profile")
    output: Literal["gps_input", "odometry", "vision_position_estimate", "global_position_sensor", "hil_gps"] = Field(
        "gps_input", description="message we feed the EKF with (see README per autopilot)"
    )
    source_system: int = Field(1, ge=1, le=255, description="our MAVLink system id (the vehicle's)")
    source_component: int = Field(197, ge=1, le=255, description="our component id (197 = MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY)")
    gps_id: int = Field(1, ge=0, le=1, description="ArduPilot GPS_INPUT instance: must equal the GPSx_TYPE=14 instance (0 or 1)")
    rate_hz: float = Field(10.0, ge=1, le=100, description="output rate")
    signing_key_file: Path | None = Field(None, description="MAVLink 2 signing key (32 bytes, file mode 0600)")
    allow_unsigned: bool = Field(False, description="with signing on, still accept unsigned messages from peers (migration only)")
    target_system: int = Field(1, ge=1, le=255, description="autopilot system id we address commands to")
    target_component: int = Field(1, ge=0, le=255, description="autopilot component id (1 = MAV_COMP_ID_AUTOPILOT1)")
    feed_in_standby: bool = Field(True, description="also feed the EKF while GNSS is trusted (secondary source, keeps the EV/GPS_INPUT path warm)")
    max_fix_age_s: float = Field(0.5, gt=0, le=5, description="a fix older than this when submitted is never sent")
    max_fix_h_acc_m: float = Field(10.0, gt=0, description="fixes with a larger 1-sigma horizontal accuracy are not sent (GPS_INPUT gets fix_type NO_FIX); below it the honest accuracy goes with the fix and the EKF weighs it")
    uere_m: float = Field(2.0, gt=0, description="nominal range error used to express h_acc/v_acc as HDOP/VDOP for GPS_INPUT (h_acc 5 m -> HDOP 2.5)")
    reported_satellites: int = Field(10, ge=6, le=64, description="satellites_visible reported with a trustworthy GPS_INPUT fix (ArduPilot needs >= 6)")
    agp_id: int = Field(1, ge=0, le=255, description="PX4 GLOBAL_POSITION_SENSOR id (= EKF2_AGP0_ID)")
    heartbeat_hz: float = Field(1.0, gt=0, le=10, description="our HEARTBEAT rate")
    gnss_stream_hz: float = Field(5.0, gt=0, le=50, description="GPS_RAW_INT/GPS2_RAW rate requested with MAV_CMD_SET_MESSAGE_INTERVAL")
    estimate_stream_hz: float = Field(0.0, ge=0, le=50, description="GLOBAL_POSITION_INT (the autopilot's own estimate, Bridge.autopilot_estimate) rate requested; 0: not requested (`terraslam sitl` asks 10 for its report)")
    link_timeout_s: float = Field(3.0, gt=0, description="no autopilot HEARTBEAT for this long = link down (streams are re-requested when it returns)")
    origin_resend_s: float = Field(2.0, gt=0, description="SET_GPS_GLOBAL_ORIGIN resend period until GPS_GLOBAL_ORIGIN comes back")
    switch_ekf_source: bool = Field(True, description="on takeover/hand-back switch the autopilot's source: ArduPilot GPS_PRIMARY (gps_input) or MAV_CMD_SET_EKF_SOURCE_SET (odometry/VPE); PX4 EKF2_GPS_CTRL")
    ekf_source_set_gnss: int = Field(1, ge=1, le=3, description="ArduPilot EKF3 source set whose POSXY is GPS (3)")
    ekf_source_set_extnav: int = Field(2, ge=1, le=3, description="ArduPilot EKF3 source set whose POSXY is ExternalNav (6)")
    px4_gps_ctrl: int = Field(7, ge=0, le=15, description="PX4 EKF2_GPS_CTRL restored at hand-back (the bridge sets 0 on takeover)")
    reconnect_max_s: float = Field(8.0, gt=0, description="longest back-off between reconnect attempts (serial/TCP)")
    gnss_delay_s: float = Field(0.0, ge=0.0, le=1.0, description="the receiver's own latency before the autopilot "
                                "stamps a solution (what its EKF assumes: ArduPilot GPS_DELAY_MS, PX4 EKF2_GPS_DELAY, in s): "
                                "GNSS positions are dated this much before the autopilot's stamp")
    gnss_antenna_m: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="antenna of the GNSS receiver the autopilot reports, from the body origin, FRD metres "
        "(ArduPilot GPS_POS1_X/Y/Z, PX4 EKF2_GPS_POS_X/Y/Z): GNSS fits carry it to the camera along the attitude")

    @field_validator("gnss_antenna_m")
    @classmethod
    def _antenna_on_the_vehicle(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not all(math.isfinite(x) and abs(x) <= 10.0 for x in v):
            raise ValueError(f"{v}: each component must be finite and within 10 m of the body origin")
        return v


class SwitchingConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    min_satellites: int = Field(6, ge=0, le=64)
    max_eph: float = Field(2.5, gt=0, description="HDOP above which GNSS is degraded")
    max_h_acc_m: float = Field(5.0, gt=0)
    stale_after_s: float = Field(0.8, gt=0, description="GNSS silence that counts as lost (0.8 s = 4 missed 5 Hz reports: loss detected within 1 s)")
    handback_good_s: float = Field(10.0, ge=0, description="good, agreeing GNSS needed before handing back")
    min_dwell_s: float = Field(3.0, ge=0, description="minimum time in a state (no flapping)")
    spoof_sigma: float = Field(3.0, gt=0, description="GNSS/vision disagreement (in combined σ) that marks GNSS untrusted")
    spoof_persist_s: float = Field(2.0, gt=0, description="how long the disagreement must persist")
    spoof_max_dt_s: float = Field(0.5, gt=0, description="GNSS and vision fixes further apart in time are not compared")
    degraded_takeover_s: float = Field(2.0, ge=0, description="DEGRADED GNSS for this long triggers a takeover (LOST/UNTRUSTED take over at once)")
    jamming_flips: int = Field(3, ge=2, description="fix-type flips between >=3D and <=no-fix within jamming_window_s read as jamming")
    jamming_window_s: float = Field(10.0, gt=0, description="window for counting fix flips")
