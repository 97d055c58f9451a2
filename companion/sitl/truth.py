"""The simulator's true vehicle state over MAVLink, and the SITL clock it defines.

- ArduPilot SITL: SIM_STATE (the physics model's attitude quaternion, position, NED velocity)
  requested on a serial port of its own. SIM_STATE has no time stamp; ArduPilot sends it and
  ATTITUDE in the same scheduler slot, SIM_STATE first (seen on the bundle's build), so each
  SIM_STATE takes the ``time_boot_ms`` of the ATTITUDE that follows it when both are requested at
  the same interval.
- PX4 SIH: HIL_STATE_QUATERNION on SIH's display link. Its time_usec is 0 in this PX4 (main of
  2026-03), so each takes the PX4 (lockstep) time of the newest HIL_ACTUATOR_CONTROLS, which the
  same link sends at 250 Hz: stamped within 4 ms (3 cm at 7 m/s).

Times are the autopilot's boot time in seconds: the pipeline, the bridge and the report all run
on it (``TruthFeed.clock``), so a SITL slower or faster than real time changes nothing they judge.
"""
from __future__ import annotations

import bisect
import logging
import math
import threading
import time
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

TRUTH_HZ = 50.0
KEEP_S = 30.0              # truth kept for interpolation and the report's lookups
#: the clock runs on from the last truth sample at the SITL's nominal speed, by at most this much
#: (a stalled SITL stops our clock too, instead of letting timeouts fire in time that never passed)
CLOCK_EXTRAPOLATE_MAX_S = 0.1


@dataclass(frozen=True)
class TruthState:
    """The vehicle's true state at ``t_s`` (autopilot boot time): body origin WGS-84 / MSL (the
    heights both SITLs use), attitude as a NED→body quaternion (w, x, y, z), NED velocity."""

    t_s: float
    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    q_ned_body: tuple[float, float, float, float]
    v_ned_mps: tuple[float, float, float]

    @property
    def R_ned_body(self) -> np.ndarray:
        w, x, y, z = self.q_ned_body
        return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    if np.dot(q0, q1) < 0:
        q1 = -q1
    q = (1 - a) * q0 + a * q1  # normalised lerp: samples 20 ms apart turn by a fraction of a degree
    return q / np.linalg.norm(q)


def interpolate(s0: TruthState, s1: TruthState, t_s: float) -> TruthState:
    a = 0.0 if s1.t_s <= s0.t_s else min(1.0, max(0.0, (t_s - s0.t_s) / (s1.t_s - s0.t_s)))
    lerp = lambda u, v: tuple(float(x + a * (y - x)) for x, y in zip(u, v))  # noqa: E731
    lat, lon, alt = lerp((s0.lat_deg, s0.lon_deg, s0.alt_msl_m), (s1.lat_deg, s1.lon_deg, s1.alt_msl_m))
    q = _slerp(np.array(s0.q_ned_body), np.array(s1.q_ned_body), a)
    return TruthState(t_s, lat, lon, alt, tuple(float(v) for v in q), lerp(s0.v_ned_mps, s1.v_ned_mps))


