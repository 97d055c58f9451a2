"""sd_notify against a real AF_UNIX datagram socket, supervised stages, signals, latency accounting.

The listener below is what systemd does for Type=notify units: bind an AF_UNIX SOCK_DGRAM socket
(path or abstract), hand its name over in $NOTIFY_SOCKET and read VAR=value datagrams. The real
``systemd-notify`` tool (when installed) is used to check that the listener reads what systemd's
own client sends.
"""
from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from companion import notify
from companion.supervisor import LatencyTracker, Stage, StageContext, StageState, Supervisor


class NotifyListener:
    """A fake systemd manager end of $NOTIFY_SOCKET."""

    def __init__(self, path: Path | None = None) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        if path is None:
            name = f"terraslam-test-{uuid.uuid4().hex}"
            self.sock.bind("\0" + name)
            self.address = "@" + name
        else:
            self.sock.bind(str(path))
            self.address = str(path)
        self.sock.settimeout(0.05)
        self.messages: list[str] = []

    @property
    def environ(self) -> dict[str, str]:
        return {"NOTIFY_SOCKET": self.address}

    def drain(self, wait_s: float = 0.2) -> list[str]:
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            try:
                self.messages.append(self.sock.recv(4096).decode())
            except socket.timeout:
                continue
        return self.messages

    def count(self, line: str) -> int:
        return sum(line in m.split("\n") for m in self.messages)

    def close(self) -> None:
        self.sock.close()


@pytest.fixture(params=["abstract", "path"])
def listener(request, tmp_path: Path):
    lst = NotifyListener(None if request.param == "abstract" else tmp_path / "notify.sock")
    yield lst
    lst.close()


# --- notify ---


def test_notify_messages_reach_the_socket(listener: NotifyListener) -> None:
    env = listener.environ
    assert notify.ready("tracking", env)
    assert notify.status("lost\nsecond line ignored", env)
    assert notify.watchdog(env)
    assert notify.stopping(env)
    msgs = listener.drain()
    assert msgs == ["READY=1\nSTATUS=tracking", "STATUS=lost", "WATCHDOG=1", "STOPPING=1"]


def test_notify_without_socket_is_a_noop() -> None:
    assert notify.watchdog({}) is False
    assert notify.ready(None, {"NOTIFY_SOCKET": "relative/path"}) is False


def test_notify_to_a_vanished_socket_degrades(tmp_path: Path) -> None:
    assert notify.watchdog({"NOTIFY_SOCKET": str(tmp_path / "gone.sock")}) is False


