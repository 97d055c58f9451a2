"""Alignment benchmarks: `python -m gis.bench` prints the figures; the functions are reusable.

- ``alignment_errors``: T_rough (TerraSLAM §4.3) and T_fine (§4.4) error as the mean
  point-to-model distance of the aligned SLAM cloud (TerraSLAM Table 4) and as true error.
- ``finetune_timing`` / ``size_sweep``: wall time of one fine-tuning registration on the pipeline's
  path (prior-aware, cold and reused crop), and its ratio between a 1 km² and a 100 km² GIS model
  (the fixed-size crop keeps it flat), the models mapped from a GIS cache as the service maps
  them, with the RAM they cost; ``track_timing``: registrations along a track, with the next
  registration's crop built ahead in the worker's idle time (FineTuner.prefetch_crop) or not.
- ``replay_flight``: Globalizer error against truth along a flight, with SLAM stood in for by
  truth in a scaled/rotated frame plus random-walk drift (no images, no real SLAM: it measures
  the alignment + globalization chain only), fine-tuning every N frames, and the integrity
  figure (fraction of fixes whose horizontal error exceeds 3× their reported h_acc).

The default world is the procedural box city (gis.synthetic); the project benchmark passes the
simulator's exported GIS model and world instead (gis/ must not import companion/).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from gis.align.fine import FineTuner, enu_sim3
from gis.align.rough import alignment_error_m, rough_align
from gis.cache import GisCache
from gis.config import AlignmentConfig
from gis.geodesy import LocalFrame
from gis.globalizer import Globalizer
from gis.model import GisModel
from gis.sim3 import Sim3, compose
from gis.synthetic import box_city_model, slam_like_cloud
from gis.types import Alignment, AlignmentSource
from slam.types import SlamPose, TrackingState

ORIGIN = LocalFrame(47.3769, 8.5417, 450.0)
#: the stand-in SLAM frame: arbitrary rotation, monocular scale, offset (ENU ← SLAM)
T_ENU_SLAM = Sim3(3.7, Rotation.from_euler("zyx", [40, 5, -3], degrees=True).as_matrix(), np.array([30.0, 20.0, 5.0]))

Observe = Callable[[np.ndarray, int, int, float], np.ndarray]  # (center_enu, n, seed, radius) → points_enu


def _observe_model(model: GisModel, noise_m: float) -> Observe:
    return lambda c, n, seed, radius: slam_like_cloud(model, c, radius, n, noise_m, seed)


@dataclass(frozen=True)
class AlignmentFigures:
    rough_error_m: float        # mean point-to-model distance after T_rough (Table 4)
    rough_true_error_m: float   # mean distance to the true positions
    corners_true_error_m: float  # T_rough from corners only (the paper's §4.3, no ICP polish)
    fine_error_m: float
    fine_true_error_m: float
    fine_ms: float


def alignment_errors(model: GisModel, observe: Observe, center_enu: np.ndarray, seed: int = 0,
                     config: AlignmentConfig | None = None) -> AlignmentFigures:
    """Rough alignment from a dense survey cloud, then fine-tuning from a sparse SLAM-like cloud."""
    T_ecef_slam = compose(enu_sim3(model.origin), T_ENU_SLAM)
    dense = observe(center_enu, 30000, seed, 100.0)
    dense_slam = T_ENU_SLAM.inverse().apply(dense)
    rough = rough_align(dense_slam, model, center_enu + np.array([30.0, -30.0, 0.0]))
    corners = rough_align(dense_slam, model, center_enu + np.array([30.0, -30.0, 0.0]), refine=False)
    T_enu_ecef = enu_sim3(model.origin).inverse()
    sparse_enu = observe(center_enu, 3000, seed + 1, 60.0)
    sparse = T_ENU_SLAM.inverse().apply(sparse_enu)
    a0 = Alignment(rough.T_ecef_slam, AlignmentSource.ROUGH, 0.0, 0, np.eye(6), 1.0)
    reg = FineTuner(model, config).register(sparse, a0, 0.0, 0)
    if reg.alignment is None:
        raise RuntimeError(f"fine-tuning rejected: {reg.reason}")
    fine = reg.alignment.T_ecef_slam
    true = lambda T, p: float(np.mean(np.linalg.norm(T.apply(p) - T_ecef_slam.apply(p), axis=1)))  # noqa: E731
    return AlignmentFigures(
        rough.error_m, true(rough.T_ecef_slam, sparse), true(corners.T_ecef_slam, sparse),
        alignment_error_m(compose(T_enu_ecef, fine).apply(sparse), model), true(fine, sparse), reg.wall_ms,
    )


def _initial(model: GisModel, c_enu: np.ndarray) -> Alignment:
    """A T_rough-quality guess: 1 % scale, 0.5° and 0.4 m off about c_enu (about 0.5–1 m within 60 m)."""
    dT = Sim3(1.01, Rotation.from_euler("zyx", [0.5, 0.2, 0.1], degrees=True).as_matrix(), np.array([0.3, -0.2, 0.1]))
    T_c = Sim3(1.0, np.eye(3), np.asarray(c_enu, float))
    T = compose(compose(T_c, compose(dT, T_c.inverse())), T_ENU_SLAM)
    return Alignment(compose(enu_sim3(model.origin), T), AlignmentSource.ROUGH, 0.0, 0, np.eye(6), 1.0)


def _gnss_like_prior(model: GisModel, c_enu: np.ndarray, cam_enu: np.ndarray) -> Alignment:
    """_initial's guess with the information a GNSS bootstrap reports (1.5 m, 0.5°, 1 % scale),
    centred on the camera: the prior-aware 5-DoF path the pipeline runs."""
    info = np.diag(np.r_[np.full(3, np.radians(0.5) ** -2), np.full(3, 1.5**-2)])
    a = _initial(model, c_enu)
    return Alignment(a.T_ecef_slam, AlignmentSource.GNSS, 0.0, 0, info, 1.5,
                     center_slam=compose(enu_sim3(model.origin).inverse(), a.T_ecef_slam).inverse().apply(cam_enu),
                     scale_sigma=0.01)


def _timed_registration(tuner: FineTuner, model: GisModel, c_ground_enu: np.ndarray, seed: int) -> float:
    """Wall time (ms) of one FineTuner.register as the pipeline calls it: 3000 SLAM-like points
    about c_ground_enu, a GNSS-like prior centred on the camera 60 m above it."""
    cam = c_ground_enu + np.array([0.0, 0.0, 60.0])
    p_slam = T_ENU_SLAM.inverse().apply(slam_like_cloud(model, c_ground_enu, 60, 3000, 0.05, seed))
    a0 = _gnss_like_prior(model, c_ground_enu, cam)
    t0 = time.perf_counter()
    tuner.register(p_slam, a0, 0.0, 0, center_slam=a0.center_slam)
    return 1e3 * (time.perf_counter() - t0)


def finetune_timing(model: GisModel, n_repeats: int = 15, seed: int = 0, step_m: float = 10.0) -> dict:
    """Wall time (ms) of FineTuner.register as the pipeline calls it (GNSS-like prior centred on the
    camera, 60 m above the ground; 3000 SLAM-like points) at n_repeats random places: at each, a
    first registration with a cold crop (new place: tiles voxelised, KD-tree built) and a second
    one step_m further on (the vehicle moved on; the crop is reused when it still covers it)."""
    tuner = FineTuner(model)
    rng = np.random.default_rng(seed)
    lo, hi = model.bounds_enu
    cold, warm = [], []
    for k in range(n_repeats):
        c0 = np.array([*rng.uniform(lo[:2] + 200, hi[:2] - 200), 0.0])
        for c, times in ((c0, cold), (c0 + np.array([step_m, 0.0, 0.0]), warm)):
            times.append(_timed_registration(tuner, model, c, seed + k))
    both = cold + warm
    return {"n_model_points": len(model), "median_ms": float(np.median(both)), "p90_ms": float(np.percentile(both, 90)),
            "cold_median_ms": float(np.median(cold)), "warm_median_ms": float(np.median(warm))}


def track_timing(model: GisModel, n_repeats: int = 15, seed: int = 0, step_m: float = 40.0) -> dict:
    """Wall time (ms) of registrations along a straight track, step_m apart (a registration every
    5 s at 8 m/s), at n_repeats random places, with the fine-tuning worker's idle step after each
    (FineTuner.prefetch_crop, timed apart): the second registration of a place moved out of its
    crop and builds a new one; after it the worker builds the third's ahead, so that one finds it."""
    tuner = FineTuner(model)
    rng = np.random.default_rng(seed)
    lo, hi = model.bounds_enu
    built, prefetched, ahead = [], [], []
    for k in range(n_repeats):
        c0 = np.array([*rng.uniform(lo[:2] + 250, hi[:2] - 250), 0.0])
        for i in range(3):
            n0 = tuner._crops.n_built
            ms = _timed_registration(tuner, model, c0 + np.array([i * step_m, 0.0, 0.0]), seed + 3 * k + i)
            if i == 1 and tuner._crops.n_built > n0:
                built.append(ms)
            elif i == 2 and tuner._crops.n_built == n0:
                prefetched.append(ms)
            t0 = time.perf_counter()
            if tuner.prefetch_crop():
                ahead.append(1e3 * (time.perf_counter() - t0))
    return {"n_places": n_repeats, "built_median_ms": float(np.median(built)) if built else float("nan"),
            "prefetched_median_ms": float(np.median(prefetched)) if prefetched else float("nan"),
            "n_prefetched": len(prefetched), "prefetch_median_ms": float(np.median(ahead)) if ahead else float("nan")}


