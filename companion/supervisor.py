"""Supervised stage threads, health, systemd watchdog, clean shutdown and latency accounting.

* ``Stage``: one thread running ``target(ctx)``; the target loops until ``ctx.stop`` is set and
  calls ``ctx.beat()`` whenever it made progress. An exception restarts the target after a
  backoff, up to ``restart_limit`` times; after that the stage is FAILED. Returning without being
  asked to stop means the stage finished its input (e.g. end of a video file): DONE.
* ``Supervisor``: starts stages, reports health, sends ``WATCHDOG=1`` only while every required
  stage beat within its deadline (a hung or failed stage lets systemd's WatchdogSec kill and
  restart the process), turns SIGTERM/SIGINT into a clean stop that runs the registered shutdown
  hooks (e.g. save the latest T_fine) in reverse registration order.
* ``LatencyTracker``: per-frame marks (capture → ... → MAVLink wire) → P50/P99 per stage and
  cumulative from capture.
"""
from __future__ import annotations

import enum
import logging
import signal
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from companion import notify
from companion.logs import log_event

log = logging.getLogger(__name__)


class StageState(enum.Enum):
    STARTING = "starting"
    RUNNING = "running"
    BACKOFF = "backoff"  # crashed, waiting to restart
    DONE = "done"  # target returned on its own (input exhausted)
    FAILED = "failed"  # crashed more than restart_limit times
    STOPPED = "stopped"


@dataclass
class StageContext:
    """What a stage target sees: ``stop`` to watch, ``beat()`` to report progress."""

    stop: threading.Event
    _beat: Callable[[], None]

    def beat(self) -> None:
        self._beat()


@dataclass(frozen=True)
class StageHealth:
    name: str
    state: StageState
    progress: int  # beats since start
    restarts: int
    since_beat_s: float | None  # None before the first beat
    healthy: bool
    last_error: str | None


class Stage:
    """A supervised thread. ``deadline_s``: longest allowed gap between beats while running."""

    def __init__(
        self,
        name: str,
        target: Callable[[StageContext], None],
        *,
        deadline_s: float = 5.0,
        required: bool = True,
        restart_limit: int = 5,
        backoff_s: float = 0.2,
        backoff_max_s: float = 5.0,
    ) -> None:
        self.name = name
        self.target = target
        self.deadline_s = deadline_s
        self.required = required
        self.restart_limit = restart_limit
        self.backoff_s = backoff_s
        self.backoff_max_s = backoff_max_s
        self.stop_event = threading.Event()
        self._lock = threading.Lock()
        self._state = StageState.STARTING
        self._progress = 0
        self._restarts = 0
        self._started_s: float | None = None
        self._last_beat_s: float | None = None
        self._last_error: str | None = None
        self._thread = threading.Thread(target=self._run, name=f"stage-{name}", daemon=True)

    def start(self) -> None:
        self._started_s = time.monotonic()
        self._thread.start()

    def stop(self) -> None:
        self.stop_event.set()

    def join(self, timeout_s: float | None = None) -> bool:
        """True when the thread ended within ``timeout_s``."""
        if self._thread.ident is not None:
            self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def _beat(self) -> None:
        with self._lock:
            self._progress += 1
            self._last_beat_s = time.monotonic()

    def _set(self, state: StageState, error: str | None = None) -> None:
        with self._lock:
            self._state = state
            if error is not None:
                self._last_error = error

    def _run(self) -> None:
        ctx = StageContext(stop=self.stop_event, _beat=self._beat)
        while True:
            self._set(StageState.RUNNING)
            try:
                self.target(ctx)
            except Exception as e:  # noqa: BLE001 — any crash of a stage is supervised here
                log.exception("stage %s crashed", self.name)
                if self.stop_event.is_set():
                    self._set(StageState.STOPPED, f"{type(e).__name__}: {e}")
                    return
                with self._lock:
                    n = self._restarts + 1  # the restart this crash would need
                if n > self.restart_limit:
                    self._set(StageState.FAILED, f"{type(e).__name__}: {e}")
                    log_event(log, "stage_failed", f"stage {self.name} crashed after {n - 1} restarts; giving up",
                              level=logging.ERROR, stage=self.name, restarts=n - 1, restart_limit=self.restart_limit)
                    return
                with self._lock:
                    self._restarts = n
                self._set(StageState.BACKOFF, f"{type(e).__name__}: {e}")
                delay = min(self.backoff_max_s, self.backoff_s * 2 ** (n - 1))
                log_event(log, "stage_restart", f"restarting stage {self.name} in {delay:.2f} s", level=logging.WARNING,
                          stage=self.name, restart=n, restart_limit=self.restart_limit, error=f"{type(e).__name__}: {e}")
                if self.stop_event.wait(delay):
                    self._set(StageState.STOPPED)
                    return
                with self._lock:  # the deadline counts from the restart, not the crash
                    self._started_s = time.monotonic()
                    self._last_beat_s = None
                continue
            self._set(StageState.STOPPED if self.stop_event.is_set() else StageState.DONE)
            return

    def health(self, now_s: float | None = None) -> StageHealth:
        now_s = time.monotonic() if now_s is None else now_s
        with self._lock:
            ref = self._last_beat_s if self._last_beat_s is not None else self._started_s
            since = None if self._last_beat_s is None else now_s - self._last_beat_s
            on_time = ref is not None and now_s - ref <= self.deadline_s
            healthy = (self._state == StageState.RUNNING and on_time) or self._state == StageState.DONE
            return StageHealth(
                name=self.name,
                state=self._state,
                progress=self._progress,
                restarts=self._restarts,
                since_beat_s=since,
                healthy=healthy,
                last_error=self._last_error,
            )


