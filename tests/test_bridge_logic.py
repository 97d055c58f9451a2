"""GNSS monitor, switch policy and emitters on real pymavlink-encoded messages (no sockets)."""
import math
import os

os.environ.setdefault("MAVLINK20", "1")

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from gis.geodesy import LocalFrame
from mavlink_bridge import emitters
from mavlink_bridge.config import MavlinkConfig, SwitchingConfig
from mavlink_bridge.link import SigningKeyError, load_signing_key
from mavlink_bridge.monitor import GnssMonitor, assess_sample, sample_from_gps_raw
from mavlink_bridge.policy import BridgeState, SwitchPolicy
from mavlink_bridge.scenario import Flight
from mavlink_bridge.types import GnssQuality, GnssStatus, GpsFixType


def wire(msg):
    """Encode with pymavlink (MAVLink 2) and decode the bytes again, as the receiver would."""
    tx = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    rx = mavlink.MAVLink(None)
    return rx.decode(bytearray(msg.pack(tx)))


MAV = mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
FLIGHT = Flight()


def test_gps_raw_int_decodes_units_and_sentinels():
    m = wire(MAV.gps_raw_int_encode(0, 3, 473977000, 85456000, 520123, 120, 180, 500, 9000, 11, 567890, 1500, 2500, 0, 0, 0))
    s = sample_from_gps_raw(m, 10.0)
    assert s.fix_type is GpsFixType.FIX_3D and s.satellites == 11
    assert s.lat_deg == pytest.approx(47.3977) and s.alt_msl_m == pytest.approx(520.123)
    assert s.eph == pytest.approx(1.2) and s.h_acc_m == pytest.approx(1.5)
    # the ellipsoidal height is alt (MSL) + EGM96, the geoid our fixes go back through (alt_ellipsoid 567.89
    # says the receiver's geoid is 47.77 m here; EGM96 within a metre of it)
    from gis.geodesy import msl_to_ellipsoid
    assert s.h_ellipsoid_m == pytest.approx(float(msl_to_ellipsoid(47.3977, 8.5456, 520.123))) == pytest.approx(567.89, abs=1.0)
    assert s.vel_ned_mps[0] == pytest.approx(0.0, abs=1e-9) and s.vel_ned_mps[1] == pytest.approx(5.0)
    lost = sample_from_gps_raw(wire(MAV.gps_raw_int_encode(0, 0, 0, 0, 0, 65535, 65535, 65535, 65535, 255)), 10.0)
    assert math.isnan(lost.eph) and math.isnan(lost.h_acc_m) and lost.vel_ned_mps is None


def test_receiver_without_a_geoid_is_reported(caplog):
    # ArduPilot and PX4 SITL report alt_ellipsoid = alt: 47 m off EGM96 at this latitude
    import mavlink_bridge.monitor as monitor
    monitor._geoid_warned = False
    with caplog.at_level("WARNING", logger="mavlink_bridge.monitor"):
        s = sample_from_gps_raw(wire(MAV.gps_raw_int_encode(0, 3, 473977000, 85456000, 520123, 120, 180, 500, 9000, 11,
                                                            520123, 1500, 2500, 0, 0, 0)), 10.0)
    assert s.h_ellipsoid_m == pytest.approx(567.9, abs=1.0)  # not the 520.1 the receiver calls ellipsoidal
    assert any("another geoid" in r.message for r in caplog.records)


def test_assess_sample_verdicts():
    cfg = SwitchingConfig()
    assert assess_sample(None, 0.0, cfg)[0] is GnssQuality.LOST
    good = FLIGHT.gnss(10.0, 0.0)
    assert assess_sample(good, 10.1, cfg) == (GnssQuality.GOOD, [])
    assert assess_sample(good, 10.0 + cfg.stale_after_s + 0.01, cfg)[0] is GnssQuality.LOST
    assert assess_sample(FLIGHT.gnss_lost(10.0), 10.0, cfg)[0] is GnssQuality.LOST
    q, why = assess_sample(FLIGHT.gnss(10.0, 0.0, fix_type=GpsFixType.FIX_3D, satellites=4, hdop=3.5), 10.0, cfg)
    assert q is GnssQuality.DEGRADED and any("satellites" in r for r in why) and any("HDOP" in r for r in why)


def test_spoofing_flagged_only_for_persistent_disagreement():
    cfg = SwitchingConfig(spoof_sigma=3.0, spoof_persist_s=2.0)
    mon = GnssMonitor(cfg)
    for k in range(30):  # 3 s of agreement (0.4 m apart, σ ≈ 1.1 m)
        t = k * 0.1
        mon.on_fix(FLIGHT.fix(t, t))
        mon.on_sample(FLIGHT.gnss(t + 0.02, t + 0.02, offset_ned_m=(0.3, 0.3, 0.0)))
    assert mon.status(3.0).quality is GnssQuality.GOOD
    flagged_at = None
    for k in range(30, 80):  # receiver dragged 10 m east, fix still perfect
        t = k * 0.1
        mon.on_fix(FLIGHT.fix(t, t))
        mon.on_sample(FLIGHT.gnss(t + 0.02, t + 0.02, offset_ned_m=(0.0, 10.0, 0.0)))
        if flagged_at is None and mon.status(t + 0.02).quality is GnssQuality.UNTRUSTED:
            flagged_at = t
    assert flagged_at is not None and 3.0 + 2.0 - 0.11 <= flagged_at <= 3.0 + 5.0
    assert "spoofing" in " ".join(mon.status(8.0).reasons)


