"""The bridge against the simulated autopilot over real UDP on 127.0.0.1, both personalities.

Each test flies the straight-line scenario in real time (20 Hz fixes, 5 Hz GNSS) for a few
seconds with short hysteresis settings; the fix-loss and spoofing detection bounds are the real
defaults' (stale_after_s 0.8, spoof_persist_s 2).
"""
import math
import socket
import time

import pytest

from gis.geodesy import LocalFrame
from mavlink_bridge import emitters
from mavlink_bridge.bridge import Bridge
from mavlink_bridge.config import MavlinkConfig, SwitchingConfig
from mavlink_bridge.link import open_connection
from mavlink_bridge.policy import BridgeState
from mavlink_bridge.scenario import Flight
from mavlink_bridge.sim_autopilot import SimAutopilot

DT_S = 0.05
GNSS_EVERY = 4  # 5 Hz receiver
# output per personality, with the autopilot parameters docs/AUTOPILOTS.md asks for
SETUPS = {
    "ardupilot": ("gps_input", {"GPS_AUTO_SWITCH": 0, "GPS_PRIMARY": 0}),
    "px4": ("odometry", {}),
}


class Rig:
    def __init__(self, personality, output=None, params=None, sw=None, sim_key=None, **mav):
        out, default_params = SETUPS[personality]
        self.sim = SimAutopilot(personality, ekf_start_s=0.2, params=params or default_params, signing_key=sim_key).start()
        self.cfg = MavlinkConfig(connect=f"udpout:127.0.0.1:{self.sim.port}", autopilot=personality,
                                 output=output or out, rate_hz=20.0, **mav)
        self.bridge = Bridge(self.cfg, sw or SwitchingConfig(handback_good_s=2.0, min_dwell_s=1.0)).start()
        self.flight = Flight()
        self.t0 = time.monotonic()
        self.k = 0

    def fly(self, seconds, gnss="good", fix=True, until=None):
        """Advance the flight; ``gnss``: good | lost | silent | (dn, de) spoof offset in metres."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            now = time.monotonic()
            t = now - self.t0
            if self.k % GNSS_EVERY == 0 and gnss != "silent":
                if gnss == "good":
                    self.sim.feed_gnss(self.flight.gnss(now, t))
                elif gnss == "lost":
                    self.sim.feed_gnss(self.flight.gnss_lost(now))
                else:
                    self.sim.feed_gnss(self.flight.gnss(now, t, offset_ned_m=(gnss[0], gnss[1], 0.0)))
            self.bridge.submit_fix(self.flight.fix(now, t, self.k) if fix else None)
            self.k += 1
            if until is not None and until():
                return True
            time.sleep(max(0.0, DT_S - (time.monotonic() - now)))
        return until is None

    def est_error_m(self):
        e = self.sim.estimate()
        if not e.valid:
            return math.inf
        t = time.monotonic() - self.t0
        truth = self.flight.frame.ned_to_geodetic(self.flight.p_ned_m(t))
        d = LocalFrame(float(truth[0]), float(truth[1])).geodetic_to_ned(e.lat_deg, e.lon_deg, 0.0)
        return math.hypot(d[0], d[1])

    def close(self):
        self.bridge.close()
        self.sim.close()


@pytest.fixture
def rigs():
    made = []

    def make(*a, **kw):
        made.append(Rig(*a, **kw))
        return made[-1]
    yield make
    for r in made:
        r.close()


OUR_SOURCE = {"ardupilot": "mavlink_gps", "px4": "external_vision"}


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_nominal_gnss_no_takeover(rigs, personality):
    rig = rigs(personality)
    rig.fly(3.0)
    assert rig.bridge.state is BridgeState.STANDBY and rig.bridge.events() == []
    assert rig.bridge.gnss_status().trusted
    assert rig.sim.estimate().source == "gnss"
    rx = rig.sim.received()
    assert rx.accepted[{"ardupilot": "GPS_INPUT", "px4": "ODOMETRY"}[personality]] > 20  # fed as secondary
    assert rig.bridge.stats().link_up


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
@pytest.mark.parametrize("how", ["lost", "silent"])
def test_gnss_loss_takeover_follow_and_handback_after_hysteresis(rigs, personality, how):
    rig = rigs(personality)
    rig.fly(2.0)
    t_loss = time.monotonic()
    assert rig.fly(3.0, gnss=how, until=lambda: rig.bridge.state is BridgeState.ACTIVE)
    ev = rig.bridge.events()[0]
    assert ev.to_state is BridgeState.ACTIVE and ev.t_s - t_loss <= 1.0, ev
    rig.fly(1.5, gnss=how)
    assert rig.sim.estimate().source == OUR_SOURCE[personality]
    assert rig.est_error_m() < 1.5  # the autopilot follows our fixes (0.25 m lag per 50 ms at 5 m/s)
    assert any(text.startswith("TerraSLAM ACTIVE") for _, text in rig.sim.received().statustext)
    assert rig.bridge.pending_confirmations() == []  # the source switch was confirmed
    t_back = time.monotonic()
    assert rig.fly(5.0, until=lambda: rig.bridge.state is BridgeState.STANDBY)
    back = rig.bridge.events()[-1]
    assert back.to_state is BridgeState.STANDBY and back.t_s - t_back >= 2.0  # handback_good_s
    rig.fly(0.5)
    assert rig.sim.estimate().source == "gnss"
    assert len(rig.bridge.events()) == 2


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_spoofing_detected_and_taken_over(rigs, personality):
    rig = rigs(personality, sw=SwitchingConfig(handback_good_s=2.0, min_dwell_s=1.0))
    rig.fly(2.0)
    t_spoof = time.monotonic()
    assert rig.fly(6.0, gnss=(0.0, 10.0), until=lambda: rig.bridge.state is BridgeState.ACTIVE)
    ev = rig.bridge.events()[0]
    assert "spoofing" in ev.reason and ev.t_s - t_spoof <= 5.0
    rig.fly(1.0, gnss=(0.0, 10.0))
    # the receiver still reports a perfect fix; the bridge moved the autopilot onto our source
    assert rig.sim.estimate().source == OUR_SOURCE[personality]
    assert rig.est_error_m() < 1.5
    assert rig.bridge.state is BridgeState.ACTIVE


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_tracking_lost_stops_output(rigs, personality):
    rig = rigs(personality)
    rig.fly(1.5)
    rig.fly(1.0, gnss="lost")
    assert rig.bridge.state is BridgeState.ACTIVE
    rig.fly(0.3, gnss="lost", fix=False)
    before = rig.sim.received().counts
    rig.fly(1.0, gnss="lost", fix=False)
    after = rig.sim.received().counts
    for t in ("GPS_INPUT", "ODOMETRY"):
        assert after[t] == before[t]  # nothing more, not even a stale fix
    assert rig.sim.estimate().source in ("dead_reckoning", "none")
    if personality == "ardupilot":  # told at once (one NO_FIX GPS_INPUT) rather than timing out after 4 s
        assert rig.sim._mgps["fix"] < 3 and rig.sim._mgps["sats"] == 0


def test_link_dropped_and_restored_resumes(rigs):
    rig = rigs("ardupilot", sw=SwitchingConfig(handback_good_s=2.0, min_dwell_s=1.0))
    rig.fly(1.5)
    port = rig.sim.port
    rig.sim.close()
    rig.fly(3.5, gnss="silent")
    assert not rig.bridge.stats().link_up
    assert rig.bridge.state is BridgeState.STANDBY  # link down: no verdict on GNSS we cannot see
    rig.sim = SimAutopilot("ardupilot", port, ekf_start_s=0.2, params=SETUPS["ardupilot"][1]).start()
    assert rig.fly(4.0, until=lambda: rig.bridge.stats().link_up and rig.sim.received().accepted["GPS_INPUT"] > 10)
    # streams were re-requested on the new link: the ArduPilot personality streams nothing unasked
    assert rig.sim.received().accepted["COMMAND_LONG:511"] >= 4
    rig.fly(1.0)
    assert rig.bridge.gnss_status().trusted


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_random_and_truncated_bytes_do_not_crash(rigs, personality):
    import random
    rig = rigs(personality)
    rig.fly(1.0)
    bridge_port = rig.bridge._link.conn.port.getsockname()[1]
    rng = random.Random(6)
    frame = bytes(rig.sim._conn.mav.heartbeat_encode(2, 3, 0, 0, 4).pack(rig.sim._conn.mav))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for i in range(400):
            junk = bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 300)))
            if i % 4 == 0:  # MAVLink 2 start byte and a plausible header, then garbage / truncation
                junk = frame[: rng.randint(1, len(frame) - 1)] + (junk if i % 8 else b"")
            s.sendto(junk, ("127.0.0.1", bridge_port))
            s.sendto(junk, ("127.0.0.1", rig.sim.port))
    rig.fly(1.5)
    st = rig.bridge.stats()
    assert rig.bridge._thread.is_alive() and st.rejected_frames > 0
    assert rig.bridge.gnss_status().trusted and st.link_up
    before = rig.sim.received().counts["GPS_INPUT"] + rig.sim.received().counts["ODOMETRY"]
    rig.fly(0.5)
    assert rig.sim.received().counts["GPS_INPUT"] + rig.sim.received().counts["ODOMETRY"] > before + 5


def test_signing_rejects_unsigned_peers(rigs, tmp_path):
    key = bytes(range(32))
    key_file = tmp_path / "mavlink.key"
    key_file.write_bytes(key)
    key_file.chmod(0o600)
    signed = rigs("ardupilot", sim_key=key, signing_key_file=key_file)
    signed.fly(1.5)
    assert signed.bridge.stats().link_up and signed.sim.received().accepted["GPS_INPUT"] > 10
    unsigned_peer = rigs("ardupilot", signing_key_file=key_file)  # the autopilot does not sign: everything it says is rejected
    unsigned_peer.fly(1.5)
    st = unsigned_peer.bridge.stats()
    assert not st.link_up and sum(st.received.values()) == 0 and st.rejected_frames > 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # an unsigned sender to a signing autopilot
        mav = signed.bridge._link.mav.__class__(None, srcSystem=1, srcComponent=197)
        s.sendto(bytes(mav.heartbeat_encode(18, 8, 0, 0, 4).pack(mav)), ("127.0.0.1", signed.sim.port))
    signed.fly(0.3)
    assert any("signature" in r.lower() for r in signed.sim.received().reasons("BAD_DATA"))


def test_ardupilot_rejects_wrong_gps_id_and_px4_ignores_gps_input(rigs):
    wrong = rigs("ardupilot", gps_id=0)  # GPS1_TYPE is the real receiver, not 14
    wrong.fly(1.0)
    assert "gps_id 0" in wrong.sim.received().reasons("GPS_INPUT")[0]
    wrong.fly(1.0, gnss="lost")
    assert wrong.sim.estimate().source != "mavlink_gps"
    px4 = SimAutopilot("px4").start()
    try:
        conn = open_connection(f"udpout:127.0.0.1:{px4.port}", 0, 1, 197)
        fix = Flight().fix(time.monotonic(), 0.0)
        for _ in range(5):
            conn.mav.send(emitters.gps_input(conn.mav, fix, MavlinkConfig(gps_id=0)))
        time.sleep(0.3)
        assert px4.received().reasons("GPS_INPUT") == ["ignored: PX4 has no GPS_INPUT handler"] * 5
        assert px4.received().accepted["GPS_INPUT"] == 0
        conn.close()
    finally:
        px4.close()


def test_ardupilot_external_nav_origin_and_source_set(rigs):
    # no GNSS at boot: the bridge must set the EKF origin (re-sent until acknowledged), then ExtNav
    rig = rigs("ardupilot", output="odometry", params={"GPS_AUTO_SWITCH": 1})
    rig.sim.ekf_start_s = 1.0
    assert rig.fly(9.0, gnss="lost", until=lambda: rig.sim.estimate().source == "external_nav")
    rx = rig.sim.received()
    assert rx.accepted["SET_GPS_GLOBAL_ORIGIN"] == 1 and rig.sim.source_set == 2
    assert rig.bridge.stats().origin is not None
    rig.fly(1.0, gnss="lost")
    assert rig.est_error_m() < 1.5


def test_unconfirmed_source_switch_is_resent_then_reported(rigs):
    rig = rigs("ardupilot", params={"GPS_AUTO_SWITCH": 1})
    del rig.sim.params["GPS_PRIMARY"]  # this autopilot never confirms the PARAM_SET
    rig.fly(1.5)
    rig.fly(1.0, gnss="lost")
    assert rig.bridge.pending_confirmations() == ["param:GPS_PRIMARY"]
    rig.fly(4.5, gnss="lost")
    assert rig.sim.received().counts["PARAM_SET"] == 5  # CONFIRM_TRIES, 1 s apart
    assert rig.bridge.pending_confirmations() == []
    assert rig.sim.estimate().source == "mavlink_gps"  # auto-switch still picks us on fix loss


@pytest.mark.parametrize("personality,output,source", [
    ("px4", "vision_position_estimate", "external_vision"),
    ("px4", "global_position_sensor", "aux_global"),
    ("px4", "hil_gps", "hil_gps"),
    ("ardupilot", "vision_position_estimate", "external_nav"),
])
def test_alternative_outputs_take_over_on_gnss_loss(rigs, personality, output, source):
    rig = rigs(personality, output=output, params={} if personality == "px4" else {"GPS_AUTO_SWITCH": 1})
    rig.fly(2.0)
    assert rig.sim.estimate().source == "gnss"
    assert rig.fly(3.0, gnss="lost", until=lambda: rig.sim.estimate().source == source)
    rig.fly(1.0, gnss="lost")
    assert rig.sim.estimate().source == source and rig.est_error_m() < 1.5
    assert rig.sim.received().rejections == [] or all("gap" in r for _, _, r in rig.sim.received().rejections)


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_bridge_attaches_the_barometric_altitude_to_the_attitude(rigs, personality):
    """The barometer (PX4: ALTITUDE.altitude_monotonic; ArduPilot: SCALED_PRESSURE as pressure
    altitude) travels with the attitude the pipeline reads; the simulated barometer is noisy
    (0.15 m) and drifts, so only its change is checked."""
    rig = rigs(personality)
    rig.sim.feed_attitude(0.0, 0.0, 0.0)

    def baro(t_wait_s):
        end = time.monotonic() + t_wait_s
        vals = []
        while time.monotonic() < end:
            a = rig.bridge.attitude(max_age_s=0.5)
            if a is not None and a.baro_alt_m is not None:
                vals.append(a.baro_alt_m)
            time.sleep(0.05)
        return vals

    rig.sim.set_truth(47.0, 8.0, 500.0)
    before = baro(2.0)
    rig.sim.set_truth(47.0, 8.0, 510.0)
    time.sleep(0.5)
    after = baro(1.5)
    assert before and after, "no ALTITUDE reached the attitude"
    assert 9.0 < sum(after) / len(after) - sum(before) / len(before) < 11.0


@pytest.mark.parametrize("delay_s", [0.0, 0.1])
def test_gnss_solutions_are_dated_by_the_autopilots_stamp_not_their_arrival(delay_s):
    """ArduPilot and PX4 stamp GPS_RAW_INT with the boot time of the fix and send it at a later
    stream tick: the bridge dates each solution by that stamp (through SYSTEM_TIME's boot offset),
    less the receiver's own latency ``gnss_delay_s``, not by when it arrived (0.15 s late here:
    1.2 m along the track at 8 m/s)."""
    lag_s = 0.15
    sim = SimAutopilot("ardupilot", ekf_start_s=0.2, gnss_report_lag_s=lag_s).start()
    bridge = Bridge(MavlinkConfig(connect=f"udpout:127.0.0.1:{sim.port}", gnss_delay_s=delay_s), SwitchingConfig()).start()
    flight = Flight()
    try:
        t0, dated = time.monotonic(), []
        while time.monotonic() - t0 < 4.0:
            now = time.monotonic()
            sim.feed_gnss(flight.gnss(now - lag_s, now - lag_s - t0))  # valid at its stamp, sent lag_s later
            deadline = now + 0.15
            while time.monotonic() < deadline:
                s = bridge.gnss_status().sample
                if s is not None and s.t_s != (dated[-1][1] if dated else None):
                    dated.append((now, s.t_s))
                    break
                time.sleep(0.005)
            time.sleep(max(0.0, 0.2 - (time.monotonic() - now)))
    finally:
        bridge.close()
        sim.close()
    late = [t_feed - t_s for t_feed, t_s in dated[-8:]]  # after SYSTEM_TIME (1 Hz) gave the boot offset
    assert len(late) == 8 and all(abs(x - (lag_s + delay_s)) < 0.01 for x in late), late


def _seen_last(rig, timeout_s=1.0) -> bool:
    """The bridge has the autopilot's last message (MAVLink sequence numbers) within timeout_s."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if rig.bridge.stats().last_seq == rig.sim.last_sent_seq():
            return True
        time.sleep(0.001)
    return False


