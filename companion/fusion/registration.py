"""GIS registrations of the SLAM map (TerraSLAM §4.4) in their own process: FineTuneWorker runs
gis.align.fine.FineTuner's registrations and barometer scale checks in a forked worker and hands
their results back (at once live; at a fixed flight-time lag in repeatable runs)."""
from __future__ import annotations

import collections
import logging
import math
import threading
import time
from concurrent.futures import CancelledError, Future
from concurrent.futures.process import BrokenProcessPool
from typing import Callable

import numpy as np

from gis.align.fine import FineTuner, ScaleCheck
from gis.align.georef import GeorefCorrection, IcpMeasurement
from gis.align.journal import Journal, RegistrationJob
from gis.types import Alignment
from slam.worker import ForkedWorker

log = logging.getLogger(__name__)


_TUNER: FineTuner | None = None  # the fine-tuning process's own FineTuner (inherited through fork)


def _adopt_tuner(tuner: FineTuner) -> None:
    global _TUNER
    _TUNER = tuner


def _register_in_worker(points: np.ndarray, initial: Alignment, center: np.ndarray, t_s: float,
                        camera_h_ell_m: float | None, camera_h_sigma_m: float | None,
                        correction: GeorefCorrection | None) -> tuple[Alignment | None, str, float, float, IcpMeasurement | None]:
    """(alignment or None, reason, wall ms, CPU ms of the worker process, the ICP's own result) of
    one registration against the model under ``correction``."""
    t0, c0 = time.perf_counter(), time.process_time()
    _TUNER.set_correction(correction)
    reg = _TUNER.register(points, initial, t_s=t_s, reset_counter=initial.reset_counter, center_slam=center,
                          map_id=initial.map_id, camera_h_ell_m=camera_h_ell_m, camera_h_sigma_m=camera_h_sigma_m)
    return reg.alignment, reg.reason, (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3, reg.icp


def _prefetch_in_worker() -> bool:
    return _TUNER.prefetch_crop()


def _check_scale_in_worker(points: np.ndarray, alignment: Alignment, center: np.ndarray, camera_h_ell_m: float,
                           correction: GeorefCorrection | None) -> ScaleCheck:
    _TUNER.set_correction(correction)
    return _TUNER.check_scale(points, alignment, center, camera_h_ell_m)


class FineTuneWorker:
    """Runs FineTuner.register in its own process (``slam.worker.ForkedWorker``); at most one
    registration in flight (a new one is refused while busy).

    A process, not a thread: the registration is numpy/scipy with many small steps, so in a thread
    it competed with tracking and mapping for the GIL (measured: 85 ms alone, ~420 ms wall inside
    the pipeline on 2 cores) and lengthened tracking's frames. The worker is forked once with the
    tuner (GIS model and its crop cache stay in the child, nothing is re-sent per job); a job sends
    the SLAM points, the prior alignment and the model's georeference ``correction`` (set by the
    caller; gis.align.georef), and gets back the alignment or the rejection reason.
    ``wall_ms`` is each registration's wall time inside the worker, ``cpu_ms`` the CPU time it used
    (on a loaded 2-core board the two differ by the time the worker waited for a core). If the worker dies, the job in
    flight reports why, and the next submit starts a new worker (never an exception on the hot path).

    ``lag_s`` (offline runs on a simulated or recorded clock): a job's result is not handed over
    when it finishes but by ``release(t_s)`` once the flight clock has passed the job's time + lag_s,
    on the caller's thread, waiting for the job if it has not finished. Which frame adopts a result
    then depends on flight time alone, not on how fast this machine ran the loop, so a run repeats
    (live, lag_s is None: results are adopted as soon as they exist).
    """

    def __init__(self, tuner: FineTuner, on_result: Callable[[Alignment | None, str, float, IcpMeasurement | None], None],
                 on_scale_check: Callable[[Alignment, ScaleCheck], None] | None = None, lag_s: float | None = None):
        self._on_result = on_result
        self._on_scale_check = on_scale_check
        self.lag_s = lag_s
        self._held: collections.deque[tuple[float, Callable[[], None]]] = collections.deque()  # (due t_s, hand over)
        self.busy = threading.Event()
        self.checking = threading.Event()  # a scale check in flight
        self.wall_ms: list[float] = []
        self.cpu_ms: list[float] = []
        self.n_prefetched = 0  # GIS crops built ahead of a registration (_prefetch)
        self.correction: GeorefCorrection | None = None  # sent with every job
        self.journal: Journal | None = None  # writes each registration's inputs and outcome (gis.align.journal)
        self._lock = threading.Lock()
        self._proc = ForkedWorker("fine-tuning", initializer=_adopt_tuner, initargs=(tuner,))

    def submit(self, points_slam: np.ndarray, initial: Alignment, center_slam: np.ndarray, t_s: float,
               camera_h_ell_m: float | None = None, camera_h_sigma_m: float | None = None) -> bool:
        with self._lock:
            if self.busy.is_set():
                return False
            job = RegistrationJob(t_s, points_slam, initial, center_slam, camera_h_ell_m, camera_h_sigma_m, self.correction)
            fut = self._proc.submit(_register_in_worker, points_slam, initial, center_slam, t_s, camera_h_ell_m,
                                    camera_h_sigma_m, self.correction)
            self.busy.set()
        self._hand_over(t_s, fut, lambda f: self._done(f, job))
        return True

    def check_scale(self, points_slam: np.ndarray, alignment: Alignment, center_slam: np.ndarray,
                    camera_h_ell_m: float, t_s: float) -> bool:
        """Run FineTuner.check_scale in the worker (queued behind a registration in flight); the
        result goes to on_scale_check with the alignment it tested. At most one in flight: False
        (nothing submitted) while one is. ``t_s``: the frame's time (for ``lag_s``)."""
        with self._lock:
            if self.checking.is_set() or self._on_scale_check is None:
                return False
            fut = self._proc.submit(_check_scale_in_worker, points_slam, alignment, center_slam, camera_h_ell_m,
                                    self.correction)
            self.checking.set()
        self._hand_over(t_s, fut, lambda f: self._checked(f, alignment))
        return True

    def _hand_over(self, t_s: float, fut: Future, deliver: Callable[[Future], None]) -> None:
        if self.lag_s is None:
            fut.add_done_callback(deliver)
        else:
            self._held.append((t_s + self.lag_s, lambda: deliver(fut)))

    def release(self, t_s: float) -> None:
        """Hand over, in submission order, every held result due by flight time ``t_s`` (waiting
        for its job if it has not finished); ``math.inf`` hands over all. Nothing to do when
        lag_s is None."""
        while self._held and self._held[0][0] <= t_s:
            self._held.popleft()[1]()

    def _checked(self, fut: Future, alignment: Alignment) -> None:
        try:
            chk = fut.result()
        except Exception as e:  # CancelledError at close, a dead worker (restarted by the next submit)
            log.debug("scale check did not run: %s: %s", type(e).__name__, e)
            self.checking.clear()
            return
        self.checking.clear()
        self._on_scale_check(alignment, chk)

    def _done(self, fut: Future, job: RegistrationJob) -> None:
        try:
            alignment, reason, ms, cpu_ms, icp = fut.result()
        except CancelledError:
            self.busy.clear()
            return
        except BrokenProcessPool as e:  # the worker died (e.g. out of memory): restarted at the next submit
            log.error("fine-tuning worker died: %s", e)
            alignment, reason, ms, cpu_ms, icp = None, f"fine-tuning worker died: {e}", float("nan"), float("nan"), None
        except Exception as e:  # a failed registration must not kill the pipeline
            log.error("fine-tuning failed: %s: %s", type(e).__name__, e)
            alignment, reason, ms, cpu_ms, icp = None, f"exception: {type(e).__name__}: {e}", float("nan"), float("nan"), None
        if math.isfinite(ms):
            self.wall_ms.append(ms)
            self.cpu_ms.append(cpu_ms)
        if self.journal is not None:
            try:
                self.journal.record(job, alignment, reason)
            except OSError as e:  # a full disk must not stop the registrations
                log.warning("registration journal not written: %s", e)
        try:  # busy until the result is adopted: whoever sees the worker free sees its alignment
            self._on_result(alignment, reason, ms, icp)
            self._prefetch()  # queued before the next registration can be
        finally:
            self.busy.clear()

    def _prefetch(self) -> None:
        """The worker builds the next registration's GIS crop in its idle time after this one
        (FineTuner.prefetch_crop), so that registration, and the fix that waits for it, need not.
        Best effort: a closed or dead worker just builds the crop when it is asked for."""
        try:
            fut = self._proc.submit(_prefetch_in_worker)
        except (RuntimeError, BrokenProcessPool) as e:
            log.debug("GIS crop not prefetched: %s: %s", type(e).__name__, e)
            return
        fut.add_done_callback(self._prefetched)

    def _prefetched(self, fut: Future) -> None:
        if fut.cancelled():
            return
        if fut.exception() is not None:
            log.warning("GIS crop prefetch failed: %s: %s", type(fut.exception()).__name__, fut.exception())
        elif fut.result():
            self.n_prefetched += 1

    def close(self) -> None:
        self._proc.close()
