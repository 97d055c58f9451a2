"""GNSS fits of the alignment (digital-twin paper §III-D): each receiver solution carried to a frame's
time and camera centre (GnssPair), collected while GNSS is trusted and fitted with a similarity
(BootstrapCollector.solve: gis.align.bootstrap)."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from gis.align.bootstrap import gnss_bootstrap
from gis.geodesy import R_NED_ENU, LocalFrame, geodetic_to_ecef
from gis.types import Alignment
from mavlink_bridge.monitor import h_acc_of, h_ellipsoid_of
from mavlink_bridge.types import GnssSample, GpsFixType
from slam.types import AttitudePrior, SlamPose

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GnssPair:
    """One receiver solution carried to a frame's time (and, with an attitude, from its antenna to
    the camera centre), with that frame's SLAM camera centre.

    R_ecef_enu: the local level frame at the GNSS position (for horizontal innovations);
    R_ecef_slam: the SLAM frame's orientation from the autopilot's attitude, or None."""

    t_s: float
    p_slam: np.ndarray
    p_ecef: np.ndarray
    R_ecef_enu: np.ndarray
    R_ecef_slam: np.ndarray | None
    h_acc_m: float
    v_acc_m: float


@dataclass
class BootstrapCollector:
    """Pairs (SLAM camera centre, GNSS ECEF position) while GNSS is trusted (digital-twin §III-D).

    A fit needs a baseline: ``min_pairs`` pairs spanning ``min_baseline_m`` metres of GNSS track,
    so that yaw and scale are observable. Pairs are dropped when the SLAM map resets; only the
    last ``max_pairs`` are kept (monocular scale drifts: the fit should describe the recent map).
    Each GNSS position is carried to the frame's capture time with its reported velocity (a 0.1 s
    lag at 10 m/s would otherwise be a 1 m along-track bias). With ``T_body_cam`` and an attitude
    prior per frame, each pair also records the SLAM frame's orientation in ECEF
    (R_ecef_enu·R_enu_ned·R_ned_body·R_body_cam·R_slam_camᵀ) and the fit uses it for the rotation,
    and the receiver's position is carried from its antenna (``p_body_gnss_m``, FRD metres from the
    body origin: the autopilot's GPS_POS*/EKF2_GPS_POS_*) to the camera centre (T_body_cam's
    translation) along the attitude: R_ecef_body·(t_body_cam − p_body_gnss). Without an attitude
    that lever arm cannot be turned into the map, and its length is added to the pair's accuracy.
    """

    min_pairs: int = 30
    min_baseline_m: float = 40.0
    max_pairs: int = 150
    T_body_cam: np.ndarray | None = None
    p_body_gnss_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    max_prior_age_s: float = 0.1
    p_slam: list[np.ndarray] = field(default_factory=list)
    p_ecef: list[np.ndarray] = field(default_factory=list)
    R_ecef_slam: list[np.ndarray | None] = field(default_factory=list)
    t_s: list[float] = field(default_factory=list)
    h_acc_m: list[float] = field(default_factory=list)
    v_acc_m: list[float] = field(default_factory=list)
    map_key: tuple[int, int] | None = None
    last_refusal: str | None = None
    _last_gnss_t: float | None = None

    def _lists(self) -> tuple[list, ...]:
        return self.p_slam, self.p_ecef, self.R_ecef_slam, self.t_s, self.h_acc_m, self.v_acc_m

    def clear(self) -> None:
        for lst in self._lists():
            lst.clear()

    def add(self, pose: SlamPose, sample: GnssSample | None, trusted: bool, prior: AttitudePrior | None = None) -> None:
        """make_pair + append for a trusted sample (the Localizer gates pairs in between)."""
        pair = self.make_pair(pose, sample, prior)
        if pair is not None and trusted:
            self.append(pair)

    def make_pair(self, pose: SlamPose, sample: GnssSample | None, prior: AttitudePrior | None = None) -> GnssPair | None:
        """The pair for a new receiver solution at this frame, or None (no pose, repeated or
        incomplete sample). A new SLAM map (map_id / reset_counter) drops the old map's pairs."""
        key = (pose.map_id, pose.reset_counter)
        if key != self.map_key:
            for lst in self._lists():
                lst.clear()
            self.map_key = key
        if sample is None or not pose.state.has_pose or sample.fix_type < GpsFixType.FIX_3D:
            return None
        if sample.t_s == self._last_gnss_t:  # one pair per receiver solution
            return None
        self._last_gnss_t = sample.t_s
        h_ell = h_ellipsoid_of(sample)
        h_acc = h_acc_of(sample)
        v_acc = sample.v_acc_m if math.isfinite(sample.v_acc_m) and sample.v_acc_m > 0 else 1.6 * h_acc
        if not all(math.isfinite(x) for x in (sample.lat_deg, sample.lon_deg, h_ell, h_acc, v_acc)):
            return None  # an incomplete solution is no reference
        p_ecef = geodetic_to_ecef(sample.lat_deg, sample.lon_deg, h_ell)
        frame = LocalFrame(sample.lat_deg, sample.lon_deg, h_ell)
        dt = pose.t_s - sample.t_s
        if sample.vel_ned_mps is not None and abs(dt) <= 1.0:
            v_ned = np.nan_to_num(np.asarray(sample.vel_ned_mps, float))  # GPS_RAW_INT has no vertical speed
            p_ecef = frame.ned_to_ecef(v_ned * dt)
        R = None
        lever_body_m = (np.zeros(3) if self.T_body_cam is None else self.T_body_cam[:3, 3]) - np.asarray(self.p_body_gnss_m, float)
        if prior is not None and self.T_body_cam is not None and abs(prior.t_s - pose.t_s) <= self.max_prior_age_s:
            R_ned_body = Rotation.from_euler("ZYX", [prior.yaw_rad, prior.pitch_rad, prior.roll_rad]).as_matrix()
            R_ecef_body = frame.R_ecef_enu @ R_NED_ENU.T @ R_ned_body
            p_ecef = p_ecef + R_ecef_body @ lever_body_m  # antenna → camera centre
            R = R_ecef_body @ self.T_body_cam[:3, :3] @ np.asarray(pose.T_slam_cam, float)[:3, :3].T
        else:
            lever_m = float(np.linalg.norm(lever_body_m))
            h_acc, v_acc = math.hypot(h_acc, lever_m), math.hypot(v_acc, lever_m)
        return GnssPair(pose.t_s, pose.T_slam_cam[:3, 3].copy(), p_ecef, frame.R_ecef_enu, R, max(h_acc, 0.1), max(v_acc, 0.1))

    def append(self, pair: GnssPair) -> None:
        self.p_slam.append(pair.p_slam)
        self.p_ecef.append(pair.p_ecef)
        self.R_ecef_slam.append(pair.R_ecef_slam)
        self.t_s.append(pair.t_s)
        self.h_acc_m.append(pair.h_acc_m)
        self.v_acc_m.append(pair.v_acc_m)
        if len(self.p_slam) > self.max_pairs:
            for lst in self._lists():
                del lst[0]

    def ready(self) -> bool:
        if len(self.p_ecef) < self.min_pairs:
            return False
        pts = np.asarray(self.p_ecef)
        return float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))) >= self.min_baseline_m

    def solve(self) -> Alignment | None:
        reset_counter = self.map_key[1] if self.map_key else 0
        map_id = self.map_key[0] if self.map_key else 0
        with_att = [i for i, R in enumerate(self.R_ecef_slam) if R is not None]
        use = with_att if len(with_att) >= self.min_pairs else list(range(len(self.p_slam)))
        h_acc = float(np.median([self.h_acc_m[i] for i in use]))
        try:
            return gnss_bootstrap(
                np.asarray([self.p_slam[i] for i in use]), np.asarray([self.p_ecef[i] for i in use]),
                t_s=self.t_s[-1], reset_counter=reset_counter, map_id=map_id,
                sigma_gnss_m=0.5,  # white per-axis noise floor of a code receiver; the fit's residuals raise it
                bias_sigma_h_m=h_acc, bias_sigma_v_m=float(np.median([self.v_acc_m[i] for i in use])),
                R_ecef_slam=np.asarray([self.R_ecef_slam[i] for i in use]) if use is with_att else None,
                t_pairs_s=np.asarray([self.t_s[i] for i in use]),
            )
        except ValueError as e:
            log.debug("GNSS bootstrap refused: %s", e)
            self.last_refusal = str(e)
            return None
