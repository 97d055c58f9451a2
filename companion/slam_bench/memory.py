"""The SLAM memory benchmark (issue 4): one lap of a loop flight rendered to disk once, flown out and
back for minutes of flight time, RSS and the map's sizes sampled every N frames."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace

import numpy as np
import psutil

from companion.slam_bench.runs import RunResult
from slam.config import SlamConfig
from slam.mapping import MapMemory
from slam.system import SlamSystem
from slam.types import CameraModel, Frame, TrackingState

MEM_CHUNK_FRAMES = 100  # frames per file of the rendered lap


@dataclass
class LapFrames:
    """One lap of a loop flight rendered to disk (gray uint8, raw chunks of MEM_CHUNK_FRAMES frames).
    ``image(i)`` reads one frame from its file, so the lap never sits in the measured process's
    memory (no mmap either: mapped file pages would count in its RSS)."""

    root: str
    camera: CameraModel
    fps: float
    n_frames: int
    T_enu_cam: np.ndarray  # (n_frames,4,4) truth

    def _chunk(self, k: int) -> str:
        return os.path.join(self.root, f"chunk_{k:04d}.u8")

    def image(self, i: int) -> np.ndarray:
        h, w = self.camera.height_px, self.camera.width_px
        with open(self._chunk(i // MEM_CHUNK_FRAMES), "rb") as f:
            f.seek((i % MEM_CHUNK_FRAMES) * h * w)
            return np.frombuffer(f.read(h * w), np.uint8).reshape(h, w).copy()


def _lap_scenario(scenario: str, seed: int, fps: float):
    """``scenario``'s loop flown exactly once: it starts and ends at rest, so an out-and-back
    replay of it is a continuous flight of any length."""
    from companion.sim.scenario import make_scenario, scenario_spec

    spec = scenario_spec(scenario, fps=fps)
    if spec.flight.kind != "loop":
        raise ValueError(f"--memory needs a loop scenario, {scenario!r} flies {spec.flight.kind!r}")
    return make_scenario(scenario, seed=seed, spec=replace(spec, flight=replace(spec.flight, laps=1.0)))


def _render_lap_chunks(scenario: str, seed: int, fps: float, root: str) -> None:
    import cv2

    sc = _lap_scenario(scenario, seed, fps)
    os.makedirs(root, exist_ok=True)
    for k in range(0, sc.n_frames, MEM_CHUNK_FRAMES):
        path = os.path.join(root, f"chunk_{k // MEM_CHUNK_FRAMES:04d}.u8")
        if os.path.exists(path):
            continue  # resumable: chunks already rendered are kept
        frames = []
        for i in range(k, min(k + MEM_CHUNK_FRAMES, sc.n_frames)):
            im = sc.render(i).image_bgr
            frames.append(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) if im.ndim == 3 else im)
        np.ascontiguousarray(np.array(frames, np.uint8)).tofile(path + ".tmp")
        os.replace(path + ".tmp", path)
        print(f"  rendered frames {k}-{k + len(frames) - 1} of {sc.n_frames}", flush=True)


def render_lap(scenario: str = "nominal", seed: int = 0, fps: float = 10.0,
               cache_dir: str = os.path.expanduser("~/.cache/terraslam/slam_bench")) -> LapFrames:
    """Render (once, in a child process so the renderer's memory is not measured) or load a lap."""
    import multiprocessing as mp

    sc = _lap_scenario(scenario, seed, fps)
    root = os.path.join(cache_dir, f"lap_{scenario}_{seed}_{fps:g}fps")
    n_chunks = -(-sc.n_frames // MEM_CHUNK_FRAMES)
    if not all(os.path.exists(os.path.join(root, f"chunk_{k:04d}.u8")) for k in range(n_chunks)):
        p = mp.get_context("fork").Process(target=_render_lap_chunks, args=(scenario, seed, fps, root))
        p.start()
        p.join()
        if p.exitcode != 0:
            raise RuntimeError(f"rendering the lap failed (exit code {p.exitcode})")
    return LapFrames(root, sc.camera, fps, sc.n_frames, sc.truth.T_enu_cam.copy())


def out_and_back(n_lap: int, n_frames: int) -> np.ndarray:
    """Frame indices of a lap flown forwards, backwards, forwards ... for n_frames frames."""
    period = np.r_[np.arange(n_lap), np.arange(n_lap - 2, 0, -1)]
    return period[np.arange(n_frames) % len(period)]



@dataclass
class MemorySample:
    frame: int
    flight_s: float
    wall_s: float
    rss_mb: float  # this process (VmRSS)
    rss_anon_mb: float  # its anonymous part (heap): file-backed pages excluded
    children_rss_mb: float  # the BA worker process
    threads: int
    loops: int
    mem: MapMemory


def _status_mb(key: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


def run_memory(lap: LapFrames, config: SlamConfig, minutes: float, sample_every: int = 300,
               realtime: bool = True, lockstep: bool = False, progress: bool = True) -> tuple[list[MemorySample], RunResult]:
    """Fly the lap out and back for ``minutes`` of flight time and sample memory every
    ``sample_every`` frames. Map updates are not polled, as in the pipeline (companion.pipeline).
    lockstep: after each keyframe wait until local mapping (and its BA) is done, as on a machine
    where mapping keeps up with the camera (on 2 shared cores it does not, and the map resets in turns)."""
    proc = psutil.Process()
    n = int(round(minutes * 60 * lap.fps))
    order = out_and_back(lap.n_frames, n)
    est, tru = np.full((n, 3), np.nan), lap.T_enu_cam[order][:, :3, 3]
    states: list[TrackingState] = []
    ms = np.zeros(n)
    samples: list[MemorySample] = []
    t_start = time.perf_counter()

    def sample(k: int, s: SlamSystem) -> None:
        kids = sum(c.memory_info().rss for c in proc.children(recursive=True)) / 2**20
        samples.append(MemorySample(k, k / lap.fps, time.perf_counter() - t_start, proc.memory_info().rss / 2**20,
                                    _status_mb("RssAnon"), kids, proc.num_threads(), s.mapper.stats.n_loops,
                                    s.mapper.memory()))
        if progress:
            print(memory_row(samples[-1]), flush=True)

    if progress:
        print(memory_header(), flush=True)
    with SlamSystem(lap.camera, config) as s:
        for k, i in enumerate(order):
            pose = s.track(Frame(lap.image(int(i)), k / lap.fps, k))
            ms[k] = pose.tracking_ms
            states.append(pose.state)
            if pose.state.has_pose:
                est[k] = pose.T_slam_cam[:3, 3]
            if lockstep:
                s.wait_mapping()  # returns at once when mapping is idle
            if k % sample_every == 0:
                sample(k, s)
            if realtime:
                time.sleep(max(0.0, t_start + (k + 1) / lap.fps - time.perf_counter()))
        s.wait_mapping()
        sample(n, s)
        ok = np.isfinite(est[:, 0])
        st = s.mapper.stats
        run = RunResult("memory", ms, np.full(n, np.nan), states, est[ok], tru[ok], s.reset_counter,
                        list(st.local_mapping_ms), list(st.local_ba_ms), list(st.ba_window), list(st.loop_ms),
                        list(st.loops), len(s.mapper.map.points), fused=(st.fused_observations, st.fused_points))
    return samples, run


def memory_header() -> str:
    return ("| frame | flight min | wall s | RSS MB | anon MB | BA worker MB | threads | keyframes all / with features | "
            "anchors | points | observations | place entries | features+points+place MB | queued kf / updates (dropped) | loops |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")


def memory_row(x: MemorySample) -> str:
    m = x.mem
    data_mb = (m.map.feature_bytes + m.map.point_bytes + m.place_bytes) / 2**20
    return (f"| {x.frame} | {x.flight_s / 60:.1f} | {x.wall_s:.0f} | {x.rss_mb:.0f} | {x.rss_anon_mb:.0f} | "
            f"{x.children_rss_mb:.0f} | {x.threads} | {m.map.keyframes} / {m.map.keyframes_with_features} | {m.loop_anchors} | "
            f"{m.map.map_points} | {m.map.observations} | {m.place_entries} | {data_mb:.1f} | "
            f"{m.queued_keyframes} / {m.queued_updates} ({m.dropped_updates}) | {x.loops} |")


def memory_summary(samples: list[MemorySample]) -> dict:
    """RSS slope over the second half of the flight (MB per flight minute, least squares) and
    RSS(end) / RSS(at 2 min)."""
    t_min = np.array([x.flight_s for x in samples]) / 60
    rss = np.array([x.rss_mb for x in samples])
    half = t_min >= t_min[-1] / 2
    slope = float(np.polyfit(t_min[half], rss[half], 1)[0]) if half.sum() >= 2 else float("nan")
    at2 = int(np.argmin(np.abs(t_min - 2.0)))
    return {"rss_start_mb": float(rss[0]), "rss_2min_mb": float(rss[at2]), "rss_end_mb": float(rss[-1]),
            "rss_peak_mb": float(rss.max()), "slope_second_half_mb_per_min": slope,
            "ratio_end_to_2min": float(rss[-1] / rss[at2]), "flight_min": float(t_min[-1])}


