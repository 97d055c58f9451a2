"""Semi-dense survey reconstruction for the offline initialization (TerraSLAM §4.3.1: "ColMap").

COLMAP (pycolmap) SfM on the survey frames with the known pinhole intrinsics: SIFT features,
sequential matching (video order, with loop detection off), incremental mapping; the largest
reconstruction's 3D points are the survey cloud.

Frame caveat: the cloud is in the reconstruction's own frame. TerraSLAM reuses T_rough online
because its online SLAM and the survey share one SLAM frame; a T_rough computed here applies to
maps in this reconstruction's frame only (the online map must be registered to it first).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class SurveyCloud:
    points: np.ndarray                  # (N,3) in the reconstruction's frame
    camera_centers: dict[str, np.ndarray]  # image name → (3,) camera centre, same frame


class SurveyReconstructionFailed(RuntimeError):
    """COLMAP produced no usable reconstruction; the message says why."""


def reconstruct_survey(image_dir: Path, image_names: list[str], K: np.ndarray, work_dir: Path,
                       progress: Callable[[str], None] | None = None, min_points: int = 1000) -> SurveyCloud:
    """Points and camera centres of the largest COLMAP reconstruction of the given undistorted images."""
    import pycolmap

    say = progress or (lambda s: None)
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    db = work_dir / "database.db"
    db.unlink(missing_ok=True)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(str(float(x)) for x in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    say(f"COLMAP: extracting SIFT features from {len(image_names)} images")
    pycolmap.extract_features(db, image_dir, image_names=list(image_names), camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, device=pycolmap.Device.cpu)
    say("COLMAP: sequential matching")
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = 8
    pairing.loop_detection = False
    pycolmap.match_sequential(db, pairing_options=pairing, device=pycolmap.Device.cpu)
    say("COLMAP: incremental mapping (minutes)")
    opts = pycolmap.IncrementalPipelineOptions()
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    recs = pycolmap.incremental_mapping(db, image_dir, work_dir / "sparse", options=opts)
    if not recs:
        raise SurveyReconstructionFailed(f"COLMAP found no reconstruction in {len(image_names)} images of {image_dir}")
    rec = max(recs.values(), key=lambda r: r.num_points3D())
    # Well-observed points only: ≥ 3 views and ≤ 2 px reprojection error, then open3d's
    # statistical outlier removal (low-parallax points far beyond the scene).
    pts = np.array([p.xyz for p in rec.points3D.values() if p.track.length() >= 3 and p.error <= 2.0], float)
    if len(pts) >= 20:
        import open3d as o3d

        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        _, keep = pcd.remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0)
        pts = pts[np.asarray(keep, int)]
    say(f"COLMAP: {rec.num_reg_images()} images registered, {len(pts)} points")
    if len(pts) < min_points:
        raise SurveyReconstructionFailed(f"COLMAP reconstruction has only {len(pts)} points (< {min_points})")
    centers = {im.name: np.asarray(im.projection_center(), float) for im in rec.images.values() if im.has_pose}
    return SurveyCloud(pts, centers)
