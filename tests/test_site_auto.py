"""``gis.site: auto``: the service chooses its GIS site by position (TerraSLAM §6: Pre-fetch the
cached site covering the rough position, else Fetch it and SaveCache).

Real parts: the GIS cache on disk (SQLite + model files), model files written by trimesh with a
georeference sidecar, a map file written by slam.persist, the bridge talking to the simulated
autopilot over UDP on 127.0.0.1, and `terraslam run` as a process with $NOTIFY_SOCKET.
"""
from __future__ import annotations

import json
import re
import signal
import subprocess
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
from pydantic import ValidationError
from pyproj import Transformer
from typer.testing import CliRunner

from companion.config import AppConfig, PersistenceConfig, SupervisorConfig
from companion.persistence import alignment_json, map_path, saved_site
from companion.service import NoPositionError, choose_site
from gis.cache import GisCache
from gis.config import GisConfig
from gis.geodesy import LocalFrame
from gis.providers import FetchError, NoSiteError, site_at
from gis.sim3 import Sim3
from gis.synthetic import box_city_model
from gis.types import Alignment, AlignmentSource
from mavlink_bridge.bridge import Bridge
from mavlink_bridge.config import MavlinkConfig, SwitchingConfig
from mavlink_bridge.scenario import Flight
from mavlink_bridge.sim_autopilot import SimAutopilot
from slam.map import SlamMap
from slam.persist import save_map_file, snapshot_map
from slam.types import CameraModel
from test_service_e2e import gis_mesh  # noqa: F401  (a fixture: the nominal scenario's GIS mesh as exported)

FLIGHT = Flight()  # the simulated vehicle on the ground: 47.3977, 8.5456
THERE = LocalFrame(47.3769, 8.5417, 450.0)  # another site, 2.3 km south
UTM32 = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True)
FAR_E, FAR_N = 470000.0, 5255000.0  # a place neither cached site covers (UTM 32N), ~5 km from both


def _cache(root: Path) -> GisCache:
    cache = GisCache(root)
    cache.save_model(box_city_model(200.0, FLIGHT.frame, seed=1, spacing_m=2.0), "here")
    cache.save_model(box_city_model(200.0, THERE, seed=2, spacing_m=2.0), "there")
    return cache


def _write_building(folder: Path, east_m: float, north_m: float) -> None:
    """A 20 x 20 x 10 m building as a binary PLY with its georeference sidecar (UTM 32N)."""
    folder.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=[20, 20, 10]).export(folder / "b.ply")
    (folder / "b.ply.georef.json").write_text(json.dumps({"crs": "EPSG:32632", "offset_m": [east_m, north_m, 400],
                                                          "vertical": "ellipsoid"}))


def _latlon(east_m: float, north_m: float) -> tuple[float, float]:
    lon, lat = UTM32.transform(east_m, north_m)
    return lat, lon


def test_site_at_prefetches_the_covering_site_else_fetches_and_caches_one(tmp_path: Path) -> None:
    cache = _cache(tmp_path / "cache")
    cfg = GisConfig(site="auto", cache_dir=cache.root)
    assert site_at(cache, FLIGHT.lat0_deg, FLIGHT.lon0_deg, cfg) == ("here", "cached")
    lat, lon = THERE.enu_to_geodetic(np.array([40.0, -30.0, 0.0]))[:2]
    assert site_at(cache, lat, lon, cfg) == ("there", "cached")

    far = _latlon(FAR_E, FAR_N)
    with pytest.raises(NoSiteError, match=rf"covers {far[0]:.6f}, {far[1]:.6f} \(sites: here, there\).*fetch_sources"):
        site_at(cache, *far, cfg)

    # a folder with a building there: fetched, saved as a new site, found in the cache next time
    src = tmp_path / "models"
    _write_building(src, FAR_E, FAR_N)
    cfg = GisConfig(site="auto", cache_dir=cache.root, fetch_sources=[str(src)], fetch_radius_m=1000.0)
    lines = []
    site, how = site_at(cache, *far, cfg, progress=lines.append)
    assert how == "fetched" and site not in ("here", "there")
    entry = cache.prefetch(*far)
    assert entry is not None and entry.site_id == site and entry.n_points > 100
    (src / "b.ply").unlink()  # the source is gone: the cached copy serves
    assert site_at(cache, *far, cfg) == (site, "cached")
    assert sorted(e.site_id for e in cache.entries()) == sorted(["here", "there", site])

    # nothing within the fetch radius of a place no site covers: the fetch fails, nothing is cached
    _write_building(src, FAR_E, FAR_N)
    with pytest.raises(FetchError, match="no GIS model within 1000 m"):
        site_at(cache, *_latlon(FAR_E + 20_000.0, FAR_N), cfg)
    assert len(cache.entries()) == 3


