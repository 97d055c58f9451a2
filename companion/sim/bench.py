"""Rendering benchmark: frames/s of the ray-cast renderer at 640×480 along a real flight.

    python -m companion.sim.bench [--frames N] [--scenario NAME]

Prints world build time, renderer set-up time, and per-frame render time (mean, P50, P95) and
frames/s, plus the split between the ray cast (open3d/Embree) and shading.
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--scenario", default="nominal")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    from companion.sim import make_scenario

    t0 = time.perf_counter()
    sc = make_scenario(a.scenario, seed=a.seed)
    mesh = sc.world.mesh
    t_world = time.perf_counter() - t0
    t0 = time.perf_counter()
    r = sc.renderer
    t_setup = time.perf_counter() - t0
    idx = np.linspace(0, sc.n_frames - 1, a.frames).astype(int)
    sc.render(int(idx[0]))  # warm-up
    dt, dcast = [], []
    for i in idx:
        t0 = time.perf_counter()
        r.cast(sc.truth.T_enu_cam[i])
        dcast.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        sc.render(int(i))
        dt.append(time.perf_counter() - t0)
    dt, dcast = np.array(dt) * 1e3, np.array(dcast) * 1e3
    res = {"scenario": a.scenario, "width_px": sc.camera.width_px, "height_px": sc.camera.height_px,
           "triangles": int(len(mesh.triangles)), "world_build_s": t_world, "renderer_setup_s": t_setup,
           "render_ms_mean": float(dt.mean()), "render_ms_p50": float(np.percentile(dt, 50)),
           "render_ms_p95": float(np.percentile(dt, 95)), "cast_ms_mean": float(dcast.mean()),
           "fps": float(1e3 / dt.mean())}
    print(f"sim render bench: scenario={a.scenario} {sc.camera.width_px}x{sc.camera.height_px}, "
          f"{res['triangles']} triangles, {a.frames} frames along the flight")
    print(f"  world build {t_world:.2f} s, renderer set-up {t_setup:.2f} s")
    print(f"  render: mean {res['render_ms_mean']:.1f} ms, P50 {res['render_ms_p50']:.1f} ms, "
          f"P95 {res['render_ms_p95']:.1f} ms  →  {res['fps']:.1f} frames/s")
    print(f"  of which ray cast: mean {res['cast_ms_mean']:.1f} ms")
    return res


if __name__ == "__main__":
    main()
