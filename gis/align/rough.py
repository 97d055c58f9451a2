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
   origin), scale from the footprint ratio, yaw from the rectangle orientation (4 options) or a
   5° grid (a partly seen building's rectangle can be tilted). Hypotheses are scored by the
   fraction of the survey cloud's structures within score_m of the model; the best is refined by Eq. 2 with
   σ(i) = nearest corners, solved in closed form (Umeyama, gis.sim3.umeyama), if that raises the
   score. Below min_score the alignment is refused.
4. Optional polish (``refine``, beyond the paper): the scale-aware point-to-plane ICP of
   gis.align.fine on the whole survey cloud, kept only if it passes its gates and lowers the
   point-to-model error.
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
from gis.model import BUILDING, GROUND, GisModel
from gis.sim3 import Sim3, compose, umeyama

log = logging.getLogger(__name__)


YAW_GRID_RAD = np.radians(np.arange(0.0, 360.0, 5.0))


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
class StartPrior:
    """Where the survey started: its first camera centre in the survey cloud's frame and, roughly
    (the dataset's ``rough_position``), in the GIS model's ENU frame, metres, with its 1-σ."""

    p_slam: np.ndarray
    p_enu: np.ndarray
    sigma_m: float


@dataclass(frozen=True)
class RoughResult:
    T_ecef_slam: Sim3
    n_inliers: int           # corner correspondences supporting it
    corner_rmse_m: float
    error_m: float           # mean point-to-model distance of the survey cloud (TerraSLAM Table 4)


def level_and_segment(p: np.ndarray, unit: float, ground: np.ndarray | None = None,
                      candidates: np.ndarray | None = None) -> tuple[Sim3, list[Building]]:
    """Ground plane → levelling similarity (up = +z, ground at z = 0) and building rectangles.

    unit: length scale of the cloud (its median point spacing); thresholds are multiples of it.
    ground / candidates: boolean masks from known labels (GIS models); when not given the
    ground is the dominant RANSAC plane and the candidates are the points above it.
    """
    o3d.utility.random.seed(0)
    sel = np.flatnonzero(ground) if ground is not None else np.arange(len(p))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p[sel]))
    plane, inl = pcd.segment_plane(distance_threshold=2 * unit, ransac_n=3, num_iterations=2000)
    n = np.asarray(plane[:3], float)
    d = float(plane[3]) / np.linalg.norm(n)
    n = n / np.linalg.norm(n)
    rest = np.delete(np.arange(len(p)), sel[inl]) if candidates is None else np.flatnonzero(candidates)
    if len(rest) and np.median(p[rest] @ n + d) < 0:
        n, d = -n, -d
    T_lev = Sim3(1.0, _rotation_to_z(n), np.array([0.0, 0.0, d]))  # z = n·p + d after rotation
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
                top_k: int = 8, progress: Callable[[str], None] | None = None, refine: bool = True,
                score_m: float = 1.5, min_score: float = 0.5, start: StartPrior | None = None,
                distinct_m: float = 10.0, max_runner_up: float = 0.9) -> RoughResult:
    """T_rough mapping the survey cloud (SLAM frame) to ECEF; RoughAlignmentFailed if none fits,
    or if the fit is not unique: a placement of the cloud at least ``distinct_m`` away (its
    centroid) scoring ``max_runner_up`` × the best or more (a regular block of buildings fits in
    several places, and a wrong T_rough would be flown with confidence). ``start``: where the
    survey started, in both frames (dataset ``rough_position``); placements that put the survey's
    first camera more than 3σ + ``distinct_m`` from it are not considered."""
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
    lab_g = model.labels[idx]
    if np.sum(lab_g == BUILDING) >= 100 and np.sum(lab_g == GROUND) >= 100:  # labelled model: use its classes
        T_lev_g, b_g = level_and_segment(p_g, _spacing(p_g), lab_g == GROUND, lab_g == BUILDING)
    else:
        T_lev_g, b_g = level_and_segment(p_g, _spacing(p_g))
    if not b_s or not b_g:
        raise RoughAlignmentFailed(f"buildings found: survey {len(b_s)}, GIS {len(b_g)}; need at least one in each")
    corners_s = np.concatenate([b.corners for b in b_s])
    corners_g = np.concatenate([b.corners for b in b_g])
    tree = cKDTree(corners_g)
    # Hypotheses are ranked by how much of the survey cloud's above-ground part lands on the
    # model (fraction of a subsample within score_m of a GIS point, levelled frames); corner
    # counts alone favour wrong hypotheses in regular city blocks.
    q_s = T_lev_s.apply(p_s)
    q_s = q_s[q_s[:, 2] > 3 * unit_s]  # structures only: ground lands on ground in any hypothesis
    sample_s = q_s[:: max(1, len(q_s) // 500)]
    tree_g = cKDTree(T_lev_g.apply(p_g))
    start_lev = None if start is None else (T_lev_s.apply(np.asarray(start.p_slam, float)[None])[0],
                                            T_lev_g.apply(np.asarray(start.p_enu, float)[None])[0],
                                            3 * start.sigma_m + distinct_m)
    hyps: list[tuple[float, Sim3, Building]] = []
    say(f"RANSAC over {min(top_k, len(b_s))}×{len(b_g)} building pairs × {4 + len(YAW_GRID_RAD)} yaws")
    for bs in b_s[:top_k]:
        for bg in b_g:
            s = np.sqrt(bg.area / bs.area)
            if not 0.67 < (bg.height / (s * bs.height)) < 1.5:
                continue
            # rectangle orientations (4 options) and, since a partly seen building's rectangle can
            # be tilted, a 5° grid of yaws; scored hypotheses are cheap (one KD-tree query)
            for yaw in np.concatenate([bg.angle_rad - bs.angle_rad + np.arange(4) * np.pi / 2, YAW_GRID_RAD]):
                c, sn = np.cos(yaw), np.sin(yaw)
                Rz = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1.0]])
                t = bg.centroid - s * Rz @ bs.centroid
                T = Sim3(s, Rz, t)
                if start_lev is not None and np.linalg.norm((T.apply(start_lev[0]) - start_lev[1])[:2]) > start_lev[2]:
                    continue
                hyps.append((float(np.mean(tree_g.query(T.apply(sample_s), distance_upper_bound=score_m)[0] < score_m)), T, bg))
    if not hyps:
        raise RoughAlignmentFailed("no building pair had a consistent height/footprint ratio"
                                   + ("" if start is None else " with the survey's start near the rough position"))
    score, T, bg = max(hyps, key=lambda h: h[0])
    best = (T, 0, float("nan"), score, bg)
    # Eq. 2 on nearest corners from the best hypothesis; kept if more of the cloud lands on the model
    T_ref, n_in, rmse = _refine_on_corners(best[0], corners_s, corners_g, tree, thresh=max(2.0, 0.15 * np.sqrt(best[4].area)))
    if T_ref is not None and n_in >= 4:
        score = float(np.mean(tree_g.query(T_ref.apply(sample_s), distance_upper_bound=score_m)[0] < score_m))
        if score >= best[3]:
            best = (T_ref, n_in, rmse, score, best[4])
    T_levg_levs, n_in, rmse, score, _ = best
    say(f"best hypothesis: {100 * score:.0f} % of the survey structures within {score_m} m of the model")
    if score < min_score:
        raise RoughAlignmentFailed(f"best hypothesis puts only {100 * score:.0f} % of the survey structures on the model (< {100 * min_score:.0f} %)")
    c_s = q_s.mean(axis=0)
    c_best = T_levg_levs.apply(c_s)
    others = [(h[0], float(np.linalg.norm(h[1].apply(c_s) - c_best))) for h in hyps]
    rival = max((o for o in others if o[1] > distinct_m), default=None)
    if rival is not None and rival[0] >= max_runner_up * score:
        raise RoughAlignmentFailed(
            f"ambiguous: a placement {rival[1]:.0f} m away puts {100 * rival[0]:.0f} % of the survey structures on the model, "
            f"the best {100 * score:.0f} % (a regular block fits in several places; survey a larger or more distinctive area"
            + ("" if start is not None else ", or give the survey's start position") + ")")
    say(f"unique: the best placement more than {distinct_m:g} m away scores "
        f"{'-' if rival is None else f'{100 * rival[0]:.0f} %'}")
    # T_enu_slam = T_levg⁻¹ ∘ T_levg_levs ∘ T_levs
    T_enu_slam = compose(compose(T_lev_g.inverse(), T_levg_levs), T_lev_s)
    T_ecef_slam = compose(enu_sim3(model.origin), T_enu_slam)
    err = alignment_error_m(T_enu_slam.apply(p_s), model)
    say(f"corners: {n_in} inliers, corner RMSE {rmse:.2f} m, mean point-to-model {err:.2f} m")
    if refine:
        T_ecef_slam, err = _refine_icp(p_s, model, T_ecef_slam, radius_m, err, say)
    return RoughResult(T_ecef_slam, n_in, rmse, err)


