"""sitl-check: MAVSDK 4 against the simulated autopilot (default suite) and against a real SITL
(marker ``sitl``, given by TERRASLAM_SITL_URL + TERRASLAM_SITL_AUTOPILOT, skipped otherwise)."""
import os
import threading
import time

import pytest
from typer.testing import CliRunner

from mavlink_bridge import emitters
from mavlink_bridge.config import MavlinkConfig
from mavlink_bridge.link import open_connection
from mavlink_bridge.scenario import Flight
from mavlink_bridge.sim_autopilot import SimAutopilot
from mavlink_bridge.sitl_check import collect, judge


def _feed(sim, gps_id, stop):
    """GNSS lost; our GPS_INPUT at 10 Hz (a plain pymavlink sender, not the bridge)."""
    conn = open_connection(f"udpout:127.0.0.1:{sim.port}", 0, 1, 197)
    f = Flight(v_ned_mps=(0.0, 0.0, 0.0))
    while not stop.is_set():
        now = time.monotonic()
        sim.feed_gnss(f.gnss_lost(now))
        conn.mav.send(emitters.gps_input(conn.mav, f.fix(now, 0.0), MavlinkConfig(gps_id=gps_id)))
        time.sleep(0.1)
    conn.close()


@pytest.mark.parametrize("gps_id,fusing", [(1, True), (0, False)])
def test_sitl_check_reads_ardupilot_evidence_through_mavsdk(gps_id, fusing):
    sim = SimAutopilot("ardupilot", ekf_start_s=0.1).start()
    # what a ground station would have requested; sitl-check only listens
    sim._interval_s.update({33: 0.2, 24: 0.0, 124: 0.2, 193: 0.5})
    stop = threading.Event()
    th = threading.Thread(target=_feed, args=(sim, gps_id, stop), daemon=True)
    th.start()
    try:
        obs = collect(f"udpout://127.0.0.1:{sim.port}", "ardupilot", seconds=1.5)
    finally:
        stop.set()
        th.join()
        sim.close()
    assert obs.autopilot_type == "ardupilot" and obs.params["GPS2_TYPE"] == 14
    report = judge(obs, "ardupilot")
    assert report.fusing is fusing, report.evidence
    if fusing:
        assert report.distance_m is not None and report.distance_m < 0.5


def test_judge_px4_is_honest_when_gnss_hides_fusion():
    from mavlink_bridge.sitl_check import Observation
    obs = Observation("px4", {"GPS_RAW_INT": {"fix_type": 6}, "ESTIMATOR_STATUS": {"flags": 16},
                              "GLOBAL_POSITION_INT": {"lat": 473977000, "lon": 85456000}},
                      {"EKF2_EV_CTRL": 3, "EKF2_GPS_CTRL": 7})
    r = judge(obs, "px4", our_fix=(47.3977, 8.5456))
    assert r.fusing is None and any("not visible over MAVLink" in e for e in r.evidence)
    far = judge(obs, "px4", our_fix=(47.3987, 8.5456))  # 111 m away: certainly not following us
    assert far.fusing is False and far.distance_m == pytest.approx(111.2, abs=0.5)
    obs.messages["GPS_RAW_INT"] = {"fix_type": 0}
    assert judge(obs, "px4", our_fix=(47.3977, 8.5456)).fusing is True


def test_cli_rejects_bad_arguments():
    from companion.cli import _register_subcommands, app
    _register_subcommands()
    r = CliRunner().invoke(app, ["sitl-check", "--autopilot", "inav", "--connect", "udpin://0.0.0.0:14540"])
    assert r.exit_code == 2 and "px4 or ardupilot" in r.output
    r = CliRunner().invoke(app, ["sitl-check", "--autopilot", "px4", "--connect", "udpin://0.0.0.0:1", "--fix", "x"])
    assert r.exit_code == 2 and "LAT,LON" in r.output


@pytest.mark.sitl
def test_real_sitl_fuses_our_source():
    url = os.environ.get("TERRASLAM_SITL_URL")
    if not url:
        pytest.skip("TERRASLAM_SITL_URL not set (e.g. udpin://0.0.0.0:14540 for PX4 SIH)")
    autopilot = os.environ.get("TERRASLAM_SITL_AUTOPILOT", "px4")
    fix = os.environ.get("TERRASLAM_SITL_FIX")  # "LAT,LON" of the companion's current fix
    our_fix = tuple(float(x) for x in fix.split(",")) if fix else None
    report = judge(collect(url, autopilot, seconds=5.0), autopilot, our_fix)
    print("\n".join(report.evidence))
    assert report.fusing is True, report.evidence
