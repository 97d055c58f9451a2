"""Values that cross the slam/ boundary.

Frames (CONTRIBUTING.md, Naming): ``T_a_b`` is a 4x4 homogeneous transform mapping points in frame b to frame a.
The camera frame is OpenCV's (x right, y down, z forward). ``slam`` is the local frame of the SLAM
map: arbitrary origin and, for monocular SLAM, arbitrary scale. Times are monotonic seconds.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with OpenCV distortion (k1, k2, p1, p2[, k3]); pixels, image size in pixels."""

    width_px: int
    height_px: int
    K: np.ndarray  # 3x3 intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def is_distorted(self) -> bool:
        return bool(np.any(np.abs(self.dist) > 0))


@dataclass(frozen=True)
class Frame:
    """One camera image as it enters SLAM.

    image: HxW uint8 grayscale or HxWx3 uint8 BGR, already at the calibrated size.
    t_s: capture time, monotonic seconds (the camera source's clock).
    seq: frame counter of the source, strictly increasing.
    """

    image: np.ndarray
    t_s: float
    seq: int


@dataclass(frozen=True)
class AttitudePrior:
    """Optional autopilot prior for one frame (beyond the papers, issue 4 §5).

    roll/pitch/yaw of the body in NED, radians; baro_alt_m: barometric altitude (relative, metres).
    gravity_cam: unit gravity direction ("down") in the camera frame at t_s, from roll/pitch and
    the camera mount (slam.geometry.gravity_cam_from_roll_pitch; filled by the pipeline, which
    knows T_body_cam). SLAM uses only this (with slam.use_attitude_prior), not the Euler angles.
    gravity_sigma_rad: its 1-σ angle; None: slam.attitude_prior_sigma_deg.
    """

    t_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    baro_alt_m: float | None = None
    gravity_cam: np.ndarray | None = None
    gravity_sigma_rad: float | None = None


class TrackingState(enum.Enum):
    INITIALIZING = "initializing"
    OK = "ok"
    LOST = "lost"
    RELOCALIZED = "relocalized"

    @property
    def has_pose(self) -> bool:
        return self in (TrackingState.OK, TrackingState.RELOCALIZED)


@dataclass(frozen=True)
class SlamPose:
    """Tracking output for one frame.

    T_slam_cam: 4x4 camera-to-SLAM transform (camera centre = T_slam_cam[:3, 3]); only meaningful
    when ``state.has_pose``. reset_counter increments only when the SLAM frame is re-created (a
    new map after a reset), so downstream alignments for the old map are dropped; a loop-closure
    correction keeps the frame (the old part of the map stays anchored) and does not increment it.
    n_inliers: map points used for the pose; tracking_ms: wall time spent in the tracking thread.
    """

    t_s: float
    seq: int
    T_slam_cam: np.ndarray
    state: TrackingState
    reset_counter: int
    n_inliers: int = 0
    tracking_ms: float = 0.0
    map_id: int = 0


@dataclass(frozen=True)
class MapUpdate:
    """New/changed map points in the SLAM frame, produced by local mapping / loop closing.

    points_slam: (N, 3) positions; point_ids: (N,) stable ids; n_obs: (N,) observation counts.
    keyframe_t_s / keyframe_centers_slam: (K,) times and (K, 3) camera centres of the keyframes
    in the current local window. reset_counter matches SlamPose.reset_counter of the map it
    describes; ``full`` is True when this update replaces all points (e.g. after a loop closure).
    parallax_deg: (N,) angle between the rays to each point from its first and last observing
    keyframes (a proxy for its depth accuracy; 0 when one keyframe sees it), in full snapshots
    (``SlamSystem.map_points``) only, else None. last_seen_kf_age: (N,) keyframes created after the
    newest keyframe that observes each point (0: the newest sees it), in full snapshots only, else
    None: alignment keeps to the points of the map the camera is flying in now (a revisited area
    holds an older layer of points, placed under an older, drifted, SLAM frame).
    """

    t_s: float
    points_slam: np.ndarray
    point_ids: np.ndarray
    n_obs: np.ndarray
    keyframe_t_s: np.ndarray
    keyframe_centers_slam: np.ndarray
    reset_counter: int
    full: bool = False
    map_id: int = 0
    parallax_deg: np.ndarray | None = None
    last_seen_kf_age: np.ndarray | None = None
