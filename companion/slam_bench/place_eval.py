"""Timing and recognition figures of slam.place (printed, not asserted: see docs/BENCHMARKS.md).

    python -m companion.slam_bench.place_eval bench     # add / query time against 100, 600, 2000 entries
    python -m companion.slam_bench.place_eval recall    # top-1 precision / recall on the `loop` flight's revisits

``--index FILE`` evaluates the PlaceIndex class of another place.py (e.g. an older version from
``git show REV:slam/place.py``) on the same data, for before/after figures.
"""
from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from slam.features import make_orb_cpu
from slam.types import CameraModel


def load_index_class(path: Path | None):
    if path is None:
        from slam.place import PlaceIndex

        return PlaceIndex
    spec = importlib.util.spec_from_file_location("place_under_test", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod.PlaceIndex


def value(c) -> float:
    """A candidate's score (this version) or vote count (the brute-force matcher before it)."""
    return float(getattr(c, "score", getattr(c, "votes", 0)))


def photo_views(n: int, n_features: int = 1000, seed: int = 1) -> list[np.ndarray]:
    """ORB descriptors of n random views of scikit-image photos (bundled, nothing rendered)."""
    import cv2
    import skimage.data

    from companion.slam_bench.vocab_train import H_PX, W_PX, random_view

    names = ("astronaut", "camera", "coffee", "rocket", "coins", "moon", "text", "brick", "grass", "chelsea")
    rng = np.random.default_rng(seed)
    extract = make_orb_cpu(CameraModel(W_PX, H_PX, np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])), n_features)
    out = []
    for j in range(n):
        img = getattr(skimage.data, names[j % len(names)])()
        gray = img if img.ndim == 2 else cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
        out.append(extract(random_view(gray, rng)).desc)
    return out


def bench(index_class, sizes=(100, 600, 2000), queries: int = 5, distinct: int = 200) -> None:
    """Entries beyond ``distinct`` images repeat them under new ids (every word then has more
    postings than distinct keyframes would give it: a pessimistic case for the inverted file)."""
    descs = photo_views(distinct + queries)
    print(f"{distinct} distinct images (skimage photo views, ~1000 ORB each), entries beyond repeat them")
    for n in sizes:
        idx = index_class()
        t0 = time.perf_counter()
        for k in range(n):
            idx.add(k, descs[k % distinct])
        add_ms = (time.perf_counter() - t0) / n * 1e3
        q_ms = []
        for j in range(queries):
            t0 = time.perf_counter()
            idx.query(descs[distinct + j], exclude_after_kf_id=n - 30)
            q_ms.append((time.perf_counter() - t0) * 1e3)
        held_mib = idx.nbytes() / 2**20
        t0 = time.perf_counter()
        for k in range(queries):  # one at a time, as local mapping forgets a keyframe per new one
            idx.remove([k])
        rm_ms = (time.perf_counter() - t0) / queries * 1e3
        print(f"{n:5d} entries: add {add_ms:7.2f} ms (mean over 0..{n})  query {statistics.median(q_ms):8.2f} ms "
              f"(median of {queries}, {min(q_ms):.2f}-{max(q_ms):.2f})  remove one {rm_ms:6.2f} ms  "
              f"held {held_mib:.1f} MiB", flush=True)


def loop_flight(step_s: float, cache: Path | None) -> dict:
    """Descriptors, times, camera centres and optical axes of the `loop` flight (seed 0, a world the
    vocabulary never saw) every step_s."""
    if cache is not None and cache.exists():
        with np.load(cache) as z:
            return {k: z[k] for k in z.files}
    from companion.sim.scenario import make_scenario

    sc = make_scenario("loop", seed=0)
    extract = make_orb_cpu(sc.camera, 1000)
    frames = np.arange(0, sc.n_frames, int(round(step_s * sc.fps)))
    descs = [extract(sc.render(int(i)).image_bgr).desc for i in frames]
    T = sc.truth.T_enu_cam[frames]
    out = dict(desc=np.concatenate(descs), n_desc=np.array([len(d) for d in descs]), t_s=sc.truth.t_s[frames],
               c_m=T[:, :3, 3], axis=T[:, :3, 2], lap_s=np.array(sc.trajectory.duration_s / sc.spec.flight.laps))
    if cache is not None:
        np.savez(cache, **out)
    return out


