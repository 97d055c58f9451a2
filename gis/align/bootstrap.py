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

Centre: the fit is expressed (covariance carried by its lever arm) at the camera of the newest
pair, not at the pairs' centroid, because the SLAM drift a registration prior or a fix adds with
distance from an alignment's centre starts where the fitted track ends. At the centroid, a 13 m/s
flight's 30 s of pairs put the crop centre ~100 m away, and 2 % drift over it made every `fast`
registration prior too vague for ICP (2.7–4.0 m). A rigid fit is also worst at the ends of a
track whose monocular scale drifts, so the mean residual of the newest MISFIT_WINDOW_S of pairs
is added there: without it, `stale` seed 2 sent 52 % of its fixes beyond 3σ. Measured on
captured flights and the four-seed suite in docs/BENCHMARKS.md, "GNSS fits expressed where the
track ends".

Recent pairs weigh more (exp(−age / RECENCY_TAU_S), τ = 5 s): even expressed at the newest pair,
a rigid fit over 30 s of a monocular track averages the track's bends into its end. On 55 fits
of 14 captured flights (the last 12 s before the GNSS loss), the rigid fit's camera at the newest
pair was 0.72 m from the truth horizontally, further than the receiver's own solution there
(0.61 m): 30 s of GNSS whose errors are correlated over ~10 s buy little averaging, and the bends
cost more. Weighted, 0.65 m. The rotation still comes from the attitude over the whole window, the
rigid fit still decides whether the track is consistent with GNSS (a scale-drifting but sound
track passes it, and refusals are unchanged), and the fit counts the GNSS samples of its effective
span (2τ) only. docs/BENCHMARKS.md, "GNSS fits: recent pairs weigh more".
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from gis.align.fine import enu_sim3
from gis.geodesy import LocalFrame, R_ecef_enu, ecef_to_geodetic
from gis.sim3 import Sim3, compose, umeyama
from gis.types import Alignment, AlignmentSource

MISFIT_WINDOW_S = 3.0  # the newest pairs whose mean residual shows a bent track's offset at its end
RECENCY_TAU_S = 5.0    # pair weights exp(−age/τ): the fit holds where the track ends (module doc)


class DegenerateAlignment(ValueError):
    """The data cannot determine the alignment (e.g. a straight trajectory without attitude, or a
    SLAM track inconsistent with GNSS): no alignment is given."""


