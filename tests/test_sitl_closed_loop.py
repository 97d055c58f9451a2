"""Closed-loop flights against the real autopilots (``terraslam sitl``): a short mission over the
simulated city per autopilot, the SITL's GNSS switched off with its own command, our camera and
SLAM feeding the autopilot. Run whenever a SITL bundle is given (TERRASLAM_SITL_DIR; CI points it
at the project's bundle), skipped with the reason otherwise. Judged from the autopilot's side: its
own estimate against the simulator's truth, its confirmation of the source switch, its texts."""
import os

import pytest

from companion.config import load_config
from companion.sitl.bundle import ENV_VAR, SitlError, find_bundle
from companion.sitl.flight import SitlOptions, run_sitl

pytestmark = pytest.mark.sitl
#: the autopilot's own horizontal error over the denial, (mean, max) metres
MAX_ERROR_M = {"ardupilot": (1.5, 3.0), "px4": (3.0, 5.0)}
MAX_VELOCITY_BEYOND_3SIGMA = {"ardupilot": 0.05, "px4": 0.10}  # fixes whose velocity error is beyond 3× its claim


@pytest.fixture(scope="module")
def bundle():
    try:
        return find_bundle(os.environ.get(ENV_VAR))
    except SitlError as e:
        pytest.skip(f"no SITL bundle ({e})")


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4"])
def test_closed_loop_gnss_off_our_fixes_carry_the_autopilot(bundle, autopilot, tmp_path):
    # 25 s of GNSS with the camera on (GNSS fits, the first GIS registrations), then 30 s without
    opts = SitlOptions(autopilot=autopilot, speed=0.6, gnss_off_after_s=25.0, gnss_off_for_s=None, max_flight_s=55.0)
    s = run_sitl(load_config(), bundle, tmp_path, opts)
    sitl = s["sitl"]
    assert sitl["takeover_after_gnss_off_s"] is not None and 0.0 <= sitl["takeover_after_gnss_off_s"] <= 1.0, sitl["events"]
    assert sitl["source_switch"] == "confirmed"          # the autopilot said it switched (PARAM_VALUE)
    # a fix on most frames: a relocalisation at a corner withholds some (ArduPilot: 0.85 and 1.0 in two runs)
    assert s["fix_ratio_after_takeover"] >= 0.75, s["tracking_events"]
    assert s["after_takeover"]["integrity_violation_ratio"] <= 0.01
    # the velocity the autopilot fuses is covered by the speed accuracy we claim (a 10-Hz fix
    # difference claimed 0.2 m/s with 80 % beyond 3σ, and ArduPilot's EKF variance failsafe landed it)
    # (PX4 SIH flies sharper corners: 1.3-4.7 % beyond in four flights, against ArduPilot's 0-1 %;
    # PX4 does not fuse it with EKF2_EV_CTRL 1, ArduPilot does)
    assert s["velocity_after_takeover"]["beyond_3sigma_ratio"] <= MAX_VELOCITY_BEYOND_3SIGMA[autopilot], s["velocity_after_takeover"]
    denial = sitl["autopilot_error_in_denial_m"]  # its own estimate vs truth
    # PX4's estimate was 1.0-2.3 m mean / 1.9-3.6 m max from truth in six flights while our fixes
    # were 0.3-0.7 m: a gap in how EKF2 takes our ODOMETRY, not understood yet (docs/AUTOPILOTS.md);
    # ArduPilot: 0.5-1.0 m mean, 1.3-1.8 m max
    mean_m, max_m = MAX_ERROR_M[autopilot]
    assert denial["n"] > 50 and denial["mean"] <= mean_m and denial["max"] <= max_m, denial
    assert sitl["failsafes"] == [], sitl["autopilot_texts"]
    assert sitl["origin_sent"] == 0                     # it had its own EKF origin from GNSS: never offered ours


def test_missing_bundle_is_a_clear_error(tmp_path):
    with pytest.raises(SitlError, match="start_arducopter.sh"):
        find_bundle(tmp_path)
    with pytest.raises(SitlError, match="TERRASLAM_SITL_DIR"):
        find_bundle("")


def test_outputs_without_a_sitl_setup_are_refused():
    with pytest.raises(SitlError, match="px4 with output gps_input"):
        SitlOptions(autopilot="px4", output="gps_input")
    with pytest.raises(ValueError, match="no spoof for px4"):
        SitlOptions(autopilot="px4", spoof_m=50.0)
