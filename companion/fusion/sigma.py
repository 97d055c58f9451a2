"""Where a fix's σ comes from beside the Globalizer's own propagation (beyond the papers): an
alignment's rough 1-σ at a camera (sigma_here_m), an alignment widened by an untestable move
(inflate_alignment), and the floors under the horizontal σ: how far the GNSS fits walked while GNSS
is trusted (walk_floor) and the distance flown in a denial (DenialFloor)."""
from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, replace

import numpy as np

from companion.fusion.integrity import walk_from_m
from gis.globalizer import with_horizontal_floor
from gis.types import Alignment, GlobalFix
from slam.types import SlamPose


def sigma_here_m(a: Alignment, c_slam: np.ndarray, slam_drift_fraction: float) -> float:
    """Rough 1-σ of a fix at SLAM position c under alignment a: its own σ plus SLAM drift over
    the distance from its centre (the Globalizer's propagation without the rotation terms;
    ``slam_drift_fraction``: the Globalizer's)."""
    if a.center_slam is None:
        return a.sigma_m
    d_m = a.T_ecef_slam.scale * float(np.linalg.norm(np.asarray(c_slam) - a.center_slam))
    return float(np.hypot(a.sigma_m, slam_drift_fraction * a.drift_distance_m(d_m) + a.scale_sigma * d_m))


def inflate_alignment(a: Alignment, add_sigma_m: float) -> Alignment:
    """``a`` with an isotropic 1-σ ``add_sigma_m`` (metres) added to its position uncertainty."""
    cov6 = a.covariance_6x6()
    cov6[3:, 3:] += add_sigma_m**2 * np.eye(3)
    return replace(a, information_6x6=np.linalg.inv(cov6), sigma_m=float(math.hypot(a.sigma_m, add_sigma_m)))


def walk_floor(fix: GlobalFix, fits: Iterable[Alignment], fit: Alignment, c_slam: np.ndarray,
               slam_drift_fraction: float) -> GlobalFix:
    """While GNSS is trusted, every alignment is anchored to it, and GnssConsistency follows a
    walk-off slower than ~1 m/s (its gate is distance from its own running mean): the fixes
    follow a slow spoofer while claiming the fit's σ (a 0.5 m/s walk: 3.7 m off 9 s into it,
    claiming 1.2 m; docs/BENCHMARKS.md, "A slow GNSS walk-off"). So no horizontal direction of
    the fix's σ is below how far the fresh GNSS fit ``fit`` puts this camera (``c_slam``) from where
    the fit WALK_WINDOW_S before it does (walk_from_m over the recent ``fits``), less that older
    fit's own σ here (sigma_here_m): the part of the difference the older fit's error does not
    explain, a lower bound on what the receiver walked. It bounds a steady walk for about 3 × the
    window (the error keeps growing, the difference does not); detecting one is not solved."""
    walk = walk_from_m(fits, fit, c_slam)
    if walk is None:
        return fix
    floor_m = walk[0] - sigma_here_m(walk[1], c_slam, slam_drift_fraction)
    return fix if floor_m <= 0.0 else with_horizontal_floor(fix, floor_m)


@dataclass
class DenialFloor:
    """With ``sigma_per_m`` > 0 (alignment.denial_sigma_per_m): while GNSS is not trusted, the fix's
    horizontal 1-σ is at least that × the distance flown since it was (the tracked camera's SLAM
    steps in metres at the alignment's scale; a step across a map reset is not counted). Beyond the
    papers: a registration in a long denial can lock onto a wrong optimum next to a drifted prior
    and claim ~1 m (docs/BENCHMARKS.md, "Registrations replayed offline"), which no registration
    gate detected; this bounds the claim by distance, as dead reckoning would."""

    sigma_per_m: float = 0.0
    denied_m: float | None = None  # metres flown since GNSS was last trusted (None: it is)
    denied_cam: tuple[tuple[int, int], np.ndarray] | None = None  # (map key, SLAM camera) of the last frame

    def apply(self, gnss_trusted: bool, pose: SlamPose, alignment: Alignment | None,
              fix: GlobalFix | None) -> GlobalFix | None:
        """The frame's fix with the floor (the distance counted on with this frame's pose)."""
        if self.sigma_per_m <= 0.0:
            return fix
        if gnss_trusted:
            self.denied_m, self.denied_cam = None, None
            return fix
        if self.denied_m is None:
            self.denied_m = 0.0
        if pose.state.has_pose:
            key, cam = (pose.map_id, pose.reset_counter), np.asarray(pose.T_slam_cam, float)[:3, 3]
            if self.denied_cam is not None and self.denied_cam[0] == key and alignment is not None:
                self.denied_m += alignment.T_ecef_slam.scale * float(np.linalg.norm(cam - self.denied_cam[1]))
            self.denied_cam = (key, cam)
        return None if fix is None else with_horizontal_floor(fix, self.sigma_per_m * self.denied_m)
