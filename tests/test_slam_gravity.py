"""Attitude (gravity) prior, issue 4 §5: conventions, gravity factors in a real gtsam BA, and the
pipeline handing the camera-frame gravity to SLAM. Simulated-flight checks are in test_slam_sim.py."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from companion.pipeline import Localizer, PipelineInput, with_gravity
from gis.globalizer import Globalizer
from slam.ba import BAProblem, bundle_adjust
from slam.geometry import (
    DOWN_SLAM,
    R_align_vectors,
    R_slam_cam_levelled,
    gravity_cam_from_roll_pitch,
    inv_T,
    make_T,
    project,
    tilt_rad,
)
from slam.types import AttitudePrior, Frame, SlamPose, TrackingState

K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
# camera (OpenCV: x right, y down, z forward) → body FRD, pitched 40° down as the simulator's mount
R_BODY_CAM = Rotation.from_euler("y", -40, degrees=True).as_matrix() @ np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0.0]])


def test_gravity_cam_matches_the_ned_attitude_convention():
    """g_cam = (R_ned_body·R_body_cam)ᵀ·(0,0,1) with R_ned_body from ZYX Euler angles, as
    companion.fusion.gnss_fit.BootstrapCollector builds the attitude; yaw does not matter."""
    for roll, pitch, yaw in [(0.0, 0.0, 0.0), (0.3, -0.2, 2.0), (-0.1, 0.4, -1.0)]:
        R_ned_body = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
        expected = (R_ned_body @ R_BODY_CAM).T @ np.array([0.0, 0.0, 1.0])
        np.testing.assert_allclose(gravity_cam_from_roll_pitch(roll, pitch, R_BODY_CAM.T), expected, atol=1e-12)


def test_levelling_rotation_puts_gravity_down():
    rng = np.random.default_rng(0)
    for g in list(rng.normal(size=(5, 3))) + [DOWN_SLAM, -DOWN_SLAM]:
        R = R_slam_cam_levelled(g)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) > 0
        np.testing.assert_allclose(R @ (g / np.linalg.norm(g)), DOWN_SLAM, atol=1e-12)
    a = np.array([1.0, 0, 0])
    np.testing.assert_allclose(R_align_vectors(a, np.array([0.0, 1, 0])) @ a, [0, 1, 0], atol=1e-12)


def _tilted_scene(tilt_deg: float, rng: np.random.Generator):
    """Forward-oblique cameras over level ground (SLAM frame z up), then the whole map (cameras and
    points) tilted by ``tilt_deg``: the pixels are the same, only gravity tells the tilt."""
    R_slam_body = np.diag([1.0, -1.0, -1.0])  # FRD body flying along +x, level
    R_slam_cam0 = R_slam_body @ R_BODY_CAM
    T_slam_cam = [make_T(Rotation.from_euler("z", 3 * i, degrees=True).as_matrix() @ R_slam_cam0,
                         np.array([4.0 * i, 0, 80])) for i in range(8)]
    P = rng.uniform([60, -60, 0], [160, 60, 15], (300, 3))
    T_cam_slam = np.array([inv_T(T) for T in T_slam_cam])
    g_cam = np.array([T[:3, :3] @ DOWN_SLAM for T in T_cam_slam])  # true gravity in each camera
    o_pose, o_pt, o_uv = [], [], []
    for i, T in enumerate(T_cam_slam):
        uv, z = project(K, T, P)
        vis = np.flatnonzero((z > 0) & (uv[:, 0] > 0) & (uv[:, 0] < 640) & (uv[:, 1] > 0) & (uv[:, 1] < 480))
        o_pose += [i] * len(vis)
        o_pt += vis.tolist()
        o_uv.append(uv[vis] + rng.normal(0, 0.5, (len(vis), 2)))
    R_tilt = Rotation.from_rotvec(np.radians(tilt_deg) * np.array([0.6, 0.8, 0.0])).as_matrix()
    T_tilt = make_T(R_tilt, np.zeros(3))
    tilted = np.array([T @ inv_T(T_tilt) for T in T_cam_slam])
    return tilted, P @ R_tilt.T, np.array(o_pose), np.array(o_pt), np.vstack(o_uv), g_cam


def _max_tilt_deg(T_cam_slam: np.ndarray, g_cam: np.ndarray) -> float:
    return max(np.degrees(tilt_rad(inv_T(T)[:3, :3], g)) for T, g in zip(T_cam_slam, g_cam))


def test_gravity_factors_level_a_tilted_map():
    """A 4° tilted but otherwise perfect map: reprojection alone keeps the tilt (the pixels are
    the same), the gravity factors (AHRS-like 0.2° noise on g_cam) level it — real gtsam solve."""
    rng = np.random.default_rng(3)
    T0, P0, o_pose, o_pt, o_uv, g_true = _tilted_scene(4.0, rng)
    noise = Rotation.from_rotvec(rng.normal(0, np.radians(0.2), (len(g_true), 3))).as_matrix()
    g_meas = np.einsum("kij,kj->ki", noise, g_true)
    free = np.zeros(len(T0), bool)
    common = dict(K=K, T_cam_slam=T0, fixed=free, points_slam=P0, obs_pose=o_pose, obs_point=o_pt, obs_uv_px=o_uv,
                  max_iterations=20)
    assert _max_tilt_deg(T0, g_true) > 3.9
    without = bundle_adjust(BAProblem(**common))
    assert _max_tilt_deg(without.T_cam_slam, g_true) > 3.8  # nothing in the pixels levels it
    res = bundle_adjust(BAProblem(**common, g_cam=g_meas, gravity_sigma_rad=np.full(len(T0), np.radians(0.5))))
    assert _max_tilt_deg(res.T_cam_slam, g_true) < 0.3
    assert np.median(res.residual_px) < 1.0  # levelled without bending the map


def test_levelled_anchors_keep_their_centres_and_level_the_map():
    """Local BA as local mapping runs it: two fixed border cameras that are tilted with the rest
    of the map. In a gravity-aligned map they keep only their centres (the gauge: yaw, translation,
    scale) and are levelled with the rest, the pixels staying at their noise (held full poses would
    keep the tilt: test_cameras_without_a_prior_stay_hard_fixed)."""
    rng = np.random.default_rng(5)
    T0, P0, o_pose, o_pt, o_uv, g_true = _tilted_scene(4.0, rng)
    fixed = np.zeros(len(T0), bool)
    fixed[:2] = True
    res = bundle_adjust(BAProblem(K, T0, fixed, P0, o_pose, o_pt, o_uv, max_iterations=5, g_cam=g_true,
                                  gravity_sigma_rad=np.full(len(T0), np.radians(1.0))))
    assert _max_tilt_deg(res.T_cam_slam, g_true) < 0.3
    for i in (0, 1):
        np.testing.assert_allclose(inv_T(res.T_cam_slam[i])[:3, 3], inv_T(T0[i])[:3, 3], atol=1e-3)
    assert np.median(res.residual_px) < 1.0


def test_cameras_without_a_prior_stay_hard_fixed():
    """Fixed cameras without a gravity prior (NaN rows) keep their full pose, and the free ones
    without a prior get no gravity factor: nothing levels the tilted map."""
    rng = np.random.default_rng(5)
    T0, P0, o_pose, o_pt, o_uv, g_true = _tilted_scene(4.0, rng)
    fixed = np.zeros(len(T0), bool)
    fixed[:2] = True
    g = np.full_like(g_true, np.nan)
    res = bundle_adjust(BAProblem(K, T0, fixed, P0, o_pose, o_pt, o_uv, max_iterations=10, g_cam=g,
                                  gravity_sigma_rad=np.full(len(T0), np.radians(0.5))))
    np.testing.assert_allclose(res.T_cam_slam[:2], T0[:2], atol=1e-9)
    assert _max_tilt_deg(res.T_cam_slam, g_true) > 3.8


class _RecordingSlam:
    """Stands in for SlamSystem: records the priors the Localizer hands over."""

    def __init__(self) -> None:
        self.priors: list[AttitudePrior | None] = []

    def track(self, frame: Frame, prior: AttitudePrior | None = None) -> SlamPose:
        self.priors.append(prior)
        return SlamPose(frame.t_s, frame.seq, np.full((4, 4), np.nan), TrackingState.INITIALIZING, 0)

    def close(self) -> None:
        pass


def test_pipeline_hands_slam_the_gravity_in_the_camera_frame():
    T_body_cam = make_T(R_BODY_CAM, np.array([0.1, 0.0, 0.05]))
    slam = _RecordingSlam()
    loc = Localizer(slam, None, Globalizer(T_body_cam))
    try:
        img = np.zeros((48, 64), np.uint8)
        loc.process(PipelineInput(Frame(img, 0.0, 0), prior=AttitudePrior(0.0, 0.1, -0.2, 1.0)))
        loc.process(PipelineInput(Frame(img, 0.1, 1)))
    finally:
        loc.close()
    assert slam.priors[1] is None
    got = slam.priors[0]
    np.testing.assert_allclose(got.gravity_cam, gravity_cam_from_roll_pitch(0.1, -0.2, R_BODY_CAM.T), atol=1e-12)
    assert (got.roll_rad, got.pitch_rad, got.yaw_rad) == (0.1, -0.2, 1.0)
    given = AttitudePrior(0.0, 0.0, 0.0, 0.0, gravity_cam=np.array([0.0, 1.0, 0.0]))
    assert with_gravity(given, R_BODY_CAM.T) is given  # a producer's own gravity direction is kept


def test_keyframes_carry_gravity_only_in_a_levelled_map():
    """A map not levelled at initialisation (no prior then, or loaded from disk) has an arbitrary
    frame: gravity factors would tilt it, so its keyframes get none."""
    from slam.config import SlamConfig
    from slam.features import Features
    from slam.tracking import Gravity, Tracker

    tracker = Tracker(K, 640, 480, SlamConfig(use_attitude_prior=True), extract=lambda img: None)
    feats = Features(np.zeros((3, 2)), np.zeros((3, 32), np.uint8), np.zeros(3, int))
    g = Gravity(np.array([0.0, 0.6, 0.8]), 0.01)
    kf = tracker._keyframe(Frame(np.zeros((480, 640), np.uint8), 0.0, 0), np.eye(4), feats, np.full(3, -1), g)
    assert kf.g_cam is None and kf.gravity_sigma_rad is None
    tracker.map.gravity_aligned = True
    kf = tracker._keyframe(Frame(np.zeros((480, 640), np.uint8), 0.1, 1), np.eye(4), feats, np.full(3, -1), g)
    np.testing.assert_array_equal(kf.g_cam, g.g_cam)
    assert kf.gravity_sigma_rad == 0.01