def test_gis_ls_at_a_position_shows_the_site_auto_would_fly(tmp_path: Path) -> None:
    from companion.cli import _register_subcommands, app

    cache = _cache(tmp_path / "cache")
    _register_subcommands()
    run = CliRunner().invoke
    res = run(app, ["gis", "ls", "--cache-dir", str(cache.root), "--at", str(FLIGHT.lat0_deg), str(FLIGHT.lon0_deg)])
    assert res.exit_code == 0 and "here" in res.output and "there" not in res.output, res.output
    res = run(app, ["gis", "ls", "--cache-dir", str(cache.root), "--at", *map(str, _latlon(FAR_E, FAR_N))])
    assert res.exit_code == 1 and "no cached site covers" in res.output, res.output
    res = run(app, ["gis", "ls", "--cache-dir", str(cache.root), "--at", "8.54", "247.37"])
    assert res.exit_code == 2 and "is not LAT LON" in res.output, res.output
    res = run(app, ["gis", "ls", "--cache-dir", str(cache.root)])
    assert res.exit_code == 0 and "here" in res.output and "there" in res.output, res.output


def test_site_auto_settings_are_checked() -> None:
    from companion.cli import _register_subcommands, app

    GisConfig(site="auto", rough_position_deg=(47.4, 8.5), fetch_sources=["/srv/gis"])
    with pytest.raises(ValidationError, match="rough_position_deg is only used with gis.site: auto"):
        GisConfig(site="here", rough_position_deg=(47.4, 8.5))
    with pytest.raises(ValidationError, match="fetch_sources is only used"):
        GisConfig(model=Path("m.ply"), fetch_sources=["/srv/gis"])
    with pytest.raises(ValidationError, match=r"latitude -90..90"):
        GisConfig(site="auto", rough_position_deg=(8.5, 247.4))
    with pytest.raises(ValueError, match="not a site id"):
        GisCache.__new__(GisCache).save_model(box_city_model(50.0, THERE, seed=0, spacing_m=5.0), "auto")
    _register_subcommands()
    res = CliRunner().invoke(app, ["gis", "import", "whatever.ply", "--site", "auto"])
    assert res.exit_code == 2 and "reserved" in res.output, res.output


def _save_map(cfg: AppConfig, site_id: str, age_s: float = 0.0, map_id: int = 7) -> None:
    """A map file as the service's saver writes it, with an alignment accepted ``age_s`` ago."""
    cam = CameraModel(640, 480, np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]))
    a = Alignment(Sim3(1.0, np.eye(3), THERE.origin_ecef_m), AlignmentSource.FINE, 100.0, 0, np.eye(6), 0.5, map_id=map_id)
    att = alignment_json(a, site_id, now_mono_s=100.0 + age_s)
    map_path(cfg).parent.mkdir(parents=True, exist_ok=True)
    save_map_file(map_path(cfg), snapshot_map(SlamMap()), cam, map_id=7, reset_counter=0, attachments={"alignment": att})