def test_an_unanchored_fix_is_no_reference_for_the_spoofing_test():
    """Our SLAM track jumped and nothing re-anchored it (GlobalFix.anchored False): 10 m between
    it and GNSS for 5 s is not taken for spoofing; once it is anchored again, it is."""
    from dataclasses import replace

    cfg = SwitchingConfig(spoof_sigma=3.0, spoof_persist_s=2.0)
    mon = GnssMonitor(cfg)
    for k in range(50):
        t = k * 0.1
        mon.on_fix(replace(FLIGHT.fix(t, t), anchored=False))
        mon.on_sample(FLIGHT.gnss(t + 0.02, t + 0.02, offset_ned_m=(0.0, 10.0, 0.0)))
    assert mon.status(5.0).quality is GnssQuality.GOOD
    for k in range(50, 80):
        t = k * 0.1
        mon.on_fix(FLIGHT.fix(t, t))
        mon.on_sample(FLIGHT.gnss(t + 0.02, t + 0.02, offset_ned_m=(0.0, 10.0, 0.0)))
    assert mon.status(8.0).quality is GnssQuality.UNTRUSTED


def test_ekf_glitch_and_fix_flapping_mark_untrusted():
    cfg = SwitchingConfig(jamming_flips=3, jamming_window_s=10.0)
    mon = GnssMonitor(cfg)
    mon.on_sample(FLIGHT.gnss(1.0, 0.0))
    mon.on_ekf_flags(True, 1.0)
    assert mon.status(1.1).quality is GnssQuality.UNTRUSTED
    mon = GnssMonitor(cfg)
    for k, fix in enumerate([6, 1, 6, 1, 6]):
        mon.on_sample(FLIGHT.gnss(float(k), 0.0, fix_type=GpsFixType(fix)))
    st = mon.status(4.0)
    assert st.quality is GnssQuality.UNTRUSTED and "jamming" in " ".join(st.reasons)


def _status(t, q):
    return GnssStatus(t, q, (q.value,))


def test_policy_takes_over_at_once_and_hands_back_after_hysteresis():
    pol = SwitchPolicy(SwitchingConfig(handback_good_s=10.0, min_dwell_s=3.0))
    assert pol.update(_status(0.0, GnssQuality.GOOD)) is None
    ev = pol.update(_status(1.0, GnssQuality.LOST))
    assert ev.to_state is BridgeState.ACTIVE and ev.t_s == 1.0
    t = 2.0
    while t < 11.9:  # 9.9 s of good GNSS: not enough
        assert pol.update(_status(t, GnssQuality.GOOD)) is None
        t += 0.1
    ev = None
    while ev is None and t < 13.0:
        ev = pol.update(_status(t, GnssQuality.GOOD))
        t += 0.1
    assert ev is not None and ev.to_state is BridgeState.STANDBY and ev.t_s >= 12.0


def test_policy_does_not_flap_on_intermittent_gnss():
    pol = SwitchPolicy(SwitchingConfig(handback_good_s=10.0, min_dwell_s=3.0))
    for k in range(600):  # 60 s alternating 2 s good / 1 s lost
        t = k * 0.1
        pol.update(_status(t, GnssQuality.LOST if (t % 3.0) >= 2.0 else GnssQuality.GOOD))
    assert [e.to_state for e in pol.events] == [BridgeState.ACTIVE]


def test_policy_holds_while_link_down_and_degraded_needs_persistence():
    pol = SwitchPolicy(SwitchingConfig(degraded_takeover_s=2.0))
    assert pol.update(_status(0.0, GnssQuality.LOST), link_up=False) is None
    assert pol.update(_status(1.0, GnssQuality.DEGRADED)) is None
    assert pol.update(_status(2.5, GnssQuality.DEGRADED)) is None
    assert pol.update(_status(3.1, GnssQuality.DEGRADED)).to_state is BridgeState.ACTIVE