def size_sweep(extents_m: tuple[float, ...] = (1000.0, 10000.0), spacing_m: float = 3.0) -> list[dict]:
    """finetune_timing on box cities of each extent (same density) as the service meets them:
    saved to a GIS cache, then mapped from it in a fresh process, whose anonymous memory after the
    registrations is reported too (``anon_mb``: what the model costs in RAM that the kernel cannot
    page out); ratio of the times to the first."""
    rows = []
    for e in extents_m:
        with tempfile.TemporaryDirectory() as d:
            GisCache(d).save_model(box_city_model(e, ORIGIN, seed=0, spacing_m=spacing_m), "sweep")
            out = subprocess.run([sys.executable, "-m", "gis.bench", "--mapped-timing", d], capture_output=True,
                                 text=True, check=True)
        rows.append({"area_km2": (e / 1000) ** 2, **json.loads(out.stdout.splitlines()[-1])})
    for r in rows:
        r["ratio"] = r["median_ms"] / rows[0]["median_ms"]
    return rows


def _mapped_timing(cache_dir: str) -> dict:
    """finetune_timing on the model of a cache's site ``sweep`` (memory-mapped), with this process's
    anonymous resident memory afterwards (Linux /proc; NaN elsewhere)."""
    r = finetune_timing(GisCache(cache_dir).load_model("sweep"))
    try:
        status = dict(line.split(":", 1) for line in Path("/proc/self/status").read_text().splitlines() if ":" in line)
        r["anon_mb"] = int(status["RssAnon"].split()[0]) / 1024
    except (OSError, KeyError, ValueError):
        r["anon_mb"] = float("nan")
    return r


