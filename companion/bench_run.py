"""One `terraslam bench` run of the real pipeline (companion.app.fly_sim: the same code as `run demo`)
over a simulator scenario in the benchmark's window or over a recorded dataset, with this process's
RSS / CPU sampled meanwhile and the GNSS baselines re-simulated on the same flight (BenchRun)."""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import psutil

from companion.app import fly_sim, open_journal
from companion.config import AppConfig
from companion.run_log import RunLog
from gis.align.journal import Journal, write_truth
from gis.geodesy import LocalFrame
from gis.model import GisModel
from gis.types import Alignment


class ResourceSampler:
    """RSS and CPU% of this process, sampled every ``period_s`` in a daemon thread."""

    def __init__(self, period_s: float = 0.25):
        self._proc = psutil.Process()
        self._period_s = period_s
        self._stop = threading.Event()
        self.rss_mb: list[float] = []
        self.cpu_percent: list[float] = []
        self._thread = threading.Thread(target=self._run, name="bench-resources", daemon=True)

    def _sample_rss(self) -> None:
        self.rss_mb.append(self._proc.memory_info().rss / 2**20)

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            self._sample_rss()
            self.cpu_percent.append(self._proc.cpu_percent(None))  # since the previous call

    def start(self) -> "ResourceSampler":
        self._sample_rss()
        self._proc.cpu_percent(None)  # primes the counter
        self._thread.start()
        return self

    def stop(self) -> dict:
        self._stop.set()
        self._thread.join(timeout=2)
        self._sample_rss()
        cpu = np.array(self.cpu_percent)
        return {
            "rss_mb": {"start": self.rss_mb[0], "peak": max(self.rss_mb), "end": self.rss_mb[-1]},
            "cpu_percent": {"mean": float(cpu.mean()) if cpu.size else None, "max": float(cpu.max()) if cpu.size else None},
        }


@dataclass
class BenchRun:
    """A finished pipeline run plus what the figures need beyond ``RunLog``."""

    name: str
    run: RunLog
    origin: LocalFrame
    model: GisModel
    alignments: list[Alignment]            # accepted alignments in order
    map_points_slam: np.ndarray            # final SLAM map (N, 3)
    map_key: tuple[int, int] | None        # (map_id, reset_counter) of the final map
    resources: dict
    wall_s: float
    duration_s: float
    gnss_loss_at_s: float | None = None
    start_s: float = 0.0                   # flight time of the first frame
    gnss_baselines: dict[str, np.ndarray] = field(default_factory=dict)  # mode → 3D errors (m)
    gnss_baselines_h: dict[str, np.ndarray] = field(default_factory=dict)
    receiver: str | None = None            # GNSS receiver grade before the loss (GnssSpec.base); None: a dataset's own
    repeatable: bool = False               # fly_sim(repeatable=True): mapping and fine-tuning in step with the flight clock


def first_turn_s(scenario, min_turn_deg: float = 60.0) -> float:
    """Flight time at which the heading has first turned by ``min_turn_deg`` (0 when it never does)."""
    v = scenario.truth.v_enu[:, :2]
    heading = np.unwrap(np.arctan2(v[:, 1], v[:, 0]))
    turned = np.flatnonzero(np.abs(heading - heading[0]) > np.radians(min_turn_deg))
    return float(scenario.truth.t_s[turned[0]]) if len(turned) else 0.0


def bench_window_s(scenario, n_frames: int) -> tuple[float, float]:
    """(start, GNSS loss) flight times of a benchmark run of n_frames.

    The run starts 10 s before the flight's first turn (the GNSS geometry of a turn sharpens the
    bootstrap's heading beyond the compass's, companion.fusion.gnss_fit.BootstrapCollector) and GNSS is lost after
    70 % of the run: SLAM is aligned through the turn while GNSS is good, then carries on alone.
    Both are clamped to the flight."""
    duration_s = n_frames / scenario.fps
    start = min(max(0.0, first_turn_s(scenario) - 10.0), scenario.duration_s - duration_s)
    start = math.floor(max(0.0, start) * scenario.fps) / scenario.fps
    return start, start + 0.7 * duration_s


def _window(scenario, start: int):
    """scenario.steps(start), without the backlog of GNSS/attitude samples before the first frame."""
    for k, step in enumerate(scenario.steps(start)):
        if k == 0:
            t_min = step.frame.t_s - 1.0 / scenario.fps
            step = replace(step, gnss=[g for g in step.gnss if g.t_s > t_min], attitude=[a for a in step.attitude if a.t_s > t_min])
        yield step