def test_gps_input_fields_and_no_fix():
    cfg = MavlinkConfig(autopilot="ardupilot", output="gps_input", gps_id=1)
    fix = FLIGHT.fix(5.0, 2.0, sigma_m=0.8)
    m = wire(emitters.gps_input(MAV, fix, cfg, unix_s=1_700_000_000.0))
    assert m.gps_id == 1 and m.fix_type == 3 and m.satellites_visible >= 6
    assert m.lat == round(fix.lat_deg * 1e7) and m.alt == pytest.approx(fix.h_msl_m, abs=1e-3)
    assert m.horiz_accuracy == pytest.approx(0.8) and m.hdop == pytest.approx(0.5)
    assert m.vn == pytest.approx(5.0) and m.yaw == 36000  # north is 36000, 0 means "no yaw"
    assert m.time_week > 2000 and m.ignore_flags == 0
    bad = FLIGHT.fix(5.0, 2.0, sigma_m=12.0)  # not trustworthy: never reported as a 3D fix
    for f in (None, bad):
        m = wire(emitters.gps_input(MAV, f, cfg))
        assert m.fix_type < 3 and m.satellites_visible == 0
    # no velocity: not sent (ArduPilot would fuse the previous message's velocity for an ignored one)
    assert emitters.gps_input(MAV, FLIGHT.fix(5.0, 2.0, with_velocity=False), cfg) is None


def test_px4_profile_refuses_gps_input():
    with pytest.raises(ValueError, match="gps_input.*px4"):
        emitters.check_profile(MavlinkConfig(autopilot="px4", output="gps_input"))
    with pytest.raises(ValueError, match="hil_gps"):
        emitters.check_profile(MavlinkConfig(autopilot="ardupilot", output="hil_gps"))


@pytest.mark.parametrize("autopilot,frames", [("px4", (1, 1)), ("ardupilot", (20, 12))])
def test_odometry_in_ekf_origin_ned(autopilot, frames):
    cfg = MavlinkConfig(autopilot=autopilot, output="odometry")
    origin = FLIGHT.frame
    fix = FLIGHT.fix(5.0, 4.0, sigma_m=0.7)  # 20 m north of the origin
    q_level_north = np.array([1.0, 0.0, 0.0, 0.0])
    m = wire(emitters.odometry(MAV, fix, origin, cfg, q_level_north))
    assert (m.frame_id, m.child_frame_id) == frames and m.estimator_type == mavlink.MAV_ESTIMATOR_TYPE_VISION
    assert (m.x, m.y, m.z) == pytest.approx((20.0, 0.0, 0.0), abs=1e-3)
    assert m.pose_covariance[0] == pytest.approx(0.49) and m.pose_covariance[6] == pytest.approx(0.49)
    assert m.pose_covariance[11] == pytest.approx(0.49) and math.isnan(m.pose_covariance[15])
    assert m.vx == pytest.approx(5.0, abs=1e-5)  # level, facing north: body x = north
    other = LocalFrame(FLIGHT.lat0_deg + 1e-4, FLIGHT.lon0_deg, origin.h0_ellipsoid_m)  # origin 11 m further north
    assert wire(emitters.odometry(MAV, fix, other, cfg, q_level_north)).x == pytest.approx(20.0 - 11.12, abs=0.05)


def test_vpe_global_position_sensor_and_hil_gps():
    cfg = MavlinkConfig(autopilot="px4", output="hil_gps", agp_id=3)
    fix = FLIGHT.fix(5.0, 4.0, sigma_m=0.7)
    vpe = wire(emitters.vision_position_estimate(MAV, fix, FLIGHT.frame, np.array([1.0, 0, 0, 0])))
    assert vpe.x == pytest.approx(20.0, abs=1e-3) and vpe.yaw == pytest.approx(0.0) and vpe.covariance[0] == pytest.approx(0.49)
    agp = wire(emitters.global_position_sensor(MAV, fix, cfg, 5.01))
    assert agp.id == 3 and agp.eph == pytest.approx(0.7) and agp.alt == pytest.approx(fix.h_msl_m, abs=1e-3)
    hil = wire(emitters.hil_gps(MAV, fix, cfg))
    assert hil.fix_type == 3 and hil.eph == 70 and hil.vn == 500 and hil.satellites_visible >= 6
    assert emitters.hil_gps(MAV, FLIGHT.fix(5.0, 4.0, with_velocity=False), cfg) is None


def test_signing_key_file_checks(tmp_path):
    key = tmp_path / "key"
    key.write_bytes(bytes(range(32)))
    key.chmod(0o644)
    with pytest.raises(SigningKeyError, match="too open"):
        load_signing_key(key)
    key.chmod(0o600)
    assert load_signing_key(key) == bytes(range(32))
    key.write_text(bytes(range(32)).hex() + "\n")
    assert load_signing_key(key) == bytes(range(32))
    key.write_bytes(b"short")
    with pytest.raises(SigningKeyError, match="32 raw bytes"):
        load_signing_key(key)
    with pytest.raises(SigningKeyError, match="cannot read"):
        load_signing_key(tmp_path / "missing")


def test_statustext_is_cut_at_a_word():
    from mavlink_bridge.bridge import statustext
    text = "TerraSLAM ACTIVE: GNSS lost: no 3D fix for 0.8 s (fix_type 1, 3 satellites)"
    out = statustext(text)
    assert len(out) <= 50 and text.encode().startswith(out) and text[len(out)] == " "
    assert statustext("short") == b"short"
    assert len(statustext("x" * 80)) == 50  # one unbroken word: cut where it must
