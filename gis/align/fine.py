"""Online fine-tuning T_fine (TerraSLAM §4.4; digital-twin paper §III-C, §III-E, §V).

One registration = crop the GIS model around the current position (fixed size, so the cost does
not grow with the model), voxel-downsample both clouds, then a scale-aware point-to-plane ICP.
The crop is made of 25 m tiles voxelised once on a global grid and cached; its KD-tree is reused
while the next registration needs no tile outside it, and any crop holding a registration's tiles
gives it the same correspondences (gis.align.crop). The ICP itself is gis.align.icp, the barometer
check gis.align.scale_check.

- Degrees of freedom: all 7 (rotation, translation, scale), with or without a prior; the
  cloud's apparent tilt is a systematic term of the measurement (below) and the Kalman update
  weighs it against the prior's. An earlier version held the tilt at the prior's whenever there
  was one (5 DoF): on the SLAM of its time a 7-DoF fit started at the truth moved the camera
  0.4–1.7 m away. Replayed on the 106 registrations of twelve demo flights of the current SLAM
  (docs/BENCHMARKS.md, "Fine-tuning solves the tilt again"), solving the tilt put the camera
  0.70–0.72 m from the truth instead of 0.82–0.91 m, and positions over the next 5 s 0.65 m
  horizontally (0.33 m vertically) instead of 0.77 (0.52), with no more registrations beyond 3σ.
- Poor guess (opt-in, ``fpfh_fallback``): FPFH + RANSAC global registration (§4.4), then ICP
  again; the same gates apply. Off by default (seconds; wrong on sparse clouds in our trials).

Uncertainty (what a fix may trust) — random + systematic + basin, then a Bayesian update:

- Random: σ²·H⁻¹ (Eq. 8–9, H over inliers) × RANDOM_INFLATION for neighbouring points sharing
  their triangulation errors.
- Systematic and basin: a monocular cloud is not rigidly consistent with its trajectory, so
  its best fit to the model sits off the truth at the camera by an offset no residual shows.
  Two estimates of that translation 1-σ, and the larger one is used (they measure the same
  thing, so they are not added):
  - SYS_OFFSET_FRACTION × the robust (MAD) residual scale of all matched points, scaled by the
    cloud's own residuals, so a clean cloud (synthetic, 5 cm noise) keeps a centimetre σ and a
    real one (σ_MAD 0.3–0.55 m inside the final correspondence window) gets 0.45–0.8 m;
  - the basin spread: ICP is restarted from its own solution shifted MULTISTART_M in three
    horizontal directions 120° apart (MULTISTARTS); ``spread_m`` is the largest disagreement of
    the restarts. On the
    real clouds the optimum moved 0.3–3 m between restarts (stale model: stable wrong optima
    4 m from truth were caught only by 3 m restarts, not by 2 m ones); the Hessian alone
    reported 0.05–0.2 m.
  Until 2026-12-03 the two were added, with 0.75 × σ_MAD. Replayed against the truth on 66
  registrations (demo seeds 0–5, dark seeds 0–5; docs/BENCHMARKS.md, "Registrations whose
  restarts agree"), those whose restarts all came back (spread < 0.2 m) had a mean NEES of
  4.4 (demo) and 8.5 (dark) against the 3 of a calibrated 3-D σ, and a dark one ended 3.9σ
  off; those with a spread were over-cautious (0.5–1.2). With the larger of the two and 1.5,
  replayed as a chain (each registration from the previous one's replayed posterior): 1.3 and
  2.9, none beyond 3σ, the camera 0.59 / 0.97 m from the truth after the registrations instead
  of 0.61 / 0.99.
  The spread enters at SPREAD_FRACTION (0.5) of its size: a restart that ends elsewhere shows
  another optimum within reach, not that the one found from the prior is that far off. Replayed
  on 156 registrations (demo, `nominal` and `stale` captures), the ICP's own result (before the
  update) sat 0.2–0.6 × the spread from the truth where the spread was over 2 m, and at its full
  size the measurement's per-axis error was 0.33–0.52 of its σ: the update kept the prior's
  error (`nominal` seed 1: a GNSS fit 1.4–2.0 m off, ICP results 1.3 and 0.4 m off, the posterior
  1.4 and 1.8 m off). docs/BENCHMARKS.md, "The restarts' spread at half its size".
  Also an apparent tilt of σ_MAD / (crop half-width) rad about the cloud's centroid, which
  moves the crop centre through the lever arm.
- Basin in rotation and scale: the restarts' largest disagreement about each ENU axis and in
  log-scale (``_Basin``) is added to the rotation and scale variances. On the stale model they
  ended 1.2–2.3° apart in yaw and 3 % in scale while the Hessian claimed 0.2–0.3°; the update
  took the registration's yaw, and the fixes ran off 2° across the track (0.25 m/s at 7 m/s)
  with a 1-σ a third of their error. Measured in docs/BENCHMARKS.md, "Restarts that disagree in
  rotation".
- Update: prior (propagated to the crop centre with its lever arm, SLAM drift, scale σ and the
  scale's own drift, ``slam_scale_drift_per_100m`` × distance; GNSS priors also with the model's
  georeference 1-σ, ``model_sigma_m`` or the correction's, below)
  and measurement z = x + v: Kalman update x = K z, P⁺ = (I − K) P, for every prior.
  Covariance intersection (Julier & Uhlmann 1997, one ω minimising the position trace) was used
  for FINE priors, since consecutive crops share map points; measured on the demo flight it chose
  ω ≈ 0.95 every time (the measurement's translation σ is 1.6–6 m from the basin spread) and so
  discarded the ICP's scale too: measured scale changes of +1.5 … +2.5 % (σ 0.54 %) moved the
  alignment by +0.04 … +0.07 %, and the error grew through the outage. The scale drift term is the
  process noise that makes a later registration informative; the shared map points' systematic
  error is in R (SYS_OFFSET_FRACTION, RANDOM_INFLATION). Integrity measured with it: 0 fixes
  beyond 3σ in the 10 bench flights and in 5 of 6 demo flights; demo seed 4 breaks it with and
  without this change (SLAM's scale breaks in a turn after the loss; docs/BENCHMARKS.md), which is
  what the barometer check below is for.
- Barometric height (beyond the papers; with ``camera_h_ell_m`` and its 1-σ ``camera_h_sigma_m``):
  after the Kalman update, a scalar update of the up translation at the crop centre (the camera)
  with the camera's barometric height. With the crop centred on a camera ~80 m above the ground it
  sees, the ICP's vertical translation and its scale are nearly collinear (1 % of scale moves the
  ground 0.8 m), and a young map's first registration put the camera 0.9–1.2 m low in `nominal`
  seeds 0/1 (its prior 0.3–0.5 m). The barometer's height is only as good as the GNSS heights its
  offset was learned from (σ: their v_acc, with 0.3 m of barometer noise and drift). Repeatable
  bench, `nominal` seeds 0–5: 3D error after the loss 1.033 against 1.093 m (4 of 6 better),
  height 0.39 against 0.49 m, horizontal unchanged, 0 violations (docs/BENCHMARKS.md,
  "The barometric height in the registration").
- Barometer check (beyond the papers; with ``camera_h_ell_m``): gis.align.scale_check; a
  registration whose map under the camera is off the alignment's scale is refused with
  SCALE_MISMATCH_REASON.
- Gates (§V: "registration declared unsuccessful"): too few points, fitness, inlier RMSE,
  degeneracy of the data alone (Eq. 8–9 along its weakest position / rotation / scale direction:
  a single facade is refused, the prior does not rescue it; and restarts that slide more than
  MULTISTART_M + max_jump_m from the optimum: no basin, as on a facade whose voxelised edges give
  the Hessian a weak hold), jump of the crop centre; a prior vaguer than MAX_PRIOR_SIGMA_M (the ICP's basin: from 6 m off it
  converged 2–5 m from truth with a spread that looked like a right answer's) is refused, and
  without a prior the basin check must agree to STANDALONE_MAX_SPREAD_M. A registration that
  disagrees with its prior beyond both uncertainties (innovation χ² zᵀS⁻¹z > χ²(99.9 %, 7 DoF))
  is no longer refused: it is fused with both covariances scaled by χ²/7 (same mean, wider
  posterior; in ``_register``). Accepted: information =
  inverse of the posterior [rot, trans] covariance in ENU at the crop centre (Eq. 10's role),
  sigma_m = its weakest position 1-σ.

- Georeference correction (beyond the papers; ``set_correction``, gis.align.georef): a model
  found metres off against GNSS is used shifted back by its estimated offset, with that estimate's
  σ as its georeference 1-σ; the ICP runs on the model's own coordinates, only their map to ECEF
  changes. Each registration reports its ICP result alone at the crop centre in the model's frame
  *as loaded* (``Registration.icp``), which is what the check compares with GNSS.

Measured on the simulator's real SLAM of an earlier session, with the tilt held (map snapshots every 50 frames of nominal and stale, 800
frames; prior offset at the camera 0–4 m with a GNSS-like σ; median error at the camera):
nominal 3.0 → 1.9 m, 4.0 → 2.1 m, 1.0 → 0.9 m; stale 3.0 → 2.6 m, 4.0 → 3.3 m, 1.0 → 1.0 m; from
the truth it stays at 0.15 m. 0 of 239 accepted registrations were beyond 3σ (largest 2.2σ); 6 m
priors are refused. With a FINE prior (covariance intersection) the gain is smaller still. The
limit is the SLAM cloud (numbers above), not the solver.

Cost: see gis.align.icp.

Thread-safe: the only state after construction is the crop cache (behind a lock) and the
model's lazily built grid index (built once, eagerly, in the constructor).
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation
from threadpoolctl import ThreadpoolController

from gis.align.crop import TILE_M, _Crop, _CropCache, _in_square
from gis.align.georef import GeorefCorrection, IcpMeasurement
from gis.align.icp import _evaluate, _Icp, _icp, compile_kernels
from gis.align.scale_check import (
    MAX_SCALE_MISMATCH,
    NADIR_MIN_POINTS,  # noqa: F401 (companion.pipeline imports it from here)
    NADIR_RADIUS_M,
    SCALE_MISMATCH_REASON,
    TRACKED_MAX_SCALE_MISMATCH,
    TRACKED_RADIUS_M,
    WALL_RADIUS_M,
    ScaleCheck,
    nadir_scale_ratio,
)
from gis.config import AlignmentConfig
from gis.geodesy import LocalFrame, ecef_to_geodetic, geodetic_to_ecef
from gis.model import GisModel
from gis.sim3 import Sim3, compose
from gis.types import Alignment, AlignmentSource

log = logging.getLogger(__name__)


RANDOM_INFLATION = 4.0         # variance factor of σ²H⁻¹ for correlated neighbouring points
SYS_OFFSET_FRACTION = 1.5      # systematic translation 1-σ ≥ this × σ_MAD (module doc: 0.75, added to the spread, gave NEES 4.4–8.5)
SPREAD_FRACTION = 0.5          # ... and ≥ this × the restarts' translation spread (module doc: the optimum sat 0.2–0.6 × it off)
SYS_SCALE_SIGMA = 0.005        # scale mismatch between a cloud and its trajectory (relative 1-σ)
MULTISTART_M = 3.0             # basin check: ICP restarted from its solution shifted this far horizontally ...
# ... in three directions 120° apart (degrees counter-clockwise from east). Every horizontal axis
# is then within 30° of a restart, which moves ≥ 2.6 m along it; east/north/west/south (until
# 2026-12-07) left axes 45° from all four, 2.1 m along them, with a fourth restart (docs/BENCHMARKS.md,
# "Fine-tuning cost", update of 2026-12-07)
MULTISTARTS = tuple((MULTISTART_M, a) for a in (0.0, 120.0, 240.0))
STANDALONE_MAX_SPREAD_M = 0.5  # without a prior to check against, the optimum must be unique to this
MAX_PRIOR_SIGMA_M = 2.5        # ICP's basin on real SLAM clouds is ≈3 m: a vaguer prior cannot be refined safely
CHI2_999 = 24.32               # χ² 99.9 % quantile, 7 degrees of freedom
UNKNOWN_VAR = 1e4              # variance standing for "not known" (rad², m², log-scale²)
MAX_SOURCE_POINTS = 1500       # SLAM points per registration after the voxel filter (random subset beyond)


@dataclass(frozen=True)
class Registration:
    """Outcome of one fine-tuning attempt: alignment (None when a gate rejected it) and why."""

    alignment: Alignment | None
    reason: str
    fitness: float = 0.0
    rmse_m: float = 0.0
    jump_m: float = 0.0
    sigma_m: float = float("inf")
    n_source: int = 0
    n_target: int = 0
    used_fpfh: bool = False
    wall_ms: float = 0.0
    icp: IcpMeasurement | None = None  # the ICP's own result at the crop centre, before the update (gis.align.georef)
    nis: float = 0.0          # innovation χ² against the prior (0 without a usable prior)
    spread_m: float = 0.0     # largest disagreement of the ICP restarts (basin check): crop centre, m
    spread_rot_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)  # ... rotation about east, north, up
    spread_scale: float = 0.0  # ... |log-scale| (≈ relative scale)
    sigma_mad_m: float = 0.0  # robust residual scale of all matched points
    scale_ratio: float = float("nan")  # barometric / SLAM height over the ground under the camera (nan: not tested)


@dataclass(frozen=True)
class _Basin:
    """How far the basin check's restarts ended from the ICP optimum, per degree of freedom (largest
    over the restarts): translation of the crop centre, rotation about each ENU axis, log-scale."""

    translation_m: float = 0.0
    rotation_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    log_scale: float = 0.0

    def widened(self, optimum: Sim3, other: Sim3) -> "_Basin":
        d_rot = np.abs(Rotation.from_matrix(other.R @ optimum.R.T).as_rotvec())
        return _Basin(max(self.translation_m, float(np.linalg.norm(other.t - optimum.t))),
                      np.maximum(self.rotation_rad, d_rot),
                      max(self.log_scale, abs(math.log(other.scale / optimum.scale))))


def enu_sim3(origin: LocalFrame) -> Sim3:
    """T_ecef_enu as a Sim3."""
    return Sim3(1.0, origin.R_ecef_enu, origin.origin_ecef_m)


class FineTuner:
    def __init__(self, model: GisModel, config: AlignmentConfig | None = None) -> None:
        self.model = model
        self.config = config or AlignmentConfig()
        self.correction: GeorefCorrection | None = None
        self._T_ecef_enu = self._T_ecef_model = enu_sim3(model.origin)  # the model's ENU as loaded → ECEF
        self._T_enu_ecef = self._T_ecef_enu.inverse()
        _ = model._grid  # build the crop index now, not in the first (timed) refine
        compile_kernels()  # and the ICP's compiled step
        self._crops = _CropCache(model, self.config.target_voxel_m)
        self._threadpools = ThreadpoolController()  # pykdtree's OpenMP runtime, limited per registration

    def set_correction(self, correction: GeorefCorrection | None) -> None:
        """Use the model shifted by −correction.offset_enu_m, with correction.sigma_m as its
        georeference 1-σ instead of ``model_sigma_m`` (gis.align.georef); None: as loaded. The ICP
        still runs on the model's own coordinates: only their map to ECEF changes."""
        T = self._T_ecef_model
        if correction is not None:
            T = compose(T, Sim3(1.0, np.eye(3), -np.asarray(correction.offset_enu_m, float).reshape(3)))
        self.correction = correction
        self._T_ecef_enu, self._T_enu_ecef = T, T.inverse()

    @property
    def model_sigma_m(self) -> float:
        """1-σ of the model's georeference: the correction's, else ``model_sigma_m`` as configured."""
        return self.correction.sigma_m if self.correction is not None else self.config.model_sigma_m

    def refine(self, points_slam: np.ndarray, initial: Alignment, t_s: float, reset_counter: int,
               center_slam: np.ndarray | None = None, map_id: int = 0) -> Alignment | None:
        """Refined alignment, or None (reason logged) when a gate rejects the registration."""
        reg = self.register(points_slam, initial, t_s, reset_counter, center_slam, map_id)
        if reg.alignment is None:
            log.info("fine-tune rejected: %s", reg.reason)
        return reg.alignment

    def register(self, points_slam: np.ndarray, initial: Alignment, t_s: float, reset_counter: int,
                 center_slam: np.ndarray | None = None, map_id: int = 0,
                 camera_h_ell_m: float | None = None, camera_h_sigma_m: float | None = None) -> Registration:
        """One registration of the SLAM points to the model about the camera centre ``center_slam``
        (module doc). camera_h_ell_m: the camera's ellipsoidal height from the barometer; with it,
        the SLAM height of the camera over the points near its nadir is checked against the
        barometric height over the model there (nadir_scale_ratio), and a map whose scale under the
        camera differs from the alignment's is refused with SCALE_MISMATCH_REASON. The KD-tree
        searches use ``finetune_threads`` OpenMP threads (the limit holds in the calling thread only)."""
        with self._threadpools.limit(limits=self.config.finetune_threads or None, user_api="openmp"):
            return self._register(points_slam, initial, t_s, reset_counter, center_slam, map_id, camera_h_ell_m,
                                  camera_h_sigma_m)

    def _register(self, points_slam: np.ndarray, initial: Alignment, t_s: float, reset_counter: int,
                  center_slam: np.ndarray | None, map_id: int, camera_h_ell_m: float | None,
                  camera_h_sigma_m: float | None = None) -> Registration:
        t0 = time.perf_counter()
        cfg = self.config
        pts = np.asarray(points_slam, float).reshape(-1, 3)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if len(pts) < cfg.min_points:
            return Registration(None, f"only {len(pts)} SLAM points (< min_points {cfg.min_points})", n_source=len(pts))
        T_enu_slam, c, src = self._source(pts, initial, center_slam)
        half = cfg.crop_size_m / 2
        if len(src) < cfg.min_points:
            return Registration(None, f"only {len(src)} SLAM points in the {cfg.crop_size_m:.0f} m crop", n_source=len(src))
        prior = self._prior_at(initial, c, T_enu_slam, cfg)
        if prior is not None:
            sig_prior = float(np.sqrt(np.linalg.eigvalsh(prior[3:5, 3:5])[-1]))
            if sig_prior > MAX_PRIOR_SIGMA_M:
                return Registration(None, f"prior too vague: horizontal 1-σ {sig_prior:.1f} m at the crop centre > "
                                          f"{MAX_PRIOR_SIGMA_M} m (ICP's convergence basin)", n_source=len(src))
        crop, min_corr = self._target(c)
        n_tgt = int(np.sum(_in_square(crop.points, c, half)))
        if n_tgt < cfg.min_points:
            return Registration(None, f"GIS crop holds only {n_tgt} points (outside the model?)", n_target=n_tgt)
        k = float("nan")
        if camera_h_ell_m is not None and math.isfinite(camera_h_ell_m):
            chk = self._scale_check(src, crop, c, camera_h_ell_m)
            k = chk.ratio
            if chk.mismatch:
                return Registration(None, f"{SCALE_MISMATCH_REASON}: {chk.describe()}",
                                    n_source=len(src), scale_ratio=k, wall_ms=1e3 * (time.perf_counter() - t0))
        icp = _evaluate(src, crop, c, _icp(src, crop, c, Sim3.identity(), cfg, min_corr), cfg, min_corr)
        reason = self._gate(icp, cfg)
        used_fpfh = False
        if reason and cfg.fpfh_fallback:
            guess = _fpfh_guess(src, crop, c, half, cfg)
            if guess is not None:
                icp2 = _evaluate(src, crop, c, _icp(src, crop, c, guess, cfg, min_corr), cfg, min_corr)
                reason2 = self._gate(icp2, cfg)
                if not reason2 or icp2.fitness > icp.fitness:
                    icp, reason, used_fpfh = icp2, reason2, True
        basin = _Basin()
        if not reason:  # basin check: restarts from shifted guesses must find the same optimum
            for dist_m, ang_deg in MULTISTARTS:
                ang = np.radians(ang_deg)
                g = compose(Sim3(1.0, np.eye(3), dist_m * np.array([np.cos(ang), np.sin(ang), 0.0])), icp.T)
                basin = basin.widened(icp.T, _icp(src, crop, c, g, cfg, min_corr))
        spread = basin.translation_m

        z = _vec(icp.T)
        R = _measurement_cov(icp, cfg, basin)
        R_loc = self._R_enuC_enuO(c)  # model ENU axes → local ENU axes at c
        measured = IcpMeasurement(self._T_ecef_model.apply((c + z[3:6])[None])[0], R_loc @ R[3:6, 3:6] @ R_loc.T)
        nis = 0.0
        if prior is None:  # the registration stands alone
            x_post, P_post = z, R
        else:
            x_post, P_post, nis = _update(z, R, prior)
            if nis > CHI2_999:
                # Prior and registration disagree beyond both covariances: one of them, or both, is
                # further off than it claims, and which one cannot be told from the pair. Both
                # covariances are scaled by the innovation's own estimate of their common factor,
                # α = χ²/7 (innovation-based adaptive estimation, Mehra 1970): the gain, and so the
                # fused mean, is unchanged, and P⁺ grows by α. Refusing it instead kept the prior
                # (demo seed 2: a scale break in a turn left the prior 1.9 and 3.2 m off horizontally
                # with a 0.9 / 1.5 m σ; the refused registrations would have left it 0.9 / 1.2 m off)
                # and the error grew to 4 m. docs/BENCHMARKS.md, "Disagreeing registrations are fused, wider".
                P_post = nis / 7.0 * P_post
            if camera_h_sigma_m is not None and camera_h_ell_m is not None and math.isfinite(camera_h_ell_m):
                # the barometer's camera height measures the up translation at the crop centre
                # (the camera, at 0 in these coordinates)
                x_post, P_post = _scalar_update(x_post, P_post, 5, self._up_baro_m(c, camera_h_ell_m), camera_h_sigma_m ** 2)
        sig_post = float(np.sqrt(np.linalg.eigvalsh(P_post[3:6, 3:6])[-1]))
        jump = float(np.linalg.norm(icp.T.t))
        common = dict(fitness=icp.fitness, rmse_m=icp.rmse_m, jump_m=jump, sigma_m=sig_post, n_source=len(src),
                      n_target=n_tgt, used_fpfh=used_fpfh, nis=nis, spread_m=spread,
                      spread_rot_deg=tuple(float(v) for v in np.degrees(basin.rotation_rad)), spread_scale=basin.log_scale,
                      sigma_mad_m=icp.sigma_mad_m, scale_ratio=k, icp=measured)
        if not reason and jump > cfg.max_jump_m:
            reason = f"jump {jump:.2f} m > max_jump_m {cfg.max_jump_m}"
        if not reason and spread > MULTISTART_M + cfg.max_jump_m:
            reason = (f"degenerate geometry: restarts {MULTISTART_M} m away slid {spread:.1f} m from the optimum "
                      f"(> {MULTISTART_M} + max_jump_m {cfg.max_jump_m} m): no basin (e.g. a single facade)")
        if not reason and prior is None and spread > STANDALONE_MAX_SPREAD_M:
            reason = (f"ambiguous optimum: restarts {MULTISTART_M} m away converge {spread:.2f} m apart "
                      f"(> {STANDALONE_MAX_SPREAD_M} m) and there is no prior to decide")
        if reason:
            return Registration(None, reason, wall_ms=1e3 * (time.perf_counter() - t0), **common)
        ok = "ok" if nis <= CHI2_999 else (
            f"ok, inconsistent with the prior alignment: innovation χ² {nis:.1f} > {CHI2_999} "
            f"(7 DoF, 99.9 %; ICP moved the crop centre {jump:.2f} m): fused with both covariances × {nis / 7.0:.1f}")

        # T_enu_slam' = T(+c) ∘ ΔT ∘ T(−c) ∘ T_enu_slam
        T_c = Sim3(1.0, np.eye(3), c)
        T_enu_slam_new = compose(compose(T_c, compose(_sim3(x_post), T_c.inverse())), T_enu_slam)
        T_ecef_slam = compose(self._T_ecef_enu, T_enu_slam_new)
        c_new_slam = T_enu_slam_new.inverse().apply(c)
        alignment = Alignment(
            T_ecef_slam=T_ecef_slam, source=AlignmentSource.FINE, t_s=t_s, reset_counter=reset_counter,
            information_6x6=self._information_at_center(P_post, c), sigma_m=sig_post,
            fitness=icp.fitness, rmse_m=icp.rmse_m, n_points=icp.n_inliers, map_id=map_id,
            center_slam=c_new_slam, scale_sigma=float(np.sqrt(P_post[6, 6])),
        )
        return Registration(alignment, ok, wall_ms=1e3 * (time.perf_counter() - t0), **common)

    def _source(self, pts: np.ndarray, initial: Alignment, center_slam: np.ndarray | None) -> tuple[Sim3, np.ndarray, np.ndarray]:
        """(T_enu_slam of the prior, crop centre c in model ENU, the SLAM points in the crop square
        about c in ENU centred on c, voxelised and subsampled): what the ICP registers."""
        cfg = self.config
        T_enu_slam = compose(self._T_enu_ecef, initial.T_ecef_slam)
        src = T_enu_slam.apply(pts)
        c_slam = np.median(pts, axis=0) if center_slam is None else np.asarray(center_slam, float).reshape(3)
        c = T_enu_slam.apply(c_slam)
        src = src[_in_square(src, c, cfg.crop_size_m / 2)] - c
        return T_enu_slam, c, _subsample(_voxel(src, cfg.source_voxel_m), MAX_SOURCE_POINTS)

    def optima(self, points_slam: np.ndarray, initial: Alignment, center_slam: np.ndarray,
               radii_m: tuple[float, ...] = (3.0, 6.0, 9.0), directions: int = 8) -> list[tuple[np.ndarray, float, float]]:
        """Where the ICP converges from the prior and from starts shifted horizontally by each
        radius in ``directions`` directions: (the camera at the optimum, ECEF m; fitness; inlier
        RMSE m) per start, the prior's own start first. A diagnostic (gis.align.replay): a
        registration whose starts all reach one optimum measures the position; starts that stop
        metres apart, at equal fitness, show the ICP keeps near wherever it starts."""
        cfg = self.config
        pts = np.asarray(points_slam, float).reshape(-1, 3)
        _, c, src = self._source(pts[np.all(np.isfinite(pts), axis=1)], initial, center_slam)
        crop, min_corr = self._target(c)
        out = []
        starts = [np.zeros(3)] + [r * np.array([math.cos(a), math.sin(a), 0.0]) for r in radii_m
                                  for a in np.linspace(0, 2 * math.pi, directions, endpoint=False)]
        for t0 in starts:
            T = _icp(src, crop, c, Sim3(1.0, np.eye(3), t0), cfg, min_corr)
            ev = _evaluate(src, crop, c, T, cfg, min_corr)
            out.append((self._T_ecef_enu.apply((c + T.t)[None])[0], ev.fitness, ev.rmse_m))
        return out

    def _target(self, c: np.ndarray) -> tuple[_Crop, float]:
        """The model about crop centre c (model ENU): its crop_size_m square and max_correspondence_m
        beyond, so border points find their matches; and the least correspondence distance, never
        below the model's own point spacing there (a sparse model would otherwise lose true
        correspondences and report a low fitness)."""
        half = self.config.crop_size_m / 2
        crop = self._crops.get(c, half + self.config.max_correspondence_m)
        return crop, 1.5 * crop.spacing_m(c, half)

    def prefetch_crop(self) -> bool:
        """Build the GIS crop the next registration will probably need, now (_CropCache.prefetch):
        for the fine-tuning worker's idle time after a registration. True when one was built."""
        return self._crops.prefetch()

    def in_crop(self, points_slam: np.ndarray, T_ecef_slam: Sim3, center_slam: np.ndarray) -> np.ndarray:
        """(N,) bool: the SLAM points a registration about ``center_slam`` under ``T_ecef_slam``
        takes (the crop_size_m square about it in the model's ENU axes, as ``register`` crops)."""
        T_enu_slam = compose(self._T_enu_ecef, T_ecef_slam)
        return _in_square(T_enu_slam.apply(points_slam), T_enu_slam.apply(center_slam), self.config.crop_size_m / 2)

    def check_scale(self, points_slam: np.ndarray, alignment: Alignment, center_slam: np.ndarray,
                    camera_h_ell_m: float) -> ScaleCheck:
        """The barometer check of ``register`` on its own (nadir_scale_ratio), for the points the
        camera sees now (the tracker's pose inliers): the pipeline runs it every second between
        registrations, so a map whose scale breaks after a registration (a turn in the outage) is
        caught within a second, not at the next registration, whose older points may still fit.
        center_slam: the camera centre; camera_h_ell_m: its ellipsoidal height from the barometer."""
        T_enu_slam = compose(self._T_enu_ecef, alignment.T_ecef_slam)
        pts = np.asarray(points_slam, float).reshape(-1, 3)
        c = T_enu_slam.apply(np.asarray(center_slam, float).reshape(1, 3))[0]
        src = T_enu_slam.apply(pts[np.all(np.isfinite(pts), axis=1)]) - c
        # its own crop (a forward-looking camera sees beyond the registration's), TILE_M of margin
        crop = self._crops.get(c, TRACKED_RADIUS_M + WALL_RADIUS_M, slot="scale check", margin_m=TILE_M)
        return self._scale_check(src, crop, c, camera_h_ell_m, TRACKED_RADIUS_M, TRACKED_MAX_SCALE_MISMATCH)

    def _scale_check(self, src: np.ndarray, crop: _Crop, c: np.ndarray, camera_h_ell_m: float,
                     radius_m: float = NADIR_RADIUS_M, tolerance: float = MAX_SCALE_MISMATCH) -> ScaleCheck:
        """nadir_scale_ratio of src (ENU about the camera at c) with the barometric height in the
        same coordinates."""
        if not math.isfinite(camera_h_ell_m):
            return ScaleCheck(float("nan"), float("nan"), float("nan"), 0, tolerance)
        return nadir_scale_ratio(src, crop, c, self._up_baro_m(c, camera_h_ell_m), radius_m, tolerance)

    def _up_baro_m(self, c: np.ndarray, camera_h_ell_m: float) -> float:
        """The barometric camera height (ellipsoidal) in ENU coordinates centred on the camera at c."""
        lat, lon, _ = ecef_to_geodetic(self._T_ecef_enu.apply(c[None])[0])
        return float(self._T_enu_ecef.apply(geodetic_to_ecef(float(lat), float(lon), camera_h_ell_m)[None])[0][2]) - c[2]

    def _prior_at(self, initial: Alignment, c_enu: np.ndarray, T_enu_slam: Sim3, cfg: AlignmentConfig) -> np.ndarray | None:
        """7x7 covariance of the prior's [rot, trans, log-scale] error at the crop centre (model ENU
        axes); None when the prior carries no information about a known point (no center_slam, as
        in gis.globalizer) or its information is not positive definite."""
        if initial.center_slam is None:
            return None
        info = np.asarray(initial.information_6x6, float)
        w, V = np.linalg.eigh(0.5 * (info + info.T))
        if not np.all(np.isfinite(w)) or w[0] <= 1e-12 * max(w[-1], 1e-12):
            return None
        c0 = T_enu_slam.apply(np.asarray(initial.center_slam, float).reshape(3))
        B = np.kron(np.eye(2), self._R_enuC_enuO(c0))
        cov6 = B.T @ ((V / w) @ V.T) @ B  # model ENU axes
        d = c_enu - c0  # lever arm: (ω, τ) about c0 moves c by τ + ω × d
        J = np.block([[np.eye(3), np.zeros((3, 3))], [-_skew(d), np.eye(3)]])
        cov = np.zeros((7, 7))
        cov[:6, :6] = J @ cov6 @ J.T
        dist = float(np.linalg.norm(d))
        iso = (cfg.slam_drift_fraction * initial.drift_distance_m(dist)) ** 2 + (initial.scale_sigma * dist) ** 2
        if initial.source is AlignmentSource.GNSS:  # GNSS vs the model: the model's georeference error
            iso += self.model_sigma_m**2
        cov[3:6, 3:6] += iso * np.eye(3)
        scale_drift = cfg.slam_scale_drift_per_100m * initial.drift_distance_m(dist) / 100.0  # the map's scale drifts as it grows
        cov[6, 6] = initial.scale_sigma**2 + scale_drift**2 if initial.scale_sigma > 0 else UNKNOWN_VAR
        return cov

    def _R_enuC_enuO(self, c_enu: np.ndarray) -> np.ndarray:
        lat, lon, _ = ecef_to_geodetic(self._T_ecef_enu.apply(c_enu))
        return LocalFrame(float(lat), float(lon)).R_ecef_enu.T @ self.model.origin.R_ecef_enu

    def _gate(self, icp: _Icp, cfg: AlignmentConfig) -> str:
        if icp.fitness < cfg.min_fitness:
            return f"fitness {icp.fitness:.2f} < min_fitness {cfg.min_fitness}"
        if icp.rmse_m > cfg.max_rmse_m:
            return f"inlier RMSE {icp.rmse_m:.2f} m > max_rmse_m {cfg.max_rmse_m}"
        sig_p, sig_r, sig_s = _sigmas(icp, cfg)
        if sig_p > cfg.max_sigma_m:
            return f"degenerate geometry: position 1-σ {sig_p:.2g} m > max_sigma_m {cfg.max_sigma_m} (e.g. a single facade)"
        if np.degrees(sig_r) > cfg.max_sigma_rot_deg:
            return f"degenerate geometry: rotation 1-σ {np.degrees(sig_r):.2g}° > max_sigma_rot_deg {cfg.max_sigma_rot_deg}"
        if sig_s > cfg.max_sigma_scale:
            return f"degenerate geometry: scale 1-σ {sig_s:.2g} > max_sigma_scale {cfg.max_sigma_scale}"
        return ""

    def _information_at_center(self, cov7: np.ndarray, c_enu: np.ndarray) -> np.ndarray:
        """Information of [rot, trans] (scale marginalised) in the ENU frame at the crop centre."""
        B = np.kron(np.eye(2), self._R_enuC_enuO(c_enu))
        return B @ np.linalg.inv(cov7[:6, :6]) @ B.T


