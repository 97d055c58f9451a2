"""Online fine-tuning T_fine (TerraSLAM §4.4; digital-twin paper §III-C, §III-E, §V).

One registration = crop the GIS model around the current position (fixed size, so the cost does
not grow with the model), voxel-downsample both clouds, then a scale-aware point-to-plane ICP.
The crop is made of 25 m tiles voxelised once on a global grid and cached; its KD-tree is reused
while the next registration needs no tile outside it, and any crop holding a registration's tiles
gives it the same correspondences (_CropCache).

- Correspondences: nearest GIS point (pykdtree, C, vectorised queries; ``finetune_threads``
  OpenMP threads; between ICP steps only for the points whose last search's NN_CANDIDATES
  nearest model points no longer decide it, _nearest), coarse-to-fine
  distances (max_correspondence_m, /2, /4) with a Tukey kernel that shrinks with them
  (max(robust_kernel_m, ½ · distance)); a fixed 0.5 m kernel gave zero weight to every residual
  from a 3 m guess and the ICP never moved.
- Solve: each iteration is one Gauss–Newton step of the point-to-plane cost of digital-twin Eq. 2
  (Tukey IRLS) over rotation, translation and log-scale; the Jacobian row is Eq. 9's A_j extended
  by the scale column n_j·a_j. Written by hand: no library here does point-to-plane with scale;
  the step is compiled with numba (_gauss_newton_step), the correspondences are pykdtree's.
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
- Barometer check (beyond the papers; with ``camera_h_ell_m``): before the ICP, the barometric
  height of the camera over the level GIS surface under each SLAM point near nadir, divided by
  its SLAM height under the alignment (nadir_scale_ratio); if even the lower quartile of these
  ratios is above 1 + MAX_SCALE_MISMATCH, or even the upper quartile below 1 − MAX_SCALE_MISMATCH
  (3σ order-statistic bounds), the registration is refused with SCALE_MISMATCH_REASON and the
  pipeline withholds fixes (the map under the camera no longer has the alignment's scale).
  ``check_scale`` runs the same test alone on the points the camera is tracking now (within
  TRACKED_RADIUS_M); the pipeline calls it every second between registrations. A registration's
  crop mixes older points, which may still fit after the map's scale broke under the camera: at
  the first registration after demo seed 4's break the points near nadir gave a median ratio of
  0.65 with a robust SD of 0.24, too mixed to flag.
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

Cost (issue 5): nearest-neighbour searches were most of it (pykdtree 0.28 µs per point, scipy's
cKDTree 0.36, identical neighbours; real SLAM crops hold 200–1400 points after the voxel filter,
and 4 ICPs × up to 36 iterations run); since 2026-12-07 a point is searched again only when its
kept candidates cannot decide its nearest model point (_nearest), and each Gauss–Newton step is
one compiled call (_gauss_newton_step). Levels
stop once a step moves no point more than ICP_STEP_TOL_M; on real clouds the IRLS still creeps by
centimetres at the end of a level, so most levels run their 12 iterations, as before. Measured
on 28 real-SLAM map snapshots (nominal + stale, 400 frames, 7 priors each): thread CPU 135 → 80 ms
mean per registration, same accuracy and integrity; on 28 journaled registrations 70 → 35 ms with
the two changes of 2026-12-07, identical alignments (docs/BENCHMARKS.md, "Fine-tuning cost").

Thread-safe: the only state after construction is the crop cache (behind a lock) and the
model's lazily built grid index (built once, eagerly, in the constructor).
"""
from __future__ import annotations

import itertools
import logging
import math
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field, replace
from functools import cached_property

import numba
import numpy as np
import open3d as o3d
from pykdtree.kdtree import KDTree
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from threadpoolctl import ThreadpoolController

from gis.align.georef import GeorefCorrection, IcpMeasurement
from gis.config import AlignmentConfig
from gis.geodesy import LocalFrame, ecef_to_geodetic, geodetic_to_ecef
from gis.model import GisModel
from gis.sim3 import Sim3, compose
from gis.types import Alignment, AlignmentSource

log = logging.getLogger(__name__)

