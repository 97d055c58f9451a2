"""The bridge: link + GNSS monitor + switch policy + emitter, wired.

Threads: ``submit_fix`` runs on the caller's (pipeline) thread and writes the fix to the wire at
once (fix-to-wire latency is the time spent inside it); one receive thread reads the autopilot,
answers TIMESYNC, sends our HEARTBEAT, requests streams, manages the EKF origin and runs the
switch policy every tick (≤ 50 ms).
"""
from __future__ import annotations

import logging
import math
import struct
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from gis.geodesy import LocalFrame, msl_to_ellipsoid, pressure_altitude_m
from gis.types import GlobalFix
from mavlink_bridge import emitters
from mavlink_bridge.config import MavlinkConfig, SwitchingConfig
from mavlink_bridge.link import Link, load_signing_key
from mavlink_bridge.monitor import EKF_STATUS_GPS_GLITCH, ESTIMATOR_GPS_GLITCH, GnssMonitor, sample_from_gps_raw
from mavlink_bridge.policy import BridgeState, SwitchEvent, SwitchPolicy
from mavlink_bridge.types import GnssQuality, GnssSample, GnssStatus, VehicleAttitude

log = logging.getLogger(__name__)

TICK_S = 0.05
CONFIRM_RESEND_S = 1.0   # source-switch commands are re-sent until the autopilot confirms them
CONFIRM_TRIES = 5
LATENCY_SAMPLES = 10000
UNIX_TIME_MIN_US = 10**15       # time_usec at or above this is UNIX time (2001 on), below: time since boot
GNSS_STAMP_MAX_AGE_S = 1.0      # a GNSS stamp older than this on arrival is not believed (arrival time used)
BOOT_OFFSET_SLACK_S = 0.05      # ... nor one this far in the future (the boot offset carries the link's latency)
BARO_MAX_AGE_S = 0.5     # a barometer sample (ALTITUDE / SCALED_PRESSURE) older than this is not attached to the attitude
STATUSTEXT_LEN = 50      # MAVLink STATUSTEXT.text
EKF_POS_HORIZ_ABS = 16   # EKF_STATUS_REPORT (ArduPilot) and ESTIMATOR_STATUS (PX4): the same bit
#: Before we ever offer an EKF origin the autopilot has this long after link-up to tell us its own
#: (answers to REQUEST_MESSAGE, re-sent every origin_resend_s): PX4 moves an existing NED origin to
#: whatever SET_GPS_GLOBAL_ORIGIN says, so one sent before its answer shifts the vehicle's frame.
ORIGIN_ANSWER_WAIT_S = 4.0


def statustext(text: str, limit: int = STATUSTEXT_LEN) -> bytes:
    """``text`` as one STATUSTEXT: cut at the last word boundary that fits, never mid-word."""
    raw = text.encode("ascii", "replace")
    if len(raw) <= limit:
        return raw
    cut = raw[:limit + 1].rfind(b" ")
    return raw[:cut if cut > limit // 2 else limit].rstrip(b" ,:;")


@dataclass
class BridgeStats:
    sent: Counter = field(default_factory=Counter)         # message type → count
    received: Counter = field(default_factory=Counter)     # message type → count (valid, from the autopilot)
    fix_to_wire_s: list[float] = field(default_factory=list)  # submit_fix entry → written to the socket
    rejected_frames: int = 0                                # garbage / bad CRC / bad signature
    link_up: bool = False
    autopilot: str | None = None                            # what the HEARTBEAT says we talk to
    origin: tuple[float, float, float] | None = None        # EKF origin lat, lon, alt MSL
    boot_offset_s: float | None = None                      # our clock − autopilot boot time
    acks: Counter = field(default_factory=Counter)          # (command, result) → count
    last_seq: int | None = None                             # MAVLink sequence number of the autopilot's last message
    lost: int = 0                                           # the autopilot's messages missing from its sequence (link loss)
    origin_sent: int = 0                                    # SET_GPS_GLOBAL_ORIGIN messages we sent
    #: the autopilot's source switch: "not configured" | "pending" | "confirmed" | "unconfirmed" (its
    #: last takeover or hand-back); "TerraSLAM ACTIVE" is announced only once it is "confirmed"
    source_switch: str = "not configured"
    other_systems: Counter = field(default_factory=Counter)  # HEARTBEATs of autopilots that are not our target_system


def _q_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy])