@pytest.mark.parametrize("personality", ["px4", "ardupilot"])
def test_autopilot_sequence_numbers_show_the_last_message_and_the_lost_ones(rigs, personality):
    """BridgeStats.last_seq is the MAVLink sequence number of the autopilot's last message (what a
    simulated flight waits for, companion.app.fly_sim), TIMESYNC requests included; ``lost`` counts
    the gaps in its sequence."""
    rig = rigs(personality)
    assert rig.fly(3.0, until=lambda: rig.bridge.stats().link_up)  # the autopilot's HEARTBEAT: 1 Hz
    rig.fly(0.5)
    assert rig.sim.last_sent_seq() is not None
    assert _seen_last(rig)
    assert rig.bridge.stats().lost == 0  # loopback loses nothing
    with rig.sim._send_lock:  # the next 5 sequence numbers never reach the wire
        rig.sim._conn.mav.seq = (rig.sim._conn.mav.seq + 5) % 256
    rig.fly(0.5)
    assert _seen_last(rig)
    assert rig.bridge.stats().lost == 5


@pytest.mark.parametrize("on_new_peer", [False, True])
def test_a_simulated_clock_autopilot_answers_a_new_peer_with_a_heartbeat(on_new_peer):
    """On a simulated clock (moved by a flight's frames; here it stands at 0) the autopilot's 1 Hz
    HEARTBEAT is due again only at 1 s: its first one, sent before the bridge spoke, reached no one,
    and the link stays down (a repeatable flight from t = 0 waited 10 s of real time on each of
    its first ten frames). With heartbeat_on_new_peer it answers the bridge's first message, and
    the link is up with the clock still at 0."""
    from companion.app import SimClock

    clock = SimClock()
    sim = SimAutopilot("ardupilot", clock=clock, heartbeat_on_new_peer=on_new_peer).start()
    time.sleep(0.1)  # its first tick (HEARTBEAT due at 0) has passed, with no peer yet
    bridge = Bridge(MavlinkConfig(connect=f"udpout:127.0.0.1:{sim.port}"), SwitchingConfig(), clock=clock).start()
    try:
        deadline = time.monotonic() + 3.0
        while not bridge.stats().link_up and time.monotonic() < deadline:
            time.sleep(0.01)
        assert bridge.stats().link_up is on_new_peer and clock() == 0.0
        assert sim.received().counts["HEARTBEAT"] >= 1  # the bridge's reached it either way
        assert (sim.last_sent_seq() is not None) is on_new_peer  # nothing was written to a peer without it
    finally:
        bridge.close()
        sim.close()