def bench_scenario(cfg: AppConfig, name: str, n_frames: int = 300, *, seed: int = 0, fps: float = 10.0,
                   work_dir: Path, progress: Callable[[int, int, str], None] | None = None,
                   receiver: str | None = None, repeatable: bool = False, journal_dir: Path | None = None) -> BenchRun:
    """n_frames of a simulator scenario in the window of ``bench_window_s``, GNSS dropped in it.
    receiver: the GNSS receiver grade before the loss (GnssSpec.base), default the scenario's.
    repeatable: see companion.app.fly_sim. journal_dir: write the registration journal there
    (gis.align.journal), with the true camera positions."""
    from companion.sim import make_scenario
    from companion.sim.gis_export import export_gis
    from companion.sim.gnss import GnssEvent
    from companion.sim.scenario import scenario_spec
    from gis.loaders import load_model

    whole = make_scenario(name, seed, spec=scenario_spec(name, fps=fps))   # frames render lazily: cheap
    if n_frames > whole.n_frames:
        raise ValueError(f"--frames {n_frames}: scenario {name!r} has only {whole.n_frames} frames at {fps:g} fps")
    t_start, t_loss = bench_window_s(whole, n_frames)
    spec = whole.spec
    spec = replace(spec, gnss=replace(spec.gnss, base=receiver or spec.gnss.base,
                                      events=spec.gnss.events + (GnssEvent("dropout", t_loss),)))
    scenario = make_scenario(name, seed, spec=spec)
    start = int(round(t_start * fps))
    gis_world, _ = scenario.gis
    files = export_gis(gis_world, work_dir / "gis", seed=seed)
    model = load_model(files.mesh_ply, sample_spacing_m=cfg.gis.sample_spacing_m)
    sampler = ResourceSampler().start()
    t0 = time.perf_counter()
    journal = open_journal(journal_dir, files.mesh_ply, cfg, scenario.origin) if journal_dir else None
    f = fly_sim(cfg, _window(scenario, start), n_frames, scenario.camera, scenario.T_body_cam, model, progress=progress,
                repeatable=repeatable, p_body_gnss_m=scenario.spec.gnss_antenna_m, journal=journal)
    wall = time.perf_counter() - t0
    res = sampler.stop()
    _close_journal(journal, f.run)
    br = BenchRun(name, f.run, scenario.origin, model, f.alignments, f.map_points_slam, f.last_map_key, res, wall,
                  n_frames / fps, t_loss, t_start, receiver=spec.gnss.base, repeatable=repeatable)
    for mode in ("standalone", "dgps"):
        br.gnss_baselines[mode], br.gnss_baselines_h[mode] = gnss_baseline_errors(scenario, mode, t_start, t_start + n_frames / fps)
    return br


def _close_journal(journal: Journal | None, run: RunLog) -> None:
    """The true camera centre at every frame that has one, beside the journal's registrations."""
    if journal is None:
        return
    recs = [r for r in run.records if r.seq in run.truth_cam_ecef_m]
    write_truth(journal.folder, np.array([r.t_s for r in recs]),
                np.array([run.truth_cam_ecef_m[r.seq] for r in recs]).reshape(-1, 3))


def bench_dataset(cfg: AppConfig, dataset_dir: Path, n_frames: int | None = None,
                  progress: Callable[[int, int, str], None] | None = None, repeatable: bool = False,
                  journal_dir: Path | None = None) -> BenchRun:
    """Any dataset in the documented layout (docs/DATASET.md); it needs truth for the error figures."""
    from companion.dataset import read_dataset
    from gis.loaders import load_model

    ds = read_dataset(dataset_dir)
    if not ds.gis_files:
        raise ValueError(f"dataset {dataset_dir}: site.yaml lists no GIS model file (gis)")
    model = load_model(ds.gis_files[0], cfg.gis.sample_spacing_m, cfg.gis.footprint_ground)
    n = ds.n_frames if n_frames is None else min(ds.n_frames, n_frames)
    sampler = ResourceSampler().start()
    t0 = time.perf_counter()
    journal = open_journal(journal_dir, ds.gis_files[0], cfg, ds.origin) if journal_dir else None
    f = fly_sim(cfg, ds.steps(), n, ds.camera, ds.T_body_cam, model, progress=progress, repeatable=repeatable,
                p_body_gnss_m=ds.p_body_gnss_m, journal=journal)
    wall = time.perf_counter() - t0
    res = sampler.stop()
    _close_journal(journal, f.run)
    return BenchRun(ds.name, f.run, ds.origin, model, f.alignments, f.map_points_slam, f.last_map_key, res, wall,
                    float(ds.frame_t_s[n - 1] - ds.frame_t_s[0]), repeatable=repeatable)


def gnss_baseline_errors(scenario, base: str, t_from_s: float = 0.0, t_to_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """3D and horizontal errors (m) of the GNSS simulator in mode ``base`` (no events) on the
    scenario's flight between t_from_s and t_to_s, against the true antenna (body) position."""
    from companion.sim.gnss import simulate_gnss

    spec = replace(scenario.spec.gnss, base=base, events=())
    t_to_s = float(scenario.truth.t_s[-1]) if t_to_s is None else t_to_s
    tg = np.arange(t_from_s, t_to_s + 1e-9, 1 / spec.rate_hz)
    pg, vg, _, _ = scenario.trajectory.state(tg)
    h_agl = pg[:, 2] - scenario.world.ground_height_m(pg[:, 0], pg[:, 1])
    samples = simulate_gnss(spec, scenario.origin, tg, pg, vg, h_agl, seed=scenario.seed + 1)
    ok = np.array([s.fix_type >= 3 for s in samples])
    p = scenario.origin.geodetic_to_enu(np.array([s.lat_deg for s in samples]), np.array([s.lon_deg for s in samples]),
                                        np.array([s.h_ellipsoid_m for s in samples]))
    e = (np.asarray(p).reshape(-1, 3) - pg)[ok]
    return np.linalg.norm(e, axis=1), np.linalg.norm(e[:, :2], axis=1)