def test_saved_site_is_the_saved_alignment_s_when_it_would_be_restored(tmp_path: Path) -> None:
    cfg = AppConfig(supervisor=SupervisorConfig(state_dir=tmp_path / "state"))
    assert saved_site(cfg) is None  # no map saved
    _save_map(cfg, "there", age_s=60.0)
    site, age = saved_site(cfg)
    assert site == "there" and 59.0 < age < 70.0
    _save_map(cfg, "there", age_s=cfg.persistence.max_restore_age_s + 10.0)  # too old to restore
    assert saved_site(cfg) is None
    _save_map(cfg, "there", map_id=8)  # the alignment of another map
    assert saved_site(cfg) is None
    _save_map(cfg, "there")
    data = bytearray(map_path(cfg).read_bytes())
    data[len(data) // 2] ^= 0xFF  # corrupted: not trusted for the site either
    map_path(cfg).write_bytes(bytes(data))
    assert saved_site(cfg) is None


class _Autopilot:
    """The simulated autopilot, its receiver on the ground at FLIGHT's start when ``gnss``."""

    def __init__(self) -> None:
        self.sim = SimAutopilot("ardupilot", ekf_start_s=0.0, params={"GPS_AUTO_SWITCH": 0, "GPS_PRIMARY": 0}).start()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._feed, daemon=True)
        self.gnss: str | None = None  # "good", "jammed" (no fix) or nothing received

    def _feed(self) -> None:
        while not self.stop.wait(0.2):
            now = time.monotonic()
            if self.gnss == "good":
                self.sim.feed_gnss(FLIGHT.gnss(now, 0.0))
            elif self.gnss == "jammed":
                self.sim.feed_gnss(FLIGHT.gnss_lost(now))

    def bridge(self) -> Bridge:
        return Bridge(MavlinkConfig(connect=f"udpout:127.0.0.1:{self.sim.port}", autopilot="ardupilot", output="gps_input"),
                      SwitchingConfig())

    def __enter__(self) -> "_Autopilot":
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join(2.0)
        self.sim.close()


def test_choose_site_by_configured_position_saved_map_trusted_gnss_or_ekf_origin(tmp_path: Path, caplog) -> None:
    cache = _cache(tmp_path / "cache")
    state = SupervisorConfig(state_dir=tmp_path / "state")

    def cfg(**gis) -> AppConfig:
        return AppConfig(gis=GisConfig(site="auto", cache_dir=cache.root, **gis), supervisor=state,
                         persistence=PersistenceConfig())

    with _Autopilot() as ap:
        # 1. the configured rough position: no link needed
        b = ap.bridge()
        assert choose_site(cfg(rough_position_deg=(THERE.lat0_deg, THERE.lon0_deg)), cache, b) == "there"
        time.sleep(0.3)
        assert ap.sim.received().counts["HEARTBEAT"] == 0  # the bridge was not started for it
        # 2. a restart in flight with GNSS jammed: the saved map's site, at once
        _save_map(cfg(), "there", age_s=30.0)
        t0 = time.monotonic()
        assert choose_site(cfg(position_wait_s=30.0), cache, b) == "there"
        assert time.monotonic() - t0 < 1.0
        b.close()
        map_path(cfg()).unlink()
        # 3. no position known: the autopilot's GNSS, once trusted (none yet → the wait ends in an error)
        b = ap.bridge()
        with pytest.raises(NoPositionError, match=r"no trusted GNSS position or EKF origin .* within gis.position_wait_s \(1.5 s; GNSS .*no GNSS data"):
            choose_site(cfg(position_wait_s=1.5), cache, b)
        ap.gnss = "good"
        t0 = time.monotonic()
        assert choose_site(cfg(position_wait_s=30.0), cache, b) == "here"
        print(f"site chosen {time.monotonic() - t0:.1f} s after the receiver came up")
        assert ap.sim.received().counts["HEARTBEAT"] >= 1  # the bridge ran for it
        b.close()

    # 4. the companion restarts in flight, GNSS jammed, no saved map: the autopilot's EKF origin
    #    (set from its GNSS before the jamming) stands in once GNSS has stayed untrusted 5 s
    with _Autopilot() as ap:
        ap.sim.feed_gnss(FLIGHT.gnss(time.monotonic(), 0.0))  # the autopilot's EKF takes its origin here
        assert ap.sim.origin is not None
        ap.gnss = "jammed"
        b = ap.bridge()
        t0 = time.monotonic()
        with caplog.at_level("INFO", logger="terraslam.service"):
            assert choose_site(cfg(position_wait_s=30.0), cache, b) == "here"
        took = time.monotonic() - t0
        b.close()
    assert 5.0 <= took < 15.0, took
    assert "covers 47.397700, 8.545600 (the autopilot's EKF origin, GNSS no 3D fix" in caplog.text, caplog.text


