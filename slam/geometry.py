"""Small geometry helpers on 4x4 transforms, projection, two-view initialization and Sim(3).

Conventions: ``T_cam_slam`` maps SLAM points into the camera (the pose tracking estimates);
``T_slam_cam`` is its inverse. Keypoints are undistorted pixels, so only K is used here.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t).reshape(3)
    return T


def T_from_rvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    return make_T(cv2.Rodrigues(rvec)[0], tvec)


def rvec_from_T(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return cv2.Rodrigues(T[:3, :3])[0], T[:3, 3].reshape(3, 1).copy()


def camera_center(T_cam_slam: np.ndarray) -> np.ndarray:
    return -T_cam_slam[:3, :3].T @ T_cam_slam[:3, 3]


def project(K: np.ndarray, T_cam_slam: np.ndarray, p_slam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project (N,3) SLAM points; returns (N,2) pixels and (N,) depths (z in the camera)."""
    p_cam = p_slam @ T_cam_slam[:3, :3].T + T_cam_slam[:3, 3]
    z = p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (p_cam[:, :2] / z[:, None]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    return uv, z


# --- gravity (autopilot attitude prior, issue 4 §5) -----------------------------------------------

#: gravity ("down") in a gravity-aligned SLAM frame: its z axis points up
DOWN_SLAM = np.array([0.0, 0.0, -1.0])


def gravity_cam_from_roll_pitch(roll_rad: float, pitch_rad: float, R_cam_body: np.ndarray) -> np.ndarray:
    """Unit gravity direction ("down") in the camera frame from the body's roll and pitch in NED.

    With R_ned_body = Rz(yaw)·Ry(pitch)·Rx(roll) (aerospace ZYX Euler angles), NED down d = (0,0,1)
    is d_body = R_ned_bodyᵀ·d = Rx(roll)ᵀ·Ry(pitch)ᵀ·d, independent of yaw, i.e.
    d_body = (−sin θ, sin φ cos θ, cos φ cos θ); then g_cam = R_cam_body · d_body.
    """
    sr, cr, sp, cp = np.sin(roll_rad), np.cos(roll_rad), np.sin(pitch_rad), np.cos(pitch_rad)
    g_body = np.array([-sp, sr * cp, cr * cp])
    g_cam = np.asarray(R_cam_body, float) @ g_body
    return g_cam / np.linalg.norm(g_cam)


def R_align_vectors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation R with R·a = b for 3-vectors a, b (scipy's align_vectors with one pair:
    the minimum-angle rotation, a half turn when they are opposite)."""
    R, _ = Rotation.align_vectors(np.asarray(b, float)[None], np.asarray(a, float)[None])
    return R.as_matrix()


def R_slam_cam_levelled(g_cam: np.ndarray) -> np.ndarray:
    """Orientation of a camera in a gravity-aligned SLAM frame (z up, yaw arbitrary) given its
    gravity direction: R_slam_cam·g_cam = DOWN_SLAM."""
    return R_align_vectors(g_cam, DOWN_SLAM)


def tilt_rad(R_slam_cam: np.ndarray, g_cam: np.ndarray) -> float:
    """Angle between a camera's gravity direction rotated into the SLAM frame and DOWN_SLAM."""
    d = np.asarray(R_slam_cam, float) @ (np.asarray(g_cam, float) / np.linalg.norm(g_cam))
    return float(np.arccos(np.clip(d @ DOWN_SLAM, -1.0, 1.0)))


# --- Sim(3) as a 4x4 matrix [[s R, t], [0, 1]] mapping points -----------------------------------

def sim3_matrix(s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    S = np.eye(4)
    S[:3, :3] = s * R
    S[:3, 3] = t
    return S


def sim3_scale(S: np.ndarray) -> float:
    return float(np.cbrt(np.linalg.det(S[:3, :3])))


def sim3_share(S: np.ndarray, alpha: float, center: np.ndarray) -> np.ndarray:
    """The share ``alpha`` (0 … 1) of the similarity S, taken about the point ``center``: scale
    s^α, rotation by α of S's angle about the same axis, and α of the move S gives ``center``
    itself. α = 0 is the identity, α = 1 is S, and the result changes smoothly with α.

    A loop correction S is measured at the loop's end (``center``: the keyframe that closed it);
    the keyframes along the loop get a share of it by their distance along the loop, so the map
    stays continuous between the corrected end and the untouched start. ORB-SLAM spreads it with a
    pose-graph optimisation over its essential graph; this linear share is that optimisation's
    first-order stand-in (the BA windows that follow refine it). About ``center`` rather than the
    SLAM origin so that the share of the translation is the share of the move at the loop, not an
    artefact of where the map's origin lies.
    """
    s = sim3_scale(S)
    rotvec = Rotation.from_matrix(S[:3, :3] / s).as_rotvec()
    sR = s ** alpha * Rotation.from_rotvec(alpha * rotvec).as_matrix()
    c = np.asarray(center, float)
    c_new = c + alpha * (S[:3, :3] @ c + S[:3, 3] - c)
    out = np.eye(4)
    out[:3, :3] = sR
    out[:3, 3] = c_new - sR @ c
    return out


def correct_pose_by_sim3(T_cam_slam: np.ndarray, S_new_old: np.ndarray) -> np.ndarray:
    """Rigid camera pose after the map is moved by the similarity ``p_new = S p_old``.

    The camera centre moves with the map (c' = S c) and its rotation turns with S's rotation;
    the scale is absorbed into the map, so the pose stays rigid.
    """
    s = sim3_scale(S_new_old)
    R_s = S_new_old[:3, :3] / s
    T_slam_cam = inv_T(T_cam_slam)
    new = np.eye(4)
    new[:3, :3] = R_s @ T_slam_cam[:3, :3]
    new[:3, 3] = S_new_old[:3, :3] @ T_slam_cam[:3, 3] + S_new_old[:3, 3]
    return inv_T(new)


def umeyama_sim3(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares similarity dst ≈ S src (Umeyama 1991).

    Written here because slam/ may not import gis/ (gis.sim3 has the same solver); OpenCV's
    estimateAffine3D does not return a similarity with RANSAC.
    """
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    E = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        E[2, 2] = -1
    R = U @ E @ Vt
    var_s = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ E) / max(var_s, 1e-12))
    return sim3_matrix(s, R, mu_d - s * R @ mu_s)


def ransac_sim3(src: np.ndarray, dst: np.ndarray, thresh: float, iters: int = 200,
                rng: np.random.Generator | None = None) -> tuple[np.ndarray | None, np.ndarray]:
    """RANSAC over minimal 3-point Umeyama fits; returns (S or None, inlier mask)."""
    rng = rng or np.random.default_rng(0)
    n = len(src)
    best = np.zeros(n, bool)
    if n < 3:
        return None, best
    for _ in range(iters):
        idx = rng.choice(n, 3, replace=False)
        S = umeyama_sim3(src[idx], dst[idx])
        err = np.linalg.norm(src @ S[:3, :3].T + S[:3, 3] - dst, axis=1)
        inl = err < thresh
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < 3:
        return None, best
    S = umeyama_sim3(src[best], dst[best])
    err = np.linalg.norm(src @ S[:3, :3].T + S[:3, 3] - dst, axis=1)
    return S, err < thresh


# --- triangulation -----------------------------------------------------------------------------

def triangulate(K: np.ndarray, T1: np.ndarray, T2: np.ndarray, uv1: np.ndarray, uv2: np.ndarray,
                max_reproj_px: float = 2.0, min_parallax_deg: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate matched pixels seen from poses T1, T2 (T_cam_slam); returns (N,3) points, good mask."""
    if len(uv1) == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    P1 = K @ T1[:3]
    P2 = K @ T2[:3]
    X = cv2.triangulatePoints(P1, P2, uv1.T.astype(np.float64), uv2.T.astype(np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        p = (X[:3] / X[3]).T
    good = np.isfinite(p).all(1)
    p[~good] = 0
    for T, uv in ((T1, uv1), (T2, uv2)):
        proj, z = project(K, T, p)
        good &= z > 0
        good &= np.linalg.norm(proj - uv, axis=1) < max_reproj_px
    good &= parallax_deg(p, camera_center(T1), camera_center(T2)) > min_parallax_deg
    return p, good


def parallax_deg(p: np.ndarray, c1: np.ndarray, c2: np.ndarray) -> np.ndarray:
    """Angle (deg) at each point p (N,3) between its rays from c1 and from c2 ((3,) or (N,3) each);
    0 where either ray has zero length. A point's depth error grows as 1/parallax."""
    r1, r2 = p - c1, p - c2
    n1, n2 = np.linalg.norm(r1, axis=1), np.linalg.norm(r2, axis=1)
    ok = (n1 > 0) & (n2 > 0)
    out = np.zeros(len(p))
    out[ok] = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", r1[ok], r2[ok]) / (n1[ok] * n2[ok]), -1.0, 1.0)))
    return out


@dataclass
class TwoViewInit:
    T_cam2_cam1: np.ndarray  # rigid, unit-free translation
    points_cam1: np.ndarray  # (N,3) triangulated in camera-1 frame
    good: np.ndarray  # (N,) mask over the input matches
    model: str  # "homography" | "essential"


def sampson_px2(K: np.ndarray, R: np.ndarray, t: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """Squared Sampson distance (px²) of each match to the epipolar geometry of x2 = R x1 + t."""
    Kinv = np.linalg.inv(K)
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    F = Kinv.T @ tx @ R @ Kinv
    x1 = np.c_[uv1, np.ones(len(uv1))]
    x2 = np.c_[uv2, np.ones(len(uv2))]
    l2, l1 = x1 @ F.T, x2 @ F
    return (x2 * l2).sum(1) ** 2 / (l2[:, 0] ** 2 + l2[:, 1] ** 2 + l1[:, 0] ** 2 + l1[:, 1] ** 2 + 1e-12)


def _motion_candidates(K: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, str]]:
    """(R, unit t, model) of x2 = R x1 + t: the homography's decompositions and the essential
    matrix's pose that passes the cheirality test."""
    out = []
    H, _ = cv2.findHomography(uv1, uv2, cv2.RANSAC, 2.0)
    if H is not None:
        _, Rs, ts, _ = cv2.decomposeHomographyMat(H, K)
        out += [(R, t.reshape(3), "homography") for R, t in zip(Rs, ts)]
    E, mask = cv2.findEssentialMat(uv1, uv2, K, cv2.RANSAC, 0.999, 1.0)
    if E is not None and E.shape == (3, 3):
        _, R, t, _ = cv2.recoverPose(E, uv1, uv2, K, mask=mask)
        out.append((R, t.reshape(3), "essential"))
    return [(R, t / np.linalg.norm(t), m) for R, t, m in out if np.linalg.norm(t) > 1e-9]


def initialize_two_view(K: np.ndarray, uv1: np.ndarray, uv2: np.ndarray, min_points: int = 80,
                        min_parallax_deg: float = 1.0, min_median_parallax_deg: float = 1.5,
                        min_translation_flow_px: float = 2.0, epipolar_px: float = 1.0,
                        ambiguity_ratio: float = 0.9, distinct_deg: float = 20.0) -> TwoViewInit | None:
    """Monocular initialization: the homography's decompositions and the essential matrix's pose
    compete; each needs ``min_points`` matches triangulated in front of both cameras with
    ``min_parallax_deg``, and the winner is the one most matches agree with epipolarly (Sampson
    distance < ``epipolar_px``).

    Aerial imagery is near-planar (ground seen from altitude), where a homography has two physically
    valid decompositions: the true motion, and a twin whose translation is the plane's normal (the
    camera "descending onto a wall" instead of flying over the ground). Both triangulate the ground
    equally well, so counting triangulated points picks either; only points off the plane
    (buildings) tell them apart, by the epipolar constraint the twin breaks for them. When a
    candidate with a translation ``distinct_deg`` or more away from the winner's is explained by at
    least ``ambiguity_ratio`` times as many matches, the views are ambiguous and None is returned
    (wait for more parallax), as ORB-SLAM does for close homography solutions. So it is when the
    winner's triangulated points have a median parallax below ``min_median_parallax_deg``, or when
    the best pure rotation explains the winner's epipolar inliers to a median of less than
    ``min_translation_flow_px``: in a turn, or when the drone pitches over at take-off, the flow is
    mostly rotation, and with this field of view a small rotation and a translation move the image
    alike, so the translation (direction and scale of the new map) is only as well determined as
    the motion no rotation can explain. (A share of the winner's derotated flow, used before, was
    fooled both ways: the winner's own rotation absorbs or invents translation, and a large
    rotation left the nominal take-off waiting 112 frames with 8 m of baseline; the 2 px default
    refuses a 10 deg yaw with 1 m at 80 m up, 1.4 px, and lets the take-off start at 2 m, 2.2 px.)
    Measured on the simulator's 10 fps flights, the twin was picked in about half the
    initialisations by the count of triangulated points; see docs/BENCHMARKS.md.
    """
    if len(uv1) < min_points:
        return None
    scored = []
    T1 = np.eye(4)
    for R, t, model in _motion_candidates(K, uv1, uv2):
        T2 = make_T(R, t)
        p, good = triangulate(K, T1, T2, uv1, uv2, max_reproj_px=4.0, min_parallax_deg=min_parallax_deg)
        if good.sum() >= min_points:
            epipolar = sampson_px2(K, R, t, uv1, uv2) < epipolar_px ** 2
            scored.append((int(epipolar.sum()), epipolar, TwoViewInit(T2, p, good, model)))
    if not scored:
        return None
    n_best, epipolar_best, best = max(scored, key=lambda x: x[0])
    t_best = best.T_cam2_cam1[:3, 3]
    cos_distinct = np.cos(np.deg2rad(distinct_deg))
    if any(n >= ambiguity_ratio * n_best and init.T_cam2_cam1[:3, 3] @ t_best < cos_distinct for n, _, init in scored):
        return None
    if np.median(parallax_deg(best.points_cam1[best.good], np.zeros(3), camera_center(best.T_cam2_cam1))) < min_median_parallax_deg:
        return None
    if rotation_residual_px(K, uv1[epipolar_best], uv2[epipolar_best]) < min_translation_flow_px:
        return None
    return best


def rotation_residual_px(K: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> float:
    """Median image motion (px) that no camera rotation explains: the residual of uv1 mapped by the
    least-squares rotation of its rays onto uv2's (a pure rotation moves pixels by K R K⁻¹)."""
    Kinv = np.linalg.inv(K)
    rays1 = np.c_[uv1, np.ones(len(uv1))] @ Kinv.T
    rays2 = np.c_[uv2, np.ones(len(uv2))] @ Kinv.T
    rot, _ = Rotation.align_vectors(rays2 / np.linalg.norm(rays2, axis=1, keepdims=True),
                                    rays1 / np.linalg.norm(rays1, axis=1, keepdims=True))
    x = rays1 @ (K @ rot.as_matrix()).T
    return float(np.median(np.linalg.norm(x[:, :2] / x[:, 2:] - uv2, axis=1)))
