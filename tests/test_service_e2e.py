"""`terraslam run --config FILE` as a real process, the way systemd runs it (systemd/terraslam.service).

Real parts only: the console-script entry point in a subprocess, the built-in simulated camera, a
GIS mesh written by the simulator's exporter (binary PLY + georef sidecar), the simulated autopilot
over real UDP on 127.0.0.1 (fed a good GNSS receiver, as on the ground before take-off), and a
real AF_UNIX datagram socket as $NOTIFY_SOCKET. Checked: READY=1, WATCHDOG=1 pings that keep
coming only because the hot path keeps beating, STATUS= lines carrying what the autopilot reports,
our HEARTBEAT at the autopilot, SIGTERM → STOPPING=1 and exit 0 within the unit's TimeoutStopSec;
and a bad gis.model → a one-line error naming the file and exit 2. Issue 7: fed what the simulated
vehicle's receiver and AHRS report on the service's own simulated flight (in real time, on the
flight's clock), the service bootstraps its alignment from GNSS, takes over when GNSS is lost, and the
autopilot keeps getting 3D fixes from us that agree with the flight's truth.
"""
from __future__ import annotations

import collections
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import psutil
import pytest
import yaml

from gis.cache import GisCache
from gis.geodesy import LocalFrame, ellipsoid_to_msl
from mavlink_bridge.scenario import Flight
from mavlink_bridge.sim_autopilot import SimAutopilot
from mavlink_bridge.types import GnssSample, GpsFixType
from test_companion_supervisor import NotifyListener  # tests/ is on sys.path (no package)

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