class Bridge:
    def __init__(self, mav_cfg: MavlinkConfig, sw_cfg: SwitchingConfig, clock=time.monotonic,
                 on_gnss: Callable[[GnssSample], None] | None = None,
                 on_attitude: Callable[[VehicleAttitude], None] | None = None,
                 on_mavlink: Callable[[bytes], None] | None = None):
        """``on_gnss`` / ``on_attitude``: called on the receive thread with every GNSS solution and
        attitude received from the autopilot; ``on_mavlink``: with the wire bytes of every message
        received and sent (Link's tap; the sending thread's). For the flight recorder; they must
        not block or raise."""
        emitters.check_profile(mav_cfg)
        self.cfg, self.sw_cfg, self.clock = mav_cfg, sw_cfg, clock
        self._on_gnss, self._on_attitude, self._on_mavlink = on_gnss, on_attitude, on_mavlink
        self._key = load_signing_key(mav_cfg.signing_key_file) if mav_cfg.signing_key_file else None
        self.monitor = GnssMonitor(sw_cfg, mav_cfg.uere_m)
        self.policy = SwitchPolicy(sw_cfg)
        self._lock = threading.Lock()          # monitor / policy / origin / attitude
        self._stats = BridgeStats()
        self._latency = deque(maxlen=LATENCY_SAMPLES)
        self._link: Link | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._origin: LocalFrame | None = None
        self._q_ned_body: np.ndarray | None = None
        self._attitude: VehicleAttitude | None = None
        self._estimate: tuple[float, float, float, float] | None = None  # GLOBAL_POSITION_INT (boot s, lat, lon, MSL m)
        self._baro: tuple[float, float] | None = None  # (bridge clock s, ALTITUDE.altitude_monotonic m)
        self._last_emit_s = -math.inf
        self._last_fix_s: float | None = None   # clock time of the last fix we wrote
        self._last_fix: GlobalFix | None = None
        self._offered_s: float | None = None     # clock time of our last fresh, trustworthy fix (sent or not)
        self._last_hb_rx_s: float | None = None
        self._link_up_since_s: float | None = None
        self._last_rx_s = -math.inf               # any message from the autopilot
        self._next_hb_s = 0.0
        self._next_origin_s = 0.0
        self._last_boot_ms: int | None = None
        self._period_s = 1.0 / mav_cfg.rate_hz
        self._origin_wait_until_s = math.inf   # link-up + ORIGIN_ANSWER_WAIT_S: no origin of ours offered before
        self._pending: dict[str, list] = {}    # key → [message, expected wire value | None, next send s, tries]
        self._announce: str | None = None      # the ACTIVE announcement waiting for the source switch's confirmation
        self._ekf_pos_abs = False              # the EKF reports an absolute horizontal position (so it has an origin)
        # ArduPilot reports GPS instance 0 in GPS_RAW_INT and 1 in GPS2_RAW: watch the one that is not ours.
        self._gnss_msg = "GPS2_RAW" if (mav_cfg.autopilot == "ardupilot" and mav_cfg.output == "gps_input" and mav_cfg.gps_id == 0) else "GPS_RAW_INT"
        if mav_cfg.autopilot == "px4" and mav_cfg.output in emitters.LOCAL_OUTPUTS and mav_cfg.rate_hz < 20:
            log.warning("mavlink.rate_hz=%g: PX4 external vision wants >= 20 Hz (drops samples > 200 ms apart)", mav_cfg.rate_hz)

    def _gnss_time(self, time_usec: int, now: float) -> float:
        """When a receiver solution was valid, on our clock. PX4 and ArduPilot stamp GPS_RAW_INT /
        GPS2_RAW with the autopilot's boot time of the fix (µs; MAVLink also allows UNIX time, told
        apart by size): carried over with SYSTEM_TIME's boot offset, it removes the stream's and
        the link's delay (ArduPilot sends a solution at its next stream tick: up to 1/rate late,
        1–2 m at 10 m/s for a 5 Hz stream). Then ``gnss_delay_s`` earlier, the receiver's own
        latency. The arrival time stands in when the offset is not known yet or the stamp is
        implausible (in the future, or older than GNSS_STAMP_MAX_AGE_S)."""
        t = now
        off = self._stats.boot_offset_s
        if off is not None and 0 < time_usec < UNIX_TIME_MIN_US:
            t_fix = time_usec / 1e6 + off
            if now - GNSS_STAMP_MAX_AGE_S <= t_fix <= now + BOOT_OFFSET_SLACK_S:
                t = min(t_fix, now)
        return t - self.cfg.gnss_delay_s

    # ---- lifecycle -------------------------------------------------------------------------
    def start(self) -> "Bridge":
        """Open the link and start the receive thread (once: a started bridge is returned as is)."""
        if self._thread is not None:
            return self
        c = self.cfg
        self._link = Link(c.connect, c.baud, c.source_system, c.source_component, self._key,
                          c.allow_unsigned, c.reconnect_max_s, tap=self._on_mavlink)
        self._thread = threading.Thread(target=self._run, name="mavlink-bridge", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop the receive thread and close the link. A GPS_INPUT feed ends with one NO_FIX, so
        ArduPilot drops our instance now instead of keeping a silent primary GPS for 4 s."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._link is not None:
            self._stop_output("bridge closing")
            self._link.close()

    # ---- public state ----------------------------------------------------------------------
    @property
    def state(self) -> BridgeState:
        return self.policy.state

    def ekf_origin(self) -> LocalFrame | None:
        """The autopilot's EKF origin (GPS_GLOBAL_ORIGIN) once it has told us, else None."""
        with self._lock:
            return self._origin

    def ekf_absolute_position(self) -> bool:
        """The autopilot's EKF reports an absolute horizontal position (EKF_STATUS_REPORT / ESTIMATOR_STATUS)."""
        return self._ekf_pos_abs

    def gnss_status(self) -> GnssStatus:
        with self._lock:
            return self.monitor.status(self.clock())

    def vision_check(self, reason: str | None) -> None:
        """The pipeline's GNSS-vs-visual-odometry verdict (None = consistent); see GnssMonitor.on_vision_check."""
        with self._lock:
            self.monitor.on_vision_check(reason)

    def attitude(self, max_age_s: float = 0.1) -> VehicleAttitude | None:
        """The autopilot's latest attitude, or None when none arrived within max_age_s."""
        with self._lock:
            a = self._attitude
        return a if a is not None and self.clock() - a.t_s <= max_age_s else None

    def autopilot_estimate(self) -> tuple[float, float, float, float] | None:
        """The autopilot's own latest position estimate (GLOBAL_POSITION_INT): (its boot time in s,
        lat_deg, lon_deg, alt MSL m), stamped by the autopilot, or None before the first."""
        with self._lock:
            return self._estimate

    def events(self) -> list[SwitchEvent]:
        with self._lock:
            return list(self.policy.events)

    def sent_count(self, msg_type: str) -> int:
        """Messages of ``msg_type`` written to the link so far (cheap: no copy of the latency window)."""
        return self._stats.sent[msg_type]

    def stats(self) -> BridgeStats:
        s = self._stats
        s.fix_to_wire_s = list(self._latency)
        s.rejected_frames = self._link.rejected if self._link else 0
        return s

    # ---- hot path --------------------------------------------------------------------------
    def submit_fix(self, fix: GlobalFix | None) -> None:
        """Our latest global fix (None = tracking lost: output stops at once)."""
        t0 = self.clock()
        # Lock-free on purpose (latency): each of these is a single reference read/write, atomic in CPython.
        self.monitor.on_fix(fix)
        state, origin, q = self.policy.state, self._origin, self._q_ned_body
        if fix is None or t0 - fix.t_s > self.cfg.max_fix_age_s:
            self._stop_output("tracking lost" if fix is None else f"fix {t0 - fix.t_s:.2f} s old")
            return
        if emitters.trustworthy(fix, self.cfg):
            self._offered_s = t0
        if state is BridgeState.STANDBY and not self.cfg.feed_in_standby:
            return
        if t0 - self._last_emit_s < 0.9 * self._period_s:
            return
        msg = self._encode(fix, origin, q, t0)
        if msg is None or self._link is None or not self._link.send(msg):
            return
        t1 = self.clock()
        self._latency.append(t1 - t0)
        self._stats.sent[msg.get_type()] += 1
        self._last_emit_s, self._last_fix_s, self._last_fix = t0, t0, fix

    def _encode(self, fix: GlobalFix, origin: LocalFrame | None, q, now_s: float):
        c, mav = self.cfg, self._link.mav
        if c.output == "gps_input":
            return emitters.gps_input(mav, fix, c)
        if not emitters.trustworthy(fix, c):
            return None
        if c.output == "global_position_sensor":
            return emitters.global_position_sensor(mav, fix, c, now_s)
        if c.output == "hil_gps":
            return emitters.hil_gps(mav, fix, c)
        if origin is None:  # NED needs the EKF origin: nothing until GPS_GLOBAL_ORIGIN is known
            return None
        if c.output == "odometry":
            return emitters.odometry(mav, fix, origin, c, q)
        return emitters.vision_position_estimate(mav, fix, origin, q)

    def _stop_output(self, why: str) -> None:
        """Stop emitting; GPS_INPUT gets one NO_FIX so ArduPilot drops it now, not after 4 s."""
        if self._last_fix_s is None:
            return
        self._last_fix_s = None
        self._last_fix = None
        log.info("output stopped: %s", why)
        if self.cfg.output == "gps_input" and self._link is not None and self._link.send(emitters.gps_input(self._link.mav, None, self.cfg)):
            self._stats.sent["GPS_INPUT"] += 1

    # ---- receive thread --------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self._link.recv(TICK_S)
            now = self.clock()
            if msg is not None:
                try:
                    self._handle(msg, now)
                except Exception:  # one malformed-but-parsable message must not kill the bridge
                    log.exception("handling %s failed", msg.get_type())
            self._tick(now)

    def _count(self, msg) -> None:
        """Per type, and the gaps in the autopilot's MAVLink sequence (messages lost on the link)."""
        s, seq = self._stats, msg.get_seq()
        s.received[msg.get_type()] += 1
        if s.last_seq is not None:
            s.lost += (seq - s.last_seq - 1) % 256
        s.last_seq = seq

    def _from_autopilot(self, msg) -> bool:
        return msg.get_srcSystem() == self.cfg.target_system and msg.get_srcComponent() == self.cfg.target_component

    def _handle(self, msg, now: float) -> None:
        t = msg.get_type()
        from_autopilot = self._from_autopilot(msg)
        if from_autopilot:
            self._count(msg)
        elif t == "HEARTBEAT" and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and msg.get_srcComponent() == 1:
            self._other_autopilot(msg.get_srcSystem())
        if t == "TIMESYNC" and msg.tc1 == 0:  # answer the autopilot's timesync request with our clock
            self._send(self._link.mav.timesync_encode(int(now * 1e9), msg.ts1))
            return
        if not from_autopilot:
            return
        self._last_rx_s = now
        if t == "HEARTBEAT":
            if self._last_hb_rx_s is None or now - self._last_hb_rx_s > self.cfg.link_timeout_s:
                self._link_up_since_s = now
                self._on_link_up(msg)
            self._last_hb_rx_s = now
        elif t == self._gnss_msg:
            sample = sample_from_gps_raw(msg, self._gnss_time(msg.time_usec, now))
            with self._lock:
                self.monitor.on_sample(sample)
            if self._on_gnss is not None:
                self._on_gnss(sample)
        elif t == "EKF_STATUS_REPORT":
            self._ekf_pos_abs = bool(msg.flags & EKF_POS_HORIZ_ABS)
            with self._lock:
                self.monitor.on_ekf_flags(bool(msg.flags & EKF_STATUS_GPS_GLITCH), now)
        elif t == "ESTIMATOR_STATUS":
            self._ekf_pos_abs = bool(msg.flags & EKF_POS_HORIZ_ABS)
            with self._lock:
                self.monitor.on_ekf_flags(bool(msg.flags & ESTIMATOR_GPS_GLITCH), now)
        elif t == "ATTITUDE":
            with self._lock:
                self._q_ned_body = _q_from_euler(msg.roll, msg.pitch, msg.yaw)
                off = self._stats.boot_offset_s  # stamp with the autopilot's own time when known
                t_att = msg.time_boot_ms / 1000.0 + off if off is not None else now
                baro = self._baro[1] if self._baro is not None and now - self._baro[0] <= BARO_MAX_AGE_S else None
                self._attitude = att = VehicleAttitude(min(t_att, now), msg.roll, msg.pitch, msg.yaw, baro)
            if self._on_attitude is not None:
                self._on_attitude(att)
        elif t == "ALTITUDE":  # PX4: altitude_monotonic is the barometric altitude
            if math.isfinite(msg.altitude_monotonic):
                with self._lock:
                    self._baro = (now, float(msg.altitude_monotonic))
        elif t == "SCALED_PRESSURE":  # ArduPilot's barometer (it does not send ALTITUDE)
            if math.isfinite(msg.press_abs) and msg.press_abs > 0:
                with self._lock:
                    self._baro = (now, pressure_altitude_m(msg.press_abs))
        elif t == "GLOBAL_POSITION_INT":
            with self._lock:
                self._estimate = (msg.time_boot_ms / 1000.0, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt / 1000.0)
        elif t == "GPS_GLOBAL_ORIGIN":
            self._on_origin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude / 1000.0)
        elif t == "SYSTEM_TIME":
            if self._last_boot_ms is not None and msg.time_boot_ms + 1000 < self._last_boot_ms:
                log.warning("autopilot rebooted: re-reading its EKF origin and re-requesting streams")
                with self._lock:
                    self._origin = None
                self._request_streams()
            self._last_boot_ms = msg.time_boot_ms
            self._stats.boot_offset_s = now - msg.time_boot_ms / 1000.0
        elif t == "COMMAND_ACK":
            self._stats.acks[(msg.command, msg.result)] += 1
            if f"cmd:{msg.command}" in self._pending and msg.result != mavlink.MAV_RESULT_IN_PROGRESS:
                del self._pending[f"cmd:{msg.command}"]
                if msg.result != mavlink.MAV_RESULT_ACCEPTED:
                    log.error("autopilot refused command %d (result %d): source switch not applied", msg.command, msg.result)
                    self._switch_outcome("unconfirmed")
                else:
                    self._switch_outcome("confirmed")
        elif t == "PARAM_VALUE":
            name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode()
            pending = self._pending.get(f"param:{name.rstrip(chr(0))}")
            if pending is not None and struct.pack("<f", msg.param_value) == struct.pack("<f", pending[1]):
                del self._pending[f"param:{name.rstrip(chr(0))}"]
                self._switch_outcome("confirmed")

    def _other_autopilot(self, sysid: int) -> None:
        """An autopilot HEARTBEAT from another system than ``target_system``: said once per system,
        because a wrong id silently drops every command (PX4 SITL instance N is system N+1)."""
        s = self._stats
        if not s.other_systems[sysid]:
            log.error("autopilot HEARTBEAT from system %d, but mavlink.target_system=%d: set target_system "
                      "(and source_system) to the vehicle's system id", sysid, self.cfg.target_system)
        s.other_systems[sysid] += 1

    def _on_link_up(self, hb) -> None:
        kind = {mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot", mavlink.MAV_AUTOPILOT_PX4: "px4"}.get(hb.autopilot, f"autopilot {hb.autopilot}")
        self._stats.autopilot, self._stats.link_up = kind, True
        log.info("link up: %s (sys %d)", kind, hb.get_srcSystem())
        if kind != self.cfg.autopilot:
            log.error("connected autopilot is %s but mavlink.autopilot=%s: it may ignore what we send", kind, self.cfg.autopilot)
        self._origin_wait_until_s = self.clock() + ORIGIN_ANSWER_WAIT_S
        self._request_streams()

    def _on_origin(self, lat: float, lon: float, alt_msl: float) -> None:
        frame = LocalFrame(lat, lon, float(msl_to_ellipsoid(lat, lon, alt_msl)))
        with self._lock:
            changed = self._origin is None or (self._origin.lat0_deg, self._origin.lon0_deg) != (lat, lon)
            self._origin = frame
        if changed:
            log.info("EKF origin %.7f %.7f %.2f m MSL", lat, lon, alt_msl)
        self._stats.origin = (lat, lon, alt_msl)

    def _send(self, msg) -> None:
        if self._link.send(msg):
            self._stats.sent[msg.get_type()] += 1

    def _command(self, command: int, *params: float) -> None:
        p = list(params) + [0.0] * (7 - len(params))
        self._send(self._link.mav.command_long_encode(self.cfg.target_system, self.cfg.target_component, command, 0, *p))

    def _request_streams(self) -> None:
        interval_us = lambda hz: 1e6 / hz  # noqa: E731
        streams = {mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: self.cfg.gnss_stream_hz,
                   mavlink.MAVLINK_MSG_ID_GPS2_RAW: self.cfg.gnss_stream_hz,
                   mavlink.MAVLINK_MSG_ID_ATTITUDE: 20.0, mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0}
        if self.cfg.estimate_stream_hz > 0:  # the autopilot's estimate, for flight reports only
            streams[mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT] = self.cfg.estimate_stream_hz
        if self.cfg.autopilot == "ardupilot":
            streams[mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT] = 2.0
            streams[mavlink.MAVLINK_MSG_ID_SCALED_PRESSURE] = 5.0   # the barometer
        else:
            streams[mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS] = 2.0
            streams[mavlink.MAVLINK_MSG_ID_ALTITUDE] = 5.0          # altitude_monotonic: the barometer
        for msg_id, hz in streams.items():
            self._command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval_us(hz))
        self._command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)

    def _tick(self, now: float) -> None:
        if now >= self._next_hb_s:
            self._next_hb_s = now + 1.0 / self.cfg.heartbeat_hz
            self._send(self._link.mav.heartbeat_encode(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE))
        link_up = self._last_hb_rx_s is not None and now - self._last_hb_rx_s <= self.cfg.link_timeout_s
        if self._stats.link_up and not link_up:
            log.warning("link down: no autopilot HEARTBEAT for %.1f s", now - self._last_hb_rx_s)
        self._stats.link_up = link_up
        # After (re)connecting, give the requested GNSS stream stale_after_s to arrive before judging it;
        # when the autopilot has gone quiet altogether, GNSS silence says nothing about its receiver.
        stale = self.sw_cfg.stale_after_s
        judged = link_up and now - self._link_up_since_s >= stale and now - self._last_rx_s <= stale / 2
        with self._lock:
            status = self.monitor.status(now)
            have_fix = self._offered_s is not None and now - self._offered_s <= self.cfg.max_fix_age_s
            event = self.policy.update(status, judged, have_fix)
            need_origin = self._origin is None
        if event is not None:
            self._on_switch(event)
        self._resend_pending(now)
        if self._last_fix_s is not None and now - self._last_fix_s > self.cfg.max_fix_age_s:
            self._stop_output("no fresh fix")
        if need_origin and self.cfg.output in emitters.LOCAL_OUTPUTS and link_up and now >= self._next_origin_s:
            self._next_origin_s = now + self.cfg.origin_resend_s
            self._command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)
            fix = self._last_fix or self.monitor.fix
            if fix is not None and emitters.trustworthy(fix, self.cfg) and self._may_offer_origin(now):
                # ArduPilot drops it before its EKF starts and accepts it once: re-send until it answers.
                self._send(self._link.mav.set_gps_global_origin_encode(
                    self.cfg.target_system, round(fix.lat_deg * 1e7), round(fix.lon_deg * 1e7), round(fix.h_msl_m * 1000), 0))
                self._stats.origin_sent += 1

    def _may_offer_origin(self, now: float) -> bool:
        """Only an autopilot that has no EKF origin gets ours: never over an existing one (PX4 moves
        its NED frame to it, shifting the vehicle's local position). It has one, or will set its own,
        when it answered GPS_GLOBAL_ORIGIN (then we are not asked), when its EKF reports an absolute
        horizontal position, or while its receiver has a 3D fix; and it gets ORIGIN_ANSWER_WAIT_S
        after link-up to answer our requests first."""
        with self._lock:
            st = self.monitor.status(now)
        receiver_fix = st.quality is not GnssQuality.LOST and st.sample is not None and st.sample.fix_type >= 3
        return now >= self._origin_wait_until_s and not self._ekf_pos_abs and not receiver_fix

    def _on_switch(self, ev: SwitchEvent) -> None:
        """Log the switch, ask the autopilot to switch its source, and tell the pilot. "TerraSLAM
        ACTIVE" is said only once the autopilot confirmed that it now uses us (_switch_outcome);
        without a source switch the text says that our fixes are only offered."""
        log.warning("switch %s -> %s at %.2f s: %s", ev.from_state.value, ev.to_state.value, ev.t_s, ev.reason)
        active = ev.to_state is BridgeState.ACTIVE
        switching = self.cfg.switch_ekf_source and self._switch_source(active)
        self._stats.source_switch = "pending" if switching else "not configured"
        self._announce = None
        if not active:
            self._statustext(mavlink.MAV_SEVERITY_NOTICE, f"TerraSLAM STANDBY: {ev.reason}")
        elif switching:
            self._announce = f"TerraSLAM ACTIVE: {ev.reason}"
        else:
            self._statustext(mavlink.MAV_SEVERITY_WARNING, f"TerraSLAM fixes offered, no source switch: {ev.reason}")

    def _switch_outcome(self, outcome: str) -> None:
        self._stats.source_switch = outcome
        if outcome == "confirmed" and self._announce is not None:
            self._statustext(mavlink.MAV_SEVERITY_WARNING, self._announce)
        elif outcome == "unconfirmed" and self._announce is not None:
            self._statustext(mavlink.MAV_SEVERITY_ERROR, "TerraSLAM: source switch not confirmed")
        self._announce = None

    def _statustext(self, severity: int, text: str) -> None:
        self._send(self._link.mav.statustext_encode(severity, statustext(text)))

    def _switch_source(self, active: bool) -> bool:
        """Ask the autopilot to take (``active``) or drop our source; False where this output has no switch."""
        c = self.cfg
        if c.autopilot == "ardupilot" and c.output == "gps_input":
            # Effective with GPS_AUTO_SWITCH=0 (docs/AUTOPILOTS.md): make our instance primary, or the receiver's.
            self._param_set(b"GPS_PRIMARY", c.gps_id if active else 1 - c.gps_id, mavlink.MAV_PARAM_TYPE_INT8)
        elif c.autopilot == "ardupilot":
            msg = self._link.mav.command_long_encode(c.target_system, c.target_component, mavlink.MAV_CMD_SET_EKF_SOURCE_SET, 0,
                                                     c.ekf_source_set_extnav if active else c.ekf_source_set_gnss, 0, 0, 0, 0, 0, 0)
            self._confirm(f"cmd:{mavlink.MAV_CMD_SET_EKF_SOURCE_SET}", msg, None)
        elif c.output == "hil_gps":
            # HIL_GPS is itself a GPS to EKF2: EKF2_GPS_CTRL=0 would drop it too. PX4 picks the better
            # receiver on fix loss; a spoofed receiver is not overridden on this path (docs/AUTOPILOTS.md).
            log.warning("px4 hil_gps: no source switch available; PX4 selects the receiver by itself")
            return False
        else:
            # PX4 keeps fusing a (spoofed) receiver that looks healthy: stop GNSS fusion while we lead.
            self._param_set(b"EKF2_GPS_CTRL", 0 if active else c.px4_gps_ctrl, mavlink.MAV_PARAM_TYPE_INT32)
        return True

    def _param_set(self, name: bytes, value: int, ptype: int) -> None:
        # ArduPilot takes integers as float values; PX4 encodes them bytewise in the float field.
        v = struct.unpack("<f", struct.pack("<i", value))[0] if self.cfg.autopilot == "px4" else float(value)
        msg = self._link.mav.param_set_encode(self.cfg.target_system, self.cfg.target_component, name, v, ptype)
        self._confirm(f"param:{name.decode()}", msg, v)

    def _confirm(self, key: str, msg, expected: float | None) -> None:
        """Send now and re-send until PARAM_VALUE / COMMAND_ACK confirms it (a lossy link must not
        leave the autopilot on the wrong source); a newer request for the same key replaces it."""
        self._pending[key] = [msg, expected, self.clock() + CONFIRM_RESEND_S, 1]
        self._send(msg)

    def _resend_pending(self, now: float) -> None:
        for key, p in list(self._pending.items()):
            if now < p[2]:
                continue
            if p[3] >= CONFIRM_TRIES:
                log.error("%s not confirmed by the autopilot after %d tries: source switch may not be applied", key, p[3])
                del self._pending[key]
                self._switch_outcome("unconfirmed")
                continue
            p[2], p[3] = now + CONFIRM_RESEND_S, p[3] + 1
            self._send(p[0])

    def pending_confirmations(self) -> list[str]:
        """Source-switch commands the autopilot has not confirmed yet."""
        return list(self._pending)