@pytest.mark.timeout(150)
def test_service_with_site_auto_waits_for_trusted_gnss_then_runs_in_the_covering_site(tmp_path: Path, gis_mesh: Path) -> None:  # noqa: F811
    """`terraslam run` with gis.site: auto and nothing else to go by: it tells systemd that startup
    goes on (EXTEND_TIMEOUT_USEC, STATUS) while the receiver has no fix, then chooses the cached
    site under the first trusted position, becomes READY and stops cleanly. Without any position
    within gis.position_wait_s it exits 1 (systemd starts it again), naming the problem."""
    from companion.sim import make_scenario
    from gis.loaders import load_model
    from test_service_e2e import TERRASLAM, TimedListener, _service_env  # tests/ is on sys.path

    scenario = make_scenario("nominal")
    cache = GisCache(tmp_path / "cache")
    cache.save_model(box_city_model(200.0, THERE, seed=2, spacing_m=2.0), "there")
    site = cache.save_model(load_model(gis_mesh, 1.0), "nominal-town")
    g0 = scenario.gnss_samples[0]
    sim = SimAutopilot("ardupilot", params={"GPS_AUTO_SWITCH": 0, "GPS_PRIMARY": 0}).start()
    fix_from = [float("inf")]
    stop = threading.Event()

    def feed() -> None:  # the receiver has no fix for the first seconds, then a good one at the flight's start
        while not stop.wait(0.2):
            now = time.monotonic()
            if now >= fix_from[0]:
                sim.feed_gnss(replace(g0, t_s=now))
    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    notify = TimedListener()

    def run(wait_s: float, name: str) -> tuple[subprocess.Popen, Path]:
        cfg = tmp_path / f"{name}.yaml"
        cfg.write_text(f"camera:\n  source: sim\n  fps: 2.0\n  stall_timeout_s: 1.0\n"
                       f"gis:\n  site: auto\n  position_wait_s: {wait_s}\n  cache_dir: {cache.root}\n"
                       f"mavlink:\n  connect: udpout:127.0.0.1:{sim.port}\n  autopilot: ardupilot\n  output: gps_input\n  max_fix_age_s: 1.0\n"
                       f"supervisor:\n  state_dir: {tmp_path / 'state'}\n")
        log_path = tmp_path / f"{name}.log"
        with open(log_path, "wb") as f:
            proc = subprocess.Popen([str(TERRASLAM), "run", "--config", str(cfg)], env=_service_env(notify.lst.environ),
                                    stdout=f, stderr=subprocess.STDOUT)
        return proc, log_path

    procs = []
    try:
        # no position at all within 3 s: exit 1, one error line, never READY
        proc, log1 = run(3.0, "nofix")
        procs.append(proc)
        rc1 = proc.wait(90)
        text1 = log1.read_text()
        # the receiver gets its fix 6 s after the start
        proc, log2 = run(120.0, "fix")
        procs.append(proc)
        fix_from[0] = time.monotonic() + 6.0
        ready = notify.wait_for(lambda: notify.times("READY=1"), 90.0, proc)
        proc.send_signal(signal.SIGTERM)
        rc2 = proc.wait(20)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(10)
        stop.set()
        feeder.join(2.0)
        sim.close()
        notify.lst.close()
    text2 = log2.read_text()
    assert rc1 == 1, text1[-3000:]
    errors = [line for line in text1.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and "no trusted GNSS position or EKF origin" in errors[0] and "Traceback" not in text1, text1[-3000:]
    assert ready and rc2 == 0 and "Traceback" not in text2, text2[-3000:]
    m = re.search(rf"GIS site {site} \(cached\) covers ([0-9.]+), ([0-9.]+) \(trusted GNSS\)", text2)
    assert m and np.allclose([float(m[1]), float(m[2])], [g0.lat_deg, g0.lon_deg], atol=2e-6), text2[-3000:]  # MAVLink's 1e-7°
    extends = notify.times("EXTEND_TIMEOUT_USEC=30000000")
    waiting = [s for s in notify.lines("STATUS=") if "waiting for a trusted GNSS position" in s]
    assert extends and waiting, notify.timed
    assert max(extends) < notify.times("READY=1")[0]