def test_px4_origin_never_offered_over_its_own(rigs):
    # PX4 (like the real SIH) moves its NED origin to any SET_GPS_GLOBAL_ORIGIN: with GNSS at boot
    # it sets its own, and the bridge, which asks for it, must never offer ours over it
    rig = rigs("px4")
    assert rig.fly(8.0, until=lambda: rig.bridge.ekf_origin() is not None and rig.k > 120)
    rig.fly(3.0, gnss="lost")  # and not after GNSS goes either: the EKF has its origin
    assert rig.bridge.stats().origin_sent == 0
    assert rig.sim.received().counts["SET_GPS_GLOBAL_ORIGIN"] == 0 and rig.sim.origin_moves == 0


def test_ardupilot_close_while_active_sends_no_fix(rigs):
    rig = rigs("ardupilot")
    rig.fly(1.5)
    assert rig.fly(3.0, gnss="lost", until=lambda: rig.sim.estimate().source == "mavlink_gps")
    rig.bridge.close()
    time.sleep(0.3)
    assert rig.sim._mgps["fix"] < 3  # NO_FIX: our instance now reports no fix instead of a silent primary GPS


@pytest.mark.parametrize("switch", [True, False])
def test_active_claimed_only_once_the_autopilot_confirms_its_switch(rigs, switch):
    rig = rigs("ardupilot", switch_ekf_source=switch)
    rig.fly(1.5)
    assert rig.fly(3.0, gnss="lost", until=lambda: rig.bridge.state is BridgeState.ACTIVE)
    rig.fly(1.0, gnss="lost")
    texts = [t for _, t in rig.sim.received().statustext]
    assert rig.bridge.stats().source_switch == ("confirmed" if switch else "not configured")
    assert any(t.startswith("TerraSLAM ACTIVE") for t in texts) is switch, texts
    if not switch:
        assert any(t.startswith("TerraSLAM fixes offered, no source switch") for t in texts), texts


