"""Offline initialization T_rough (TerraSLAM §4.3) from a dense SLAM-frame survey cloud.

Steps, each on both clouds (the SLAM survey cloud, arbitrary frame and scale; the GIS model crop
around the rough position, ENU metres):
1. Segmentation (geometric, the issue allows it in place of the paper's PointNet++): the
   dominant plane is the ground (open3d RANSAC ``segment_plane``), its normal the up axis
   (signed so the structures stand above it); points above it are clustered into buildings
   (open3d DBSCAN). Thresholds for the SLAM cloud are in units of its median point spacing, so
   they do not depend on its unknown scale.
2. Corners: each building's minimum-area rectangle (OpenCV ``minAreaRect``) at roof height.
3. Eq. 2 with RANSAC over correspondences: a hypothesis pairs one of the largest SLAM buildings
   with a GIS building (origin = that building's centroid, the paper's "largest building"
   origin), scale from the footprint ratio, yaw from the rectangle orientation (4 options); the
   σ(i) of Eq. 2 are nearest corners, and the inliers are re-solved in closed form (Umeyama,
   gis.sim3.umeyama). The hypothesis with most corner inliers (then least residual) wins.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from gis.align.fine import enu_sim3
from gis.model import GisModel
from gis.sim3 import Sim3, compose, umeyama

log = logging.getLogger(__name__)


class RoughAlignmentFailed(RuntimeError):
    """No consistent building correspondence was found; the message says what was missing."""


@dataclass(frozen=True)
class Building:
    centroid: np.ndarray     # (3,) roof-level centre in the levelled frame
    corners: np.ndarray      # (4, 3) roof corners
    area: float              # footprint area (frame units²)
    angle_rad: float         # rectangle orientation
    height: float            # roof height above ground


@dataclass(frozen=True)
class RoughResult:
    T_ecef_slam: Sim3
    n_inliers: int           # corner correspondences supporting it
    corner_rmse_m: float
    error_m: float           # mean point-to-model distance of the survey cloud (TerraSLAM Table 4)


def level_and_segment(p: np.ndarray, unit: float) -> tuple[Sim3, list[Building]]:
    """Ground plane → levelling similarity (up = +z, ground at z = 0) and building rectangles.

    unit: length scale of the cloud (its median point spacing); thresholds are multiples of it.
    """
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    o3d.utility.random.seed(0)
    plane, ground = pcd.segment_plane(distance_threshold=2 * unit, ransac_n=3, num_iterations=2000)
    n = np.asarray(plane[:3], float)
    d = float(plane[3]) / np.linalg.norm(n)
    n = n / np.linalg.norm(n)
    rest = np.delete(np.arange(len(p)), ground)
    if len(rest) and np.median(p[rest] @ n + d) < 0:
        n, d = -n, -d
    R = _rotation_to_z(n)
    T_lev = Sim3(1.0, R, np.array([0.0, 0.0, d]))  # z = n·p + d after rotation
    q = T_lev.apply(p)
    above = rest[q[rest, 2] > 3 * unit]
    if len(above) < 10:
        return T_lev, []
    sub = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(q[above]))
    lab = np.asarray(sub.cluster_dbscan(eps=4 * unit, min_points=8))
    buildings = []
    for k in range(lab.max() + 1):
        c = q[above][lab == k]
        if len(c) < 30:
            continue
        roof_z = float(np.percentile(c[:, 2], 95))
        (cx, cy), (w, h), ang = cv2.minAreaRect(c[:, :2].astype(np.float32))
        box = cv2.boxPoints(((cx, cy), (w, h), ang))
        corners = np.hstack([box, np.full((4, 1), roof_z)])
        buildings.append(Building(np.array([cx, cy, roof_z]), corners, float(w * h), np.radians(ang), roof_z))
    buildings.sort(key=lambda b: -b.area)
    return T_lev, buildings


def rough_align(cloud_slam: np.ndarray, model: GisModel, center_enu: np.ndarray, radius_m: float = 250.0,
                top_k: int = 3, progress: Callable[[str], None] | None = None) -> RoughResult:
    """T_rough mapping the survey cloud (SLAM frame) to ECEF; RoughAlignmentFailed if none fits."""
    say = progress or (lambda s: log.info(s))
    p_s = np.asarray(cloud_slam, float)
    p_s = p_s[np.all(np.isfinite(p_s), axis=1)]
    if len(p_s) < 200:
        raise RoughAlignmentFailed(f"survey cloud has only {len(p_s)} points (need ≥ 200)")
    unit_s = _spacing(p_s)
    say(f"segmenting the survey cloud ({len(p_s)} points, spacing {unit_s:.3g} SLAM units)")
    T_lev_s, b_s = level_and_segment(p_s, unit_s)
    idx = model.crop(np.asarray(center_enu, float), 2 * radius_m)
    p_g = model.points_enu[idx]
    if len(p_g) < 200:
        raise RoughAlignmentFailed(f"GIS model has only {len(p_g)} points within {radius_m} m of the rough position")
    say(f"segmenting the GIS model crop ({len(p_g)} points)")
    T_lev_g, b_g = level_and_segment(p_g, _spacing(p_g))
    if not b_s or not b_g:
        raise RoughAlignmentFailed(f"buildings found: survey {len(b_s)}, GIS {len(b_g)}; need at least one in each")
    corners_s = np.concatenate([b.corners for b in b_s])
    corners_g = np.concatenate([b.corners for b in b_g])
    tree = cKDTree(corners_g)
    best = None
    say(f"RANSAC over {min(top_k, len(b_s))}×{len(b_g)} building pairs × 4 yaws")
    for bs in b_s[:top_k]:
        for bg in b_g:
            s = np.sqrt(bg.area / bs.area)
            if not 0.5 < (bg.height / (s * bs.height)) < 2.0:
                continue
            for k in range(4):
                yaw = bg.angle_rad - bs.angle_rad + k * np.pi / 2
                c, sn = np.cos(yaw), np.sin(yaw)
                Rz = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1.0]])
                t = bg.centroid - s * Rz @ bs.centroid
                t[2] = bg.centroid[2] - s * bs.centroid[2]
                T = Sim3(s, Rz, t)
                T, n_in, rmse = _refine_on_corners(T, corners_s, corners_g, tree, thresh=max(2.0, 0.15 * np.sqrt(bg.area)))
                if T is not None and (best is None or (n_in, -rmse) > (best[1], -best[2])):
                    best = (T, n_in, rmse)
    if best is None or best[1] < 4:
        raise RoughAlignmentFailed("no building correspondence hypothesis had 4 or more consistent corners")
    T_levg_levs, n_in, rmse = best
    # T_enu_slam = T_levg⁻¹ ∘ T_levg_levs ∘ T_levs
    T_enu_slam = compose(compose(T_lev_g.inverse(), T_levg_levs), T_lev_s)
    T_ecef_slam = compose(enu_sim3(model.origin), T_enu_slam)
    err = alignment_error_m(T_enu_slam.apply(p_s), model)
    say(f"T_rough: {n_in} corner inliers, corner RMSE {rmse:.2f} m, mean point-to-model {err:.2f} m")
    return RoughResult(T_ecef_slam, n_in, rmse, err)


def alignment_error_m(p_enu: np.ndarray, model: GisModel) -> float:
    """Mean point-to-plane distance of aligned points to the model (TerraSLAM Table 4's metric)."""
    idx_all = model.crop(np.median(p_enu, axis=0), 2 * float(np.ptp(p_enu[:, :2], axis=0).max()) + 20)
    _, j = cKDTree(model.points_enu[idx_all]).query(p_enu)
    n = model.normals_enu[idx_all[j]]
    return float(np.mean(np.abs(np.einsum("ij,ij->i", p_enu - model.points_enu[idx_all[j]], n))))


def _refine_on_corners(T: Sim3, cs: np.ndarray, cg: np.ndarray, tree: cKDTree, thresh: float):
    """Eq. 2 with σ(i) = nearest GIS corner, solved by Umeyama on the inliers; 3 rounds."""
    n_in, rmse = 0, np.inf
    for _ in range(3):
        d, j = tree.query(T.apply(cs))
        inl = d < thresh
        if inl.sum() < 4:
            return None, 0, np.inf
        try:
            T = umeyama(cs[inl], cg[j[inl]], with_scale=True)
        except ValueError:
            return None, 0, np.inf
        d, j = tree.query(T.apply(cs))
        inl = d < thresh
        n_in, rmse = int(inl.sum()), float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else np.inf
    return T, n_in, rmse


def _spacing(p: np.ndarray) -> float:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p - p.mean(axis=0)))
    return float(np.median(np.asarray(pcd.compute_nearest_neighbor_distance())))


def _rotation_to_z(n: np.ndarray) -> np.ndarray:
    """Rotation taking unit vector n to +z (Rodrigues; identity/180° handled)."""
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(n, z), float(n @ z)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)