def _refine_icp(p_s: np.ndarray, model: GisModel, T_ecef_slam: Sim3, radius_m: float, err: float, say) -> tuple[Sim3, float]:
    """Polish the corner solution with the scale-aware point-to-plane ICP of gis.align.fine on the
    whole survey cloud (large crop, wide first correspondence distance); kept only if it passes
    the fine-tuner's gates and lowers the point-to-model error."""
    from gis.align.fine import FineTuner
    from gis.config import AlignmentConfig
    from gis.types import Alignment, AlignmentSource

    cfg = AlignmentConfig(crop_size_m=min(2 * radius_m, 5000), max_correspondence_m=6.0, robust_kernel_m=1.0,
                          inlier_distance_m=1.0, max_jump_m=10.0, fpfh_fallback=False, min_fitness=0.5)
    a0 = Alignment(T_ecef_slam, AlignmentSource.ROUGH, 0.0, 0, np.eye(6), 1.0)
    reg = FineTuner(model, cfg).register(p_s, a0, 0.0, 0)
    if reg.alignment is None:
        say(f"ICP polish rejected ({reg.reason}); keeping the corner solution")
        return T_ecef_slam, err
    T_enu_slam = compose(enu_sim3(model.origin).inverse(), reg.alignment.T_ecef_slam)
    err2 = alignment_error_m(T_enu_slam.apply(p_s), model)
    say(f"ICP polish: mean point-to-model {err:.2f} → {err2:.2f} m")
    return (reg.alignment.T_ecef_slam, err2) if err2 < err else (T_ecef_slam, err)


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
