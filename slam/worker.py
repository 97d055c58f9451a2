"""One forked worker process that comes back after it dies.

Bundle adjustment (``slam.ba``) and GIS fine-tuning (``companion.pipeline``) each run in their
own process: both hold the GIL for long stretches (gtsam's optimizer, many small numpy steps), and
in a thread they stalled tracking. A process can be killed (OOM killer, an operator's kill -9);
the job in flight then fails with ``BrokenProcessPool``, and the next ``submit`` starts a new
process instead of raising on the caller's hot path.

Fork, not spawn/forkserver: those re-import the caller's ``__main__`` (which breaks scripts without
a ``__main__`` guard) and would re-send large state (the GIS model); a forked child inherits it.
Forking while another thread is inside an OpenBLAS call can leave the child's BLAS thread pool
stuck, hence ``OPENBLAS_NUM_THREADS=1`` in ``companion/__init__.py`` and the systemd unit.

``nice``: the child lowers its own scheduling priority (``os.nice``) before anything else, so that
where the cores are shared the kernel runs the tracking thread first (CFS weights: nice 10 gets
~1/9 of a contended core against nice 0). Measured for the BA worker (docs/BENCHMARKS.md,
"Bundle adjustment at a lower priority").
"""
from __future__ import annotations

import logging
import multiprocessing as mp
import os
import threading
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable

log = logging.getLogger(__name__)


class ForkedWorker:
    """A single-process pool, forked at construction with ``initializer(*initargs)``, then
    ``warm()`` (e.g. an import the first job should not pay for), at ``nice`` more than this
    process's niceness (0: the same priority); restarted by the first ``submit`` after it died."""

    def __init__(self, name: str, initializer: Callable[..., None] | None = None, initargs: tuple = (),
                 warm: Callable[[], Any] = bool, nice: int = 0) -> None:
        if not 0 <= nice <= 19:
            raise ValueError(f"{name} worker: nice {nice} outside 0..19")
        self.name = name
        self._initializer, self._initargs, self._warm, self._nice = initializer, initargs, warm, nice
        self._lock = threading.Lock()
        self._pool: ProcessPoolExecutor | None = self._start()

    def _start(self) -> ProcessPoolExecutor:
        pool = ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("fork"),
                                   initializer=_child_start, initargs=(self._nice, self._initializer, self._initargs))
        pool.submit(self._warm)  # the first submit forks the process: do it now, not at the first job
        return pool

    def submit(self, fn: Callable, *args) -> Future:
        with self._lock:
            if self._pool is None:
                raise RuntimeError(f"{self.name} worker is closed")
            try:
                return self._pool.submit(fn, *args)
            except BrokenProcessPool:  # died (killed, out of memory) since the last job
                log.error("%s worker process had died: starting a new one", self.name)
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = self._start()
                return self._pool.submit(fn, *args)

    def restart(self, why: str) -> None:
        """Abandon the current process (killed, its queued jobs cancelled) and fork a new one: for a
        job that will not come back (see slam.local_ba.BA_TIMEOUT_S)."""
        with self._lock:
            if self._pool is None:
                return
            log.error("%s worker restarted: %s", self.name, why)
            old, self._pool = self._pool, self._start()
        # ProcessPoolExecutor has no public way to end a busy worker (terminate_workers is 3.14+)
        for proc in list((getattr(old, "_processes", None) or {}).values()):
            proc.kill()
        old.shutdown(wait=False, cancel_futures=True)

    def close(self) -> None:
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)


def _child_start(nice: int, initializer: Callable[..., None] | None, initargs: tuple) -> None:
    if nice:
        os.nice(nice)  # raising one's own niceness needs no privilege
    if initializer is not None:
        initializer(*initargs)