@dataclass(frozen=True)
class FlightFigures:
    n_frames: int
    n_fixes: int
    mean_m: float
    p99_m: float
    integrity_fraction: float   # fixes with horizontal error > 3·h_acc
    n_accepted: int
    n_rejected: int


def replay_flight(model: GisModel, T_enu_cam: np.ndarray, observe: Observe, T_body_cam: np.ndarray,
                  every_n: int = 200, drift_m_per_frame: float = 0.002, noise_m: float = 0.02,
                  config: AlignmentConfig | None = None, seed: int = 0) -> FlightFigures:
    """Globalizer vs truth along T_enu_cam (K,4,4) with stand-in SLAM (see module doc)."""
    cfg = config or AlignmentConfig()
    rng = np.random.default_rng(seed)
    tuner = FineTuner(model, cfg)
    glob = Globalizer.from_config(T_body_cam, cfg)
    T_slam_enu = T_ENU_SLAM.inverse()
    alignment = _initial(model, T_enu_cam[0, :3, 3])
    walk = np.zeros(3)
    T_cam_body = np.linalg.inv(T_body_cam)
    errs, exceed, acc, rej = [], [], 0, 0
    for k, T in enumerate(T_enu_cam):
        walk = walk + rng.normal(0, drift_m_per_frame, 3)
        if k % every_n == 0:
            seen = observe(T[:3, 3], 2500, seed + k, 70.0)
            reg = tuner.register(T_slam_enu.apply(seen + walk), alignment, float(k), 0,
                                 center_slam=T_slam_enu.apply(T[:3, 3] + walk))
            if reg.alignment is not None:
                alignment, acc = reg.alignment, acc + 1
                glob.update_alignment(alignment)
            else:
                rej += 1
        T_slam_cam = np.eye(4)
        T_slam_cam[:3, :3] = T_slam_enu.R @ T[:3, :3]
        T_slam_cam[:3, 3] = T_slam_enu.apply(T[:3, 3] + walk + rng.normal(0, noise_m, 3))
        fix = glob.fix(SlamPose(k / 30, k, T_slam_cam, TrackingState.OK, 0))
        if fix is None:
            continue
        truth_ecef = model.origin.enu_to_ecef((T @ T_cam_body)[:3, 3])
        e_ned = LocalFrame(fix.lat_deg, fix.lon_deg, fix.h_ellipsoid_m).ecef_to_ned(truth_ecef)
        errs.append(float(np.linalg.norm(e_ned)))
        exceed.append(np.linalg.norm(e_ned[:2]) > 3 * fix.h_acc_m)
    errs = np.asarray(errs) if errs else np.array([np.nan])
    return FlightFigures(len(T_enu_cam), len(exceed), float(np.mean(errs)), float(np.percentile(errs, 99)),
                         float(np.mean(exceed)) if exceed else float("nan"), acc, rej)