def gnss_bootstrap(p_slam: np.ndarray, p_ecef: np.ndarray, t_s: float, reset_counter: int = 0,
                   map_id: int = 0, sigma_gnss_m: float = 1.0, max_sigma_rot_deg: float = 3.0, *,
                   bias_sigma_h_m: float = 0.0, bias_sigma_v_m: float = 0.0,
                   R_ecef_slam: np.ndarray | None = None,
                   attitude_sigma_deg: tuple[float, float, float] = (0.5, 0.5, 2.0),
                   t_pairs_s: np.ndarray | None = None, gnss_corr_time_s: float = 10.0,
                   max_rmse_factor: float = 3.0, recency_tau_s: float | None = RECENCY_TAU_S) -> Alignment:
    """T_ecef_slam from SLAM camera positions p_slam (N,3) and GNSS positions p_ecef (N,3) at the same times.

    sigma_gnss_m: lower bound of the per-axis white GNSS noise (the fit's residuals raise it).
    bias_sigma_h_m / bias_sigma_v_m: 1-σ horizontal / vertical accuracy the receiver reports; the
    correlated part of the GNSS error that no averaging removes (added to the translation).
    R_ecef_slam: optional (N,3,3) rotation of the SLAM frame in ECEF per pair, from the autopilot's
    attitude (see module doc); attitude_sigma_deg: its 1-σ (east, north, up axes: roll/pitch
    tilt and heading). It is fused with the rotation the positions determine (a prior in a
    Gauss–Newton solve), so turns sharpen the heading and straight flight still works.
    t_pairs_s / gnss_corr_time_s: GNSS errors are correlated over about gnss_corr_time_s, so N
    fixes spanning T seconds weigh as about T/gnss_corr_time_s + 1 independent ones (without times:
    N, optimistic). max_rmse_factor: refuse when the fit's RMS residual exceeds this many times the
    GNSS accuracy (SLAM track distorted or GNSS inconsistent). recency_tau_s: with pair times, pair
    i weighs exp(−(t_newest − t_i)/τ) in the fit and its effective span is min(span, 2τ); the
    consistency test (max_rmse_factor) judges the rigid fit of all pairs alike. None: the rigid fit.
    Raises DegenerateAlignment when the rotation is not determined to max_sigma_rot_deg (1-σ) or
    the fit is inconsistent, ValueError on bad input.
    """
    p_slam = np.asarray(p_slam, float)
    p_ecef = np.asarray(p_ecef, float)
    if p_slam.shape != p_ecef.shape or p_slam.ndim != 2 or p_slam.shape[1] != 3:
        raise ValueError(f"gnss_bootstrap needs (N,3) arrays of equal shape, got {p_slam.shape} and {p_ecef.shape}")
    if not (np.all(np.isfinite(p_slam)) and np.all(np.isfinite(p_ecef))):
        raise ValueError("gnss_bootstrap: non-finite positions")
    n = len(p_slam)
    if n < 4:
        raise DegenerateAlignment(f"gnss_bootstrap needs at least 4 positions, got {n}")
    lat, lon, h = ecef_to_geodetic(p_ecef.mean(axis=0))
    frame = LocalFrame(float(lat), float(lon), float(h))  # ENU at the centroid: info axes and moments
    p_enu = frame.ecef_to_enu(p_ecef)
    weighted = t_pairs_s is not None and recency_tau_s is not None
    n_eff_rigid = float(n)
    if t_pairs_s is not None:
        t_pairs_s = np.asarray(t_pairs_s, float)
        span_s = float(t_pairs_s.max() - t_pairs_s.min())
        n_eff_rigid = float(np.clip(span_s / gnss_corr_time_s + 1.0, 1.0, n))
    if R_ecef_slam is not None:
        R_att, info_att = _attitude_rotation(frame, np.asarray(R_ecef_slam, float), n, attitude_sigma_deg)
        T = _scale_translation(p_slam, p_enu, R_att)
    else:
        try:
            T = umeyama(p_slam, p_enu, with_scale=True)
        except ValueError as e:
            raise DegenerateAlignment(str(e)) from None
        R_att, info_att = None, np.zeros((3, 3))
    sigma2 = sigma_gnss_m**2
    for _ in range(2):  # rigid fit, judge the residuals, refit with the noise they show
        T, H = _gauss_newton(T, p_slam, p_enu, np.full(n, (n_eff_rigid / n) / sigma2), R_att, info_att)
        res = T.apply(p_slam) - p_enu
        dof_frac = max(1.0 - (4 if R_att is not None else 7) / (3 * n), 1.0 / (3 * n))
        rmse_h = float(np.sqrt(np.mean(res[:, :2] ** 2) / dof_frac))  # per horizontal axis
        rmse_v = float(np.sqrt(np.mean(res[:, 2] ** 2) / dof_frac))
        for what, r, acc in (("horizontal", rmse_h, max(sigma_gnss_m, bias_sigma_h_m / np.sqrt(2))),
                             ("vertical", rmse_v, max(sigma_gnss_m, bias_sigma_v_m))):
            if r > max_rmse_factor * acc:
                raise DegenerateAlignment(
                    f"SLAM track inconsistent with GNSS: {what} fit residual {r:.2f} m per axis > "
                    f"{max_rmse_factor:g} × GNSS accuracy {acc:.2f} m"
                )
        sigma2 = max((2 * rmse_h**2 + rmse_v**2) / 3, sigma_gnss_m**2)  # white noise per axis
    if weighted:
        # the estimate: the same fit with recent pairs weighing more (the consistency test above
        # stays with the rigid fit, which a scale-drifting but sound track passes); pair weights
        # of mean 1, and the GNSS samples of the effective span 2τ
        w_pair = np.exp(-(t_pairs_s.max() - t_pairs_s) / recency_tau_s)
        w_pair *= n / w_pair.sum()
        n_eff = float(np.clip(min(span_s, 2.0 * recency_tau_s) / gnss_corr_time_s + 1.0, 1.0, n))
        T, H = _gauss_newton(T, p_slam, p_enu, (n_eff / n) / sigma2 * w_pair, R_att, info_att)
        res = T.apply(p_slam) - p_enu
    w, V = np.linalg.eigh(H)
    if w[0] <= 1e-12 * w[-1]:
        raise DegenerateAlignment("GNSS trajectory is collinear: rotation about it is undetermined")
    cov7 = (V / w) @ V.T
    # Expressed at the newest pair, not at the centroid: the fit holds along the whole track, so
    # the SLAM drift that a prior or a fix adds with distance from the alignment's centre
    # (gis.align.fine._prior_at, gis.globalizer) starts where the track ends. A perturbation
    # [ω, τ, log s] about the ENU origin (the GNSS centroid) moves a point at d by
    # τ − [d]×ω + d·log s: the covariance there is J cov7 Jᵀ.
    i_new = int(np.argmax(t_pairs_s)) if t_pairs_s is not None else n - 1
    d = T.apply(p_slam[i_new][None])[0]
    J = np.eye(7)
    J[3:6, :3], J[3:6, 6] = -_skew(d[None])[0], d
    cov7 = J @ cov7 @ J.T
    # That covariance is of a rigid fit to a rigid track. A monocular track whose scale drifts is
    # not rigid, and a rigid fit to it is worst at its ends (the `stale` flight of seed 2: ~2 m off
    # at the newest pair, claiming 1.3 m). The residuals of the newest MISFIT_WINDOW_S of pairs
    # show that local offset (plus that stretch's correlated GNSS error): their mean, per axis, is
    # added to the variance there (without pair times: the last 10 pairs). Over 10 s the residuals
    # of a bent track cross zero and showed a third of it.
    recent = (t_pairs_s >= t_pairs_s[i_new] - MISFIT_WINDOW_S) if t_pairs_s is not None else np.arange(n) >= n - 10
    cov7[3:6, 3:6] += np.diag(res[recent].mean(axis=0) ** 2)
    lat_n, lon_n, _ = ecef_to_geodetic(frame.enu_to_ecef(d[None])[0])
    # centroid ENU axes → the local ENU at the new centre (gis.types.Alignment's convention)
    B = R_ecef_enu(float(lat_n), float(lon_n)).T @ frame.R_ecef_enu
    B6 = np.kron(np.eye(2), B)
    cov = B6 @ cov7[:6, :6] @ B6.T
    cov[3:, 3:] += np.diag([bias_sigma_h_m**2 / 2, bias_sigma_h_m**2 / 2, bias_sigma_v_m**2])
    sig_rot_deg = float(np.degrees(np.sqrt(np.linalg.eigvalsh(cov[:3, :3])[-1])))
    if sig_rot_deg > max_sigma_rot_deg:
        raise DegenerateAlignment(
            f"GNSS trajectory too short or too straight: rotation 1-σ {sig_rot_deg:.2f}° > {max_sigma_rot_deg}°"
        )
    return Alignment(
        T_ecef_slam=compose(enu_sim3(frame), T), source=AlignmentSource.GNSS, t_s=t_s,
        reset_counter=reset_counter, information_6x6=np.linalg.inv(cov),
        sigma_m=float(np.sqrt(np.linalg.eigvalsh(cov[3:, 3:])[-1])),
        rmse_m=float(np.sqrt(np.mean(np.sum(res**2, axis=1)))), n_points=n, map_id=map_id,
        center_slam=p_slam[i_new].copy(), scale_sigma=float(np.sqrt(cov7[6, 6])),
    )


