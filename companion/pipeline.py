"""The real-time localisation pipeline: frames in, global fixes out (DESIGN.md data flow).

Hot path, one thread, top to bottom per frame::

    frame ─▶ slam.track ─SlamPose─▶ globalizer.fix ─GlobalFix─▶ sink (MAVLink bridge, recorder)

Background: SLAM's own local-mapping/loop-closing threads, and one fine-tuning worker that every
``alignment.finetune_every_frames`` frames registers the current SLAM map to the GIS model
(TerraSLAM §4.4) and hands the accepted T_fine to the Globalizer. Until an alignment exists, good
GNSS bootstraps one (digital-twin paper §III-D): pairs of (SLAM camera centre, GNSS position) are
collected while GNSS is trusted and fitted with a similarity.

The pipeline knows no camera device, MAVLink or simulator: callers pass an iterator of
``PipelineInput`` and a sink; ``companion.app`` wires cameras, the bridge and the simulator.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator

import numpy as np

from gis.align.bootstrap import gnss_bootstrap
from gis.align.fine import FineTuner
from gis.geodesy import geodetic_to_ecef
from gis.globalizer import Globalizer
from gis.types import Alignment, AlignmentSource, GlobalFix
from mavlink_bridge.types import GnssSample
from slam.types import AttitudePrior, Frame, SlamPose

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PipelineInput:
    """One camera frame plus what the vehicle knew at its capture time.

    gnss: the latest receiver sample and whether the GNSS monitor trusts it (None when unknown).
    prior: optional autopilot attitude/baro prior for SLAM.
    """

    frame: Frame
    gnss: GnssSample | None = None
    gnss_trusted: bool = False
    prior: AttitudePrior | None = None


@dataclass(frozen=True)
class FrameRecord:
    """What the pipeline did with one frame (the evaluation and the recorder read these)."""

    seq: int
    t_s: float
    pose: SlamPose
    fix: GlobalFix | None
    alignment_source: AlignmentSource | None
    wall_done_s: float  # time.monotonic() when the fix left the pipeline


@dataclass
class BootstrapCollector:
    """Pairs (SLAM camera centre, GNSS ECEF position) while GNSS is trusted (digital-twin §III-D).

    A fit needs a baseline: ``min_pairs`` pairs spanning ``min_baseline_m`` metres of GNSS track,
    so that yaw and scale are observable. Pairs are dropped when the SLAM map resets.
    """

    min_pairs: int = 30
    min_baseline_m: float = 40.0
    max_pairs: int = 600
    p_slam: list[np.ndarray] = field(default_factory=list)
    p_ecef: list[np.ndarray] = field(default_factory=list)
    t_s: list[float] = field(default_factory=list)
    sigma_m: list[float] = field(default_factory=list)
    map_key: tuple[int, int] | None = None
    last_refusal: str | None = None
    _last_gnss_t: float | None = None

    def add(self, pose: SlamPose, sample: GnssSample | None, trusted: bool) -> None:
        key = (pose.map_id, pose.reset_counter)
        if key != self.map_key:
            self.p_slam.clear(), self.p_ecef.clear(), self.t_s.clear(), self.sigma_m.clear()
            self.map_key = key
        if not (trusted and sample is not None and pose.state.has_pose):
            return
        if sample.t_s == self._last_gnss_t:  # one pair per receiver solution
            return
        self._last_gnss_t = sample.t_s
        self.p_slam.append(pose.T_slam_cam[:3, 3].copy())
        self.p_ecef.append(geodetic_to_ecef(sample.lat_deg, sample.lon_deg, sample.h_ellipsoid_m))
        self.t_s.append(pose.t_s)
        self.sigma_m.append(max(sample.h_acc_m, 0.1))
        if len(self.p_slam) > self.max_pairs:
            del self.p_slam[0], self.p_ecef[0], self.t_s[0], self.sigma_m[0]

    def ready(self) -> bool:
        if len(self.p_ecef) < self.min_pairs:
            return False
        pts = np.asarray(self.p_ecef)
        return float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))) >= self.min_baseline_m

    def solve(self) -> Alignment | None:
        reset_counter = self.map_key[1] if self.map_key else 0
        map_id = self.map_key[0] if self.map_key else 0
        try:
            return gnss_bootstrap(
                np.asarray(self.p_slam), np.asarray(self.p_ecef), t_s=self.t_s[-1],
                reset_counter=reset_counter, map_id=map_id, sigma_gnss_m=float(np.median(self.sigma_m)),
            )
        except ValueError as e:
            log.debug("GNSS bootstrap refused: %s", e)
            self.last_refusal = str(e)
            return None


class FineTuneWorker:
    """Runs FineTuner.refine in a background thread; at most one registration queued (latest wins)."""

    def __init__(self, tuner: FineTuner, on_result: Callable[[Alignment | None, str, float], None]):
        self._tuner = tuner
        self._on_result = on_result
        self._jobs: queue.Queue = queue.Queue(maxsize=1)
        self._stop = threading.Event()
        self.busy = threading.Event()
        self.wall_ms: list[float] = []
        self._thread = threading.Thread(target=self._run, name="finetune", daemon=True)
        self._thread.start()

    def submit(self, points_slam: np.ndarray, initial: Alignment, center_slam: np.ndarray, t_s: float) -> bool:
        if self.busy.is_set():
            return False
        try:
            self._jobs.put_nowait((points_slam, initial, center_slam, t_s))
        except queue.Full:
            return False
        self.busy.set()
        return True

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                points, initial, center, t_s = self._jobs.get(timeout=0.1)
            except queue.Empty:
                continue
            t0 = time.perf_counter()
            try:
                reg = self._tuner.register(points, initial, t_s=t_s, reset_counter=initial.reset_counter,
                                           center_slam=center, map_id=initial.map_id)
                alignment, reason = reg.alignment, reg.reason
            except Exception as e:  # a failed registration must not kill the pipeline
                log.exception("fine-tuning failed")
                alignment, reason = None, f"exception: {e}"
            ms = (time.perf_counter() - t0) * 1e3
            self.wall_ms.append(ms)
            self.busy.clear()
            self._on_result(alignment, reason, ms)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


class Localizer:
    """SLAM + alignment + globalisation for one camera; ``process`` is the per-frame hot path."""

    def __init__(self, slam, tuner: FineTuner | None, globalizer: Globalizer, finetune_every_frames: int = 200,
                 initial_alignment: Alignment | None = None, bootstrap: BootstrapCollector | None = None,
                 min_points_for_finetune: int = 200):
        self.slam = slam
        self.globalizer = globalizer
        self.every = finetune_every_frames
        self.min_points = min_points_for_finetune
        self.bootstrap = bootstrap if bootstrap is not None else BootstrapCollector()
        self.alignment: Alignment | None = None
        self.events: list[tuple[float, str]] = []  # (t_s, text): alignment timeline
        self._lock = threading.Lock()
        self._frames_since_tune = 0
        self._frames_since_boot = 0
        self.rebootstrap_every = 30  # frames between GNSS re-fits while GNSS is the only alignment
        self._last_pose: SlamPose | None = None
        self.worker = FineTuneWorker(tuner, self._on_finetune) if tuner is not None else None
        if initial_alignment is not None:
            self._accept(initial_alignment, "initial")

    def _accept(self, alignment: Alignment, why: str) -> None:
        with self._lock:
            self.alignment = alignment
            self.globalizer.update_alignment(alignment)
        self.events.append((alignment.t_s, f"alignment {alignment.source.value} accepted ({why}; σ={alignment.sigma_m:.2f} m)"))

    def _on_finetune(self, alignment: Alignment | None, reason: str, wall_ms: float) -> None:
        t = self._last_pose.t_s if self._last_pose else 0.0
        if alignment is None:
            self.events.append((t, f"fine-tuning rejected: {reason} ({wall_ms:.0f} ms)"))
            return
        with self._lock:
            current = self.alignment
        if current is not None and (alignment.map_id, alignment.reset_counter) != (current.map_id, current.reset_counter):
            return  # the map changed while we registered: stale
        self._accept(alignment, f"{reason}, {wall_ms:.0f} ms")

    def process(self, item: PipelineInput) -> FrameRecord:
        pose = self.slam.track(item.frame, item.prior)
        self._last_pose = pose
        with self._lock:
            alignment = self.alignment
        if alignment is not None and (alignment.map_id, alignment.reset_counter) != (pose.map_id, pose.reset_counter):
            # SLAM map reset or loop-corrected: the alignment no longer applies (the Globalizer
            # refuses fixes for another map by itself).
            self.events.append((pose.t_s, "SLAM map changed: alignment dropped"))
            with self._lock:
                self.alignment = alignment = None
        if pose.state.has_pose:
            self.bootstrap.add(pose, item.gnss, item.gnss_trusted)
            self._frames_since_boot += 1
            gnss_sourced = alignment is None or alignment.source is AlignmentSource.GNSS
            if (item.gnss_trusted and gnss_sourced and self.bootstrap.ready()
                    and (alignment is None or self._frames_since_boot >= self.rebootstrap_every)):
                self._frames_since_boot = 0
                boot = self.bootstrap.solve()
                if boot is not None:
                    self._accept(boot, f"{len(self.bootstrap.p_slam)} GNSS pairs")
                    alignment = boot
            self._frames_since_tune += 1
            if alignment is not None and self.worker is not None and self._frames_since_tune >= self.every:
                snapshot = self.slam.map_points()
                if len(snapshot.points_slam) >= self.min_points and self.worker.submit(
                    snapshot.points_slam, alignment, pose.T_slam_cam[:3, 3].copy(), pose.t_s
                ):
                    self._frames_since_tune = 0
        fix = self.globalizer.fix(pose)
        return FrameRecord(pose.seq, pose.t_s, pose, fix, alignment.source if alignment else None, time.monotonic())

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()
        self.slam.close()


def run(inputs: Iterable[PipelineInput], localizer: Localizer, sink: Callable[[GlobalFix | None], None] | None = None,
        on_record: Callable[[FrameRecord], None] | None = None) -> Iterator[FrameRecord]:
    """Drive the localizer over ``inputs``; every fix (or None) goes to ``sink`` at once."""
    for item in inputs:
        rec = localizer.process(item)
        if sink is not None:
            sink(rec.fix)
        if on_record is not None:
            on_record(rec)
        yield rec