def ground_point(c_m: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Where the optical axis meets the plane z = 0 (the world's ground is near it)."""
    return c_m - axis * (c_m[:, 2:3] / axis[:, 2:3])


def recall(index_class, step_s: float = 1.5, same_place_m: float = 20.0, same_heading_deg: float = 30.0,
           elsewhere_m: float = 80.0, cache: Path | None = None, thresholds=()) -> None:
    """Index the first lap; query every later frame. A frame's true places: first-lap frames whose
    optical axes hit the ground within same_place_m and point within same_heading_deg; its
    elsewhere: those whose axes hit the ground over elsewhere_m away. Prints, at thresholds on the
    candidate's score (votes before): recall (top-1 a true place at or above it), and false alarms
    (queries whose best elsewhere frame reaches it: a wrong loop candidate for Sim(3) checks)."""
    f = loop_flight(step_s, cache)
    descs = np.split(f["desc"], np.cumsum(f["n_desc"])[:-1])
    db = np.flatnonzero(f["t_s"] < f["lap_s"])
    qs = np.flatnonzero(f["t_s"] >= f["lap_s"])
    g = ground_point(f["c_m"], f["axis"])
    idx = index_class()
    for i in db:
        idx.add(int(i), descs[i])
    q_ms, tops, truth, best_elsewhere = [], [], [], []
    for q in qs:
        dist_m = np.linalg.norm(g[db] - g[q], axis=1)
        aligned = f["axis"][db] @ f["axis"][q] > np.cos(np.deg2rad(same_heading_deg))
        truth.append(set(db[(dist_m < same_place_m) & aligned].tolist()))
        elsewhere = set(db[dist_m > elsewhere_m].tolist())
        t0 = time.perf_counter()
        top = idx.query(descs[q], top=1)
        q_ms.append((time.perf_counter() - t0) * 1e3)
        tops.append((top[0].kf_id, value(top[0])) if top else (-1, 0.0))
        ranked = idx.query(descs[q], top=len(db))
        best_elsewhere.append(max([value(c) for c in ranked if c.kf_id in elsewhere], default=0.0))
    revisits = sum(1 for t in truth if t)
    print(f"{len(db)} first-lap frames indexed, {len(qs)} later frames queried ({revisits} have a true place), "
          f"query median {statistics.median(q_ms):.1f} ms")
    vals, wrong = np.array([v for _, v in tops]), np.array(best_elsewhere)
    hit = np.array([k in t for (k, _), t in zip(tops, truth)])
    print(f"top-1 a true place (no threshold): {hit.sum()}/{revisits} revisits; top-1 score of those: "
          f"median {np.median(vals[hit]):.3f}; best elsewhere ({elsewhere_m:.0f} m+) per query: median {np.median(wrong):.3f}, "
          f"max {wrong.max():.3f}")
    for th in sorted(set(np.quantile(vals[hit], [0.1, 0.5]).tolist()) | {float(wrong.max())} | set(thresholds)):
        print(f"  threshold {th:8.3f}: recall {(hit & (vals >= th)).sum() / max(revisits, 1):.2f}, "
              f"false alarms {(wrong >= th).mean():.2f} of queries")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("bench", "recall"))
    ap.add_argument("--index", type=Path, help="place.py whose PlaceIndex to evaluate (default: this one)")
    ap.add_argument("--cache", type=Path, help="recall: rendered flight's descriptors, reused by later runs (npz)")
    ap.add_argument("--threshold", type=float, action="append", help="recall: also report at this threshold")
    a = ap.parse_args(argv)
    cls = load_index_class(a.index)
    if a.what == "bench":
        bench(cls)
    else:
        recall(cls, cache=a.cache, thresholds=a.threshold or ())


if __name__ == "__main__":
    main()