def _write_config(tmp_path: Path, model: Path, port: int, fps: float = 10.0, max_fix_age_s: float = 0.5,
                  record: bool = False) -> Path:
    cfg = tmp_path / "config.yaml"
    cfg.write_text(('recording:\n  enabled: true\n  image_format: png\n' if record else "") +
        "camera:\n"
        "  source: sim\n"
        f"  fps: {fps}\n"
        f"  stall_timeout_s: {STALL_TIMEOUT_S}\n"
        "gis:\n"
        f"  model: {model}\n"
        f"  cache_dir: {tmp_path / 'cache'}\n"
        "mavlink:\n"
        f"  connect: udpout:127.0.0.1:{port}\n"
        "  autopilot: ardupilot\n"
        "  output: gps_input\n"
        f"  max_fix_age_s: {max_fix_age_s}\n"
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


def _earlier_flights_found_the_model_off(cfg_path: Path) -> str:
    """Store in the service's GIS cache the evidence of earlier flights at the site: six
    registrations that put the model 2.5 m east of GNSS (gis.align.georef); returns the site id."""
    from companion.config import load_config
    from gis.align.georef import GeorefCheck
    from gis.cache import GisCache
    from gis.loaders import load_model

    cfg = load_config(cfg_path)
    cache = GisCache(cfg.gis.cache_dir)
    site_id = cache.save_model(load_model(cfg.gis.model, cfg.gis.sample_spacing_m, cfg.gis.footprint_ground))
    chk = GeorefCheck(cfg.alignment.model_sigma_m)
    rng = np.random.default_rng(0)
    for k in range(6):
        chk.add(20.0 * k, np.array([2.5, 0.0, 0.0]) + rng.normal(0, 0.5, 3), np.eye(3))
    cache.save_georef(site_id, chk.evidence)
    return site_id


def test_service_runs_supervised_talks_mavlink_and_stops_cleanly(tmp_path: Path, gis_mesh: Path) -> None:
    t_test = time.monotonic()
    sim = SimAutopilot("ardupilot", params={"GPS_AUTO_SWITCH": 0, "GPS_PRIMARY": 0}).start()
    stop_gnss = threading.Event()
    feeder = threading.Thread(target=_feed_good_gnss, args=(sim, stop_gnss), daemon=True)
    feeder.start()
    notify = TimedListener()
    log_path = tmp_path / "service.log"
    cfg = _write_config(tmp_path, gis_mesh, sim.port)
    site_id = _earlier_flights_found_the_model_off(cfg)
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
    # fine-tuning's kernels were compiled or loaded before READY, under an extended start timeout
    msgs = notify.lst.messages
    kernels = [i for i, m in enumerate(msgs) if m.startswith("STATUS=starting: fine-tuning kernels")]
    ready = next(i for i, m in enumerate(msgs) if "READY=1" in m.split("\n"))
    assert kernels and kernels[0] < ready and any(m.startswith("EXTEND_TIMEOUT_USEC=") for m in msgs)
    # pings kept coming, both early and after the stage had to prove it beats on its own
    assert len([t for t in pings if t_ready < t]) >= 4
    assert any(t_ready + DEADLINE_S < t for t in pings)
    # STATUS lines carry bridge state, GNSS quality and alignment
    assert statuses and all(
        re.fullmatch(r"STATUS=(starting: .+|tracking|(standby|active); GNSS \w+; alignment \w+(; GNSS \d+\.\d m from ours)?|degraded: .+)", s)
        for s in statuses
    ), statuses
    # the bridge talks MAVLink over UDP both ways: our heartbeats arrive, and it heard the autopilot
    assert received.counts["HEARTBEAT"] >= 2
    assert "link up: ardupilot" in log_text
    # clean stop within the unit's TimeoutStopSec, exit 0 (Restart=on-failure must not restart it)
    assert rc == 0, log_text[-3000:]
    assert stop_s < TIMEOUT_STOP_S
    assert notify.lst.count("STOPPING=1") == 1
    assert notify.times("STOPPING=1")[0] >= max(pings)
    # the GIS cache's evidence on the model's georeference (earlier flights) corrected it at start
    assert "6 registrations vs GNSS; GIS model georeference off by" in log_text, log_text[-3000:]
    assert site_id in log_text
    assert "Traceback" not in log_text, log_text[-3000:]
    # the model went into the GIS cache (CacheDirectory= in the unit)
    entries = GisCache(tmp_path / "cache").entries()
    assert [Path(e.source_path) for e in entries] == [gis_mesh] and entries[0].model_file.is_file()


# The renderer needs ~0.3 s for a 640x480 frame on 2 cores, so the simulated camera plays in real time
# at 2 fps (at 10 fps it would fall further behind every frame). The nominal flight's first leg is
# straight until 27 s; then comes a 90° turn at up to ~28°/s that monocular SLAM does not track at
# 2 fps. The GNSS bootstrap needs 30 pairs (one a frame: 15 s at 2 fps, plus SLAM initialisation).
SIM_FPS = 2.0
EARLIEST_LOSS_S = 20.0  # flight time: GNSS is cut 1 s after the service reports a GNSS alignment, not before this
LATEST_LOSS_S = 23.0    # ... nor after this (the test fails: no alignment in time)
END_S = 27.0            # the run ends before the turn
MAX_FIX_AGE_S = 1.0     # a 2 fps camera's fix stays current until the next frame's (the 0.5 s default suits >= 3 fps)
EPOCH_RE = re.compile(r"camera source sim: realtime playback, source time 0 s plays at monotonic ([0-9.]+) s")


class VehicleFeed:
    """What the simulated vehicle's receiver and AHRS report on the service's own simulated flight,
    fed to the simulated autopilot in real time on that flight's clock: flight time t plays at
    monotonic ``epoch_s`` + t (the service logs the epoch; CLOCK_MONOTONIC is one clock for every
    process on the machine). GNSS goes NO_FIX from ``loss_at_s`` on, as the simulator's dropout does.

    It also records every GPS_INPUT the autopilot took in, read from the simulated autopilot's record
    of the last one: its ``estimate()`` ignores a MAVLink GPS below 5 Hz, and our output follows the
    2 fps camera."""

    def __init__(self, sim: SimAutopilot, scenario, epoch_s: float) -> None:
        self.sim, self.scenario, self.epoch_s = sim, scenario, epoch_s
        self.loss_at_s = float("inf")  # set by the test while the feed runs
        self.gps_input: list[tuple[float, int, float, float, float]] = []  # (flight t at receipt, fix, lat, lon, h_acc)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="vehicle-feed", daemon=True)

    def flight_t(self, mono_s: float | None = None) -> float:
        return (time.monotonic() if mono_s is None else mono_s) - self.epoch_s

    def truth(self, t_s: float) -> tuple[float, float, float]:
        """(lat, lon, h_msl) of the vehicle at flight time t_s (body = camera centre: no lever arm)."""
        p, _, _, _ = self.scenario.trajectory.state(t_s)
        lat, lon, h = self.scenario.origin.enu_to_geodetic(p[0])
        return float(lat), float(lon), float(ellipsoid_to_msl(lat, lon, h))

    def _run(self) -> None:
        gnss, att = self.scenario.gnss_samples, self.scenario.attitude_samples
        gi = ai = 0
        fed_g = fed_a = -1
        last_mgps = None
        while not self.stop.wait(0.005):
            t = self.flight_t()
            while ai < len(att) and att[ai].t_s <= t:
                ai += 1
            if ai and ai - 1 != fed_a:  # the newest attitude due (50 Hz in the scenario)
                a = att[ai - 1]
                self.sim.feed_attitude(a.roll_rad, a.pitch_rad, a.yaw_rad)
                fed_a = ai - 1
            while gi < len(gnss) and gnss[gi].t_s <= t:
                gi += 1
            if gi and gi - 1 != fed_g:  # the newest receiver solution due (5 Hz), stamped on the autopilot's clock
                g = gnss[gi - 1]
                stamp = self.epoch_s + g.t_s
                if g.t_s < self.loss_at_s:
                    self.sim.feed_gnss(replace(g, t_s=stamp))
                else:
                    self.sim.feed_gnss(GnssSample(stamp, GpsFixType.NO_FIX, 0.0, 0.0, 0.0, 0.0, 99.99, 99.99, 100.0, 100.0, 3))
                self.sim.set_truth(*self.truth(g.t_s))
                fed_g = gi - 1
            with self.sim._lock:
                m = dict(self.sim._mgps) if self.sim._mgps is not None else None
            if m is not None and m["t"] != last_mgps:
                last_mgps = m["t"]
                self.gps_input.append((self.flight_t(m["t"]), int(m["fix"]), m["lat"], m["lon"], m["hacc"]))

    def __enter__(self) -> "VehicleFeed":
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join(2.0)


def stop_all(procs, feeds, sim: SimAutopilot, notify: TimedListener) -> None:
    """Test teardown: kill the service processes still running, stop the vehicle feeds, close the
    simulated autopilot and the notify listener."""
    for p in procs:
        if p is not None and p.poll() is None:
            p.kill()
            p.wait(10)
    for f in feeds:
        if f is not None:
            f.__exit__()
    sim.close()
    notify.lst.close()


def _horizontal_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    ned = LocalFrame(lat2, lon2, 0.0).geodetic_to_ned(lat1, lon1, 0.0)
    return float(np.hypot(ned[0], ned[1]))


def test_service_takes_over_and_emits_fixes_after_gnss_loss(tmp_path: Path, gis_mesh: Path) -> None:
    """Issue 7: `terraslam run` against the simulated autopilot bootstraps its alignment from the
    simulated flight's GNSS + attitude; when GNSS is lost it takes over, and the autopilot gets 3D
    fixes from us that agree with the flight's truth within their reported accuracy — also after
    its worker processes are killed mid-outage (a killed stage)."""
    from companion.sim import make_scenario

    t_test = time.monotonic()
    scenario = make_scenario("nominal", fps=SIM_FPS)  # the service's flight: same name, seed (0) and fps
    sim = SimAutopilot("ardupilot", params={"GPS_AUTO_SWITCH": 0, "GPS_PRIMARY": 0}).start()
    notify = TimedListener()
    log_path = tmp_path / "service.log"
    cfg = _write_config(tmp_path, gis_mesh, sim.port, fps=SIM_FPS, max_fix_age_s=MAX_FIX_AGE_S, record=True)
    with open(log_path, "wb") as log_file:
        proc = subprocess.Popen([str(TERRASLAM), "run", "--config", str(cfg)], env=_service_env(notify.lst.environ),
                                stdout=log_file, stderr=subprocess.STDOUT)
    feed = at_loss = rc = None
    try:
        # the simulated flight starts when the service opens its camera (before the bridge and READY)
        epoch = None
        deadline = time.monotonic() + 45.0
        while epoch is None and time.monotonic() < deadline and proc.poll() is None:
            m = EPOCH_RE.search(log_path.read_text())
            epoch = float(m.group(1)) if m else None
            time.sleep(0.02)
        assert epoch is not None, f"no playback epoch logged (exit code {proc.poll()}):\n{log_path.read_text()[-3000:]}"
        feed = VehicleFeed(sim, scenario, epoch).__enter__()
        feed_start_t = feed.flight_t()  # receiver/AHRS output due before this was not fed (the bridge was not up yet)
        assert notify.wait_for(lambda: notify.times("READY=1"), 45.0, proc), \
            f"no READY=1 (exit code {proc.poll()}):\n{log_path.read_text()[-3000:]}"
        ready_t = feed.flight_t(notify.times("READY=1")[0])

        def aligned() -> bool:
            return any(re.search(r"; alignment gnss(;|$)", s) for s in notify.lines("STATUS="))
        notify.wait_for(lambda: aligned() or feed.flight_t() >= LATEST_LOSS_S - 1.0, LATEST_LOSS_S + 5.0, proc)
        aligned_t = feed.flight_t() if aligned() else None
        feed.loss_at_s = loss_at = min(max(EARLIEST_LOSS_S, feed.flight_t() + 1.0), LATEST_LOSS_S)
        notify.wait_for(lambda: feed.flight_t() >= loss_at - 0.15, LATEST_LOSS_S + 5.0, proc)
        at_loss = sim.received()  # the last look before the first NO_FIX sample
        # a killed stage: 1 s into the outage the service's worker processes (bundle adjustment,
        # GIS fine-tuning) are SIGKILLed, as the kernel's OOM killer would; fixes must go on
        notify.wait_for(lambda: feed.flight_t() >= loss_at + 1.0, 5.0, proc)
        killed = [c.pid for c in psutil.Process(proc.pid).children(recursive=True)]
        for pid in killed:
            os.kill(pid, signal.SIGKILL)
        notify.wait_for(lambda: feed.flight_t() >= END_S, END_S - loss_at + 5.0, proc)
        alive_before_term = proc.poll() is None
        received = sim.received()
        est = sim.estimate()
        end_t = feed.flight_t()
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(TIMEOUT_STOP_S + 5)
        notify.poll(0.2)
    finally:
        stop_all([proc], [feed], sim, notify)
    log_text = log_path.read_text()
    wall_s = time.monotonic() - t_test
    texts = [t for _, t in received.statustext]
    texts_before = [t for _, t in at_loss.statustext]
    before_3d = [r for r in feed.gps_input if r[0] < loss_at and r[1] >= 3]
    after = [r for r in feed.gps_input if loss_at <= r[0] <= end_t]
    fixes_3d = [r for r in after if r[1] >= 3]
    # A fix is for the newest frame due before it arrived (frames play at k / fps; tracking takes
    # < 0.4 s): its error against the truth at that frame's time, and (conservative, adds the
    # latency's along-track motion) at the time of receipt.
    err = [(t, _horizontal_m(lat, lon, *feed.truth(np.floor(t * SIM_FPS) / SIM_FPS)[:2]),
            _horizontal_m(lat, lon, *feed.truth(t)[:2]), hacc) for t, _, lat, lon, hacc in fixes_3d]
    statuses = [(round(feed.flight_t(t), 1), kv[7:]) for t, m in notify.timed for kv in m.split("\n") if kv.startswith("STATUS=")]
    statuses = [c for i, c in enumerate(statuses) if i == 0 or c[1] != statuses[i - 1][1]]
    summary = (f"wall {wall_s:.1f} s; flight t: feed start {feed_start_t:.1f} s, READY {ready_t:.1f} s, GNSS alignment "
               f"seen {aligned_t if aligned_t is None else round(aligned_t, 1)} s, loss {loss_at:.1f} s, end {end_t:.1f} s; "
               f"STATUS changes {statuses}; GPS_INPUT with 3D fix before the loss {len(before_3d)}, after {len(fixes_3d)} "
               f"of {len(after)}; accepted at loss {at_loss.accepted['GPS_INPUT']}, at end {received.accepted['GPS_INPUT']}; "
               f"STATUSTEXT {texts}; autopilot estimate {est.source}; rejections {received.rejections[:5]}; "
               f"after-loss fixes (t, horizontal error at frame time / at receipt, h_acc; m): "
               f"{[tuple(round(x, 1) for x in e) for e in err]}")
    print(summary)
    diag = summary + "\n" + log_text[-3000:]

    assert alive_before_term, f"service exited on its own with {proc.returncode}:\n{diag}"
    assert feed_start_t < 5.0, diag  # GNSS was fed long before the bootstrap could finish
    assert aligned_t is not None, f"no GNSS alignment by {LATEST_LOSS_S - 1.0} s of flight:\n{diag}"
    # on good GNSS the bridge stood by; it took over when GNSS was lost
    assert any(s.startswith("standby; GNSS good; alignment gnss") for _, s in statuses), diag
    # ... and said how far GNSS sat from our position (the readiness figure): within GnssConsistency's 5 m gate
    offs = [float(m.group(1)) for t, s in statuses if t < loss_at and (m := re.search(r"; GNSS (\d+\.\d) m from ours$", s))]
    assert offs and max(offs) < 5.0, diag
    assert not any(t.startswith("TerraSLAM ACTIVE") for t in texts_before), diag
    assert any(t.startswith("TerraSLAM ACTIVE: GNSS lost") for t in texts[len(texts_before):]), diag
    # after the loss the autopilot keeps taking GPS_INPUT from us, with a 3D fix (one a frame, 2 Hz)
    assert received.accepted["GPS_INPUT"] > at_loss.accepted["GPS_INPUT"], diag
    assert len(fixes_3d) >= 2 * (END_S - loss_at) - 3, diag
    # ... that is where the vehicle was, within 3x the 1-sigma accuracy we claim for it
    assert all(e_frame <= 3.0 * hacc for _, e_frame, _, hacc in err), diag
    assert "Traceback" not in log_text, diag
    assert rc == 0, diag
    # the worker processes were killed during the outage, and bundle adjustment came back by itself
    assert len(killed) == 2, diag
    assert "bundle-adjustment worker process had died: starting a new one" in log_text, diag
    _check_recording(tmp_path / "state" / "recordings", feed, loss_at, fixes_3d, diag)


def _check_recording(root: Path, feed: "VehicleFeed", loss_at: float, fixes_3d: list, diag: str) -> None:
    """The run's flight recording (recording.enabled): a dataset of the frames the service tracked,
    every GNSS solution and attitude the bridge received and the fixes it computed, on one clock
    (monotonic; flight time + the playback epoch), that `terraslam replay` sees the GNSS loss in."""
    from companion.app import run_replay
    from companion.config import load_config
    from companion.dataset import read_dataset

    (out,) = root.glob("flight-*")
    ds = read_dataset(out)
    meta = yaml.safe_load((out / "dataset.yaml").read_text())["recording"]
    t_frames = ds.frame_t_s - feed.epoch_s
    g_t = np.array([g.t_s for g in ds.gnss]) - feed.epoch_s
    g_fix = np.array([int(g.fix_type) >= 3 for g in ds.gnss])
    print(f"recording {out.name}: {ds.n_frames} frames at flight t {t_frames[0]:.1f}..{t_frames[-1]:.1f} s, "
          f"{len(ds.gnss)} GNSS, {len(ds.attitude)} attitude; {meta}")
    assert meta["complete"] and meta["frames_dropped"] == 0 and meta["samples_retimed"] == 0, f"{meta}\n{diag}"
    assert t_frames[0] < loss_at - 5.0 and t_frames[-1] > loss_at + 2.0, diag
    assert np.all(np.diff(t_frames) > 0.3), "2 fps: every frame the service tracked, each once"
    # GNSS as the autopilot reported it: 3D fixes before the loss, none after (5 Hz, fed on the flight clock)
    assert g_fix[g_t < loss_at - 0.5].all() and not g_fix[g_t > loss_at + 0.5].any(), diag
    assert np.sum(g_t < loss_at) >= 4 * (loss_at - g_t[0]), diag
    assert len(ds.attitude) >= 10 * (t_frames[-1] - t_frames[0]), diag  # ATTITUDE streams at the 20 Hz the bridge asks for
    with open(out / "fixes.csv") as f:
        fixes = [line.split(",") for line in f.read().splitlines()[1:]]
    assert sum(float(r[1]) - feed.epoch_s > loss_at for r in fixes) >= len(fixes_3d) - 2, diag
    # the MAVLink traffic both ways as a telemetry log (pymavlink's reader), on the dataset's clock
    # through unix_time_minus_clock_s: every GPS_INPUT the autopilot got is in it, and ATTITUDE
    from pymavlink import mavutil

    from mavlink_bridge.link import DIALECT  # sets MAVLINK20 before pymavlink is imported

    tlog = mavutil.mavlink_connection(str(out / "mavlink.tlog"), dialect=DIALECT)
    msgs = []
    while (m := tlog.recv_match()) is not None:
        msgs.append((m._timestamp - meta["unix_time_minus_clock_s"] - feed.epoch_s, m.get_type()))
    kinds = collections.Counter(k for _, k in msgs)
    print(f"mavlink.tlog: {len(msgs)} messages, {dict(kinds.most_common(8))}")
    assert meta["mavlink_messages"] == len(msgs) and kinds["GPS_INPUT"] >= len(feed.gps_input) > 0, diag
    assert kinds["ATTITUDE"] >= len(ds.attitude), diag
    t_att = [t for t, k in msgs if k == "ATTITUDE"]
    assert abs(t_att[0] - (ds.attitude[0].t_s - feed.epoch_s)) < 0.5 and abs(t_att[-1] - (ds.attitude[-1].t_s - feed.epoch_s)) < 0.5, diag
    # the registration journal beside it (gis.align.journal), naming the model the service loaded;
    # this short flight makes no registration (every 200 frames at 2 fps): test_gis_journal replays some
    from gis.align.journal import read_journal, read_meta

    jmeta = read_meta(out / "registrations")
    assert Path(jmeta["model_file"]) == Path(yaml.safe_load((out / "site.yaml").read_text())["gis"]["files"][0]), jmeta
    print(f"registration journal: {len(read_journal(out / 'registrations'))} registrations")
    summary = run_replay(load_config(environ={}), out, root.parent / "replay", repeatable=True)
    assert summary["frames"] == ds.n_frames
    # replayed, the GNSS monitor judges the recorded solutions: lost where the flight lost them
    # (the first frames, before the bridge had any GNSS, count as a loss too)
    lost_t = [t - feed.epoch_s for t, _ in summary["switch_events"]]
    assert any(abs(t - loss_at) < 1.0 for t in lost_t), (lost_t, loss_at, diag)


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
