"""Values that cross the gis/ boundary: the SLAM→ECEF alignment and the global fix.

Frames: ``ecef`` is EPSG:4978, geodetic is WGS-84 EPSG:4979 (ellipsoidal height). Heights are
always named by their datum: ``h_ellipsoid_m`` (WGS-84 ellipsoid), ``h_msl_m`` (EGM96 geoid).
NED is the local level frame at the fix position (north, east, down).
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from gis.sim3 import Sim3


class AlignmentSource(enum.Enum):
    GNSS = "gnss"     # bootstrap from GNSS positions (digital-twin paper §III-D)
    ROUGH = "rough"   # TerraSLAM §4.3 offline semantic alignment
    FINE = "fine"     # TerraSLAM §4.4 online ICP refinement


@dataclass(frozen=True)
class Alignment:
    """T_ecef_slam: similarity mapping SLAM-frame points to ECEF metres.

    information_6x6: information of the alignment's pose in the local ENU frame at the site
    origin, ordered [rot_x, rot_y, rot_z, t_e, t_n, t_u] (digital-twin paper Eq. 8–10), in
    1/rad² and 1/m². When center_slam is given, the ENU frame is the one at T_ecef_slam(center_slam)
    and rotations are about that point (the registration's crop centre), which keeps it well
    conditioned; gis.globalizer propagates it to the camera with the lever arm from there.
    sigma_m: 1-σ position uncertainty (metres) the alignment contributes at the
    map centre along the weakest direction. reset_counter / map_id: the SLAM map it applies to.
    fitness: fraction of SLAM points with a model correspondence; rmse_m: inlier RMSE.
    center_slam: (3,) SLAM-frame point the registration was centred on (its crop centre; for a GNSS
    fit, the camera at its newest pair, where SLAM drift beyond the fitted track starts), or None;
    scale_sigma: relative 1-σ of the similarity's scale (monocular scale), dimensionless.
    drift_free_radius_m: within this distance (metres) of center_slam the alignment registers the
    SLAM map itself, so SLAM drift adds nothing there: a survey map's T_rough, fitted on every
    keyframe of a map that the flight does not move (its keyframes and points are held). 0: drift
    accrues from center_slam on (every registration and GNSS fit).
    """

    T_ecef_slam: Sim3
    source: AlignmentSource
    t_s: float
    reset_counter: int
    information_6x6: np.ndarray
    sigma_m: float
    fitness: float = 0.0
    rmse_m: float = 0.0
    n_points: int = 0
    map_id: int = 0
    center_slam: np.ndarray | None = None
    scale_sigma: float = 0.0
    drift_free_radius_m: float = 0.0

    def drift_distance_m(self, dist_m: float) -> float:
        """The part of a distance (metres) from center_slam over which SLAM drift accrues."""
        return max(0.0, dist_m - self.drift_free_radius_m)

    def covariance_6x6(self) -> np.ndarray:
        """information_6x6 inverted, eigenvalues floored at 1e-12 of the largest (a direction the
        data do not constrain gets a huge, finite variance instead of a failed inverse)."""
        w, V = np.linalg.eigh(self.information_6x6)
        return (V / np.maximum(w, 1e-12 * max(w[-1], 1e-12))) @ V.T


@dataclass(frozen=True)
class GlobalFix:
    """Camera/vehicle global position for one frame.

    p_ecef_m: (3,) ECEF metres. lat_deg/lon_deg WGS-84; h_ellipsoid_m and h_msl_m (EGM96).
    v_ned_mps: (3,) velocity in NED at the fix, or None when unknown. yaw_deg: body heading
    clockwise from true north in [0, 360), or None. q_ned_body: (w, x, y, z) attitude of the body
    FRD frame in NED, or None. cov_ned_m2: 3x3 position covariance in NED (m²); h_acc_m / v_acc_m
    are the 1-σ horizontal / vertical accuracies derived from it (what GPS_INPUT reports).
    anchored: False while the SLAM track has jumped past 3× its alignment's σ and no alignment has
    re-anchored it since (gis.globalizer, ``unanchored``): the σ covers the fix, but the fix is
    no reference to judge GNSS by.
    """

    t_s: float
    seq: int
    p_ecef_m: np.ndarray
    lat_deg: float
    lon_deg: float
    h_ellipsoid_m: float
    h_msl_m: float
    cov_ned_m2: np.ndarray
    h_acc_m: float
    v_acc_m: float
    source: AlignmentSource
    v_ned_mps: np.ndarray | None = None
    speed_acc_mps: float | None = None
    yaw_deg: float | None = None
    q_ned_body: np.ndarray | None = None
    reset_counter: int = 0
    anchored: bool = True

    @property
    def R_ned_body(self) -> np.ndarray | None:
        """q_ned_body as a 3x3 rotation (body FRD → NED), or None."""
        if self.q_ned_body is None:
            return None
        w, x, y, z = self.q_ned_body
        return Rotation.from_quat([x, y, z, w]).as_matrix()
