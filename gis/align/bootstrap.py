"""Alignment from GNSS while it is good (digital-twin paper §III-D, Eq. 11), before GIS registration.

Eq. 11 solves yaw + translation with Umeyama because that paper's VIO frame is gravity-aligned.
Our monocular SLAM frame is neither gravity-aligned nor metric. Two solvers:

- **With the autopilot's attitude** (the normal case: every autopilot streams ATTITUDE): each
  frame gives the SLAM frame's orientation directly, R_enu_slam = R_enu_body·R_body_cam·R_slam_camᵀ;
  their chordal mean (scipy ``Rotation.mean``) fixes the rotation, and scale + translation follow
  by linear least squares. Straight flight paths are fine. Rotation 1-σ: the AHRS accuracy
  (roll/pitch, and magnetometer yaw, whose bias does not average out) plus the per-frame scatter.
- **Without attitude**: the full similarity with ``gis.sim3.umeyama``; a straight path leaves the
  roll about it unobserved, which the information (point-to-point analogue of Eq. 9,
  A_i = [−[q_i]×, I]) exposes and the function refuses.

Integrity: GNSS errors are correlated over tens of seconds (multipath, atmosphere), so averaging
N fixes does not shrink the common error by √N. The translation covariance therefore never drops
below the receiver's own reported accuracy (bias_sigma_h_m / bias_sigma_v_m), and a fit whose
residuals are too large for that accuracy (a distorted SLAM track) is refused.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from gis.geodesy import LocalFrame, ecef_to_geodetic
from gis.sim3 import Sim3, compose, umeyama
from gis.types import Alignment, AlignmentSource
from gis.align.fine import enu_sim3


class DegenerateAlignment(ValueError):
    """The data cannot determine the alignment (e.g. a straight trajectory without attitude, or a
    SLAM track inconsistent with GNSS): no alignment is given."""


def gnss_bootstrap(p_slam: np.ndarray, p_ecef: np.ndarray, t_s: float, reset_counter: int = 0,
                   map_id: int = 0, sigma_gnss_m: float = 1.0, max_sigma_rot_deg: float = 3.0, *,
                   bias_sigma_h_m: float = 0.0, bias_sigma_v_m: float = 0.0,
                   R_ecef_slam: np.ndarray | None = None,
                   attitude_sigma_deg: tuple[float, float, float] = (0.5, 0.5, 2.0),
                   max_rmse_factor: float = 3.0) -> Alignment:
    """T_ecef_slam from SLAM camera positions p_slam (N,3) and GNSS positions p_ecef (N,3) at the same times.

    sigma_gnss_m: lower bound of the per-axis white GNSS noise (the fit's residuals raise it).
    bias_sigma_h_m / bias_sigma_v_m: 1-σ horizontal / vertical accuracy the receiver reports; the
    correlated part of the GNSS error that no averaging removes (added to the translation).
    R_ecef_slam: optional (N,3,3) rotation of the SLAM frame in ECEF per pair, from the autopilot's
    attitude (see module doc); attitude_sigma_deg: its 1-σ (east, north, up axes: roll/pitch
    tilt and heading). max_rmse_factor: refuse when the fit's RMS residual exceeds this many
    times the GNSS accuracy (SLAM track distorted or GNSS inconsistent).
    Raises DegenerateAlignment when the rotation is not determined to max_sigma_rot_deg (1-σ) or
    the fit is inconsistent, ValueError on bad input.
    """
    p_slam = np.asarray(p_slam, float)
    p_ecef = np.asarray(p_ecef, float)
    if p_slam.shape != p_ecef.shape or p_slam.ndim != 2 or p_slam.shape[1] != 3:
        raise ValueError(f"gnss_bootstrap needs (N,3) arrays of equal shape, got {p_slam.shape} and {p_ecef.shape}")
    if not (np.all(np.isfinite(p_slam)) and np.all(np.isfinite(p_ecef))):
        raise ValueError("gnss_bootstrap: non-finite positions")
    if len(p_slam) < 4:
        raise DegenerateAlignment(f"gnss_bootstrap needs at least 4 positions, got {len(p_slam)}")
    lat, lon, h = ecef_to_geodetic(p_ecef.mean(axis=0))
    frame = LocalFrame(float(lat), float(lon), float(h))  # ENU at the centroid: info axes and moments
    p_enu = frame.ecef_to_enu(p_ecef)
    if R_ecef_slam is not None:
        T_enu_slam, cov_rot = _fit_with_attitude(p_slam, p_enu, frame, np.asarray(R_ecef_slam, float), attitude_sigma_deg)
    else:
        try:
            T_enu_slam = umeyama(p_slam, p_enu, with_scale=True)
        except ValueError as e:
            raise DegenerateAlignment(str(e)) from None
        cov_rot = None
    res = T_enu_slam.apply(p_slam) - p_enu
    n = len(p_slam)
    dof_frac = max(1.0 - (4 if cov_rot is not None else 7) / (3 * n), 1.0 / (3 * n))
    rmse_h = float(np.sqrt(np.mean(res[:, :2] ** 2) / dof_frac))  # per horizontal axis
    rmse_v = float(np.sqrt(np.mean(res[:, 2] ** 2) / dof_frac))
    rmse = float(np.sqrt((2 * rmse_h**2 + rmse_v**2) / 3))
    for what, r, acc in (("horizontal", rmse_h, max(sigma_gnss_m, bias_sigma_h_m / np.sqrt(2))),
                         ("vertical", rmse_v, max(sigma_gnss_m, bias_sigma_v_m))):
        if r > max_rmse_factor * acc:
            raise DegenerateAlignment(
                f"SLAM track inconsistent with GNSS: {what} fit residual {r:.2f} m per axis > "
                f"{max_rmse_factor:g} × GNSS accuracy {acc:.2f} m"
            )
    sigma2 = max(rmse**2, sigma_gnss_m**2)  # white noise per axis
    q = p_enu  # centred: the frame origin is the centroid
    if cov_rot is None:
        A = np.zeros((n, 3, 6))
        A[:, :, :3] = -_skew(q)
        A[:, :, 3:] = np.eye(3)
        H = np.einsum("nij,nik->jk", A, A) / sigma2
        w, V = np.linalg.eigh(H)
        if w[0] <= 1e-12 * w[-1]:
            raise DegenerateAlignment("GNSS trajectory is collinear: rotation about it is undetermined")
        cov = (V / w) @ V.T
    else:  # rotation from attitude (independent of the positions); translation at the centroid
        cov = np.zeros((6, 6))
        cov[:3, :3] = cov_rot
        cov[3:, 3:] = np.eye(3) * sigma2 / n
    cov[3:, 3:] += np.diag([bias_sigma_h_m**2 / 2, bias_sigma_h_m**2 / 2, bias_sigma_v_m**2])
    sig_rot_deg = float(np.degrees(np.sqrt(np.linalg.eigvalsh(cov[:3, :3])[-1])))
    if sig_rot_deg > max_sigma_rot_deg:
        raise DegenerateAlignment(
            f"GNSS trajectory too short or too straight: rotation 1-σ {sig_rot_deg:.2f}° > {max_sigma_rot_deg}°"
        )
    spread2 = float(np.sum((T_enu_slam.scale * (p_slam - p_slam.mean(axis=0))) ** 2))
    return Alignment(
        T_ecef_slam=compose(enu_sim3(frame), T_enu_slam), source=AlignmentSource.GNSS, t_s=t_s,
        reset_counter=reset_counter, information_6x6=np.linalg.inv(cov),
        sigma_m=float(np.sqrt(np.linalg.eigvalsh(cov[3:, 3:])[-1])),
        rmse_m=float(np.sqrt(np.mean(np.sum(res**2, axis=1)))), n_points=n, map_id=map_id,
        center_slam=p_slam.mean(axis=0), scale_sigma=float(np.sqrt(sigma2 / max(spread2, 1e-12))),
    )


def _fit_with_attitude(p_slam: np.ndarray, p_enu: np.ndarray, frame: LocalFrame, R_ecef_slam: np.ndarray,
                       attitude_sigma_deg: tuple[float, float, float]) -> tuple[Sim3, np.ndarray]:
    """Rotation = chordal mean of the per-pair attitudes; then p_enu ≈ s·R·p_slam + t by least squares.

    Returns (T_enu_slam, 3x3 rotation covariance in rad², ENU axes, left perturbation)."""
    if R_ecef_slam.shape != (len(p_slam), 3, 3) or not np.all(np.isfinite(R_ecef_slam)):
        raise ValueError(f"R_ecef_slam must be ({len(p_slam)}, 3, 3) finite rotations, got {R_ecef_slam.shape}")
    rots = Rotation.from_matrix(frame.R_ecef_enu.T @ R_ecef_slam)  # R_enu_slam per pair
    mean = rots.mean()
    d = (rots * mean.inv()).as_rotvec()  # scatter about the mean, ENU axes
    cov_rot = np.diag(np.radians(np.asarray(attitude_sigma_deg, float)) ** 2) + d.T @ d / len(d)
    R = mean.as_matrix()
    q = p_slam @ R.T
    qc, pc = q - q.mean(axis=0), p_enu - p_enu.mean(axis=0)
    den = float(np.sum(qc**2))
    if den <= 1e-12:
        raise DegenerateAlignment("SLAM camera did not move: scale is undetermined")
    s = float(np.sum(qc * pc)) / den
    if s <= 0:
        raise DegenerateAlignment("SLAM track runs against the GNSS track under the attitude rotation")
    return Sim3(s, R, p_enu.mean(axis=0) - s * q.mean(axis=0)), cov_rot


def _skew(v: np.ndarray) -> np.ndarray:
    """(N,3) → (N,3,3) cross-product matrices [v]×."""
    z = np.zeros(len(v))
    return np.stack([
        np.stack([z, -v[:, 2], v[:, 1]], 1),
        np.stack([v[:, 2], z, -v[:, 0]], 1),
        np.stack([-v[:, 1], v[:, 0], z], 1),
    ], 1)
