"""Simulated autopilot: a real pymavlink endpoint on UDP loopback with PX4 and ArduPilot
personalities that accept, reject and fuse our messages the way docs/AUTOPILOTS.md says the real ones do.

It streams HEARTBEAT, SYSTEM_TIME, ATTITUDE, ALTITUDE, GPS_RAW_INT (from ``feed_gnss``), GPS2_RAW
(ArduPilot's MAVLink GPS instance), EKF_STATUS_REPORT / ESTIMATOR_STATUS, GLOBAL_POSITION_INT and
GPS_GLOBAL_ORIGIN; answers COMMAND_LONG (SET_MESSAGE_INTERVAL, REQUEST_MESSAGE, SET_EKF_SOURCE_SET)
and PARAM_SET. Its position estimate is deliberately simple: it *snaps* to whichever source its
rules select (EKF3 and EKF2 both snap on a source change), so tests can assert which source the
autopilot uses and that it follows our fixes. It is not a filter model of EKF2/EKF3.

Personality rules (docs/AUTOPILOTS.md):
- px4: no GPS_INPUT handler (ignored); ODOMETRY needs frame LOCAL_NED/LOCAL_FRD and estimator
  VISION/VIO; EV samples > 200 ms apart are dropped; EV/AGP used when GNSS is not fused;
  GLOBAL_POSITION_SENSOR needs id = EKF2_AGP0_ID and is rejected while good GNSS disagrees;
  HIL_GPS needs MAV_USEHILGPS=1, the vehicle's system id, fix ≥ 3, ≥ 6 satellites, eph < 3 m;
  EKF2_GPS_CTRL=0 stops GNSS fusion; dead-reckons 6 s after losing every source; streams by default.
- ardupilot: GPS_INPUT only to a GPSx_TYPE=14 instance whose index equals gps_id; MAVLink GPS
  unhealthy below 5 Hz (mean gap ≥ 215 ms), NO_FIX after 4 s silence; EKF3 pre-use checks (HDOP,
  satellites, accuracies) only before it aids with an absolute position; primary by GPS_AUTO_SWITCH / GPS_PRIMARY; ExternalNav (VPE, or ODOMETRY
  only LOCAL_FRD/BODY_FRD) at most one sample per 20 ms, used when the active EK3 source set has
  POSXY=6; SET_GPS_GLOBAL_ORIGIN dropped before the EKF starts and accepted once; streams only what
  is requested with SET_MESSAGE_INTERVAL.
- px4 (as the real SIH): SET_GPS_GLOBAL_ORIGIN over an existing origin moves it (``origin_moves``).
"""
from __future__ import annotations

import math
import struct
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from gis.geodesy import LocalFrame, ellipsoid_to_msl, msl_to_ellipsoid, pressure_hpa_at
from mavlink_bridge.link import open_connection
from mavlink_bridge.types import GnssSample, GpsFixType

PERSONALITIES = ("px4", "ardupilot")
DEFAULT_PARAMS = {
    "ardupilot": {"GPS1_TYPE": 1, "GPS2_TYPE": 14, "GPS_AUTO_SWITCH": 1, "GPS_PRIMARY": 0, "VISO_TYPE": 1,
                  "EK3_SRC1_POSXY": 3, "EK3_SRC2_POSXY": 6, "EK3_SRC3_POSXY": 0},
    "px4": {"EKF2_GPS_CTRL": 7, "EKF2_EV_CTRL": 3, "EKF2_AGP0_ID": 1, "EKF2_AGP0_CTRL": 1, "MAV_USEHILGPS": 1,
            "EKF2_REQ_EPH": 3.0},
}
PX4_DEAD_RECKON_S = 6.0
AP_DEAD_RECKON_S = 5.0
MAVGPS_TIMEOUT_S = 4.0          # ArduPilot: 4 s of GPS_INPUT silence → NO_FIX
MAVGPS_MAX_MEAN_GAP_S = 0.215   # ArduPilot: healthy needs ≥ 5 Hz
EV_MAX_GAP_S = 0.2              # PX4: EV samples further apart are dropped
EXTNAV_MIN_GAP_S = 0.02         # ArduPilot: at most one ExternalNav sample per 20 ms
SOURCE_FRESH_S = 0.5            # a fused sample older than this no longer drives the estimate


