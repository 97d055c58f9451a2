"""SLAM benchmark on the simulator's scenarios (issue 4 targets, TerraSLAM Fig. 14 ablation).

    python -m companion.slam_bench --scenario nominal --frames 600 [--ablation] [--force-loss 300:15]
    python -m companion.slam_bench --memory --minutes 10 [--fps 10] [--sample-every 300]
    python -m companion.slam_bench --scenario loop --frames 600 --camera-fps 10 --attitude-prior both --repeat 3
    python -m companion.slam_bench --frames 300 --export seq.npz --jpeg-quality 75   # then, on a board or GPU machine:
    python -m companion.slam_bench --sequence seq.npz --ablation --device cuda:0 [--features]

Prints per-frame tracking latency (wall and tracking-thread CPU, mean/P99), tracking ratio,
ATE after Sim(3) alignment as % of path length, local-mapping and loop-closing times, map size
and process memory. Frames are fed at the scenario's frame rate (real-time pacing) so the
background threads compete with tracking as they would in flight.

``--memory``: one lap of the scenario's loop is rendered once to --cache-dir (a child process, one
frame at a time read back from disk) and flown out and back for --minutes of flight time; every
--sample-every frames it prints RSS, the BA worker's RSS and the map's sizes, then the RSS slope
over the second half (MB per flight minute) and RSS(end) / RSS(at 2 min).
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

from companion.slam_bench.memory import memory_summary, render_lap, run_memory
from companion.slam_bench.runs import (
    ablation_configs,
    local_window_ms,
    loop_ablation,
    percentile,
    prior_row,
    report,
    run_sequence,
    time_features,
)
from companion.slam_bench.sequence import Sequence, load_sequence, render_sequence, save_sequence, start_frame
from slam.config import SlamConfig


def cli_config(a: argparse.Namespace) -> SlamConfig:
    """The SlamConfig of the command line: --backend, --device, then every --set KEY=VALUE."""
    overrides = dict(kv.split("=", 1) for kv in a.set)
    return SlamConfig(**{**SlamConfig().model_dump(), "feature_backend": a.backend, "torch_device": a.device, **overrides})


def memory_main(a: argparse.Namespace) -> None:
    t0 = time.perf_counter()
    lap = render_lap(a.scenario, a.seed, a.fps, a.cache_dir)
    print(f"lap of '{a.scenario}': {lap.n_frames} frames at {a.fps:g} fps, ready in {time.perf_counter() - t0:.0f} s "
          f"(cache {lap.root})", flush=True)
    if a.render_only:
        return
    cfg = cli_config(a)
    samples, run = run_memory(lap, cfg, a.minutes, a.sample_every, realtime=not a.no_realtime, lockstep=a.lockstep)
    f = memory_summary(samples)
    rmse, length, pct = run.ate()
    print(f"\nRSS MB: start {f['rss_start_mb']:.0f}, at 2 min {f['rss_2min_mb']:.0f}, end {f['rss_end_mb']:.0f}, "
          f"peak {f['rss_peak_mb']:.0f}; slope over the second half {f['slope_second_half_mb_per_min']:+.2f} MB/min; "
          f"RSS(end)/RSS(2 min) {f['ratio_end_to_2min']:.3f} over {f['flight_min']:.1f} min of flight")
    print(f"SLAM: tracked {100 * run.tracking_ratio:.1f} % of {len(run.states)} frames, resets {run.reset_counter}, "
          f"loops closed {len(run.loops)}, ATE after Sim(3) {rmse:.2f} m over {length:.0f} m = {pct:.2f} %; "
          f"config max_keyframes {cfg.max_keyframes}, loop_anchor_every {cfg.loop_anchor_every}, "
          f"max_loop_anchors {cfg.max_loop_anchors}, max_trajectory_keyframes {cfg.max_trajectory_keyframes}")
    print(f"  load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; {'real-time' if not a.no_realtime else 'as fast as possible'}"
          f"{', lockstep with local mapping' if a.lockstep else ''}; overrides {', '.join(a.set) or 'none'}")


def prior_main(seq: Sequence, base: SlamConfig, a: argparse.Namespace) -> None:
    """Without / with the attitude prior on the same frames, runs alternated so both see the same
    machine load; one line per run, then mean [min, max] per configuration."""
    modes = {"off": [False], "on": [True], "both": [False, True]}[a.attitude_prior]
    rows: dict[bool, list[dict]] = {m: [] for m in modes}
    for k in range(a.repeat):
        for use in modes:
            cfg = base.model_copy(update=dict(use_attitude_prior=use))
            r = run_sequence(seq, cfg, f"prior {'on' if use else 'off'} #{k + 1}", realtime=not a.no_realtime,
                             drop_late=a.drop_late, lockstep=a.lockstep)
            print(report(r), flush=True)
            rows[use].append(prior_row(r))
    keys = list(rows[modes[0]][0])
    pacing = "lockstep with local mapping" if a.lockstep else ("as fast as possible" if a.no_realtime else "real-time")
    print(f"\n{seq.name}, {len(seq.images)} frames at {seq.fps:g} fps ({pacing}), {a.repeat} run(s) each: mean [min, max]")
    print("| prior | " + " | ".join(keys) + " |\n|---|" + "---|" * len(keys))
    for use in modes:
        cells = []
        for key in keys:
            v = np.array([row[key] for row in rows[use]], float)
            cells.append(f"{np.nanmean(v):.3g} [{np.nanmin(v):.3g}, {np.nanmax(v):.3g}]" if np.isfinite(v).any() else "nan")
        print(f"| {'on' if use else 'off'} | " + " | ".join(cells) + " |")
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m companion.slam_bench", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", default="nominal")
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ablation", action="store_true", help="run baseline/+GA/+PLM/+RLC (Fig. 14)")
    ap.add_argument("--force-loss", default=None, help="FIRST:COUNT black frames to force a tracking loss")
    ap.add_argument("--no-ga", action="store_true", help="ablation without the torch (GA) step, for CPU-only machines")
    ap.add_argument("--loop-ablation", action="store_true", help="RLC vs full-loop correction on a constructed drifted revisit")
    ap.add_argument("--backend", choices=["cpu", "torch"], default="cpu")
    ap.add_argument("--device", default="cpu", help="torch device for the torch backend")
    ap.add_argument("--cache-dir", default=os.path.expanduser("~/.cache/terraslam/slam_bench"))
    ap.add_argument("--no-realtime", action="store_true", help="feed frames as fast as possible")
    ap.add_argument("--drop-late", action="store_true", help="skip frames tracking is too late for (live camera)")
    ap.add_argument("--memory", action="store_true", help="long out-and-back flight; RSS and map sizes every --sample-every frames")
    ap.add_argument("--minutes", type=float, default=10.0, help="--memory: flight time")
    ap.add_argument("--fps", type=float, default=10.0, help="--memory: camera frame rate")
    ap.add_argument("--sample-every", type=int, default=300, help="--memory: frames between samples")
    ap.add_argument("--render-only", action="store_true", help="--memory: render the lap into --cache-dir and stop")
    ap.add_argument("--lockstep", action="store_true", help="wait for local mapping after each frame (--memory: each keyframe)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="SlamConfig override, e.g. --set max_keyframes=200 (repeatable)")
    ap.add_argument("--camera-fps", type=float, default=None, help="render the scenario at this frame rate instead of its own")
    ap.add_argument("--start-s", default="0",
                    help="flight time of the first frame (s), or 'turn': 10 s before the first turn, as terraslam bench's window")
    ap.add_argument("--attitude-prior", choices=["off", "on", "both"], default="off",
                    help="feed the simulated autopilot's gravity direction (slam.use_attitude_prior); both: alternate off/on runs")
    ap.add_argument("--repeat", type=int, default=1, help="runs per configuration (SLAM is not bit-reproducible)")
    ap.add_argument("--export", metavar="FILE.npz", help="write the rendered frames, truth and priors to FILE and stop")
    ap.add_argument("--jpeg-quality", type=int, default=None, help="--export: store frames as JPEG of this quality")
    ap.add_argument("--sequence", metavar="FILE.npz", help="replay a sequence written by --export (no simulator needed)")
    ap.add_argument("--features", action="store_true",
                    help="time feature extraction alone: OpenCV ORB and the torch extractor on cpu and --device")
    a = ap.parse_args(argv)
    if a.memory:
        memory_main(a)
        return
    t0 = time.perf_counter()
    if a.sequence:
        seq = load_sequence(a.sequence)
        print(f"loaded {len(seq.images)} frames of '{seq.name}' from {a.sequence} in {time.perf_counter() - t0:.0f} s")
    else:
        start = start_frame(a.scenario, a.seed, a.camera_fps, a.start_s, a.frames)
        seq = render_sequence(a.scenario, a.frames, a.seed, a.cache_dir, start=start, fps=a.camera_fps)
        print(f"rendered/loaded {len(seq.images)} frames of '{a.scenario}' from frame {start} in {time.perf_counter() - t0:.0f} s")
    if a.export:
        save_sequence(seq, a.export, a.jpeg_quality)
        print(f"wrote {a.export} ({os.path.getsize(a.export) / 1e6:.1f} MB)")
        return
    base = cli_config(a)
    if a.features:
        cpu = base.model_copy(update=dict(feature_backend="cpu"))
        configs = [("OpenCV ORB (cpu)", cpu)] + [(f"torch patch-parallel ({d})", cpu.model_copy(
            update=dict(feature_backend="torch", torch_device=d))) for d in dict.fromkeys(["cpu", a.device])]
        print(f"feature extraction per frame, {seq.camera.width_px}x{seq.camera.height_px}, {len(seq.images)} frames:")
        print("\n".join(time_features(seq, configs)))
        return
    if a.loop_ablation:
        res = loop_ablation(seq, base)
        for mode, ms, loops, err in res:
            print(f"[loop {mode}] loops {loops}  correction ms {', '.join(f'{x:.0f}' for x in ms) or '-'}  "
                  f"revisit error after correction {err:.4f} (map units)")
        if all(r[1] for r in res):
            print(f"  RLC loop-correction time change vs full: {100 * (res[1][1][0] / res[0][1][0] - 1):+.0f} %")
        return
    blackout = tuple(int(x) for x in a.force_loss.split(":")) if a.force_loss else None
    if a.attitude_prior != "off" and not a.ablation:
        prior_main(seq, base, a)
        return
    runs = ablation_configs(base, with_ga=not a.no_ga) if a.ablation else [(f"{a.backend}", base)]
    results = []
    for name, cfg in runs:
        cfg = cfg.model_copy(update=dict(torch_device=a.device))
        r = run_sequence(seq, cfg, name, realtime=not a.no_realtime, blackout=blackout, drop_late=a.drop_late,
                         lockstep=a.lockstep)
        print(report(r), flush=True)
        results.append(r)
    if a.ablation:
        print("\nablation (vs baseline):")
        for r in results:
            print(f"  {r.name:9s} track mean {r.tracking_ms.mean():6.1f} ms  P99 {percentile(r.tracking_ms, 99):6.1f} ms  "
                  f"local BA {np.mean(r.local_ba_ms or [np.nan]):6.0f} ms  loop {np.mean(r.loop_ms or [np.nan]):6.0f} ms  "
                  f"ATE {r.ate()[2]:.2f} %")
        plm, ga = results[-2], results[-3]
        print(f"  PLM local-BA solve time change: {100 * (np.mean(plm.local_ba_ms) / np.mean(ga.local_ba_ms) - 1):+.0f} %"
              f", ATE change {100 * (plm.ate()[0] / ga.ate()[0] - 1):+.0f} %")
        print(f"  PLM local-BA solve CPU time change (worker CPU, not slowed by other processes): "
              f"{100 * (np.mean(plm.local_ba_cpu_ms) / np.mean(ga.local_ba_cpu_ms) - 1):+.0f} %")
        w = base.local_window
        loc = [local_window_ms(r, w) for r in (ga, plm)]
        print(f"  PLM on the local-window BAs only (the periodic BAs of up to {base.periodic_ba_window} keyframes "
              f"left out): {loc[0]:.0f} → {loc[1]:.0f} ms, {100 * (loc[1] / loc[0] - 1):+.0f} %")
        if results[-1].loop_ms and results[-2].loop_ms:
            print(f"  RLC loop-correction time change: {100 * (np.mean(results[-1].loop_ms) / np.mean(results[-2].loop_ms) - 1):+.0f} %")
        else:
            print("  RLC: no loop closed in this sequence (see --loop-ablation, or --scenario loop with enough frames)")