ICP_ITERATIONS_PER_LEVEL = 12
KERNEL_FRACTION = 0.5          # Tukey width per level = max(robust_kernel_m, this × correspondence distance)
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
ICP_STEP_TOL_M = 0.005         # a level has converged when a Gauss–Newton step moves no cloud point more than this
COARSE_LEVEL_STRIDE = 2        # the two coarse ICP levels on every 2nd source point, the last on all (_icp)
CORR_REUSE_STEP_M = 0.1        # after an ICP step that moved no point more than this, the next step keeps its correspondences (_icp)
NN_CANDIDATES = 6              # nearest model points kept per SLAM point between searches (_nearest) ...
NN_SEARCH_MARGIN_M = 0.5       # ... searched for this far beyond the correspondence distance
MAX_SOURCE_POINTS = 1500       # SLAM points per registration after the voxel filter (random subset beyond)
TILE_M = 25.0                  # GIS crop tiles (voxelised once, cached); rounded to a multiple of target_voxel_m
MAX_CACHED_TILES = 4096        # ≈ 2.5 km² of voxelised tiles kept (least recently used dropped)
PREFETCH_MAX_STEP_M = 150.0    # a prefetched crop reaches at most this far beyond the last registration's (_CropCache.prefetch)
PREFETCH_MARGIN_M = TILE_M     # ... and this far around the guessed one (turns; journals: 4 of 5 registrations after the second found it built, 3 of 5 without)
# Scale check against the barometer (beyond the papers; docs/BENCHMARKS.md "Fine-tuning update"):
SCALE_MISMATCH_REASON = "SLAM scale under the camera disagrees with the barometer"
NADIR_RADIUS_M = 30.0          # SLAM points within this horizontal distance of the camera are tested
NADIR_MIN_POINTS = 20          # fewer: no test
TRACKED_MAX_SCALE_MISMATCH = 0.12  # check_scale's tolerance: a frame over trees the model lacks read a lower
                               # quartile up to 1.077 (demo seeds 1, 2, 4); offline, maps shrunk 20 % were flagged
                               # by 99–100 % of the checks, 15 % by 48–94 %, 10 % by 13–18 % (docs/BENCHMARKS.md)
TRACKED_RADIUS_M = 150.0       # check_scale: the tracked points this close (horizontally); a forward-looking
                               # camera's are 40–200 m away (a 0.5° tilt error then moves k by ≤ 2 %)
SURFACE_RADIUS_M = 1.5         # the model surface under a point: level model points this close (horizontally)
WALL_RADIUS_M = 3.0            # ... and no wall of the model this close: a point on a facade, a metre or two off
                               # it, found only ground (or roof) within SURFACE_RADIUS_M and read k ≈ 1.5 (`loop` seed 1)
SURFACE_STEP_M = 1.0           # level model surfaces under a point further apart in height: an edge, no test
LEVEL_NORMAL_Z = 0.8           # a model point on a level surface (ground, roof): |normal up-component| above this
MAX_SCALE_MISMATCH = 0.06      # |k − 1| tolerated beyond the quartiles' 3σ bounds (demo seeds 0/4/5: good registrations' medians 0.946–1.022, the scale break 1.080–1.084)


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
class ScaleCheck:
    """The barometer against the SLAM map under the camera (nadir_scale_ratio): per point, k_i =
    barometric ÷ SLAM height of the camera over the model surface under the point."""

    ratio: float     # median k_i (nan: too few points to test)
    low: float       # lower 3σ confidence bound of the 25 % quantile of k_i
    high: float      # upper 3σ confidence bound of the 75 % quantile of k_i
    n_points: int
    tolerance: float = MAX_SCALE_MISMATCH

    @property
    def mismatch(self) -> bool:
        """The map under the camera is not at the alignment's scale: even its lower quarter of
        points is more than ``tolerance`` too close to the camera (the map shrank), or even its
        upper quarter too far (it grew)."""
        return math.isfinite(self.ratio) and (self.low > 1.0 + self.tolerance or self.high < 1.0 - self.tolerance)

    def describe(self) -> str:
        return (f"ratio {self.ratio:.3f} over {self.n_points} points, quartiles beyond {self.low:.3f} … "
                f"{self.high:.3f} (3σ; tolerance 1 ± {self.tolerance:g})")


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


@dataclass(frozen=True)
class _Icp:
    T: Sim3                   # increment in centred ENU coordinates
    fitness: float
    rmse_m: float             # inlier RMSE (|r| < inlier_distance_m)
    H7: np.ndarray            # 7x7 Gauss–Newton Hessian [rot, trans, log-scale] at the crop centre (inliers)
    n_inliers: int
    centroid: np.ndarray      # inlier centroid, centred coordinates (lever arm of the systematic tilt)
    sigma_mad_m: float        # 1.4826·MAD of all matched residuals (not truncated at the inlier distance)


def enu_sim3(origin: LocalFrame) -> Sim3:
    """T_ecef_enu as a Sim3."""
    return Sim3(1.0, origin.R_ecef_enu, origin.origin_ecef_m)