class Supervisor:
    """Owns the stages, the watchdog pings, signals and shutdown hooks."""

    def __init__(self, stages: Sequence[Stage], *, watchdog: bool = True, environ: dict[str, str] | None = None) -> None:
        names = [s.name for s in stages]
        if len(set(names)) != len(names):
            raise ValueError(f"stage names must be unique, got {names}")
        self.stages = list(stages)
        self.environ = environ  # None → os.environ (tests pass their own NOTIFY_SOCKET)
        self.watchdog_interval_s = notify.watchdog_interval_s(environ) if watchdog else None
        self.stop_requested = threading.Event()
        self._signal: int | None = None  # set by the signal handler; read by run()
        self._hooks: list[tuple[str, Callable[[], None]]] = []
        self._last_ping_s = float("-inf")
        self._status = ""

    def on_shutdown(self, name: str, hook: Callable[[], None]) -> None:
        """Run ``hook`` at clean shutdown (hooks run newest first; one failing does not stop the rest)."""
        self._hooks.append((name, hook))

    def install_signal_handlers(self) -> None:
        """SIGTERM/SIGINT → request a clean stop (main thread only, as Python requires)."""
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self._on_signal)

    def _on_signal(self, signum: int, _frame: object) -> None:
        # Only a plain assignment here: the handler runs in the main thread between bytecodes, possibly
        # while that thread holds stop_requested's internal (non-reentrant) lock inside Event.wait, so
        # calling Event.set() or logging from here can deadlock. run() notices within one poll.
        self._signal = signum

    def start(self, ready_status: str = "running") -> None:
        for s in self.stages:
            s.start()
        notify.ready(ready_status, self.environ)

    def health(self) -> list[StageHealth]:
        now = time.monotonic()
        return [s.health(now) for s in self.stages]

    def healthy(self) -> bool:
        """Every required stage is running and beat within its deadline (or finished its input)."""
        return all(h.healthy for s, h in zip(self.stages, self.health()) if s.required)

    def failed(self) -> list[str]:
        return [h.name for h in self.health() if h.state == StageState.FAILED]

    def finished(self) -> bool:
        """All required stages have ended on their own (DONE) — e.g. a replayed file ran out."""
        return all(h.state == StageState.DONE for s, h in zip(self.stages, self.health()) if s.required)

    def tick(self, status: str | None = None) -> bool:
        """Call periodically: pings the watchdog when healthy and due; updates STATUS. Returns healthy."""
        ok = self.healthy()
        now = time.monotonic()
        if ok and self.watchdog_interval_s is not None and now - self._last_ping_s >= self.watchdog_interval_s:
            notify.watchdog(self.environ)
            self._last_ping_s = now
        if not ok:
            status = "degraded: " + ", ".join(f"{h.name}={h.state.value}" for h in self.health() if not h.healthy)
        if status is not None and status != self._status:
            notify.status(status, self.environ)
            self._status = status
        return ok

    def run(self, poll_s: float = 0.5, status: Callable[[], str] | None = None) -> int:
        """Tick until a stop is requested, a required stage fails or all finish; then shut down.

        Returns a process exit code: 0 after a requested stop or finished input, 1 when a stage failed
        (so systemd's Restart=on-failure restarts the service).
        """
        poll_s = min(poll_s, self.watchdog_interval_s or poll_s)
        code = 0
        while not self.stop_requested.wait(poll_s):
            if self._signal is not None:
                log.info("received %s; shutting down", signal.Signals(self._signal).name)
                break
            self.tick(status() if status else None)
            failed = [n for n in self.failed() if any(s.name == n and s.required for s in self.stages)]
            if failed:
                log.error("required stage(s) failed: %s", ", ".join(failed))
                code = 1
                break
            if self.finished():
                break
        self.shutdown()
        return code

    def shutdown(self, join_timeout_s: float = 5.0) -> None:
        """STOPPING=1, stop and join every stage, then run the shutdown hooks."""
        notify.stopping(self.environ)
        self.stop_requested.set()
        for s in self.stages:
            s.stop()
        deadline = time.monotonic() + join_timeout_s
        for s in self.stages:
            if not s.join(max(0.0, deadline - time.monotonic())):
                log.warning("stage %s did not stop within %.1f s", s.name, join_timeout_s)
        for name, hook in reversed(self._hooks):
            try:
                hook()
            except Exception:  # noqa: BLE001 — a failing hook must not skip the others
                log.exception("shutdown hook %s failed", name)
        self._hooks.clear()


