"""The scale-aware point-to-plane ICP of the fine-tuner (gis.align.fine): correspondences, the
compiled Gauss–Newton step, and the final evaluation (inliers, RMSE, Hessian).

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
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numba
import numpy as np

from gis.align.crop import _Crop
from gis.config import AlignmentConfig
from gis.sim3 import Sim3

log = logging.getLogger(__name__)


ICP_ITERATIONS_PER_LEVEL = 12
KERNEL_FRACTION = 0.5          # Tukey width per level = max(robust_kernel_m, this × correspondence distance)
ICP_STEP_TOL_M = 0.005         # a level has converged when a Gauss–Newton step moves no cloud point more than this
COARSE_LEVEL_STRIDE = 2        # the two coarse ICP levels on every 2nd source point, the last on all (_icp)
CORR_REUSE_STEP_M = 0.1        # after an ICP step that moved no point more than this, the next step keeps its correspondences (_icp)
NN_CANDIDATES = 6              # nearest model points kept per SLAM point between searches (_nearest) ...
NN_SEARCH_MARGIN_M = 0.5       # ... searched for this far beyond the correspondence distance


@dataclass(frozen=True)
class _Icp:
    T: Sim3                   # increment in centred ENU coordinates
    fitness: float
    rmse_m: float             # inlier RMSE (|r| < inlier_distance_m)
    H7: np.ndarray            # 7x7 Gauss–Newton Hessian [rot, trans, log-scale] at the crop centre (inliers)
    n_inliers: int
    centroid: np.ndarray      # inlier centroid, centred coordinates (lever arm of the systematic tilt)
    sigma_mad_m: float        # 1.4826·MAD of all matched residuals (not truncated at the inlier distance)


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