def _data_cov(icp: _Icp, cfg: AlignmentConfig) -> np.ndarray | None:
    """σ²·H⁻¹ over [rot, trans, log-scale] (Eq. 8–9, the data alone; σ the inlier RMSE, floored);
    None when H is singular."""
    w, V = np.linalg.eigh(icp.H7)
    if w[0] <= 1e-9 * max(w[-1], 1e-12):
        return None
    return max(icp.rmse_m, cfg.sigma_floor_m) ** 2 * (V / w) @ V.T


def _sigmas(icp: _Icp, cfg: AlignmentConfig) -> tuple[float, float, float]:
    """Weakest 1-σ of (position m, rotation rad, relative scale) of _data_cov (inf if singular).
    Degeneracy test only: not the reported uncertainty."""
    cov = _data_cov(icp, cfg)
    if cov is None:
        return float("inf"), float("inf"), float("inf")
    sig_p = float(np.sqrt(np.linalg.eigvalsh(cov[3:6, 3:6])[-1]))
    sig_r = float(np.sqrt(np.linalg.eigvalsh(cov[:3, :3])[-1]))
    return sig_p, sig_r, float(np.sqrt(cov[6, 6]))


def _measurement_cov(icp: _Icp, cfg: AlignmentConfig, basin: _Basin) -> np.ndarray:
    """Covariance of the ICP solution [rot, trans, log-scale] (module doc: random + systematic + basin)."""
    cov = _data_cov(icp, cfg)
    if cov is None:
        return np.eye(7) * UNKNOWN_VAR
    cov = RANDOM_INFLATION * cov
    s_mad = max(icp.sigma_mad_m, cfg.sigma_floor_m)
    sig_tilt = s_mad / (cfg.crop_size_m / 2)  # apparent rotation of the cloud about its centroid, rad
    # the solved rotation carries the cloud's apparent tilt, and it moves the centre by ω × (c − p̄)
    A = np.vstack([np.eye(3), _skew(icp.centroid), np.zeros((1, 3))])
    cov += sig_tilt**2 * A @ A.T
    cov[3:6, 3:6] += max(SYS_OFFSET_FRACTION * s_mad, SPREAD_FRACTION * basin.translation_m) ** 2 * np.eye(3)
    cov[:3, :3] += np.diag(basin.rotation_rad**2)
    cov[6, 6] += SYS_SCALE_SIGMA**2 + basin.log_scale**2
    return cov


