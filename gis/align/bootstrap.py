"""Alignment from GNSS while it is good (digital-twin paper §III-D, Eq. 11), before GIS registration.

Eq. 11 solves yaw + translation with Umeyama because that paper's VIO frame is gravity-aligned.
Our monocular SLAM frame is neither gravity-aligned nor metric, so the same least squares is
solved over the full similarity (rotation, translation, scale) with ``gis.sim3.umeyama``; a
straight-line trajectory leaves the roll about that line unobserved, which the information
(point-to-point analogue of Eq. 9: A_i = [−[q_i]×, I]) exposes and the function refuses.
"""
from __future__ import annotations

import numpy as np

from gis.geodesy import LocalFrame, ecef_to_geodetic
from gis.sim3 import compose, umeyama
from gis.types import Alignment, AlignmentSource
from gis.align.fine import enu_sim3


class DegenerateAlignment(ValueError):
    """The data cannot determine the alignment (e.g. a straight trajectory): no alignment is given."""


def gnss_bootstrap(p_slam: np.ndarray, p_ecef: np.ndarray, t_s: float, reset_counter: int = 0,
                   map_id: int = 0, sigma_gnss_m: float = 1.0, max_sigma_rot_deg: float = 2.0) -> Alignment:
    """T_ecef_slam from SLAM camera positions p_slam (N,3) and GNSS positions p_ecef (N,3) at the same times.

    sigma_gnss_m: lower bound of the per-axis GNSS noise used for the information (the fit's own
    residuals raise it). Raises DegenerateAlignment when rotation is not determined to
    max_sigma_rot_deg (1-σ), ValueError on bad input.
    """
    p_slam = np.asarray(p_slam, float)
    p_ecef = np.asarray(p_ecef, float)
    if p_slam.shape != p_ecef.shape or p_slam.ndim != 2 or p_slam.shape[1] != 3:
        raise ValueError(f"gnss_bootstrap needs (N,3) arrays of equal shape, got {p_slam.shape} and {p_ecef.shape}")
    if len(p_slam) < 4:
        raise DegenerateAlignment(f"gnss_bootstrap needs at least 4 positions, got {len(p_slam)}")
    lat, lon, h = ecef_to_geodetic(p_ecef.mean(axis=0))
    frame = LocalFrame(float(lat), float(lon), float(h))  # ENU at the centroid: info axes and moments
    p_enu = frame.ecef_to_enu(p_ecef)
    try:
        T_enu_slam = umeyama(p_slam, p_enu, with_scale=True)
    except ValueError as e:
        raise DegenerateAlignment(str(e)) from None
    res = T_enu_slam.apply(p_slam) - p_enu
    dof = max(3 * len(p_slam) - 7, 1)
    sigma2 = max(float(np.sum(res**2)) / dof, sigma_gnss_m**2)
    q = p_enu  # centred: the frame origin is the centroid
    A = np.zeros((len(q), 3, 6))
    A[:, :, :3] = -_skew(q)
    A[:, :, 3:] = np.eye(3)
    H = np.einsum("nij,nik->jk", A, A) / sigma2
    w, V = np.linalg.eigh(H)
    if w[0] <= 1e-12 * w[-1]:
        raise DegenerateAlignment("GNSS trajectory is collinear: rotation about it is undetermined")
    cov = (V / w) @ V.T
    sig_rot_deg = float(np.degrees(np.sqrt(np.linalg.eigvalsh(cov[:3, :3])[-1])))
    if sig_rot_deg > max_sigma_rot_deg:
        raise DegenerateAlignment(
            f"GNSS trajectory too short or too straight: rotation 1-σ {sig_rot_deg:.2f}° > {max_sigma_rot_deg}°"
        )
    return Alignment(
        T_ecef_slam=compose(enu_sim3(frame), T_enu_slam), source=AlignmentSource.GNSS, t_s=t_s,
        reset_counter=reset_counter, information_6x6=H,
        sigma_m=float(np.sqrt(np.linalg.eigvalsh(cov[3:, 3:])[-1])),
        rmse_m=float(np.sqrt(np.mean(np.sum(res**2, axis=1)))), n_points=len(p_slam), map_id=map_id,
        center_slam=p_slam.mean(axis=0), scale_sigma=float(np.sqrt(sigma2 / np.sum(q**2))),
    )


def _skew(v: np.ndarray) -> np.ndarray:
    """(N,3) → (N,3,3) cross-product matrices [v]×."""
    z = np.zeros(len(v))
    return np.stack([
        np.stack([z, -v[:, 2], v[:, 1]], 1),
        np.stack([v[:, 2], z, -v[:, 0]], 1),
        np.stack([-v[:, 1], v[:, 0], z], 1),
    ], 1)
