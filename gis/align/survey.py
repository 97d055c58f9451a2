"""Semi-dense survey reconstruction for the offline initialization (TerraSLAM §4.3.1: "ColMap").

COLMAP (pycolmap) SfM on the survey frames with the known pinhole intrinsics: SIFT features,
sequential matching (video order, with loop detection off), incremental mapping; the largest
reconstruction's 3D points are the survey cloud.

Frame: the cloud is in the reconstruction's own frame. TerraSLAM reuses T_rough online because
its online SLAM and the survey share one SLAM frame. Here our SLAM also maps the survey frames
(companion/survey.py: the survey map the service starts in) and ``register_centres`` maps that
map's frame to the reconstruction's through the camera centres of the frames both hold, so
T_rough ∘ T_colmap_slam maps the survey map to ECEF.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from gis.sim3 import Sim3, umeyama


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


class SurveyRegistrationFailed(RuntimeError):
    """The survey SLAM map and the reconstruction cannot be put in one frame; the message says why."""


@dataclass(frozen=True)
class CentreRegistration:
    T_dst_src: Sim3        # maps the source frame (survey SLAM map) into the destination (COLMAP)
    n_pairs: int           # frames used (after trimming)
    rmse_rel: float        # residual RMSE / extent of the destination track (dimensionless)


def register_centres(src: dict[str, np.ndarray], dst: dict[str, np.ndarray], min_pairs: int = 6,
                     max_rmse_rel: float = 0.02) -> CentreRegistration:
    """Sim(3) mapping the camera centres ``src`` (name → (3,)) onto ``dst`` of the same frames
    (Umeyama, gis.sim3.umeyama), trimmed twice of pairs beyond 3× the median residual (a frame one
    of the two placed badly). Both tracks are in arbitrary scale: ``max_rmse_rel`` bounds the
    residual RMSE relative to the destination track's extent (its bounding-box diagonal).
    SurveyRegistrationFailed with fewer than ``min_pairs`` common frames, a straight track (its
    rotation about the line is undetermined) or a residual beyond the bound."""
    names = sorted(set(src) & set(dst))
    if len(names) < min_pairs:
        raise SurveyRegistrationFailed(f"only {len(names)} frames are in both the survey map and the reconstruction "
                                       f"(need ≥ {min_pairs})")
    a = np.array([src[n] for n in names], float)
    b = np.array([dst[n] for n in names], float)
    extent = float(np.linalg.norm(np.ptp(b, axis=0)))
    sv = np.linalg.svd(b - b.mean(axis=0), compute_uv=False)
    if extent <= 0 or sv[1] < 0.05 * sv[0]:
        raise SurveyRegistrationFailed("the survey track is (nearly) a straight line: its rotation about it is undetermined")
    keep = np.ones(len(names), bool)
    for _ in range(3):
        T = umeyama(a[keep], b[keep], with_scale=True)
        r = np.linalg.norm(T.apply(a) - b, axis=1)
        new = r <= max(3 * float(np.median(r[keep])), 1e-9 * extent)
        if new.sum() < min_pairs or (new == keep).all():
            break
        keep = new
    else:  # trimmed on the last pass: the similarity of the pairs kept, not of the set before it
        T = umeyama(a[keep], b[keep], with_scale=True)
        r = np.linalg.norm(T.apply(a) - b, axis=1)
    rmse_rel = float(np.sqrt(np.mean(r[keep] ** 2))) / extent
    if rmse_rel > max_rmse_rel:
        raise SurveyRegistrationFailed(f"the survey map and the reconstruction disagree: camera centres {100 * rmse_rel:.1f} % "
                                       f"of the track apart after the best similarity (> {100 * max_rmse_rel:.1f} %)")
    return CentreRegistration(T, int(keep.sum()), rmse_rel)
