"""A procedural box city as a labelled triangle mesh, for tests and the alignment benchmark.

Not the project's simulator (companion/sim builds the textured world); this is the minimal
geometry the alignment needs — a ground plane and rotated box buildings — at any size, so the
benchmark can sweep the model size (1 km² … 100 km²) without the renderer.
"""
from __future__ import annotations

import numpy as np
import trimesh

from gis.geodesy import LocalFrame
from gis.loaders import sample_mesh
from gis.model import BUILDING, GROUND, GisModel


def box_city_mesh(extent_m: float, seed: int = 0, block_m: float = 40.0) -> tuple[trimesh.Trimesh, np.ndarray]:
    """Ground square of side extent_m centred at 0 plus one random box per block; (mesh, face labels)."""
    rng = np.random.default_rng(seed)
    half = extent_m / 2
    ground = trimesh.Trimesh(
        vertices=[[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], faces=[[0, 1, 2], [0, 2, 3]],
        process=False,
    )
    n = max(1, int(extent_m // block_m))
    centres = (np.stack(np.meshgrid(np.arange(n), np.arange(n)), -1).reshape(-1, 2) + 0.5) * (extent_m / n) - half
    boxes = []
    for cx, cy in centres:
        ext = [rng.uniform(10, 25), rng.uniform(10, 25), rng.uniform(6, 40)]
        T = trimesh.transformations.rotation_matrix(rng.uniform(0, np.pi / 2), [0, 0, 1])
        T[:3, 3] = [cx + rng.uniform(-4, 4), cy + rng.uniform(-4, 4), ext[2] / 2]
        boxes.append(trimesh.creation.box(extents=ext, transform=T))
    mesh = trimesh.util.concatenate([ground] + boxes)
    labels = np.concatenate([np.full(2, GROUND, np.uint8), np.full(12 * len(boxes), BUILDING, np.uint8)])
    return mesh, labels


def box_city_model(extent_m: float, origin: LocalFrame, seed: int = 0, spacing_m: float = 1.0) -> GisModel:
    """The box city sampled on its surface as a GisModel whose ENU frame is ``origin``."""
    mesh, face_labels = box_city_mesh(extent_m, seed)
    p, n, f = sample_mesh(mesh, spacing_m, seed=seed)
    return GisModel(p, n, face_labels[f], origin, "synthetic ENU", "synthetic://box_city")


def slam_like_cloud(model: GisModel, center_enu: np.ndarray, radius_m: float, n_points: int,
                    noise_m: float, seed: int = 0) -> np.ndarray:
    """A sparse 'SLAM-like' sample of the model around center_enu (ENU), with Gaussian noise."""
    rng = np.random.default_rng(seed)
    idx = model.crop(center_enu, 2 * radius_m)
    idx = idx[np.linalg.norm(model.points_enu[idx, :2] - center_enu[:2], axis=1) <= radius_m]
    pick = rng.choice(idx, size=min(n_points, len(idx)), replace=False)
    return model.points_enu[pick] + rng.normal(0, noise_m, (len(pick), 3))
