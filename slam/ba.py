"""Bundle adjustment with gtsam (compiled projection factors, Levenberg-Marquardt).

gtsam's Python binding holds the GIL while optimizing (measured: a thread spinning next to a
1.3 s optimize got 3 turns), so BA runs in a separate worker process (``ba_worker``) and the
tracking thread is never stalled by it. ``bundle_adjust`` itself is a pure function on arrays.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from slam.worker import ForkedWorker


@dataclass
class BAProblem:
    K: np.ndarray  # 3x3
    T_cam_slam: np.ndarray  # (P,4,4) initial poses
    fixed: np.ndarray  # (P,) bool: held at their initial value (gauge + window border)
    points_slam: np.ndarray  # (M,3)
    obs_pose: np.ndarray  # (O,) pose index
    obs_point: np.ndarray  # (O,) point index
    obs_uv_px: np.ndarray  # (O,2) undistorted pixels
    max_iterations: int = 10
    huber_px: float = 2.0
    sigma_px: float = 1.0
    g_cam: np.ndarray | None = None  # (P,3) unit gravity ("down") per camera, NaN rows: no prior
    gravity_sigma_rad: np.ndarray | None = None  # (P,) 1-sigma angles of g_cam
    # Levenberg-Marquardt stops when an iteration lowers the (robust) cost by less than this
    # fraction (gtsam's default). 1e-3 stopped local BAs after 2-3 iterations instead of 3-5 (-25 %
    # BA CPU, nominal ATE unchanged) but the loop scenario at 10 fps drifted more (ATE 5.2-5.5 %,
    # 3 runs, vs 3.7-4.9 %, 2 runs) and loop BAs stopped short of the revisit; not used until shown
    # harmless there
    lm_relative_decrease: float = 1e-5
    # (M,) bool: points held at their initial value (a map loaded from disk: its alignment
    # registers them, as it does its keyframes); None: every point is a variable
    fixed_points: np.ndarray | None = None

    @property
    def levelled_anchors(self) -> np.ndarray:
        """(P,) fixed cameras with a gravity prior: only their centres are held (see bundle_adjust)."""
        if self.g_cam is None:
            return np.zeros(len(self.fixed), bool)
        return self.fixed & np.isfinite(self.g_cam).all(axis=1)


@dataclass
class BAResult:
    T_cam_slam: np.ndarray  # (P,4,4) (fixed ones unchanged, levelled anchors re-oriented)
    points_slam: np.ndarray  # (M,3)
    residual_px: np.ndarray  # (O,) reprojection error after optimization
    initial_error: float
    final_error: float
    solve_ms: float  # wall clock in the worker (includes waiting for a CPU on a busy machine)
    solve_cpu_ms: float = float("nan")  # CPU time of the worker process for this BA (it runs nothing else)


def reprojection_errors(K: np.ndarray, T: np.ndarray, P: np.ndarray, obs_pose: np.ndarray,
                        obs_point: np.ndarray, uv: np.ndarray) -> np.ndarray:
    R = T[obs_pose, :3, :3]
    t = T[obs_pose, :3, 3]
    pc = np.einsum("nij,nj->ni", R, P[obs_point]) + t
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = pc[:, :2] / z[:, None] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    err = np.linalg.norm(proj - uv, axis=1)
    return np.where((z > 0) & np.isfinite(err), err, np.inf)


def bundle_adjust(problem: BAProblem) -> BAResult:
    """Solve the BA problem. Fixed poses are not variables: their observations become
    TriangulationFactors (camera known, only the point moves). Measured on loop-closing BAs
    (30-50 keyframes, 10-16k observations): the same optimum as hard NonlinearEquality constraints
    on the fixed poses, 4-6x faster (those made every LM step slow).

    Except in a gravity-aligned map (g_cam given): there a fixed camera with a gravity prior (a
    levelled anchor) is a variable that keeps its centre (a tight PoseTranslationPrior3D) while its
    orientation follows its gravity factor and the points. The gauge of a gravity-aligned
    monocular map is yaw, translation and scale, which two held centres fix; holding the anchors'
    full poses would also hold whatever tilt they carry, and the gravity factors of the free
    cameras would then bend the map instead of levelling it.

    Keys: pose i is key i, point j is key P + j (see _pose_key/_point_key). The projection factors
    of each free camera go in with one gtsam.utilities.insertProjectionFactors call instead of one
    Python call per observation. Levenberg-Marquardt stops at max_iterations or when an iteration
    lowers the cost by less than problem.lm_relative_decrease."""
    import gtsam

    t0, c0 = time.perf_counter(), time.process_time()
    p = problem
    n_poses = len(p.T_cam_slam)
    K = gtsam.Cal3_S2(p.K[0, 0], p.K[1, 1], 0.0, p.K[0, 2], p.K[1, 2])
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(p.huber_px / p.sigma_px),
        gtsam.noiseModel.Isotropic.Sigma(2, p.sigma_px))
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    poses_wc = [gtsam.Pose3(np.linalg.inv(T)) for T in p.T_cam_slam]  # gtsam wants camera-to-world
    levelled = p.levelled_anchors
    held = p.fixed & ~levelled  # not variables: their observations constrain the points only
    center_model = gtsam.noiseModel.Isotropic.Sigma(3, ANCHOR_CENTER_SIGMA * _scene_depth(p))
    for i in np.flatnonzero(~held).tolist():
        values.insert(_pose_key(i), poses_wc[i])
        if levelled[i]:
            graph.add(gtsam.PoseTranslationPrior3D(_pose_key(i), poses_wc[i].translation(), center_model))
    points = np.asarray(p.points_slam, float)
    for j, pt in enumerate(points):
        values.insert(_point_key(n_poses, j), pt)
    held_pts = np.zeros(len(points), bool) if p.fixed_points is None else np.asarray(p.fixed_points, bool)
    if held_pts.any():  # a tight prior, as for a levelled anchor's centre: cheaper than a constraint
        point_model = gtsam.noiseModel.Isotropic.Sigma(3, ANCHOR_CENTER_SIGMA * _scene_depth(p))
        for j in np.flatnonzero(held_pts).tolist():
            graph.add(gtsam.PriorFactorPoint3(_point_key(n_poses, j), points[j], point_model))
    order = np.argsort(p.obs_pose, kind="stable")
    bounds = np.searchsorted(p.obs_pose[order], np.arange(n_poses + 1))
    for i in range(n_poses):
        sel = order[bounds[i]:bounds[i + 1]]
        if len(sel) == 0:
            continue
        if held[i]:
            cam = gtsam.PinholeCameraCal3_S2(poses_wc[i], K)
            for j, uv in zip(p.obs_point[sel].tolist(), p.obs_uv_px[sel]):
                graph.add(gtsam.TriangulationFactorCal3_S2(cam, uv, noise, _point_key(n_poses, j)))
        else:  # landmark keys go in as float64 (the binding's type): exact, they are < 2**53
            gtsam.utilities.insertProjectionFactors(
                graph, _pose_key(i), _point_key(n_poses, p.obs_point[sel]).astype(float),
                np.ascontiguousarray(p.obs_uv_px[sel].T, float), noise, K)
    for f in gravity_factors(p):
        graph.add(f)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(p.max_iterations)
    params.setRelativeErrorTol(p.lm_relative_decrease)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    e0 = opt.error()
    res = opt.optimize()
    T_out = np.array([p.T_cam_slam[i] if held[i] else np.linalg.inv(res.atPose3(_pose_key(i)).matrix())
                      for i in range(n_poses)])
    P_out = np.array([res.atPoint3(_point_key(n_poses, j)) for j in range(len(p.points_slam))]).reshape(-1, 3)
    P_out[held_pts] = points[held_pts]  # exactly where they were
    resid = reprojection_errors(p.K, T_out, P_out, p.obs_pose, p.obs_point, p.obs_uv_px)
    return BAResult(T_out, P_out, resid, e0, opt.error(), (time.perf_counter() - t0) * 1e3,
                    (time.process_time() - c0) * 1e3)


def _pose_key(i):
    return i


def _point_key(n_poses: int, j):
    return n_poses + j


#: 1-sigma of a levelled anchor's centre, as a fraction of the median camera-to-point distance
ANCHOR_CENTER_SIGMA = 1e-5


def _scene_depth(p: BAProblem) -> float:
    """Median camera-to-point distance over the observations (the map's length unit is arbitrary)."""
    c = np.array([-T[:3, :3].T @ T[:3, 3] for T in p.T_cam_slam])
    d = np.linalg.norm(p.points_slam[p.obs_point] - c[p.obs_pose], axis=1) if len(p.obs_point) else np.ones(1)
    return float(np.median(d)) if np.isfinite(d).any() else 1.0


def gravity_factors(p: BAProblem) -> list:
    """One gravity-direction factor per camera with a prior (free cameras and levelled anchors;
    the SLAM frame is gravity-aligned, z up). gtsam 4.3 AttitudeFactorPose3(key, nRef, model,
    bMeasured) has the error e = nRef.error(nRb·bMeasured) ∈ R² (gtsam/navigation/AttitudeFactor.h;
    the argument order changed in 4.3): with the pose nRb = R_slam_cam, nRef = DOWN_SLAM and
    bMeasured = g_cam it is zero when the camera's measured gravity, rotated into the SLAM frame,
    points straight down (checked by tests/test_slam_gravity.py)."""
    import gtsam

    from slam.geometry import DOWN_SLAM

    if p.g_cam is None:
        return []
    n_ref = gtsam.Unit3(DOWN_SLAM)
    out = []
    for i in np.flatnonzero(np.isfinite(p.g_cam).all(axis=1)).tolist():
        model = gtsam.noiseModel.Isotropic.Sigma(2, float(p.gravity_sigma_rad[i]))
        out.append(gtsam.AttitudeFactorPose3(_pose_key(i), n_ref, model, gtsam.Unit3(np.asarray(p.g_cam[i], float))))
    return out


def _warm() -> bool:
    import gtsam  # noqa: F401  (import once in the worker so the first BA is not slowed)

    return True


def ba_worker(nice: int = 0) -> ForkedWorker:
    """The BA worker process shared by local mapping and loop closing: ``submit(bundle_adjust,
    problem)``, at ``nice`` below this process's priority (``slam.ba_nice``). If it dies the BA in
    flight fails (BrokenProcessPool) and mapping goes on."""
    return ForkedWorker("bundle-adjustment", warm=_warm, nice=nice)
