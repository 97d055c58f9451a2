"""Values the simulator yields (live API) and the dataset reader returns."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavlink_bridge.types import GnssSample
from slam.types import Frame


@dataclass(frozen=True)
class TruthPose:
    """Ground truth of one frame.

    T_enu_cam / T_enu_body: 4x4 camera→ENU and body(FRD)→ENU at the site origin. p_ecef_m: (3,)
    camera centre in ECEF. lat/lon/h_ellipsoid_m/h_msl_m (EGM96) and p_body_ecef_m (3,): the body
    origin, the point a GlobalFix reports (and truth.csv holds). v_enu_mps: (3,) vehicle velocity
    in ENU.
    """

    t_s: float
    seq: int
    T_enu_cam: np.ndarray
    T_enu_body: np.ndarray
    p_ecef_m: np.ndarray
    lat_deg: float
    lon_deg: float
    h_ellipsoid_m: float
    h_msl_m: float
    v_enu_mps: np.ndarray
    p_body_ecef_m: np.ndarray


@dataclass(frozen=True)
class AttitudeSample:
    """Autopilot attitude (body FRD in the local NED at the vehicle, radians) and barometric altitude
    (metres above the take-off point, with baro noise and drift), as ATTITUDE / altitude messages."""

    t_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    baro_alt_m: float | None  # None: no barometer reading (an empty cell in a dataset's attitude.csv)


@dataclass(frozen=True)
class SimStep:
    """One camera frame with what arrived since the previous one."""

    frame: Frame
    truth: TruthPose | None
    gnss: list[GnssSample]
    attitude: list[AttitudeSample]