@dataclass(frozen=True)
class SimEstimate:
    t_s: float
    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    source: str      # gnss | mavlink_gps | external_nav | external_vision | aux_global | hil_gps | dead_reckoning | none
    valid: bool


@dataclass
class Received:
    counts: Counter = field(default_factory=Counter)      # message type → received
    accepted: Counter = field(default_factory=Counter)    # message type → accepted for fusion
    rejections: list = field(default_factory=list)        # (t_s, message type, reason)
    timesync_answers: int = 0
    statustext: list = field(default_factory=list)        # (severity, text)

    def reasons(self, msg_type: str) -> list[str]:
        return [r for _, t, r in self.rejections if t == msg_type]


@dataclass
class _Pos:
    t_s: float
    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    h_acc_m: float = math.nan


class SimAutopilot:
    def __init__(self, personality: str, port: int = 0, *, sysid: int = 1, compid: int = 1,
                 ekf_start_s: float | None = None, params: dict | None = None,
                 signing_key: bytes | None = None, clock=time.monotonic, gnss_report_lag_s: float = 0.0,
                 heartbeat_on_new_peer: bool = False):
        """``heartbeat_on_new_peer``: answer a new peer's first message with a HEARTBEAT at once
        instead of at the next 1 Hz tick (for a simulated ``clock``, _run)."""
        if personality not in PERSONALITIES:
            raise ValueError(f"personality must be one of {PERSONALITIES}, got {personality!r}")
        self.personality, self.sysid, self.compid, self.clock = personality, sysid, compid, clock
        # GPS_RAW_INT's time_usec is the boot time the fix was stamped at (PX4, ArduPilot); a real
        # autopilot sends it at its next stream tick: here each fed solution is sent at once but
        # stamped this much earlier (feed solutions valid at that earlier time)
        self.gnss_report_lag_s = gnss_report_lag_s
        self.params = dict(DEFAULT_PARAMS[personality], **(params or {}))
        self.ekf_start_s = ekf_start_s if ekf_start_s is not None else (3.5 if personality == "ardupilot" else 1.0)
        self._conn = open_connection(f"udpin:127.0.0.1:{port}", 0, sysid, compid, signing_key)
        self.port = self._conn.port.getsockname()[1]
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._sent_seq: int | None = None  # of the last message written to a peer
        self._peers = 0  # peers (UDP addresses) heard from so far
        self._heartbeat_on_new_peer = heartbeat_on_new_peer
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._rx = Received()
        self._t0 = clock()
        self._gnss: GnssSample | None = None
        self._glitch = False
        self._att = (0.0, 0.0, 0.0)
        self._truth: _Pos | None = None
        # barometer (PX4 ALTITUDE / ArduPilot SCALED_PRESSURE): altitude since the first truth, plus a random-walk
        # drift and white noise (companion/sim/autopilot_signals.py's model: 0.02 m/√s, 0.15 m)
        self._baro_rng = np.random.default_rng(0)
        self._baro_zero_m: float | None = None
        self._baro_drift_m = 0.0
        self._baro_last_s: float | None = None
        self.origin: _Pos | None = None
        self.origin_moves = 0  # px4: SET_GPS_GLOBAL_ORIGIN over an existing origin (the real one moves its frame)
        self._mgps: dict | None = None          # last GPS_INPUT fields (ArduPilot MAVLink GPS)
        self._mgps_times: deque = deque(maxlen=10)
        self._ext: _Pos | None = None           # ExternalNav / EV (converted to global)
        self._ext_prev_t: float | None = None
        self._agp: _Pos | None = None
        self._hil: _Pos | None = None
        self._hil_fix = 0
        self.source_set = 1
        self._last_est: SimEstimate | None = None
        self._lost_since: float | None = None
        default_streams = {} if personality == "ardupilot" else {
            mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0, mavlink.MAVLINK_MSG_ID_ATTITUDE: 0.1,
            mavlink.MAVLINK_MSG_ID_ALTITUDE: 0.2, mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 0.0,
            mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS: 0.5, mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 0.2,
        }
        self._interval_s: dict[int, float] = default_streams  # 0 = on every new sample
        self._next_s: dict[int, float] = {}

    # ---- lifecycle / inputs ---------------------------------------------------------------
    def start(self) -> "SimAutopilot":
        self._thread = threading.Thread(target=self._run, name=f"sim-{self.personality}", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._conn.close()

    def feed_gnss(self, sample: GnssSample, glitch: bool = False) -> None:
        """The real receiver's solution (GNSS simulator); sent as GPS_RAW_INT right away if streamed.
        ``glitch`` raises the EKF's GPS-glitch flag (what EKF3/EKF2 do on a position jump)."""
        with self._lock:
            self._gnss = sample
            self._glitch = glitch
            now = self.clock()
            if self.origin is None and self._ekf_started(now) and sample.fix_type >= GpsFixType.FIX_3D:
                self._set_origin(sample.lat_deg, sample.lon_deg, sample.alt_msl_m)
        if mavlink.MAVLINK_MSG_ID_GPS_RAW_INT in self._interval_s:
            self._send(self._gps_raw(sample))

    def feed_attitude(self, roll_rad: float, pitch_rad: float, yaw_rad: float) -> None:
        self._att = (roll_rad, pitch_rad, yaw_rad)

    def _baro(self, now: float, alt_msl_m: float) -> float:
        """Barometric altitude since the first truth: drifting, noisy (call with the lock held)."""
        if self._baro_zero_m is None:
            self._baro_zero_m = alt_msl_m
        dt = max(0.0, now - self._baro_last_s) if self._baro_last_s is not None else 0.0
        self._baro_last_s = now
        self._baro_drift_m += 0.02 * math.sqrt(dt) * float(self._baro_rng.standard_normal())
        return alt_msl_m - self._baro_zero_m + self._baro_drift_m + 0.15 * float(self._baro_rng.standard_normal())

    def set_truth(self, lat_deg: float, lon_deg: float, alt_msl_m: float) -> None:
        """True vehicle position: drives the barometric ALTITUDE stream."""
        self._truth = _Pos(self.clock(), lat_deg, lon_deg, alt_msl_m)

    # ---- outputs for tests -----------------------------------------------------------------
    def received(self) -> Received:
        with self._lock:
            r = self._rx
            return Received(Counter(r.counts), Counter(r.accepted), list(r.rejections), r.timesync_answers, list(r.statustext))

    def estimate(self) -> SimEstimate:
        with self._lock:
            return self._estimate(self.clock())

    # ---- helpers ---------------------------------------------------------------------------
    def _ekf_started(self, now: float) -> bool:
        return now - self._t0 >= self.ekf_start_s

    def _boot_ms(self, now: float) -> int:
        return int((now - self._t0) * 1000)

    def _send(self, msg) -> None:
        try:
            with self._send_lock:
                self._conn.mav.send(msg)
                if getattr(self._conn, "clients", True):  # udpin: written only once a peer has spoken
                    self._sent_seq = msg.get_seq()
        except OSError:  # no peer yet / peer gone: a real autopilot just keeps streaming
            pass

    def last_sent_seq(self) -> int | None:
        """MAVLink sequence number (0–255) of the last message written to the socket; None before
        the first. A simulated flight waits until the bridge has seen it (BridgeStats.last_seq)."""
        with self._send_lock:
            return self._sent_seq

    def _reject(self, now: float, t: str, reason: str) -> None:
        self._rx.rejections.append((now, t, reason))

    def _set_origin(self, lat: float, lon: float, alt_msl: float) -> None:
        self.origin = _Pos(self.clock(), lat, lon, alt_msl)
        self._frame = LocalFrame(lat, lon, float(msl_to_ellipsoid(lat, lon, alt_msl)))
        self._send(self._origin_msg())

    def _origin_msg(self):
        o = self.origin
        return self._conn.mav.gps_global_origin_encode(round(o.lat_deg * 1e7), round(o.lon_deg * 1e7), round(o.alt_msl_m * 1000), 0)

    def _gps_raw(self, s: GnssSample):
        def cm(x, scale=100):
            return 65535 if not math.isfinite(x) else min(65534, round(x * scale))

        def mm(x):
            return 0 if not math.isfinite(x) else round(x * 1000)
        vel = cm(math.hypot(s.vel_ned_mps[0], s.vel_ned_mps[1])) if s.vel_ned_mps else 65535
        cog = cm(s.cog_deg) if s.cog_deg is not None else 65535
        boot_us = int(max(0.0, self.clock() - self.gnss_report_lag_s - self._t0) * 1e6)
        return self._conn.mav.gps_raw_int_encode(
            boot_us, int(s.fix_type), round(s.lat_deg * 1e7), round(s.lon_deg * 1e7), mm(s.alt_msl_m),
            cm(s.eph), cm(s.epv), vel, cog, s.satellites, mm(s.h_ellipsoid_m), mm(s.h_acc_m), mm(s.v_acc_m), 0, 0, 0)

    # ---- ArduPilot GPS instances -----------------------------------------------------------
    def _mgps_usable(self, now: float, aiding: bool = False) -> tuple[int, str | None]:
        """(effective fix type, why unusable) of the MAVLink GPS. ``aiding``: the EKF already fuses
        an absolute position; EKF3's pre-use checks (calcGpsGoodToAlign) gate only the origin and
        the start of GPS aiding, not a GPS it fuses in flight."""
        m = self._mgps
        if m is None or now - m["t"] > MAVGPS_TIMEOUT_S:
            return 0, "no GPS_INPUT for 4 s"
        times = list(self._mgps_times)
        if len(times) < 2 or (times[-1] - times[0]) / (len(times) - 1) >= MAVGPS_MAX_MEAN_GAP_S or now - times[-1] > 0.5:
            return 0, "MAVLink GPS unhealthy: rate below 5 Hz"
        if m["fix"] < 3:
            return m["fix"], "no 3D fix"
        if aiding:
            return m["fix"], None
        checks = [(m["hdop"] > 2.5, "hdop > 2.5"), (m["sats"] < 6, "< 6 satellites"),
                  (not m["ign"] & mavlink.GPS_INPUT_IGNORE_FLAG_HORIZONTAL_ACCURACY and m["hacc"] > 5.0, "horiz_accuracy > 5 m"),
                  (not m["ign"] & mavlink.GPS_INPUT_IGNORE_FLAG_VERTICAL_ACCURACY and m["vacc"] > 7.5, "vert_accuracy > 7.5 m"),
                  (not m["ign"] & mavlink.GPS_INPUT_IGNORE_FLAG_SPEED_ACCURACY and m["sacc"] > 1.0, "speed_accuracy > 1 m/s")]
        for bad, why in checks:
            if bad:
                return m["fix"], f"EKF3 pre-use check: {why}"
        return m["fix"], None

    def _real_fix(self, now: float) -> int:
        g = self._gnss
        return 0 if g is None or now - g.t_s > MAVGPS_TIMEOUT_S else int(g.fix_type)

    def _ap_primary(self, now: float) -> int:
        mavgps = 0 if self.params["GPS1_TYPE"] == 14 else 1
        if self.params["GPS_AUTO_SWITCH"] == 0:
            return int(self.params["GPS_PRIMARY"])
        mfix, why = self._mgps_usable(now)
        mfix = mfix if why is None else 0
        rfix = self._real_fix(now)
        msats = self._mgps["sats"] if self._mgps else 0
        rsats = self._gnss.satellites if self._gnss else 0
        return mavgps if (mfix, msats) > (rfix, rsats) else 1 - mavgps

    # ---- estimate ---------------------------------------------------------------------------
    def _fresh(self, p: _Pos | None, now: float, max_age: float = SOURCE_FRESH_S) -> bool:
        return p is not None and now - p.t_s <= max_age

    def _estimate(self, now: float) -> SimEstimate:
        src, pos = ("none", None)
        g = self._gnss
        gnss_pos = None if g is None or now - g.t_s > SOURCE_FRESH_S or g.fix_type < GpsFixType.FIX_3D else \
            _Pos(g.t_s, g.lat_deg, g.lon_deg, g.alt_msl_m)
        if self.personality == "ardupilot":
            posxy = self.params.get(f"EK3_SRC{self.source_set}_POSXY", 0)
            if posxy == 3:
                mavgps = 0 if self.params["GPS1_TYPE"] == 14 else 1
                if self._ap_primary(now) == mavgps:
                    aiding = self._last_est is not None and (self._lost_since is None or now - self._lost_since <= AP_DEAD_RECKON_S)
                    _, why = self._mgps_usable(now, aiding)
                    m = self._mgps
                    if why is None:
                        src, pos = "mavlink_gps", _Pos(m["t"], m["lat"], m["lon"], m["alt"])
                elif gnss_pos is not None:
                    src, pos = "gnss", gnss_pos
            elif posxy == 6 and self.params["VISO_TYPE"] > 0 and self._fresh(self._ext, now):
                src, pos = "external_nav", self._ext
            dr_s = AP_DEAD_RECKON_S
        else:
            gps_on = int(self.params["EKF2_GPS_CTRL"]) & 1
            if gps_on and gnss_pos is not None:
                src, pos = "gnss", gnss_pos
            elif int(self.params["EKF2_EV_CTRL"]) & 1 and self._fresh(self._ext, now, EV_MAX_GAP_S):
                src, pos = "external_vision", self._ext
            elif self._fresh(self._agp, now, 1.0):
                src, pos = "aux_global", self._agp
            elif gps_on and self._fresh(self._hil, now):
                src, pos = "hil_gps", self._hil
            dr_s = PX4_DEAD_RECKON_S
        if pos is not None:
            self._lost_since = None
            self._last_est = SimEstimate(now, pos.lat_deg, pos.lon_deg, pos.alt_msl_m, src, True)
            return self._last_est
        if self._lost_since is None:
            self._lost_since = now
        last = self._last_est
        if last is not None and now - self._lost_since <= dr_s:
            return SimEstimate(now, last.lat_deg, last.lon_deg, last.alt_msl_m, "dead_reckoning", True)
        return SimEstimate(now, math.nan, math.nan, math.nan, "none", False)

    # ---- receive ----------------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self._conn.recv_match(blocking=True, timeout=0.01)
            except Exception as e:  # garbage must not kill the simulated autopilot either
                msg = None
                with self._lock:
                    self._reject(self.clock(), "BAD_DATA", str(e))
            now = self.clock()
            if msg is not None:
                with self._lock:
                    self._handle(msg, now)
            peers = len(getattr(self._conn, "clients", ()))
            if peers > self._peers and self._heartbeat_on_new_peer:
                # A new peer spoke: our HEARTBEAT now, not at the next 1 Hz tick. A real autopilot's
                # comes within a second; on a simulated clock, which moves only with the frames,
                # that second is ten frames the bridge cannot see us (a repeatable flight waited
                # 10 s of real time on each: REPEATABLE_DELIVERY_TIMEOUT_S in companion.app).
                self._next_s[0] = -math.inf
            self._peers = peers
            self._tick(now)

    def _handle(self, msg, now: float) -> None:
        t = msg.get_type()
        if t == "BAD_DATA":
            self._reject(now, t, getattr(msg, "reason", "bad data"))
            return
        self._rx.counts[t] += 1
        handler = getattr(self, f"_on_{t.lower()}", None)
        if handler is not None:
            handler(msg, now)

    def _accept(self, t: str) -> None:
        self._rx.accepted[t] += 1

    def _on_timesync(self, msg, now):
        if msg.tc1 != 0:
            self._rx.timesync_answers += 1

    def _on_statustext(self, msg, now):
        self._rx.statustext.append((msg.severity, msg.text))

    def _on_gps_input(self, msg, now):
        if self.personality == "px4":
            return self._reject(now, "GPS_INPUT", "ignored: PX4 has no GPS_INPUT handler")
        if self.params.get(f"GPS{msg.gps_id + 1}_TYPE") != 14:
            return self._reject(now, "GPS_INPUT", f"gps_id {msg.gps_id} does not match a GPSx_TYPE=14 instance")
        self._mgps_times.append(now)
        self._mgps = {"t": now, "fix": msg.fix_type, "lat": msg.lat * 1e-7, "lon": msg.lon * 1e-7, "alt": msg.alt,
                      "hdop": msg.hdop, "sats": msg.satellites_visible, "hacc": msg.horiz_accuracy,
                      "vacc": msg.vert_accuracy, "sacc": msg.speed_accuracy, "ign": msg.ignore_flags}
        if self.origin is None and self._ekf_started(now) and msg.fix_type >= 3:
            self._set_origin(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt)
        self._accept("GPS_INPUT")

    def _ext_from_ned(self, t: str, x: float, y: float, z: float, cov0: float, now: float) -> None:
        if self.origin is None:
            return self._reject(now, t, "EKF origin not set")
        if not all(math.isfinite(v) for v in (x, y, z)):
            return self._reject(now, t, "non-finite position")
        lat, lon, h = self._frame.ned_to_geodetic(np.array([x, y, z]))
        alt = float(ellipsoid_to_msl(lat, lon, h))
        self._ext = _Pos(now, float(lat), float(lon), alt, math.sqrt(cov0) if math.isfinite(cov0) else math.nan)
        self._ext_prev_t = now
        self._accept(t)

    def _ext_gap_ok(self, t: str, now: float) -> bool:
        prev = self._ext_prev_t
        if self.personality == "ardupilot" and prev is not None and now - prev < EXTNAV_MIN_GAP_S:
            self._reject(now, t, "more than one ExternalNav sample per 20 ms")
            return False
        if self.personality == "px4" and (prev is None or now - prev > EV_MAX_GAP_S):
            self._ext_prev_t = now  # the next sample can be fused
            self._reject(now, t, "EV sample gap > 200 ms: dropped")
            return False
        return True

    def _on_odometry(self, msg, now):
        if self.personality == "ardupilot":
            if (msg.frame_id, msg.child_frame_id) != (mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD):
                return self._reject(now, "ODOMETRY", "frame_id must be LOCAL_FRD and child_frame_id BODY_FRD")
            if self.params["VISO_TYPE"] == 0:
                return self._reject(now, "ODOMETRY", "VISO_TYPE=0")
        else:
            if msg.frame_id not in (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_FRD):
                return self._reject(now, "ODOMETRY", f"frame_id {msg.frame_id} not LOCAL_NED/LOCAL_FRD")
            if msg.estimator_type not in (mavlink.MAV_ESTIMATOR_TYPE_VISION, mavlink.MAV_ESTIMATOR_TYPE_VIO):
                return self._reject(now, "ODOMETRY", f"estimator_type {msg.estimator_type} is not fused (VISION/VIO only)")
        if self._ext_gap_ok("ODOMETRY", now):
            self._ext_from_ned("ODOMETRY", msg.x, msg.y, msg.z, msg.pose_covariance[0], now)

    def _on_vision_position_estimate(self, msg, now):
        if self.personality == "ardupilot" and self.params["VISO_TYPE"] == 0:
            return self._reject(now, "VISION_POSITION_ESTIMATE", "VISO_TYPE=0")
        if self._ext_gap_ok("VISION_POSITION_ESTIMATE", now):
            self._ext_from_ned("VISION_POSITION_ESTIMATE", msg.x, msg.y, msg.z, msg.covariance[0], now)

    def _on_global_position_sensor(self, msg, now):
        t = "GLOBAL_POSITION_SENSOR"
        if self.personality != "px4":
            return self._reject(now, t, "not handled by ArduPilot")
        if msg.id != self.params["EKF2_AGP0_ID"] or not int(self.params["EKF2_AGP0_CTRL"]) & 1:
            return self._reject(now, t, f"id {msg.id} != EKF2_AGP0_ID or EKF2_AGP0_CTRL off")
        pos = _Pos(now, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt, msg.eph)
        g = self._gnss
        if int(self.params["EKF2_GPS_CTRL"]) & 1 and g is not None and g.fix_type >= 3 and now - g.t_s <= SOURCE_FRESH_S:
            d = LocalFrame(g.lat_deg, g.lon_deg).geodetic_to_ned(pos.lat_deg, pos.lon_deg, 0.0)
            gate = 3.0 * math.hypot(msg.eph, g.h_acc_m if math.isfinite(g.h_acc_m) else 2.0)
            if math.hypot(d[0], d[1]) > gate:
                return self._reject(now, t, "innovation check failed against fused GNSS")
        self._agp = pos
        self._accept(t)

    def _on_hil_gps(self, msg, now):
        t = "HIL_GPS"
        if self.personality != "px4":
            return self._reject(now, t, "not handled by ArduPilot")
        why = ("MAV_USEHILGPS=0" if not self.params["MAV_USEHILGPS"] else
               f"sent from system {msg.get_srcSystem()}, not the vehicle's {self.sysid}" if msg.get_srcSystem() != self.sysid else
               "fix_type < 3" if msg.fix_type < 3 else
               "satellites < 6" if msg.satellites_visible < 6 else
               "eph >= EKF2_REQ_EPH" if msg.eph >= self.params["EKF2_REQ_EPH"] * 100 else None)
        if why:
            return self._reject(now, t, why)
        self._hil = _Pos(now, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt / 1000.0, msg.eph / 100.0)
        self._accept(t)

    def _on_set_gps_global_origin(self, msg, now):
        t = "SET_GPS_GLOBAL_ORIGIN"
        if not self._ekf_started(now):
            return self._reject(now, t, "EKF not started yet")
        if self.origin is not None and self.personality == "ardupilot":
            return self._reject(now, t, "origin already set")
        if self.origin is not None:  # real PX4 SIH: moves its NED origin to the new one (docs/AUTOPILOTS.md)
            self.origin_moves += 1
        self._set_origin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude / 1000.0)
        self._accept(t)

    def _on_param_set(self, msg, now):
        name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode()
        name = name.rstrip("\x00")
        if name not in self.params:
            return self._reject(now, "PARAM_SET", f"unknown parameter {name}")
        value = msg.param_value
        if self.personality == "px4" and msg.param_type == mavlink.MAV_PARAM_TYPE_INT32:
            value = struct.unpack("<i", struct.pack("<f", value))[0]  # PX4 bytewise encoding
        self.params[name] = value
        self._accept("PARAM_SET")
        self._send(self._conn.mav.param_value_encode(name.encode(), msg.param_value, msg.param_type, len(self.params), 0))

    def _on_param_request_read(self, msg, now):
        name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode()
        name = name.rstrip("\x00")
        if name not in self.params:
            return self._reject(now, "PARAM_REQUEST_READ", f"unknown parameter {name}")
        value = self.params[name]
        if isinstance(value, float):
            ptype, wire = mavlink.MAV_PARAM_TYPE_REAL32, value
        else:
            ptype = mavlink.MAV_PARAM_TYPE_INT32
            wire = struct.unpack("<f", struct.pack("<i", int(value)))[0] if self.personality == "px4" else float(value)
        self._send(self._conn.mav.param_value_encode(name.encode(), wire, ptype, len(self.params), list(self.params).index(name)))

    def _on_command_long(self, msg, now):
        result = mavlink.MAV_RESULT_ACCEPTED
        if msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            msg_id, us = int(msg.param1), msg.param2
            if us < 0:
                self._interval_s.pop(msg_id, None)
            else:
                self._interval_s[msg_id] = us / 1e6
        elif msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            if int(msg.param1) == mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN and self.origin is not None:
                self._send(self._origin_msg())
            elif int(msg.param1) == mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
                result = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        elif msg.command == mavlink.MAV_CMD_SET_EKF_SOURCE_SET and self.personality == "ardupilot" and 1 <= msg.param1 <= 3:
            self.source_set = int(msg.param1)
        else:
            result = mavlink.MAV_RESULT_UNSUPPORTED
        if result == mavlink.MAV_RESULT_ACCEPTED:
            self._accept(f"COMMAND_LONG:{msg.command}")
        self._send(self._conn.mav.command_ack_encode(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))

    # ---- streams ----------------------------------------------------------------------------
    def _due(self, msg_id: int, now: float) -> bool:
        period = self._interval_s.get(msg_id)
        if not period:  # not streamed, or sent on each new sample
            return False
        if now >= self._next_s.get(msg_id, 0.0):
            self._next_s[msg_id] = now + period
            return True
        return False

    def _tick(self, now: float) -> None:
        mav = self._conn.mav
        out = []
        if now >= self._next_s.get(0, 0.0):  # HEARTBEAT 1 Hz always; PX4 also asks for TIMESYNC
            self._next_s[0] = now + 1.0
            ap = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA if self.personality == "ardupilot" else mavlink.MAV_AUTOPILOT_PX4
            out.append(mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, ap, 0, 0, mavlink.MAV_STATE_ACTIVE))
            if self.personality == "px4":
                out.append(mav.timesync_encode(0, int(now * 1e9)))
        with self._lock:
            est = self._estimate(now)
            if self._due(mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, now):
                out.append(mav.system_time_encode(int(time.time() * 1e6), self._boot_ms(now)))
            if self._due(mavlink.MAVLINK_MSG_ID_ATTITUDE, now):
                out.append(mav.attitude_encode(self._boot_ms(now), *self._att, 0.0, 0.0, 0.0))
            # the barometer: PX4 streams ALTITUDE (altitude_monotonic = baro altitude); ArduPilot does not
            # implement ALTITUDE, its barometer comes as SCALED_PRESSURE
            if self.personality == "px4" and self._due(mavlink.MAVLINK_MSG_ID_ALTITUDE, now) and self._truth is not None:
                a = self._truth.alt_msl_m
                out.append(mav.altitude_encode(int(now * 1e6), self._baro(now, a), a, math.nan, math.nan, math.nan, math.nan))
            if self.personality == "ardupilot" and self._due(mavlink.MAVLINK_MSG_ID_SCALED_PRESSURE, now) and self._truth is not None:
                h = self._baro(now, self._truth.alt_msl_m) + self._baro_zero_m  # pressure altitude ≈ MSL
                out.append(mav.scaled_pressure_encode(self._boot_ms(now), pressure_hpa_at(h), 0.0, 2000))
            if self._due(mavlink.MAVLINK_MSG_ID_GPS2_RAW, now):  # the MAVLink GPS instance, fix 0 until fed
                m = self._mgps or {"lat": 0.0, "lon": 0.0, "alt": 0.0, "hdop": 655.35, "sats": 0}
                fix, _ = self._mgps_usable(now)
                out.append(mav.gps2_raw_encode(int((now - self._t0) * 1e6), fix, round(m["lat"] * 1e7), round(m["lon"] * 1e7), round(m["alt"] * 1000),
                                               min(65534, round(m["hdop"] * 100)), 65535, 65535, 65535, m["sats"], 0, 0))
            if self._due(mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT, now):
                flags = (mavlink.EKF_POS_HORIZ_ABS if est.valid and est.source != "dead_reckoning" else 0) | (32768 if self._glitch else 0)
                out.append(mav.ekf_status_report_encode(flags, 0.1, 0.1, 0.1, 0.1, 0.0))
            if self._due(mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS, now):
                flags = (mavlink.ESTIMATOR_POS_HORIZ_ABS if est.valid and est.source != "dead_reckoning" else 0) | \
                        (mavlink.ESTIMATOR_GPS_GLITCH if self._glitch else 0)
                out.append(mav.estimator_status_encode(int(now * 1e6), flags, 0, 0, 0, 0, 0, 0, 0, 0))
            if self._due(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, now) and est.valid:
                out.append(mav.global_position_int_encode(self._boot_ms(now), round(est.lat_deg * 1e7), round(est.lon_deg * 1e7),
                                                          round(est.alt_msl_m * 1000), 0, 0, 0, 0, 65535))
        for m in out:
            self._send(m)