def test_unconfirmed_switch_is_not_claimed(rigs):
    rig = rigs("ardupilot", params={"GPS_AUTO_SWITCH": 1})
    del rig.sim.params["GPS_PRIMARY"]  # never confirmed
    rig.fly(1.5)
    rig.fly(6.5, gnss="lost")
    texts = [t for _, t in rig.sim.received().statustext]
    assert rig.bridge.stats().source_switch == "unconfirmed"
    assert not any(t.startswith("TerraSLAM ACTIVE") for t in texts)
    assert "TerraSLAM: source switch not confirmed" in texts


def test_wrong_target_system_is_reported(rigs):
    rig = rigs("px4", target_system=1)
    rig.sim.close()
    sim = SimAutopilot("px4", sysid=2, ekf_start_s=0.2).start()  # PX4 SITL instance 1 is system 2
    try:
        rig.bridge.close()
        rig.bridge = Bridge(rig.cfg.model_copy(update={"connect": f"udpout:127.0.0.1:{sim.port}"}), SwitchingConfig()).start()
        deadline = time.monotonic() + 3.0
        while not rig.bridge.stats().other_systems and time.monotonic() < deadline:
            rig.bridge.submit_fix(None)
            time.sleep(0.05)
        assert 2 in rig.bridge.stats().other_systems and not rig.bridge.stats().link_up
    finally:
        sim.close()


def test_no_takeover_without_a_fix_to_offer(rigs):
    # the companion boots before the receiver's first fix (seen on ArduPilot SITL): taking over then
    # made our empty GPS instance primary during the receiver's acquisition
    rig = rigs("ardupilot")
    rig.fly(2.5, gnss="lost", fix=False)
    assert rig.bridge.state is BridgeState.STANDBY and rig.bridge.events() == []
    assert rig.sim.received().counts["PARAM_SET"] == 0
    assert rig.fly(2.0, gnss="lost", until=lambda: rig.bridge.state is BridgeState.ACTIVE)  # a fix to offer: now
