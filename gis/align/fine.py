"""Online fine-tuning T_fine (TerraSLAM §4.4; digital-twin paper §III-C, §III-E, §V).

One registration = crop the GIS model around the current position (fixed size, so the cost does
not grow with the model), voxel-downsample both clouds, then a scale-aware point-to-plane ICP:

- Correspondences: nearest GIS point (scipy cKDTree, C, vectorised queries; open3d's KDTreeFlann
  answers one query per Python call), coarse-to-fine distances (max_correspondence_m, /2, /4).
- Solve: open3d's point-to-plane ICP is rigid (6 DoF), but monocular SLAM scale drifts, so each
  iteration is one Gauss–Newton step over 7 DoF (rotation, translation, log-scale) of the
  point-to-plane cost of digital-twin Eq. 2 with a Tukey robust kernel (IRLS). Its Jacobian row
  is Eq. 9's A_j extended by the scale column n_j·a_j. Written by hand because no library here
  does point-to-plane with scale; it is 15 lines of vectorised numpy.
- Poor guess (opt-in, ``fpfh_fallback``): if ICP fails the gates, retry from open3d's FPFH +
  RANSAC global registration (§4.4 "ICP with FPFH features and normals"), then ICP again; the
  same gates apply. Off by default: it costs seconds, and with a sparse SLAM cloud against a
  dense model of a regular city the FPFH matches were wrong in our trials (tens of metres).
- Gates (§V: "registration declared unsuccessful"): too few points, fitness, inlier RMSE, jump of
  the map centre, and degeneracy: covariance σ²·H⁻¹ from the ICP Hessian H = Σ A_jᵀA_j (Eq. 8–9)
  along its weakest position / rotation / scale direction; a single straight facade leaves a
  direction unobserved and is refused instead of giving a confident wrong fix. The accepted
  information is H·exp(−γ²/2)/σ² (Eq. 10's shape; absolute units instead of β/trace).

Pure and thread-safe: no state changes after construction except the model's lazily built grid
index (built once, eagerly, in the constructor).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from gis.config import AlignmentConfig
from gis.geodesy import LocalFrame, ecef_to_geodetic
from gis.model import GisModel
from gis.sim3 import Sim3, compose
from gis.types import Alignment, AlignmentSource

log = logging.getLogger(__name__)

ICP_ITERATIONS_PER_LEVEL = 12


@dataclass(frozen=True)
class Registration:
    """Outcome of one fine-tuning attempt: alignment (None when a gate rejected it) and why."""

    alignment: Alignment | None
    reason: str
    fitness: float = 0.0
    rmse_m: float = 0.0
    jump_m: float = 0.0
    sigma_m: float = float("inf")
    n_source: int = 0
    n_target: int = 0
    used_fpfh: bool = False
    wall_ms: float = 0.0


@dataclass(frozen=True)
class _Icp:
    T: Sim3                   # increment in centred ENU coordinates
    fitness: float
    rmse_m: float
    H7: np.ndarray            # 7x7 Gauss–Newton Hessian [rot, trans, log-scale] at the crop centre
    n_inliers: int


def enu_sim3(origin: LocalFrame) -> Sim3:
    """T_ecef_enu as a Sim3."""
    return Sim3(1.0, origin.R_ecef_enu, origin.origin_ecef_m)


class FineTuner:
    def __init__(self, model: GisModel, config: AlignmentConfig | None = None) -> None:
        self.model = model
        self.config = config or AlignmentConfig()
        self._T_ecef_enu = enu_sim3(model.origin)
        self._T_enu_ecef = self._T_ecef_enu.inverse()
        _ = model._grid  # build the crop index now, not in the first (timed) refine

    def refine(self, points_slam: np.ndarray, initial: Alignment, t_s: float, reset_counter: int,
               center_slam: np.ndarray | None = None, map_id: int = 0) -> Alignment | None:
        """Refined alignment, or None (reason logged) when a gate rejects the registration."""
        reg = self.register(points_slam, initial, t_s, reset_counter, center_slam, map_id)
        if reg.alignment is None:
            log.info("fine-tune rejected: %s", reg.reason)
        return reg.alignment

    def register(self, points_slam: np.ndarray, initial: Alignment, t_s: float, reset_counter: int,
                 center_slam: np.ndarray | None = None, map_id: int = 0) -> Registration:
        t0 = time.perf_counter()
        cfg = self.config
        pts = np.asarray(points_slam, float).reshape(-1, 3)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if len(pts) < cfg.min_points:
            return Registration(None, f"only {len(pts)} SLAM points (< min_points {cfg.min_points})", n_source=len(pts))
        T_enu_slam = compose(self._T_enu_ecef, initial.T_ecef_slam)
        src = T_enu_slam.apply(pts)
        c_slam = np.median(pts, axis=0) if center_slam is None else np.asarray(center_slam, float).reshape(3)
        c = T_enu_slam.apply(c_slam)
        half = cfg.crop_size_m / 2
        src = src[np.all(np.abs(src[:, :2] - c[:2]) <= half, axis=1)] - c
        idx = self.model.crop(c, cfg.crop_size_m)
        src = _voxel(src, cfg.source_voxel_m)
        if len(src) < cfg.min_points:
            return Registration(None, f"only {len(src)} SLAM points in the {cfg.crop_size_m:.0f} m crop", n_source=len(src))
        if len(idx) < cfg.min_points:
            return Registration(None, f"GIS crop holds only {len(idx)} points (outside the model?)", n_target=len(idx))
        tgt, tgt_n = _voxel_with_normals(self.model.points_enu[idx] - c, self.model.normals_enu[idx], cfg.target_voxel_m)
        tree = cKDTree(tgt)
        # Correspondence distances never drop below the model's own point spacing (a sparse
        # model would otherwise lose true correspondences and report a low fitness).
        spacing = float(np.median(tree.query(tgt[:: max(1, len(tgt) // 300)], k=2)[0][:, 1]))
        min_corr = 1.5 * spacing

        icp = _icp(src, tgt, tgt_n, tree, Sim3.identity(), cfg, min_corr)
        reason = self._gate(icp, cfg)
        used_fpfh = False
        if reason and cfg.fpfh_fallback:
            guess = _fpfh_guess(src, tgt, tgt_n, cfg)
            if guess is not None:
                icp2 = _icp(src, tgt, tgt_n, tree, guess, cfg, min_corr)
                reason2 = self._gate(icp2, cfg)
                if not reason2 or icp2.fitness > icp.fitness:
                    icp, reason, used_fpfh = icp2, reason2, True
        sigmas = _sigmas(icp, cfg)
        jump = float(np.linalg.norm(icp.T.t))
        common = dict(fitness=icp.fitness, rmse_m=icp.rmse_m, jump_m=jump, sigma_m=sigmas[0],
                      n_source=len(src), n_target=len(tgt), used_fpfh=used_fpfh)
        if not reason and jump > cfg.max_jump_m:
            reason = f"jump {jump:.2f} m > max_jump_m {cfg.max_jump_m}"
        if reason:
            return Registration(None, reason, wall_ms=1e3 * (time.perf_counter() - t0), **common)

        # T_enu_slam' = T(+c) ∘ ΔT ∘ T(−c) ∘ T_enu_slam
        T_c = Sim3(1.0, np.eye(3), c)
        T_enu_slam_new = compose(compose(T_c, compose(icp.T, T_c.inverse())), T_enu_slam)
        T_ecef_slam = compose(self._T_ecef_enu, T_enu_slam_new)
        c_new_slam = T_enu_slam_new.inverse().apply(c)
        alignment = Alignment(
            T_ecef_slam=T_ecef_slam, source=AlignmentSource.FINE, t_s=t_s, reset_counter=reset_counter,
            information_6x6=self._information_at_center(icp, c, cfg), sigma_m=sigmas[0],
            fitness=icp.fitness, rmse_m=icp.rmse_m, n_points=icp.n_inliers, map_id=map_id,
            center_slam=c_new_slam, scale_sigma=sigmas[2],
        )
        return Registration(alignment, "ok", wall_ms=1e3 * (time.perf_counter() - t0), **common)

    def _gate(self, icp: _Icp, cfg: AlignmentConfig) -> str:
        if icp.fitness < cfg.min_fitness:
            return f"fitness {icp.fitness:.2f} < min_fitness {cfg.min_fitness}"
        if icp.rmse_m > cfg.max_rmse_m:
            return f"inlier RMSE {icp.rmse_m:.2f} m > max_rmse_m {cfg.max_rmse_m}"
        sig_p, sig_r, sig_s = _sigmas(icp, cfg)
        if sig_p > cfg.max_sigma_m:
            return f"degenerate geometry: position 1-σ {sig_p:.2g} m > max_sigma_m {cfg.max_sigma_m} (e.g. a single facade)"
        if np.degrees(sig_r) > cfg.max_sigma_rot_deg:
            return f"degenerate geometry: rotation 1-σ {np.degrees(sig_r):.2g}° > max_sigma_rot_deg {cfg.max_sigma_rot_deg}"
        if sig_s > cfg.max_sigma_scale:
            return f"degenerate geometry: scale 1-σ {sig_s:.2g} > max_sigma_scale {cfg.max_sigma_scale}"
        return ""

    def _information_at_center(self, icp: _Icp, c_enu: np.ndarray, cfg: AlignmentConfig) -> np.ndarray:
        """Eq. 10-shaped information of [rot, trans] in the ENU frame at the crop centre."""
        sigma2 = max(icp.rmse_m, cfg.sigma_floor_m) ** 2
        info = icp.H7[:6, :6] * np.exp(-(icp.rmse_m**2) / 2) / sigma2
        lat, lon, _ = ecef_to_geodetic(self._T_ecef_enu.apply(c_enu))
        R = LocalFrame(float(lat), float(lon)).R_ecef_enu.T @ self.model.origin.R_ecef_enu  # R_enuC_enuO
        B = np.kron(np.eye(2), R)
        return B @ info @ B.T


def _sigmas(icp: _Icp, cfg: AlignmentConfig) -> tuple[float, float, float]:
    """Weakest 1-σ of (position m, rotation rad, relative scale) from σ²·H⁻¹ (inf if singular)."""
    sigma2 = max(icp.rmse_m, cfg.sigma_floor_m) ** 2
    H = icp.H7
    w, V = np.linalg.eigh(H)
    if w[0] <= 1e-9 * max(w[-1], 1e-12):
        return float("inf"), float("inf"), float("inf")
    cov = sigma2 * (V / w) @ V.T
    sig_p = float(np.sqrt(np.linalg.eigvalsh(cov[3:6, 3:6])[-1]))
    sig_r = float(np.sqrt(np.linalg.eigvalsh(cov[:3, :3])[-1]))
    return sig_p, sig_r, float(np.sqrt(cov[6, 6]))


def _icp(src: np.ndarray, tgt: np.ndarray, tgt_n: np.ndarray, tree: cKDTree, T0: Sim3, cfg: AlignmentConfig,
         min_corr_m: float) -> _Icp:
    """Scale-aware point-to-plane ICP (Gauss–Newton, Tukey IRLS) in centred coordinates."""
    T = T0
    k = cfg.robust_kernel_m
    for level in range(3):
        max_d = max(cfg.max_correspondence_m / 2**level, min_corr_m)
        for _ in range(ICP_ITERATIONS_PER_LEVEL):
            x = T.apply(src)
            d, j = tree.query(x, distance_upper_bound=max_d)
            ok = np.isfinite(d)
            if ok.sum() < 7:
                break
            x, n, b = x[ok], tgt_n[j[ok]], tgt[j[ok]]
            r = np.einsum("ij,ij->i", n, x - b)
            w = np.where(np.abs(r) < k, (1 - (r / k) ** 2) ** 2, 0.0)  # Tukey biweight
            J = np.hstack([np.cross(x, n), n, np.einsum("ij,ij->i", n, x)[:, None]])  # Eq. 9 + scale column
            H = (J * w[:, None]).T @ J
            g = (J * w[:, None]).T @ r
            try:
                delta = -np.linalg.solve(H + 1e-6 * np.trace(H) / 7 * np.eye(7), g)
            except np.linalg.LinAlgError:
                break
            dT = Sim3(float(np.exp(delta[6])), Rotation.from_rotvec(delta[:3]).as_matrix(), delta[3:6])
            T = compose(dT, T)
            if np.linalg.norm(delta[:3]) < 1e-6 and np.linalg.norm(delta[3:6]) < 1e-5 and abs(delta[6]) < 1e-6:
                break
    # Final inliers, RMSE and the Hessian of Eq. 8–9 (unweighted, inliers only).
    x = T.apply(src)
    d, j = tree.query(x, distance_upper_bound=max(cfg.max_correspondence_m / 4, min_corr_m))
    ok = np.isfinite(d)
    n, b, x = tgt_n[j[ok]], tgt[j[ok]], x[ok]
    r = np.einsum("ij,ij->i", n, x - b)
    inl = np.abs(r) < cfg.inlier_distance_m
    fitness = float(inl.sum()) / len(src)
    rmse = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("inf")
    J = np.hstack([np.cross(x[inl], n[inl]), n[inl], np.einsum("ij,ij->i", n[inl], x[inl])[:, None]])
    return _Icp(T, fitness, rmse, J.T @ J, int(inl.sum()))


def _voxel(p: np.ndarray, voxel_m: float) -> np.ndarray:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    return np.asarray(pcd.voxel_down_sample(voxel_m).points)


def _voxel_with_normals(p: np.ndarray, n: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    pcd.normals = o3d.utility.Vector3dVector(n)
    d = pcd.voxel_down_sample(voxel_m)
    nn = np.asarray(d.normals)
    norm = np.linalg.norm(nn, axis=1, keepdims=True)
    keep = norm[:, 0] > 0.5  # averaged opposite normals (thin walls) are unreliable: drop
    return np.asarray(d.points)[keep], nn[keep] / norm[keep]


def _fpfh_guess(src: np.ndarray, tgt: np.ndarray, tgt_n: np.ndarray, cfg: AlignmentConfig) -> Sim3 | None:
    """Global registration from FPFH features + RANSAC (open3d), rigid (scale is close already)."""
    reg = o3d.pipelines.registration
    voxel = max(cfg.target_voxel_m, cfg.source_voxel_m) * 2
    s = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src)).voxel_down_sample(voxel)
    t = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt))
    t.normals = o3d.utility.Vector3dVector(tgt_n)
    t = t.voxel_down_sample(voxel)
    if len(s.points) < 10 or len(t.points) < 10:
        return None
    s.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 3, max_nn=30))
    param = o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 5, max_nn=100)
    fs = reg.compute_fpfh_feature(s, param)
    ft = reg.compute_fpfh_feature(t, param)
    res = reg.registration_ransac_based_on_feature_matching(
        s, t, fs, ft, True, voxel * 1.5, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(voxel * 1.5)],
        reg.RANSACConvergenceCriteria(20000, 0.999),
    )
    if res.fitness <= 0:
        return None
    return Sim3.from_matrix(res.transformation)
