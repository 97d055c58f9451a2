"""The service at a surveyed site with no GNSS at all (slow: the real `terraslam run` against the
simulated ArduPilot over UDP, as tests/test_service_e2e.py).

The GIS cache holds the site's model and a survey map with its T_rough (tests/test_survey_map.py's
``build_survey``: our SLAM's map of the same flight's first 40 s at 10 fps, T_rough from a stand-in
reconstruction), and a second site 5 km away. The service is configured with ``gis.site: auto``
and the operator's rough position of the field (GNSS is jammed from power-on: nothing else could
say where it is): it must choose the surveyed site. The autopilot's receiver reports no fix from
the first sample on; the autopilot must get 3D GPS_INPUT fixes from us that agree with the
flight's truth within 3× their accuracy.
"""
from __future__ import annotations

import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest

from mavlink_bridge.sim_autopilot import SimAutopilot
from test_service_e2e import TERRASLAM, TimedListener, VehicleFeed, _horizontal_m, _service_env, gis_mesh, stop_all  # noqa: F401
from test_service_restart import _epoch
from test_survey_map import build_survey

FPS = 5.0
N_FIXES = 15


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_service_at_a_surveyed_site_sends_fixes_with_no_gnss_ever(tmp_path: Path, gis_mesh: Path) -> None:  # noqa: F811
    from companion.sim import make_scenario
    from gis.geodesy import LocalFrame
    from gis.loaders import load_model
    from gis.synthetic import box_city_model

    cache, site, *_ = build_survey(tmp_path, model=load_model(gis_mesh, 1.0))
    scenario = make_scenario("nominal", fps=FPS)  # the service's flight: same name, seed (0) and fps
    lat, lon, _ = scenario.origin.enu_to_geodetic(np.array([60.0, -40.0, 0.0]))  # roughly the field, not the take-off
    elsewhere = LocalFrame(*scenario.origin.enu_to_geodetic(np.array([5000.0, 0.0, 0.0])))
    cache.save_model(box_city_model(300.0, elsewhere, seed=1, spacing_m=3.0), "elsewhere")
    sim = SimAutopilot("ardupilot", params={"GPS_AUTO_SWITCH": 0, "GPS_PRIMARY": 0}).start()
    notify = TimedListener()
    cfg = tmp_path / "config.yaml"
    cfg.write_text(f"camera:\n  source: sim\n  fps: {FPS}\n"
                   f"gis:\n  site: auto\n  rough_position_deg: [{lat}, {lon}]\n  cache_dir: {cache.root}\n"
                   f"mavlink:\n  connect: udpout:127.0.0.1:{sim.port}\n  autopilot: ardupilot\n  output: gps_input\n"
                   f"  max_fix_age_s: {2 / FPS}\n"
                   f"supervisor:\n  state_dir: {tmp_path / 'state'}\n")
    log_path = tmp_path / "service.log"
    with open(log_path, "wb") as f:
        proc = subprocess.Popen([str(TERRASLAM), "run", "--config", str(cfg)], env=_service_env(notify.lst.environ),
                                stdout=f, stderr=subprocess.STDOUT)
    feed = None
    try:
        feed = VehicleFeed(sim, scenario, _epoch(proc, log_path))
        feed.loss_at_s = 0.0  # the receiver never has a fix
        feed.__enter__()
        ready = lambda: [t for t, m in notify.timed if "READY=1" in m.split("\n")]  # noqa: E731
        assert notify.wait_for(lambda: ready(), 90.0, proc), f"no READY=1:\n{log_path.read_text()[-3000:]}"
        notify.wait_for(lambda: len([r for r in feed.gps_input if r[1] >= 3]) >= N_FIXES, 60.0, proc)
        alive = proc.poll() is None
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(20)
    finally:
        stop_all([proc], [feed], sim, notify)
    text = log_path.read_text()
    fixes = [r for r in feed.gps_input if r[1] >= 3]
    err = [(t, _horizontal_m(lat, lon, *feed.truth(np.floor(t * FPS) / FPS)[:2]), hacc) for t, _, lat, lon, hacc in fixes]
    t_ready = feed.flight_t(ready()[0])
    summary = (f"READY at flight t {t_ready:.1f} s; first 3D fix at {fixes[0][0] if fixes else None} s; {len(fixes)} fixes "
               f"(flight t, horizontal error at frame time, h_acc) {[tuple(round(x, 2) for x in e) for e in err]}")
    print(summary)
    diag = summary + "\n" + text[-3000:]
    assert alive and f"GIS site {site} (cached) covers {lat:.6f}, {lon:.6f} (gis.rough_position_deg)" in text, diag
    assert "survey_map_loaded" in text, diag
    assert "alignment rough accepted (restored from the site's survey map" in text, diag  # the timeline is journaled
    assert len(fixes) >= N_FIXES, diag
    assert fixes[0][0] - t_ready < 10.0, diag  # relocalised on the first frames (the pipeline is up at READY)
    assert all(e <= 3.0 * hacc for _, e, hacc in err), diag
    assert rc == 0 and "Traceback" not in text, diag
