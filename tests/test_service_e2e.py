"""`terraslam run --config FILE` as a real process, the way systemd runs it (systemd/terraslam.service).

Real parts only: the console-script entry point in a subprocess, the built-in simulated camera, a
GIS mesh written by the simulator's exporter (binary PLY + georef sidecar), the simulated autopilot
over real UDP on 127.0.0.1 (fed a good GNSS receiver, as on the ground before take-off), and a
real AF_UNIX datagram socket as $NOTIFY_SOCKET. Checked: READY=1, WATCHDOG=1 pings that keep
coming only because the hot path keeps beating, STATUS= lines carrying what the autopilot reports,
our HEARTBEAT at the autopilot, SIGTERM → STOPPING=1 and exit 0 within the unit's TimeoutStopSec;
and a bad gis.model → a one-line error naming the file and exit 2.
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from test_companion_supervisor import NotifyListener  # tests/ is on sys.path (no package)

from gis.cache import GisCache
from mavlink_bridge.scenario import Flight
from mavlink_bridge.sim_autopilot import SimAutopilot

TERRASLAM = Path(sys.executable).with_name("terraslam")
STALL_TIMEOUT_S = 1.0
DEADLINE_S = max(2.0, 3 * STALL_TIMEOUT_S)  # the hot-path stage deadline run_service derives from it
WATCHDOG_USEC = 1_000_000  # ping every 0.5 s
TIMEOUT_STOP_S = 15.0  # TimeoutStopSec in systemd/terraslam.service

pytestmark = [
    pytest.mark.skipif(not TERRASLAM.exists(), reason="terraslam entry point not installed in this environment"),
    pytest.mark.timeout(150),
]


@pytest.fixture(scope="module")
def gis_mesh(tmp_path_factory) -> Path:
    """The nominal scenario's (stale) GIS world as the exporter writes it: model.ply + sidecar."""
    from companion.sim import make_scenario
    from companion.sim.gis_export import export_gis

    gis_world, _ = make_scenario("nominal").gis
    return export_gis(gis_world, tmp_path_factory.mktemp("gis"), seed=0).mesh_ply


def _write_config(tmp_path: Path, model: Path, port: int) -> Path:
    cfg = tmp_path / "config.yaml"
    cfg.write_text(
        "camera:\n"
        "  source: sim\n"
        "  fps: 10.0\n"
        f"  stall_timeout_s: {STALL_TIMEOUT_S}\n"
        "gis:\n"
        f"  model: {model}\n"
        f"  cache_dir: {tmp_path / 'cache'}\n"
        "mavlink:\n"
        f"  connect: udpout:127.0.0.1:{port}\n"
        "  autopilot: ardupilot\n"
        "  output: gps_input\n"
        "supervisor:\n"
        f"  state_dir: {tmp_path / 'state'}\n"
    )
    return cfg