def circle_flight(n: int, radius_m: float = 150.0, alt_m: float = 60.0, pitch_down_deg: float = 30.0) -> np.ndarray:
    """T_enu_cam (n,4,4) of a circular flight looking forward and down."""
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    out = np.tile(np.eye(4), (n, 1, 1))
    for i, t in enumerate(th):
        fwd = np.array([-np.sin(t), np.cos(t), 0.0])
        z = np.cos(np.radians(pitch_down_deg)) * fwd - np.array([0, 0, np.sin(np.radians(pitch_down_deg))])
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        out[i, :3, :3] = np.stack([x, np.cross(z, x), z], 1)
        out[i, :3, 3] = [radius_m * np.cos(t), radius_m * np.sin(t), alt_m]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sweep", default="1000,10000", help="box-city extents (m) for the map-size sweep")
    ap.add_argument("--sweep-spacing", type=float, default=3.0, help="sampling (m) of the sweep's models (memory: ~50 B/point)")
    ap.add_argument("--frames", type=int, default=1200, help="frames of the replayed flight")
    ap.add_argument("--mapped-timing", metavar="CACHE_DIR", help=argparse.SUPPRESS)  # size_sweep's child process
    args = ap.parse_args()
    if args.mapped_timing:
        print(json.dumps(_mapped_timing(args.mapped_timing)))
        return
    model = box_city_model(1000.0, ORIGIN, seed=0, spacing_m=1.0)
    obs = _observe_model(model, noise_m=0.05)
    a = alignment_errors(model, obs, np.array([20.0, -30.0, 0.0]))
    print(f"alignment error (mean point-to-model, Table 4): T_rough {a.rough_error_m:.3f} m (true {a.rough_true_error_m:.3f} m; "
          f"corners only, no ICP polish: true {a.corners_true_error_m:.3f} m), "
          f"T_fine {a.fine_error_m:.3f} m (true {a.fine_true_error_m:.3f} m), fine-tune {a.fine_ms:.1f} ms")
    r = finetune_timing(model)
    print(f"fine-tune on the 1 km² model at its default 1 m sampling ({r['n_model_points']} pts): "
          f"median {r['median_ms']:.1f} ms (cold crop {r['cold_median_ms']:.1f}, reused {r['warm_median_ms']:.1f}), P90 {r['p90_ms']:.1f} ms")
    r = track_timing(model)
    print(f"fine-tune along a track (40 m between registrations): the crop built in the registration "
          f"{r['built_median_ms']:.1f} ms, built ahead in the worker's idle time (in {r['prefetch_median_ms']:.1f} ms) "
          f"{r['prefetched_median_ms']:.1f} ms ({r['n_prefetched']} of {r['n_places']} places found it built)")
    T_body_cam = np.eye(4)
    T_body_cam[:3, :3] = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0.0]])
    for every in (200, 50):
        f = replay_flight(model, circle_flight(args.frames), obs, T_body_cam, every_n=every)
        print(f"replay (stand-in SLAM, fine-tune every {every} frames): {f.n_fixes}/{f.n_frames} fixes, mean {f.mean_m:.3f} m, "
              f"P99 {f.p99_m:.3f} m, integrity {100 * f.integrity_fraction:.2f} % beyond 3·h_acc, "
              f"registrations {f.n_accepted} accepted / {f.n_rejected} rejected")
    del model
    for r in size_sweep(tuple(float(x) for x in args.sweep.split(",")), args.sweep_spacing):
        print(f"fine-tune on a {r['area_km2']:.0f} km² model ({r['n_model_points']} pts) mapped from the GIS cache: median "
              f"{r['median_ms']:.1f} ms (cold crop {r['cold_median_ms']:.1f}, reused {r['warm_median_ms']:.1f}), P90 {r['p90_ms']:.1f} ms, "
              f"ratio {r['ratio']:.2f}; anonymous memory {r['anon_mb']:.0f} MB")


if __name__ == "__main__":
    main()