@dataclass(frozen=True)
class LatencySummary:
    n: int
    p50_ms: float
    p99_ms: float
    max_ms: float


@dataclass
class LatencyTracker:
    """Per-frame marks → latency distributions over the last ``window`` frames.

    ``start(seq, t_capture_s)`` when the frame is grabbed, ``mark(seq, name)`` as it leaves each
    stage (e.g. "tracked", "globalized", "wire"). Each mark records the stage span (since the
    previous mark) under ``name`` and the cumulative time since capture under ``capture→name``.
    Frames that never reach a stage (dropped, lost tracking) simply add no sample there; at most
    ``max_pending`` frames are kept open. All times are ``time.monotonic()`` seconds.
    """

    window: int = 2000
    max_pending: int = 256
    _pending: OrderedDict[int, tuple[float, float]] = field(default_factory=OrderedDict)  # seq → (t_capture_s, t_last_mark_s)
    _samples: dict[str, deque] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def start(self, seq: int, t_capture_s: float) -> None:
        with self._lock:
            self._pending[seq] = (t_capture_s, t_capture_s)
            while len(self._pending) > self.max_pending:
                self._pending.popitem(last=False)

    def mark(self, seq: int, name: str, t_s: float | None = None) -> None:
        t_s = time.monotonic() if t_s is None else t_s
        with self._lock:
            entry = self._pending.get(seq)
            if entry is None:
                return
            t0, t_prev = entry
            self._pending[seq] = (t0, t_s)
            self._add(name, t_s - t_prev)
            self._add(f"capture→{name}", t_s - t0)

    def finish(self, seq: int) -> None:
        """Forget the frame (after its last mark)."""
        with self._lock:
            self._pending.pop(seq, None)

    def _add(self, key: str, dt_s: float) -> None:
        self._samples.setdefault(key, deque(maxlen=self.window)).append(dt_s * 1e3)

    def samples_ms(self, key: str) -> np.ndarray:
        with self._lock:
            return np.array(self._samples.get(key, ()), dtype=float)

    def summary(self) -> dict[str, LatencySummary]:
        with self._lock:
            items = {k: np.array(v, dtype=float) for k, v in self._samples.items() if v}
        return {
            k: LatencySummary(n=len(v), p50_ms=float(np.percentile(v, 50)), p99_ms=float(np.percentile(v, 99)), max_ms=float(v.max()))
            for k, v in items.items()
        }

    def format(self) -> str:
        """One log line: ``name P50/P99 ms`` per key."""
        return "; ".join(f"{k} p50={s.p50_ms:.1f} p99={s.p99_ms:.1f} ms (n={s.n})" for k, s in self.summary().items())
