"""Helpers the GIS loaders share: JSON files, point thinning, normals, surface sampling of meshes and polygons,
glTF's Y-up turn."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh
from matplotlib.path import Path as PolyPath

from gis.model import GisFormatError

#: glTF is Y-up; 3D Tiles and our georeferenced files are Z-up: (x, y, z)_gltf → (x, −z, y).
R_ZUP_YUP = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])


def estimate_normals(p_enu: np.ndarray, radius_m: float) -> np.ndarray:
    """Per-point normals by local PCA (open3d), oriented upward where the sign is free."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p_enu))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=12))  # 12: half the time of 30, planes are as good
    pcd.orient_normals_to_align_with_direction(np.array([0.0, 0.0, 1.0]))
    return np.asarray(pcd.normals)


def sample_mesh(mesh: trimesh.Trimesh, spacing_m: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Uniform surface samples (about one per spacing_m²), their face normals and face indices."""
    area = float(mesh.area)
    if not np.isfinite(area) or area <= 0:
        raise ValueError("mesh has zero or non-finite surface area")
    count = max(int(np.ceil(area / spacing_m**2)), len(mesh.faces))
    p, face_idx = trimesh.sample.sample_surface(mesh, count, seed=seed)
    normals = np.asarray(mesh.face_normals)[face_idx]
    return np.asarray(p, float), normals, np.asarray(face_idx)


def first_per_voxel(p: np.ndarray, voxel_m: float) -> np.ndarray:
    """Sorted indices of the first point in each voxel_m cube of a grid fixed in the coordinates
    (so that chunks thinned apart agree), keeping the points themselves, not voxel centroids:
    they stay on the surveyed surface and keep their labels."""
    keys = np.floor(p / voxel_m).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first)


def _median_spacing(p: np.ndarray) -> float:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p[:: max(1, len(p) // 2000)] - p.mean(axis=0)))
    d = np.asarray(pcd.compute_nearest_neighbor_distance())
    return float(np.median(d)) if len(d) and np.median(d) > 0 else 1.0


def sample_polygon(outer: np.ndarray, holes: list[np.ndarray], spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Grid samples (spacing_m) inside a planar 3D polygon with holes, and its Newell normal.

    The polygon is projected on its own plane and tested with matplotlib's point-in-polygon, so
    concave footprints and holes need no triangulation library.
    """
    outer = np.asarray(outer, float)
    nrm = np.cross(outer, np.roll(outer, -1, axis=0)).sum(axis=0)  # Newell's method
    if np.linalg.norm(nrm) < 1e-12:
        return np.zeros((0, 3)), np.zeros(3)
    nrm /= np.linalg.norm(nrm)
    u = np.cross(nrm, [0.0, 0.0, 1.0] if abs(nrm[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(nrm, u)
    o = outer.mean(axis=0)
    to2 = lambda r: np.stack([(r - o) @ u, (r - o) @ v], axis=1)  # noqa: E731
    o2 = to2(outer)
    lo, hi = o2.min(axis=0), o2.max(axis=0)
    gu = np.arange(lo[0] + spacing_m / 2, hi[0], spacing_m)
    gv = np.arange(lo[1] + spacing_m / 2, hi[1], spacing_m)
    g = np.stack(np.meshgrid(gu, gv), axis=-1).reshape(-1, 2)
    inside = PolyPath(o2).contains_points(g) if len(g) else np.zeros(0, bool)
    for h in holes:
        if len(g):
            inside &= ~PolyPath(to2(np.asarray(h, float))).contains_points(g)
    g = g[inside]
    if len(g) == 0:  # smaller than one grid cell: keep its centroid
        g = o2.mean(axis=0, keepdims=True)
    return o + g[:, :1] * u + g[:, 1:] * v, nrm


def _read_json(path: Path):
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise GisFormatError(path, f"invalid JSON: {e}") from None