@dataclass(frozen=True)
class _Crop:
    """The GIS model over a box of whole tiles, voxelised on the global voxel grid, with its KD-tree
    (ENU coordinates). Tiles are concatenated in index order, so any crop holding a tile holds the
    same points for it in the same order: a registration gets the same correspondences from any
    crop that covers the tiles it needs."""

    box: tuple[int, int, int, int]   # tile indices (i0, j0, i1, j1), inclusive
    tile_m: float
    points: np.ndarray
    normals: np.ndarray
    tree: KDTree | None              # pykdtree (ICP correspondences); None for an empty crop (pykdtree
                                     # refuses one; registrations stop at the GIS-crop gate first)

    @cached_property
    def tree_en(self) -> cKDTree:
        """The points' horizontal coordinates, for radius searches over most of the crop
        (nadir_scale_ratio); built when first asked for: 6 ms for a crop of the demo flight, three
        times its 3-D KD-tree, and a registration's own check needs only the crop's middle."""
        return cKDTree(self.points[:, :2], balanced_tree=False)

    def covers(self, box: tuple[int, int, int, int]) -> bool:
        i0, j0, i1, j1 = self.box
        return i0 <= box[0] and j0 <= box[1] and box[2] <= i1 and box[3] <= j1

    def spacing_m(self, c_enu: np.ndarray, half_m: float) -> float:
        """Median nearest-neighbour distance of the crop's points within half_m of c_enu (≤ 300,
        taken in the crop's order: the same whichever covering crop is asked)."""
        inner = np.flatnonzero(_in_square(self.points, c_enu, half_m))
        if len(inner) < 2:
            return 0.0
        sample = self.points[inner[:: max(1, len(inner) // 300)]]
        return float(np.median(self.tree.query(sample, k=2)[0][:, 1]))


class _CropCache:
    """Fixed-size GIS crops (digital-twin §III-E) without rebuilding them every registration:
    the model is voxelised per tile once (LRU-cached), and the last crop of each user (``slot``:
    the registrations, the barometer checks) and its KD-tree are reused while that user's next
    request needs no tile outside it. Thread-safe."""

    def __init__(self, model: GisModel, voxel_m: float) -> None:
        self._model = model
        self._voxel_m = voxel_m
        self.tile_m = voxel_m * max(1, round(TILE_M / voxel_m))  # tile edges on voxel edges: no voxel straddles two tiles
        self._tiles: OrderedDict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._last: dict[str, _Crop] = {}
        self._asked: dict[str, deque] = {}  # per slot, the last two requests: (centre EN m, half_m)
        self._lock = threading.Lock()
        self.n_built = 0  # crops (KD-trees) built so far

    def last(self, slot: str = "registration") -> _Crop | None:
        return self._last.get(slot)

    def _box(self, c_enu: np.ndarray, half_m: float) -> tuple[int, int, int, int]:
        lo = np.floor((np.asarray(c_enu[:2], float) - half_m) / self.tile_m).astype(int)
        hi = np.floor((np.asarray(c_enu[:2], float) + half_m) / self.tile_m).astype(int)
        return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])

    def get(self, c_enu: np.ndarray, half_m: float, slot: str = "registration", margin_m: float = 0.0) -> _Crop:
        """A crop holding every model point within half_m (horizontally, square) of c_enu; a new
        one reaches margin_m further, so that a moving user rebuilds it less often."""
        box = self._box(c_enu, half_m)
        with self._lock:
            self._asked.setdefault(slot, deque(maxlen=2)).append((np.array(c_enu[:2], float), half_m))
            last = self._last.get(slot)
            if last is not None and last.covers(box):
                return last
            return self._build(self._box(c_enu, half_m + margin_m), slot)

    def prefetch(self, slot: str = "registration") -> bool:
        """Build, ahead of time, the crop the slot's next request will probably need, so that
        request finds it built (the next registration then skips voxelising its new tiles and the
        KD-tree: about a quarter of a registration's CPU on the journals of a moving camera, which
        needed a new crop every time). The guess: the next request lies as far on from the last
        one as that one from the one before (at most PREFETCH_MAX_STEP_M); the crop covers both
        the last request's box and the guessed one's, PREFETCH_MARGIN_M wider for a turn, so any
        request along the way is covered too (a registration every 20 s while GNSS is trusted,
        then every 5 s in a denial, at the same speed, lands between them). True when a crop was
        built; False when fewer than two requests were made or the slot's crop already covers
        the guess. Any crop covering a request gives it the same points in the same order
        (_Crop), so a prefetched crop changes no result, only when the work is done."""
        with self._lock:
            asked = self._asked.get(slot)
            if asked is None or len(asked) < 2:
                return False
            (c0, _), (c1, half_m) = asked
            step = c1 - c0
            n = float(np.hypot(*step))
            if n > PREFETCH_MAX_STEP_M:
                step *= PREFETCH_MAX_STEP_M / n
            a, b = self._box(c1, half_m), self._box(c1 + step, half_m + PREFETCH_MARGIN_M)
            box = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
            last = self._last.get(slot)
            if last is not None and last.covers(box):
                return False
            self._build(box, slot)
            return True

    def _build(self, box: tuple[int, int, int, int], slot: str) -> _Crop:
        """The crop over ``box`` (tile indices), the slot's crop from now on (lock held)."""
        keys = [(i, j) for j in range(box[1], box[3] + 1) for i in range(box[0], box[2] + 1)]
        self._voxelise_missing([k for k in keys if k not in self._tiles])
        parts = [self._tiles[k] for k in keys]
        for k in keys:
            self._tiles.move_to_end(k)
        while len(self._tiles) > max(MAX_CACHED_TILES, len(keys)):
            self._tiles.popitem(last=False)
        pts = np.concatenate([p for p, _ in parts]) if parts else np.zeros((0, 3))
        nrm = np.concatenate([n for _, n in parts]) if parts else np.zeros((0, 3))
        crop = _Crop(box, self.tile_m, pts, nrm, KDTree(pts) if len(pts) else None)
        self._last[slot] = crop
        self.n_built += 1
        return crop

    def _voxelise_missing(self, keys: list[tuple[int, int]]) -> None:
        """Voxelise the model over the given tiles in one pass: one model crop over their bounding
        box, each point assigned to the tile that floor(east/north / tile_m) names (a point on a
        tile edge goes to one tile), the points of tiles not asked for dropped. One crop, not one
        per tile: the model's 50 m index cells made each 25 m tile crop sort through up to 16× its
        points (≈0.6 ms a tile; 16 → 10 ms per registration of the demo flight)."""
        if not keys:
            return
        k = np.asarray(keys, np.int64)
        idx = self._model.crop_box(k.min(axis=0) * self.tile_m, (k.max(axis=0) + 1) * self.tile_m)
        p = self._model.points_enu[idx]
        tile = np.floor(p[:, :2] / self.tile_m).astype(np.int64)
        want = np.isin(tile[:, 1] * (1 << 32) + tile[:, 0], k[:, 1] * (1 << 32) + k[:, 0])
        p, n = _voxel_global(p[want], self._model.normals_enu[idx[want]], self._voxel_m)
        tile = np.floor(p[:, :2] / self.tile_m).astype(int)
        order = np.lexsort((tile[:, 0], tile[:, 1]))  # stable: voxel order kept within a tile
        p, n, tile = p[order], n[order], tile[order]
        for key in keys:
            lo, hi = np.searchsorted(tile[:, 1], key[1], "left"), np.searchsorted(tile[:, 1], key[1], "right")
            row = tile[lo:hi, 0]
            a, b = lo + np.searchsorted(row, key[0], "left"), lo + np.searchsorted(row, key[0], "right")
            self._tiles[key] = (p[a:b], n[a:b])


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


def nadir_scale_ratio(src: np.ndarray, crop: _Crop, c: np.ndarray, up_baro_m: float,
                      radius_m: float = NADIR_RADIUS_M, tolerance: float = MAX_SCALE_MISMATCH) -> ScaleCheck:
    """The ratios, over the SLAM points p_i within radius_m (horizontally) of the camera, of

        k_i = (up_baro_m − (z_model(p_i) − c_z)) / (−p_i,z)

    with src the points in ENU centred on the camera (the camera at 0), up_baro_m the barometric
    camera height in the same coordinates, and z_model the height of the level model surface
    (ground, roof: normal within ~37° of vertical) within SURFACE_RADIUS_M of p_i horizontally that
    is nearest to p_i in height. Points over walls only, and points near an edge (level model
    surfaces more than SURFACE_STEP_M apart in height within that radius: roof and ground) are
    skipped: a map a few percent off in scale moves its points metres sideways there, onto the
    other surface (in a box city 25 % of the points read k_i < 0.8 or > 1.15 before). So are points
    with a wall of the model within WALL_RADIUS_M: a point on a facade that its triangulation put a
    metre or two off the wall finds only the ground within SURFACE_RADIUS_M, and reads the height
    of the facade above it as scale (`loop` seed 1: 55–65 % of the tested points, lower quartile's
    bound 1.17–1.18 and fixes withheld at 78 s and for the rest of the denial from 212 s, while the
    track kept its scale within 3 %; without them 1.01, median 1.06).
    k_i is the true height of the
    camera over what it sees divided by the height the SLAM map and the alignment give it: 1 when
    the map under the camera has the alignment's scale, 1.06 at every point when it has shrunk 6 %
    (a scale break in a turn). A vertical shift of the alignment moves camera and points together
    and leaves k alone.

    Quartiles, not the median: points on what the model lacks (trees, cars, new buildings) sit
    above its surface and read k_i > 1 (a 10 m tree under a camera 76 m up: 1.15), and points on
    walls read anything. Measured on demo seed 1 at 67–70 s, over trees: median 1.23–1.32 while the
    camera moved at the alignment's scale (0.94–1.07 per second against truth); the lower
    quartile's bound stayed ≤ 1.06. A
    shrunk map moves even its lowest (ground) points, so the lower quartile; a grown one the upper.
    Their bounds are order statistics at ranks n·q ∓ 3·√(n·q·(1 − q)) (binomial: no distribution
    assumed, and narrow where the ground points crowd). Written by hand: sorting and two ranks.
    Not tested (nan) with fewer than NADIR_MIN_POINTS usable points."""
    near = src[(np.hypot(src[:, 0], src[:, 1]) < radius_m) & (src[:, 2] < -1.0)]
    untested = ScaleCheck(float("nan"), float("nan"), float("nan"), len(near), tolerance)
    if len(near) < NADIR_MIN_POINTS:
        return untested
    q = near[:, :2] + c[:2]
    i0, j0, i1, j1 = crop.box  # either tree finds the same neighbours, in the same order
    if (2 * (radius_m + WALL_RADIUS_M)) ** 2 < 0.5 * (i1 - i0 + 1) * (j1 - j0 + 1) * crop.tile_m ** 2:
        # a registration's check, in the crop's middle: a tree over the points it can reach
        local = np.flatnonzero(_in_square(crop.points, c, radius_m + WALL_RADIUS_M))
        hits = cKDTree(crop.points[local, :2], balanced_tree=False).query_ball_point(q, WALL_RADIUS_M)
    else:  # check_scale's wide radius: the crop's own tree, built once for the crop
        local, hits = None, crop.tree_en.query_ball_point(q, WALL_RADIUS_M)
    # The neighbourhoods flattened to (point, model point) pairs, in the search's order: one
    # numpy pass instead of a Python loop per point (check_scale tests ~1000 points).
    counts = np.fromiter(map(len, hits), np.intp, count=len(hits))
    owner = np.repeat(np.arange(len(near)), counts)
    j = np.fromiter(itertools.chain.from_iterable(hits), np.intp, count=int(counts.sum()))
    if local is not None:
        j = local[j]
    walled = np.zeros(len(near), bool)  # one level surface (ground, roof) only, and no wall near
    walled[owner[np.abs(crop.normals[j, 2]) <= LEVEL_NORMAL_Z]] = True
    keep = ~walled[owner] & (np.hypot(*(crop.points[j, :2] - q[owner]).T) <= SURFACE_RADIUS_M)
    owner, z = owner[keep], crop.points[j[keep], 2]
    z_model = np.full(len(near), np.nan)
    if len(owner):
        # by point, then by height from the point (stable: the search's order among ties)
        order = np.lexsort((np.abs(z - (near[owner, 2] + c[2])), owner))
        owner, z = owner[order], z[order]
        first = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
        level = np.maximum.reduceat(z, first) - np.minimum.reduceat(z, first) <= SURFACE_STEP_M
        z_model[owner[first[level]]] = z[first[level]]
    ok = np.isfinite(z_model)
    n = int(ok.sum())
    if n < NADIR_MIN_POINTS:
        return replace(untested, n_points=n)
    k = np.sort((up_baro_m - (z_model[ok] - c[2])) / (-near[ok, 2]))
    half = 3.0 * math.sqrt(n * 0.25 * 0.75)
    low = k[max(int(math.floor(0.25 * n - half)), 0)]
    high = k[min(int(math.ceil(0.75 * n + half)), n - 1)]
    return ScaleCheck(float(np.median(k)), float(low), float(high), n, tolerance)


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


def _jit(fn):
    """numba.njit (nogil) with numba's on-disk cache; without it where numba finds no writable cache
    directory (a read-only install run without NUMBA_CACHE_DIR or a home: numba refuses to import
    such a function), and then compile_kernels compiles at every start."""
    try:
        return numba.njit(cache=True, nogil=True)(fn)
    except RuntimeError as e:
        log.warning("%s; compiling it at every start (set NUMBA_CACHE_DIR to a writable directory)", e)
        return numba.njit(nogil=True)(fn)


def compile_kernels() -> None:
    """Compile the ICP's numba kernels for the argument types _icp passes them (or load them from
    numba's on-disk cache: ``__pycache__`` beside this file, else NUMBA_CACHE_DIR / the user's cache
    directory), so that the first registration does not pay for it: 8.5 s on the 2-core x86 VM
    the first time, 0.3 s from the cache. Later calls cost microseconds."""
    p = np.zeros((8, 3))
    _gauss_newton_step(p, np.zeros(8, np.uint32), p, p, np.zeros(3), 1.0, np.eye(3), np.zeros(3), 1.0, 1.0)
    _nearest_among(p, np.zeros((8, NN_CANDIDATES), np.uint32), p, np.zeros(8), p, 1.0)


def _icp(src: np.ndarray, crop: _Crop, c: np.ndarray, T0: Sim3, cfg: AlignmentConfig, min_corr_m: float) -> Sim3:
    """Scale-aware point-to-plane ICP (Gauss–Newton, Tukey IRLS) over [rot, trans, log-scale] in
    coordinates centred at c, from T0.

    Each iteration: the correspondences (nearest model points within the level's distance: _nearest,
    which searches the KD-tree only for points that moved too far from their last search), then one Gauss–Newton step of
    digital-twin Eq. 2 with the Jacobian rows A_j of Eq. 9 extended by the scale column n_j·a_j. A level ends when a step moves
    no cloud point more than ICP_STEP_TOL_M (10× below the σ floor).

    The two coarse levels (max_correspondence_m, /2) run on every COARSE_LEVEL_STRIDE-th source
    point and the last level on all of them, so where a registration settles is decided by the
    whole cloud. The KD-tree queries are most of a registration's cost and each level usually runs
    all its iterations: this saves about a third of them. After a step that moved no cloud point
    more than CORR_REUSE_STEP_M (a tenth of the model's 1 m voxel spacing, so a nearest model
    point seldom changes), the next step is solved on the same correspondences instead of a new
    query (two Gauss–Newton steps per query, as ICP variants with inner iterations do); a level
    ends on a converged step only when its correspondences were fresh (docs/BENCHMARKS.md,
    "Fine-tuning cost"). Each step (_gauss_newton_step) is compiled."""
    # contiguous float64 throughout: the argument types compile_kernels compiled for
    s, R, t, c = float(T0.scale), np.ascontiguousarray(T0.R, float), np.ascontiguousarray(T0.t, float), np.ascontiguousarray(c, float)
    reach_m = float(np.max(np.linalg.norm(src, axis=1))) if len(src) else 0.0
    for level in range(3):
        max_d = max(cfg.max_correspondence_m / 2**level, min_corr_m)
        k = max(cfg.robust_kernel_m, KERNEL_FRACTION * max_d)
        pts = np.ascontiguousarray(src if level == 2 else src[::COARSE_LEVEL_STRIDE], float)
        if level != 1:
            cand = None  # level 1 runs on level 0's points: their candidates carry over
        j, step_m, fresh = None, math.inf, True
        for _ in range(ICP_ITERATIONS_PER_LEVEL):
            fresh = j is None or step_m >= CORR_REUSE_STEP_M or not fresh
            if fresh:
                j, cand = _nearest(crop, s * pts @ R.T + (t + c), max_d, cand)
            ok, s, R, t, step_m = _gauss_newton_step(pts, j, crop.points, crop.normals, c, s, R, t, k, reach_m)
            if not ok:
                break
            if step_m < ICP_STEP_TOL_M and fresh:
                break
    return Sim3(s, R, t)


@dataclass
class _Candidates:
    """Each query point's NN_CANDIDATES nearest model points when it was last searched for (crop
    indices, nearest first; len(model) where fewer were within the bound), where it was then
    (anchor) and how far that search is known to be complete (radius: the last candidate's
    distance, or the search bound where fewer were found)."""

    idx: np.ndarray      # (N, K) uint32
    anchor: np.ndarray   # (N, 3) query positions, crop ENU [m]
    radius_m: np.ndarray  # (N,)


def _search(crop: _Crop, q: np.ndarray, bound_m: float, max_d: float) -> tuple[np.ndarray, _Candidates]:
    """(nearest crop point within max_d of each q, len(model) for none; the candidates within
    bound_m ≥ max_d): one KD-tree query."""
    d, i = crop.tree.query(q, k=NN_CANDIDATES, distance_upper_bound=bound_m)
    j = np.where(d[:, 0] < max_d, i[:, 0], len(crop.points)).astype(np.uint32)
    return j, _Candidates(i, q.copy(), np.where(np.isfinite(d[:, -1]), d[:, -1], bound_m))


def _nearest(crop: _Crop, q: np.ndarray, max_d: float, cand: _Candidates | None) -> tuple[np.ndarray, _Candidates]:
    """Index of the nearest crop point within max_d of each query point q (len(model): none), as
    one KD-tree query with that bound gives it, and the candidates it came from.

    Exact without a search for a point that moved δ from where its candidates were searched for:
    every model point not among them lay ≥ radius from there, so ≥ radius − δ from here (triangle
    inequality); where the nearest candidate is closer than that, it is the nearest point; where
    radius − δ ≥ max_d and no candidate is within max_d, no point is. The other points are searched
    again (pykdtree, NN_CANDIDATES nearest within max_d + NN_SEARCH_MARGIN_M: the margin lets a
    point with no model point in reach keep that answer while it moves less than the margin).
    Measured on 28 journaled registrations: identical alignments, 15 % of the points searched
    per step, registration CPU ×0.75 (docs/BENCHMARKS.md, "Fine-tuning cost"). Written here, not
    taken from a library: KD-tree libraries answer each query from scratch."""
    bound_m = max_d + NN_SEARCH_MARGIN_M
    if cand is None:
        return _search(crop, q, bound_m, max_d)
    j, stale = _nearest_among(q, cand.idx, cand.anchor, cand.radius_m, crop.points, max_d)
    if stale.any():
        k = np.flatnonzero(stale)
        j[k], again = _search(crop, q[k], bound_m, max_d)
        cand.idx[k], cand.anchor[k], cand.radius_m[k] = again.idx, again.anchor, again.radius_m
    return j, cand


@_jit
def _nearest_among(q: np.ndarray, idx: np.ndarray, anchor: np.ndarray, radius_m: np.ndarray,
                   model_points: np.ndarray, max_d: float) -> tuple[np.ndarray, np.ndarray]:
    """(j, stale) of _nearest: j the nearest candidate within max_d where the candidates decide it
    (len(model) for none), stale where they do not."""
    n_model = model_points.shape[0]
    j = np.full(q.shape[0], n_model, np.uint32)
    stale = np.zeros(q.shape[0], np.bool_)
    for i in range(q.shape[0]):
        moved = math.sqrt((q[i, 0] - anchor[i, 0]) ** 2 + (q[i, 1] - anchor[i, 1]) ** 2 + (q[i, 2] - anchor[i, 2]) ** 2)
        outside_m = radius_m[i] - moved  # no model point outside the candidates is closer than this
        best, arg = math.inf, n_model
        for k in range(idx.shape[1]):
            m = idx[i, k]
            if m >= n_model:
                break
            d = math.sqrt((model_points[m, 0] - q[i, 0]) ** 2 + (model_points[m, 1] - q[i, 1]) ** 2
                          + (model_points[m, 2] - q[i, 2]) ** 2)
            if d < best:
                best, arg = d, m
        if best < outside_m:
            if best < max_d:
                j[i] = arg
        elif outside_m < max_d:
            stale[i] = True
    return j, stale


@_jit
def _gauss_newton_step(p: np.ndarray, j: np.ndarray, model_points: np.ndarray, model_normals: np.ndarray,
                       c: np.ndarray, s: float, R: np.ndarray, t: np.ndarray, kernel_m: float,
                       reach_m: float) -> tuple[bool, float, np.ndarray, np.ndarray, float]:
    """One Gauss–Newton step of _icp on the correspondences j: (ok, s, R, t, step_m) after
    T ← δ ∘ T with δ = −(H + εI)⁻¹ g over [rot, trans, log-scale] (ε = 10⁻⁶ · trace(H)/7, a
    Levenberg-style guard), and step_m a bound on how far the step moved any point within reach_m
    of the centre. ok is False (T unchanged) with fewer than 7 matched points or a singular H."""
    H, g, matched = _normal_equations(p, j, model_points, model_normals, c, s, R, t, kernel_m)
    if matched < 7:
        return False, s, R, t, 0.0
    A = H + 1e-6 * np.trace(H) / 7 * np.eye(7)
    try:
        delta = -np.linalg.solve(A, g)
    except Exception:  # numba raises LinAlgError for a singular matrix
        return False, s, R, t, 0.0
    sd = math.exp(delta[6])
    Rd = _rotvec_matrix(delta[:3])
    R_new = Rd @ R
    t_new = sd * (Rd @ t) + delta[3:6]
    s_new = sd * s
    step_m = (math.sqrt(delta[3] ** 2 + delta[4] ** 2 + delta[5] ** 2)
              + (math.sqrt(delta[0] ** 2 + delta[1] ** 2 + delta[2] ** 2) + abs(delta[6])) * s_new * reach_m)
    return True, s_new, R_new, t_new, step_m


@_jit
def _normal_equations(p: np.ndarray, j: np.ndarray, model_points: np.ndarray, model_normals: np.ndarray,
                      c: np.ndarray, s: float, R: np.ndarray, t: np.ndarray,
                      kernel_m: float) -> tuple[np.ndarray, np.ndarray, int]:
    """(H, g, matched) of one Gauss–Newton step of digital-twin Eq. 2 with Tukey IRLS weights:
    H = Σ w_i J_iᵀ J_i, g = Σ w_i J_iᵀ r_i over the source points p_i whose nearest model point j_i
    exists (pykdtree gives j_i = len(model) for none within its bound), with x_i = s·R·p_i + t,
    r_i = n·(x_i − (b − c)) and the rows J_i of _jacobian; ``matched`` counts those points, weighted
    or not. w_i = (1 − (r_i/kernel_m)²)² inside the kernel, 0 outside.

    Compiled with numba: the same sums in numpy took about 40 % of a registration's CPU as a dozen
    array passes of ~1000 rows each (per-call overhead, not arithmetic); one loop over the points
    does them in a single pass (docs/BENCHMARKS.md, "Fine-tuning cost")."""
    H = np.zeros((7, 7))
    g = np.zeros(7)
    J = np.empty(7)
    n_model = model_points.shape[0]
    matched = 0
    for i in range(p.shape[0]):
        m = j[i]
        if m >= n_model:
            continue
        matched += 1
        x0 = s * (R[0, 0] * p[i, 0] + R[0, 1] * p[i, 1] + R[0, 2] * p[i, 2]) + t[0]
        x1 = s * (R[1, 0] * p[i, 0] + R[1, 1] * p[i, 1] + R[1, 2] * p[i, 2]) + t[1]
        x2 = s * (R[2, 0] * p[i, 0] + R[2, 1] * p[i, 1] + R[2, 2] * p[i, 2]) + t[2]
        n0, n1, n2 = model_normals[m, 0], model_normals[m, 1], model_normals[m, 2]
        r = (n0 * (x0 - (model_points[m, 0] - c[0])) + n1 * (x1 - (model_points[m, 1] - c[1]))
             + n2 * (x2 - (model_points[m, 2] - c[2])))
        if abs(r) >= kernel_m:
            continue
        u = r / kernel_m
        w = (1.0 - u * u) ** 2
        J[0] = x1 * n2 - x2 * n1
        J[1] = x2 * n0 - x0 * n2
        J[2] = x0 * n1 - x1 * n0
        J[3], J[4], J[5] = n0, n1, n2
        J[6] = n0 * x0 + n1 * x1 + n2 * x2
        for a in range(7):
            wa = w * J[a]
            g[a] += wa * r
            for b in range(a, 7):
                H[a, b] += wa * J[b]
    for a in range(7):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g, matched


def _evaluate(src: np.ndarray, crop: _Crop, c: np.ndarray, T: Sim3, cfg: AlignmentConfig, min_corr_m: float) -> _Icp:
    """Final inliers, RMSE, robust scale and the Hessian of Eq. 8–9 (unweighted, inliers only) at T."""
    max_d = max(cfg.max_correspondence_m / 4, min_corr_m)
    x, n, r = _matches(src, crop, c, T.scale, T.R, T.t, max_d)
    inl = np.abs(r) < cfg.inlier_distance_m
    fitness = float(inl.sum()) / len(src)
    rmse = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("inf")
    mad = float(1.4826 * np.median(np.abs(r - np.median(r)))) if len(r) else float("inf")
    J = _jacobian(x[inl], n[inl])
    cen = x[inl].mean(axis=0) if inl.any() else np.zeros(3)
    return _Icp(T, fitness, rmse, J.T @ J, int(inl.sum()), cen, mad)


def _matches(src: np.ndarray, crop: _Crop, c: np.ndarray, s: float, R: np.ndarray, t: np.ndarray,
             max_d: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Moved source points x = s·R·p + t (centred at c) whose nearest model point lies within
    max_d, the model normals n there and the point-to-plane residuals r of digital-twin Eq. 2."""
    p, n, b = _correspondences(src, crop, c, s, R, t, max_d)
    x, r = _residuals(p, n, b, s, R, t)
    return x, n, r


def _correspondences(src: np.ndarray, crop: _Crop, c: np.ndarray, s: float, R: np.ndarray, t: np.ndarray,
                     max_d: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(source points p, model normals n, model points b centred at c): the points whose moved
    position s·R·p + t (centred at c) has its nearest model point b within max_d (one KD-tree query)."""
    d, j = crop.tree.query(s * src @ R.T + t + c, distance_upper_bound=max_d)
    ok = np.isfinite(d)
    j = j[ok]
    return src[ok], crop.normals[j], crop.points[j] - c


def _residuals(p: np.ndarray, n: np.ndarray, b: np.ndarray, s: float, R: np.ndarray,
               t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x = s·R·p + t, r = n·(x − b)): moved points and their point-to-plane residuals (Eq. 2)."""
    x = s * p @ R.T + t
    return x, np.einsum("ij,ij->i", n, x - b)


def _jacobian(x: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Rows [ (x × n)ᵀ, nᵀ, n·x ] over [rot, trans, log-scale]: Eq. 9's A_j (sign folded into the
    step) extended by the scale column. Cross product written out (np.cross costs more than the
    arithmetic at these sizes)."""
    J = np.empty((len(x), 7))
    J[:, 0] = x[:, 1] * n[:, 2] - x[:, 2] * n[:, 1]
    J[:, 1] = x[:, 2] * n[:, 0] - x[:, 0] * n[:, 2]
    J[:, 2] = x[:, 0] * n[:, 1] - x[:, 1] * n[:, 0]
    J[:, 3:6] = n
    J[:, 6] = np.einsum("ij,ij->i", n, x)
    return J


@_jit
def _rotvec_matrix(w: np.ndarray) -> np.ndarray:
    """Rodrigues: exp([w]×) = I + sin θ K + (1 − cos θ) K², K = [w/θ]×, θ = |w|."""
    theta = math.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2)
    if theta < 1e-12:
        return np.eye(3) + np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    u = w / theta
    K = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    return np.eye(3) + math.sin(theta) * K + (1.0 - math.cos(theta)) * (K @ K)


def _in_square(p_enu: np.ndarray, c_enu: np.ndarray, half_m: float) -> np.ndarray:
    """(N,) bool: points within ``half_m`` of ``c_enu`` in east and in north (a crop square)."""
    return np.all(np.abs(p_enu[:, :2] - c_enu[:2]) <= half_m, axis=1)


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


def _voxel_global(p: np.ndarray, n: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean point and unit mean normal per voxel of the global grid (edges at multiples of voxel_m,
    so a crop made of whole tiles voxelises every tile the same way); voxels whose normals cancel
    (|mean| ≤ 0.5: both faces of a thin wall) are dropped. Sorted by voxel (deterministic order)."""
    if len(p) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    v = np.floor(p / voxel_m).astype(np.int64)
    v -= v.min(axis=0)
    span = v.max(axis=0) + 1
    key = (v[:, 0] * span[1] + v[:, 1]) * span[2] + v[:, 2]
    _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    mean = lambda a: np.stack([np.bincount(inv, a[:, k], len(counts)) for k in range(3)], 1) / counts[:, None]  # noqa: E731
    pts, nrm = mean(p), mean(n)
    norm = np.linalg.norm(nrm, axis=1)
    keep = norm > 0.5
    return pts[keep], nrm[keep] / norm[keep, None]


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