def _attitude_rotation(frame: LocalFrame, R_ecef_slam: np.ndarray, n: int,
                       attitude_sigma_deg: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """R_enu_slam = chordal mean of the per-pair attitudes, and its information (1/rad², ENU axes).

    The AHRS bias does not average out, so the covariance is its σ² plus the pairs' own scatter
    (SLAM rotation drift within the window), not divided by N."""
    if R_ecef_slam.shape != (n, 3, 3) or not np.all(np.isfinite(R_ecef_slam)):
        raise ValueError(f"R_ecef_slam must be ({n}, 3, 3) finite rotations, got {R_ecef_slam.shape}")
    rots = Rotation.from_matrix(frame.R_ecef_enu.T @ R_ecef_slam)  # R_enu_slam per pair
    mean = rots.mean()
    d = (rots * mean.inv()).as_rotvec()  # scatter about the mean, ENU axes
    cov = np.diag(np.radians(np.asarray(attitude_sigma_deg, float)) ** 2) + d.T @ d / n
    return mean.as_matrix(), np.linalg.inv(cov)


def _scale_translation(p_slam: np.ndarray, p_enu: np.ndarray, R: np.ndarray) -> Sim3:
    """p_enu ≈ s·R·p_slam + t by linear least squares for a given rotation."""
    q = p_slam @ R.T
    qc, pc = q - q.mean(axis=0), p_enu - p_enu.mean(axis=0)
    den = float(np.sum(qc**2))
    if den <= 1e-12:
        raise DegenerateAlignment("SLAM camera did not move: scale is undetermined")
    s = float(np.sum(qc * pc)) / den
    if s <= 0:
        raise DegenerateAlignment("SLAM track runs against the GNSS track under the attitude rotation")
    return Sim3(s, R, p_enu.mean(axis=0) - s * q.mean(axis=0))


def _gauss_newton(T: Sim3, p_slam: np.ndarray, p_enu: np.ndarray, w: np.ndarray, R_prior: np.ndarray | None,
                  info_prior: np.ndarray, iterations: int = 5) -> tuple[Sim3, np.ndarray]:
    """min Σ w_i·|s·R·p_i + t − g_i|² + log(R·R_priorᵀ)ᵀ·Λ·log(R·R_priorᵀ) over (R, t, log s)
    (w: (N,) weights, the information per axis of each pair).

    Left perturbations x' = e^δσ·exp(δθ)·x + δt about the ENU origin (the GNSS centroid, where the
    SLAM centroid lands), as the Globalizer propagates them; returns the fit and the 7x7
    Gauss–Newton Hessian (its inverse is the covariance of [rot, trans, log-scale])."""
    H = np.zeros((7, 7))
    wr = np.repeat(w, 3)[:, None]  # per residual row
    for _ in range(iterations):
        x = T.apply(p_slam)  # s·R·p + t, centred near the origin
        r = (x - p_enu).reshape(-1)
        J = np.zeros((len(x), 3, 7))
        J[:, :, :3] = -_skew(x)
        J[:, :, 3:6] = np.eye(3)
        J[:, :, 6] = x
        J = J.reshape(-1, 7)
        Jw = J * wr
        H = Jw.T @ J
        g = Jw.T @ r
        if R_prior is not None:
            e = Rotation.from_matrix(T.R @ R_prior.T).as_rotvec()
            H[:3, :3] += info_prior
            g[:3] += info_prior @ e
        try:
            dx = -np.linalg.solve(H + 1e-12 * np.trace(H) * np.eye(7), g)
        except np.linalg.LinAlgError:
            break
        T = compose(Sim3(float(np.exp(dx[6])), Rotation.from_rotvec(dx[:3]).as_matrix(), dx[3:6]), T)
        if np.linalg.norm(dx) < 1e-9:
            break
    return T, H


def _skew(v: np.ndarray) -> np.ndarray:
    """(N,3) → (N,3,3) cross-product matrices [v]×."""
    z = np.zeros(len(v))
    return np.stack([
        np.stack([z, -v[:, 2], v[:, 1]], 1),
        np.stack([v[:, 2], z, -v[:, 0]], 1),
        np.stack([-v[:, 1], v[:, 0], z], 1),
    ], 1)