def _service_env(extra: dict[str, str]) -> dict[str, str]:
    """This environment without TERRASLAM_* overrides (the test's config file is the whole config)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("TERRASLAM_")}
    env.update(PYTHONUNBUFFERED="1", MPLBACKEND="Agg", **extra)
    return env


class TimedListener:
    """NotifyListener plus the monotonic time each datagram was read (to within one poll)."""

    def __init__(self) -> None:
        self.lst = NotifyListener()
        self.timed: list[tuple[float, str]] = []

    def poll(self, wait_s: float = 0.1) -> None:
        n = len(self.lst.messages)
        self.lst.drain(wait_s)
        now = time.monotonic()
        self.timed.extend((now, m) for m in self.lst.messages[n:])

    def times(self, line: str) -> list[float]:
        return [t for t, m in self.timed if line in m.split("\n")]

    def lines(self, prefix: str) -> list[str]:
        return [kv for _, m in self.timed for kv in m.split("\n") if kv.startswith(prefix)]

    def wait_for(self, pred, timeout_s: float, proc: subprocess.Popen | None = None) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.poll()
            if pred():
                return True
            if proc is not None and proc.poll() is not None:
                break
        self.poll()
        return pred()


def _feed_good_gnss(sim: SimAutopilot, stop: threading.Event) -> None:
    """A healthy 5 Hz receiver on the autopilot, as on the ground before take-off."""
    flight, t0 = Flight(), time.monotonic()
    while not stop.wait(0.2):
        now = time.monotonic()
        sim.feed_gnss(flight.gnss(now, now - t0))


def test_service_runs_supervised_talks_mavlink_and_stops_cleanly(tmp_path: Path, gis_mesh: Path) -> None:
    t_test = time.monotonic()
    sim = SimAutopilot("ardupilot", params={"GPS_AUTO_SWITCH": 0, "GPS_PRIMARY": 0}).start()
    stop_gnss = threading.Event()
    feeder = threading.Thread(target=_feed_good_gnss, args=(sim, stop_gnss), daemon=True)
    feeder.start()
    notify = TimedListener()
    log_path = tmp_path / "service.log"
    cfg = _write_config(tmp_path, gis_mesh, sim.port)
    env = _service_env({"NOTIFY_SOCKET": notify.lst.address, "WATCHDOG_USEC": str(WATCHDOG_USEC)})
    with open(log_path, "wb") as log_file:
        proc = subprocess.Popen([str(TERRASLAM), "run", "--config", str(cfg)], env=env,
                                stdout=log_file, stderr=subprocess.STDOUT)
    rc = stop_s = None
    try:
        # startup: imports, scenario, GIS model load + cache (TimeoutStartSec=120 s in the unit)
        assert notify.wait_for(lambda: notify.times("READY=1"), 45.0, proc), \
            f"no READY=1 (exit code {proc.poll()}):\n{log_path.read_text()[-3000:]}"
        t_ready = notify.times("READY=1")[0]
        # Run past two stage deadlines: a ping after t_ready + DEADLINE_S needs a hot-path beat
        # after start (Supervisor pings only while every required stage beat within its deadline),
        # i.e. frames flowing; and until the autopilot has our heartbeats and the STATUS shows the
        # GNSS the autopilot reports (autopilot → bridge → service → sd_notify).
        def settled() -> bool:
            pings = notify.times("WATCHDOG=1")
            return (bool(pings) and pings[-1] > t_ready + 2 * DEADLINE_S
                    and sim.received().counts["HEARTBEAT"] >= 2
                    and any("GNSS good" in s for s in notify.lines("STATUS=")))
        settled_ok = notify.wait_for(settled, 2 * DEADLINE_S + 25.0, proc)
        alive_before_term = proc.poll() is None
        received = sim.received()
        proc.send_signal(signal.SIGTERM)
        t_term = time.monotonic()
        rc = proc.wait(TIMEOUT_STOP_S + 5)
        stop_s = time.monotonic() - t_term
        notify.poll(0.3)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        stop_gnss.set()
        feeder.join(2.0)
        sim.close()
        notify.lst.close()
    log_text = log_path.read_text()
    pings = notify.times("WATCHDOG=1")
    statuses = notify.lines("STATUS=")
    print(f"READY after {t_ready - t_test:.1f} s; {len(pings)} pings; stop took {stop_s:.1f} s; "
          f"autopilot received {dict(received.counts)}; statuses {sorted(set(statuses))}")

    assert alive_before_term, f"service exited on its own with {proc.returncode}:\n{log_text[-3000:]}"
    assert settled_ok, (f"pings at +{[round(t - t_ready, 1) for t in pings]} s after READY, autopilot got "
                        f"{dict(received.counts)}, statuses {statuses}:\n{log_text[-3000:]}")
    assert notify.lst.count("READY=1") == 1
    # pings kept coming, both early and after the stage had to prove it beats on its own
    assert len([t for t in pings if t_ready < t]) >= 4
    assert any(t_ready + DEADLINE_S < t for t in pings)
    # STATUS lines carry bridge state, GNSS quality and alignment
    assert statuses and all(
        re.fullmatch(r"STATUS=(tracking|(standby|active); GNSS \w+; alignment \w+|degraded: .+)", s) for s in statuses
    ), statuses
    # the bridge talks MAVLink over UDP both ways: our heartbeats arrive, and it heard the autopilot
    assert received.counts["HEARTBEAT"] >= 2
    assert "link up: ardupilot" in log_text
    # clean stop within the unit's TimeoutStopSec, exit 0 (Restart=on-failure must not restart it)
    assert rc == 0, log_text[-3000:]
    assert stop_s < TIMEOUT_STOP_S
    assert notify.lst.count("STOPPING=1") == 1
    assert notify.times("STOPPING=1")[0] >= max(pings)
    assert "Traceback" not in log_text, log_text[-3000:]
    # the model went into the GIS cache (CacheDirectory= in the unit)
    entries = GisCache(tmp_path / "cache").entries()
    assert [Path(e.source_path) for e in entries] == [gis_mesh] and entries[0].model_file.is_file()


def _truncated_copy(src: Path, dst_dir: Path) -> Path:
    """A download cut short: the real mesh's header and first bytes, its sidecar intact."""
    dst = dst_dir / "cut.ply"
    data = src.read_bytes()
    dst.write_bytes(data[: len(data) // 3])
    side = src.with_name(src.name + ".georef.json")
    dst.with_name(dst.name + ".georef.json").write_text(side.read_text())
    return dst


@pytest.mark.parametrize("case", ["missing", "truncated"])
def test_bad_gis_model_exits_2_with_a_one_line_error_naming_the_file(tmp_path: Path, gis_mesh: Path, case: str) -> None:
    model = tmp_path / "nowhere" / "model.ply" if case == "missing" else _truncated_copy(gis_mesh, tmp_path)
    # nothing listens on this port: the service must stop before it opens the link
    cfg = _write_config(tmp_path, model, 9)
    notify = NotifyListener()
    try:
        res = subprocess.run([str(TERRASLAM), "run", "--config", str(cfg)], env=_service_env(notify.environ),
                             capture_output=True, text=True, timeout=90)
        notify.drain(0.1)
    finally:
        notify.close()
    out = res.stdout + res.stderr
    assert res.returncode == 2, out
    assert "Traceback" not in out and "╭" not in out, out  # no (rich) traceback
    errors = [line for line in out.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and str(model) in errors[0] and "gis.model" in errors[0], out
    assert ("no such file" if case == "missing" else "cannot parse") in errors[0]
    assert notify.count("READY=1") == 0  # systemd sees a failed start, not a running service
    assert not (tmp_path / "cache").exists() or not GisCache(tmp_path / "cache").entries()