class TruthFeed:
    """Reads the truth link on a thread; ``clock()`` is the SITL's time, ``at(t)`` its state then."""

    def __init__(self, url: str, autopilot: str, speed: float = 1.0, target_system: int = 1):
        from mavlink_bridge.link import open_connection

        self.autopilot, self.speed, self.target_system = autopilot, speed, target_system
        self._conn = open_connection(url, 0, 255, 191)  # a ground-side peer of its own
        self._t: list[float] = []
        self._s: list[TruthState] = []
        self._pending: TruthState | None = None  # ArduPilot: SIM_STATE waiting for its ATTITUDE
        self._px4_time_s: float | None = None    # PX4: time of the newest HIL_ACTUATOR_CONTROLS
        self._last_wall = time.monotonic()
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sitl-truth", daemon=True)

    def start(self) -> "TruthFeed":
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._conn.close()

    # ---- reading -------------------------------------------------------------------------
    def clock(self) -> float:
        """The SITL's time now (s since its boot); 0 until the first sample."""
        with self._lock:
            if not self._t:
                return 0.0
            ahead = (time.monotonic() - self._last_wall) * self.speed
            return self._t[-1] + min(ahead, CLOCK_EXTRAPOLATE_MAX_S)

    def latest(self) -> TruthState | None:
        with self._lock:
            return self._s[-1] if self._s else None

    def wait_until(self, t_s: float, timeout_s: float) -> bool:
        """Block (wall time) until truth at or after ``t_s`` has arrived."""
        end = time.monotonic() + timeout_s
        with self._cond:
            while not (self._t and self._t[-1] >= t_s):
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, 0.5))
        return True

    def at(self, t_s: float) -> TruthState | None:
        """The true state at ``t_s``, interpolated between the samples around it (None outside them)."""
        with self._lock:
            i = bisect.bisect_left(self._t, t_s)
            if i >= len(self._t) or (i == 0 and self._t[0] > t_s):
                return None
            if self._t[i] == t_s or i == 0:
                return self._s[i]
            return interpolate(self._s[i - 1], self._s[i], t_s)

    # ---- receive thread ---------------------------------------------------------------------
    def _request(self) -> None:
        from pymavlink.dialects.v20 import ardupilotmega as mavlink

        ids = (mavlink.MAVLINK_MSG_ID_SIM_STATE, mavlink.MAVLINK_MSG_ID_ATTITUDE) if self.autopilot == "ardupilot" else ()
        for msg_id in ids:
            self._conn.mav.command_long_send(self.target_system, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                             msg_id, 1e6 / TRUTH_HZ, 0, 0, 0, 0, 0)

    def _run(self) -> None:
        requested_at = -math.inf
        while not self._stop.is_set():
            if self.autopilot == "ardupilot" and not self._t and time.monotonic() - requested_at > 2.0:
                requested_at = time.monotonic()  # until the first sample: the port may not be served yet
                self._request()
            msg = self._conn.recv_match(blocking=True, timeout=0.2)
            if msg is None:
                continue
            t = msg.get_type()
            if t == "SIM_STATE":
                q = (msg.q1, msg.q2, msg.q3, msg.q4)
                self._pending = TruthState(math.nan, msg.lat_int * 1e-7, msg.lon_int * 1e-7, float(msg.alt), q,
                                           (msg.vn, msg.ve, msg.vd))
            elif t == "ATTITUDE" and self._pending is not None:
                s, self._pending = self._pending, None
                self._add(TruthState(msg.time_boot_ms / 1e3, s.lat_deg, s.lon_deg, s.alt_msl_m, s.q_ned_body, s.v_ned_mps))
            elif t == "HIL_ACTUATOR_CONTROLS":
                self._px4_time_s = msg.time_usec / 1e6
            elif t == "HIL_STATE_QUATERNION" and (msg.time_usec or self._px4_time_s is not None):
                q = tuple(float(v) for v in msg.attitude_quaternion)
                self._add(TruthState(msg.time_usec / 1e6 if msg.time_usec else self._px4_time_s, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt / 1e3, q,
                                     (msg.vx / 100.0, msg.vy / 100.0, msg.vz / 100.0)))

    def _add(self, s: TruthState) -> None:
        with self._cond:
            if self._t and s.t_s <= self._t[-1]:
                if s.t_s < self._t[-1] - 1.0:
                    log.warning("SITL time went back %.1f s (reboot?): truth restarts", self._t[-1] - s.t_s)
                    self._t, self._s = [], []
                else:
                    return
            self._t.append(s.t_s)
            self._s.append(s)
            self._last_wall = time.monotonic()
            if self._t[-1] - self._t[0] > KEEP_S + 5.0:
                k = bisect.bisect_left(self._t, self._t[-1] - KEEP_S)
                del self._t[:k], self._s[:k]
            self._cond.notify_all()