def test_watchdog_interval() -> None:
    pid = str(os.getpid())
    assert notify.watchdog_interval_s({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": pid}) == 5.0
    assert notify.watchdog_interval_s({"WATCHDOG_USEC": "3000000"}) == 1.5
    assert notify.watchdog_interval_s({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "1"}) is None
    assert notify.watchdog_interval_s({"WATCHDOG_USEC": "abc"}) is None
    assert notify.watchdog_interval_s({}) is None


@pytest.mark.skipif(shutil.which("systemd-notify") is None, reason="systemd-notify not installed")
def test_listener_reads_what_systemd_notify_sends() -> None:
    lst = NotifyListener()
    try:
        env = dict(os.environ, **lst.environ)
        subprocess.run(["systemd-notify", "--no-block", "--ready", "--status=from systemd"], env=env, check=True, timeout=10)
        ours = notify.ready("from systemd", lst.environ)
        msgs = lst.drain()
    finally:
        lst.close()
    assert ours and len(msgs) == 2
    # systemd's client and ours produce the same variables (systemd may add MAINPID=...)
    theirs = {kv for kv in msgs[0].split("\n") if not kv.startswith("MAINPID=")}
    assert theirs == set(msgs[1].split("\n")) == {"READY=1", "STATUS=from systemd"}


# --- stages and supervisor ---


def _counting_stage(name: str, fail_at: set[int] | None = None, **kw) -> tuple[Stage, list[int]]:
    seen: list[int] = []

    def target(ctx: StageContext) -> None:
        while not ctx.stop.is_set():
            i = len(seen)
            seen.append(i)
            if fail_at and i in fail_at:
                raise RuntimeError(f"boom at {i}")
            ctx.beat()
            time.sleep(0.01)

    return Stage(name, target, **kw), seen


def _wait_for(pred, timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.02)
    return pred()


def test_stage_crash_is_restarted_and_keeps_progressing() -> None:
    stage, seen = _counting_stage("tracking", fail_at={5}, backoff_s=0.05)
    stage.start()
    assert _wait_for(lambda: len(seen) > 20)
    h = stage.health()
    stage.stop()
    assert stage.join(2.0)
    assert h.restarts == 1 and h.state == StageState.RUNNING and h.healthy
    assert h.last_error == "RuntimeError: boom at 5" and h.progress >= 19
    assert stage.health().state == StageState.STOPPED


def test_stage_exceeding_restart_limit_fails() -> None:
    stage, seen = _counting_stage("gis", fail_at=set(range(100)), restart_limit=2, backoff_s=0.01)
    stage.start()
    assert stage.join(5.0)
    h = stage.health()
    assert h.state == StageState.FAILED and h.restarts == 2 and not h.healthy and len(seen) == 3  # 1 run + 2 restarts


def test_hung_stage_stops_watchdog_pings(listener: NotifyListener) -> None:
    release = threading.Event()

    def hangs_after_a_while(ctx: StageContext) -> None:
        for _ in range(15):
            ctx.beat()
            time.sleep(0.02)
        release.wait()  # stuck (e.g. a blocked driver call): no more beats

    ok_stage, _ = _counting_stage("capture")
    env = dict(listener.environ, WATCHDOG_USEC="100000")  # ping every 50 ms
    sup = Supervisor([ok_stage, Stage("tracking", hangs_after_a_while, deadline_s=0.3)], environ=env)
    sup.start()

    def tick_for(duration_s: float) -> None:
        t_end = time.monotonic() + duration_s
        while time.monotonic() < t_end:
            sup.tick()
            time.sleep(0.01)

    tick_for(0.25)  # both stages beating
    listener.drain()
    pings_healthy = listener.count("WATCHDOG=1")
    assert _wait_for(lambda: not sup.healthy(), 5.0)  # tracking missed its 0.3 s deadline
    tick_for(0.05)
    listener.drain()
    pings_at_hang = listener.count("WATCHDOG=1")
    tick_for(0.5)
    listener.drain()
    pings_after = listener.count("WATCHDOG=1")
    release.set()
    sup.shutdown()
    listener.drain()
    assert listener.count("READY=1") == 1
    assert pings_healthy >= 2  # pinged while both stages beat
    assert pings_after == pings_at_hang  # not a single ping while tracking is stuck
    assert any(m.startswith("STATUS=degraded: tracking=running") for m in listener.messages)
    assert listener.count("STOPPING=1") == 1


def test_supervisor_run_exits_1_when_a_required_stage_fails(listener: NotifyListener) -> None:
    stage, _ = _counting_stage("slam", fail_at=set(range(100)), restart_limit=1, backoff_s=0.01)
    optional, _ = _counting_stage("viz", fail_at=set(range(100)), restart_limit=0, required=False)
    saved: list[str] = []
    sup = Supervisor([stage, optional], environ=listener.environ)
    sup.on_shutdown("save T_fine", lambda: saved.append("T_fine"))
    sup.start()
    assert sup.run(poll_s=0.05) == 1
    assert saved == ["T_fine"]


def test_supervisor_run_exits_0_when_input_is_exhausted(listener: NotifyListener) -> None:
    def finite(ctx: StageContext) -> None:
        for _ in range(5):
            ctx.beat()

    sup = Supervisor([Stage("replay", finite)], environ=listener.environ)
    sup.start()
    assert sup.run(poll_s=0.05) == 0
    assert sup.health()[0].state == StageState.DONE


def test_shutdown_hooks_run_newest_first_even_if_one_fails(listener: NotifyListener) -> None:
    order: list[str] = []
    sup = Supervisor([], environ=listener.environ)
    sup.on_shutdown("first", lambda: order.append("first"))
    sup.on_shutdown("broken", lambda: 1 / 0)
    sup.on_shutdown("last", lambda: order.append("last"))
    sup.shutdown()
    assert order == ["last", "first"]


def test_duplicate_stage_names_refused() -> None:
    a, _ = _counting_stage("x")
    b, _ = _counting_stage("x")
    with pytest.raises(ValueError, match="unique"):
        Supervisor([a, b])


SERVICE_SCRIPT = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from companion.supervisor import Stage, Supervisor

    def work(ctx):
        while not ctx.stop.is_set():
            ctx.beat()
            time.sleep(0.01)

    out = Path(sys.argv[1])
    sup = Supervisor([Stage("tracking", work)])
    sup.on_shutdown("save T_fine", lambda: out.write_text("T_fine saved"))
    sup.install_signal_handlers()
    sup.start()
    sys.exit(sup.run(poll_s=0.05))
    """
)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_gives_clean_shutdown_in_a_real_process(tmp_path: Path, sig: signal.Signals) -> None:
    lst = NotifyListener()
    try:
        out = tmp_path / "state.txt"
        env = dict(os.environ, **lst.environ)
        proc = subprocess.Popen([sys.executable, "-c", SERVICE_SCRIPT, str(out)], env=env)
        assert _wait_for(lambda: lst.drain(0.05) and lst.count("READY=1") == 1, 20.0)
        proc.send_signal(sig)
        assert proc.wait(10) == 0
        lst.drain()
    finally:
        lst.close()
    assert out.read_text() == "T_fine saved"
    assert lst.count("STOPPING=1") == 1


# --- latency ---


def test_latency_tracker_spans_and_percentiles() -> None:
    tr = LatencyTracker(window=1000)
    rng = np.random.default_rng(0)
    track_ms = rng.uniform(5, 15, 200)
    glob_ms = rng.uniform(1, 2, 200)
    for seq in range(200):
        t0 = 100.0 + seq
        tr.start(seq, t0)
        tr.mark(seq, "tracked", t0 + track_ms[seq] / 1e3)
        if seq % 4:  # every 4th frame is lost: never reaches the wire
            tr.mark(seq, "wire", t0 + (track_ms[seq] + glob_ms[seq]) / 1e3)
        tr.finish(seq)
    s = tr.summary()
    wire = np.array([track_ms[i] + glob_ms[i] for i in range(200) if i % 4])
    assert s["tracked"].n == 200 and s["wire"].n == 150 and s["capture→wire"].n == 150
    assert s["tracked"].p50_ms == pytest.approx(np.percentile(track_ms, 50))
    assert s["capture→wire"].p99_ms == pytest.approx(np.percentile(wire, 99))
    assert s["wire"].max_ms == pytest.approx(max(glob_ms[i] for i in range(200) if i % 4))
    assert "capture→wire p50=" in tr.format()
    tr.mark(12345, "wire")  # unknown / evicted frame: ignored
    assert tr.summary()["wire"].n == 150