def _update(z: np.ndarray, R: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Kalman update of the increment x (prior N(0, P)) given z = x + v, v ~ N(0, R): x⁺ = K z,
    P⁺ = (I − K) P, K = P (P + R)⁻¹. Returns (x⁺, P⁺, innovation χ² = zᵀ (P + R)⁻¹ z)."""
    S = P + R
    nis = float(z @ np.linalg.solve(S, z))
    K = P @ np.linalg.inv(S)
    Pp = (np.eye(len(P)) - K) @ P
    return K @ z, 0.5 * (Pp + Pp.T), nis


def _scalar_update(x: np.ndarray, P: np.ndarray, i: int, z: float, var: float) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update of state x ~ N(x, P) with one measurement of its component i:
    z = x_i + v, v ~ N(0, var). K = P e_i / (P_ii + var), x⁺ = x + K (z − x_i), P⁺ = P − K P_i·."""
    K = P[:, i] / (P[i, i] + var)
    Pp = P - np.outer(K, P[i, :])
    return x + K * (z - x[i]), 0.5 * (Pp + Pp.T)


def _skew(a: np.ndarray) -> np.ndarray:
    """[a]× with [a]× b = a × b."""
    return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0.0]])


def _vec(T: Sim3) -> np.ndarray:
    """[rotation vector, translation, log-scale] of an increment in centred coordinates."""
    return np.r_[Rotation.from_matrix(T.R).as_rotvec(), T.t, np.log(T.scale)]


