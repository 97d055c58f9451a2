"""Config sections ``mavlink`` and ``switching`` (validated; unknown keys are errors)."""
from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


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


class SwitchingConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    min_satellites: int = Field(6, ge=0, le=64)
    max_eph: float = Field(2.5, gt=0, description="HDOP above which GNSS is degraded")
    max_h_acc_m: float = Field(5.0, gt=0)
    stale_after_s: float = Field(1.0, gt=0, description="GNSS silence that counts as lost")
    handback_good_s: float = Field(10.0, ge=0, description="good, agreeing GNSS needed before handing back")
    min_dwell_s: float = Field(3.0, ge=0, description="minimum time in a state (no flapping)")
    spoof_sigma: float = Field(3.0, gt=0, description="GNSS/vision disagreement (in combined σ) that marks GNSS untrusted")
    spoof_persist_s: float = Field(2.0, gt=0, description="how long the disagreement must persist")
