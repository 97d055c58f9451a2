"""Similarity transforms Sim(3): p_a = s · R · p_b + t.

A monocular SLAM map has arbitrary scale, so the physically meaningful SLAM→ECEF map is a
similarity (TerraSLAM §4.1 calls it affine; a similarity is the case with a physical meaning).
``T_a_b`` maps points in frame b to frame a; ``compose(T_a_b, T_b_c) = T_a_c``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d


@dataclass(frozen=True)
class Sim3:
    """scale (dimensionless, > 0), R (3x3 rotation), t (3,) translation in the target frame's units."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        if not np.isfinite(self.scale) or self.scale <= 0:
            raise ValueError(f"Sim3 scale must be finite and > 0, got {self.scale}")
        R = np.asarray(self.R, dtype=float)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("Sim3 R must be a proper 3x3 rotation matrix")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", np.asarray(self.t, dtype=float).reshape(3))

    @staticmethod
    def identity() -> "Sim3":
        return Sim3(1.0, np.eye(3), np.zeros(3))

    @staticmethod
    def from_matrix(M: np.ndarray) -> "Sim3":
        """From a 4x4 matrix [[sR, t], [0, 1]]."""
        M = np.asarray(M, dtype=float)
        sR = M[:3, :3]
        s = float(np.cbrt(np.linalg.det(sR)))
        return Sim3(s, sR / s, M[:3, 3])

    def matrix(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3] = self.scale * self.R
        M[:3, 3] = self.t
        return M

    def apply(self, p: np.ndarray) -> np.ndarray:
        """Map points (..., 3) from the source frame to the target frame."""
        p = np.asarray(p, dtype=float)
        return self.scale * p @ self.R.T + self.t

    def apply_pose(self, T_b_c: np.ndarray) -> np.ndarray:
        """Map a rigid pose T_b_c (4x4) to T_a_c: rotation R·R_bc, position s·R·t_bc + t (unit scale kept)."""
        T = np.eye(4)
        T[:3, :3] = self.R @ T_b_c[:3, :3]
        T[:3, 3] = self.apply(T_b_c[:3, 3])
        return T

    def inverse(self) -> "Sim3":
        Rinv = self.R.T
        return Sim3(1.0 / self.scale, Rinv, -(Rinv @ self.t) / self.scale)

    def __matmul__(self, other: "Sim3") -> "Sim3":
        return compose(self, other)


def compose(T_a_b: Sim3, T_b_c: Sim3) -> Sim3:
    """T_a_c = T_a_b ∘ T_b_c."""
    return Sim3(
        T_a_b.scale * T_b_c.scale,
        T_a_b.R @ T_b_c.R,
        T_a_b.scale * (T_a_b.R @ T_b_c.t) + T_a_b.t,
    )


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> Sim3:
    """Least-squares similarity with dst ≈ s·R·src + t (Umeyama 1991, Eq. 40–42).

    Solved by open3d's TransformationEstimationPointToPoint (which implements Umeyama's closed
    form) on the given one-to-one correspondences src[i] ↔ dst[i]; needs ≥ 3 non-collinear points.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama needs two (N, 3) arrays of equal shape, got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise ValueError(f"umeyama needs at least 3 correspondences, got {len(src)}")
    centred = src - src.mean(axis=0)
    if np.linalg.matrix_rank(centred, tol=1e-9 * max(1.0, np.abs(centred).max())) < 2:
        raise ValueError("umeyama: source points are collinear or coincident; rotation is undetermined")
    # Shift both clouds to their centroids before handing them to float64 open3d: ECEF-sized
    # coordinates (6e6 m) would otherwise cost precision in the covariance sums.
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    pcd_s = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src - mu_s))
    pcd_d = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(dst - mu_d))
    idx = np.arange(len(src), dtype=np.int32)
    corres = o3d.utility.Vector2iVector(np.stack([idx, idx], axis=1))
    est = o3d.pipelines.registration.TransformationEstimationPointToPoint(with_scaling=with_scale)
    centred_T = Sim3.from_matrix(est.compute_transformation(pcd_s, pcd_d, corres))
    # dst - mu_d = s R (src - mu_s) + t'  =>  t = t' + mu_d - s R mu_s
    t = centred_T.t + mu_d - centred_T.scale * centred_T.R @ mu_s
    return Sim3(centred_T.scale, centred_T.R, t)