def _sim3(d: np.ndarray) -> Sim3:
    return Sim3(float(np.exp(d[6])), Rotation.from_rotvec(d[:3]).as_matrix(), np.asarray(d[3:6], float))


def _voxel(p: np.ndarray, voxel_m: float) -> np.ndarray:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    return np.asarray(pcd.voxel_down_sample(voxel_m).points)


def _subsample(p: np.ndarray, n_max: int) -> np.ndarray:
    """At most n_max of the points, a fixed-seed random subset (repeatable registrations)."""
    if len(p) <= n_max:
        return p
    return p[np.sort(np.random.default_rng(0).choice(len(p), n_max, replace=False))]


def _fpfh_guess(src: np.ndarray, crop: _Crop, c: np.ndarray, half_m: float, cfg: AlignmentConfig) -> Sim3 | None:
    """Global registration from FPFH features + RANSAC (open3d), rigid (scale is close already)."""
    reg = o3d.pipelines.registration
    inner = _in_square(crop.points, c, half_m)
    tgt, tgt_n = crop.points[inner] - c, crop.normals[inner]
    voxel = max(cfg.target_voxel_m, cfg.source_voxel_m) * 2
    s = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src)).voxel_down_sample(voxel)
    t = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt))
    t.normals = o3d.utility.Vector3dVector(tgt_n)
    t = t.voxel_down_sample(voxel)
    if len(s.points) < 10 or len(t.points) < 10:
        return None
    s.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 3, max_nn=30))
    param = o3d.geometry.KDTreeSearchParamHybrid(radius=voxel * 5, max_nn=100)
    fs = reg.compute_fpfh_feature(s, param)
    ft = reg.compute_fpfh_feature(t, param)
    res = reg.registration_ransac_based_on_feature_matching(
        s, t, fs, ft, True, voxel * 1.5, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(voxel * 1.5)],
        reg.RANSACConvergenceCriteria(20000, 0.999),
    )
    if res.fitness <= 0:
        return None
    return Sim3.from_matrix(res.transformation)
