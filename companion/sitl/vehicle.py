"""The mission client: what a ground station does with the vehicle, through MAVSDK (4.x native API).

Waits until the autopilot is ready to fly on GNSS, takes off, flies waypoints, returns home, and
switches the SITL's simulated receiver off and on. Everything the vehicle reports that a pilot
would watch (flight mode, landed state, status texts, its own position estimate) is recorded with
the SITL's time (the ``clock`` given: truth.TruthFeed.clock).
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

log = logging.getLogger(__name__)

#: texts an autopilot sends when a failsafe takes the vehicle (ArduPilot "EKF Failsafe", "EKF variance";
#: PX4 "Failsafe activated", "blind land"); matched case-insensitively
FAILSAFE_WORDS = ("failsafe", "ekf variance", "blind land")


@dataclass
class Telemetry:
    """What the vehicle told the ground station, on the SITL clock."""

    positions: list[tuple[float, float, float, float]] = field(default_factory=list)  # (t, lat, lon, alt MSL): its own estimate
    modes: list[tuple[float, str]] = field(default_factory=list)                    # flight mode changes
    texts: list[tuple[float, str]] = field(default_factory=list)                    # STATUSTEXT
    landed: list[tuple[float, str]] = field(default_factory=list)                   # landed state changes
    mission: list[tuple[float, int, int]] = field(default_factory=list)             # (t, current, total)

    def failsafes(self) -> list[tuple[float, str]]:
        return [(t, s) for t, s in self.texts if any(w in s.lower() for w in FAILSAFE_WORDS)]


class Vehicle:
    def __init__(self, url: str, clock: Callable[[], float], timeout_s: float = 60.0):
        from mavsdk import ComponentType, Configuration, ConnectionResult, Mavsdk
        from mavsdk.plugins.action import Action
        from mavsdk.plugins.mission import Mission
        from mavsdk.plugins.param import Param
        from mavsdk.plugins.telemetry import Telemetry as MavsdkTelemetry

        self.clock = clock
        self._sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        deadline = time.monotonic() + timeout_s
        while True:  # a TCP port is served a moment after the process starts
            result = self._sdk.add_any_connection(url)
            if result == ConnectionResult.SUCCESS or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        if result != ConnectionResult.SUCCESS:
            raise ConnectionError(f"{url}: {ConnectionResult(result).name}")
        system = self._sdk.first_autopilot(max(1.0, deadline - time.monotonic()))
        if system is None:
            raise TimeoutError(f"{url}: no autopilot HEARTBEAT within {timeout_s:g} s")
        self.action, self.mission, self.param = Action(system), Mission(system), Param(system)
        self.telemetry = MavsdkTelemetry(system)
        self.log = Telemetry()
        self._lock = threading.Lock()
        self._in_air = False
        self._subscribe()
        # ArduPilot streams nothing on a port no ground station configured: ask for what we watch
        for rate in ("position", "in_air", "landed_state"):
            try:
                getattr(self.telemetry, f"set_rate_{rate}")(10.0 if rate == "position" else 2.0)
            except Exception as e:  # PX4 streams these by default and may answer UNSUPPORTED
                log.info("set_rate_%s: %s", rate, e)

    def _subscribe(self) -> None:
        t, lg = self.telemetry, self.log

        def add(lst, item):
            with self._lock:
                lst.append(item)

        t.subscribe_position(lambda p, _: add(lg.positions, (self.clock(), p.latitude_deg, p.longitude_deg, p.absolute_altitude_m)))
        t.subscribe_flight_mode(lambda m, _: (not lg.modes or lg.modes[-1][1] != getattr(m, "name", str(m)))
                                and add(lg.modes, (self.clock(), getattr(m, "name", str(m)))))
        t.subscribe_status_text(lambda s, _: add(lg.texts, (self.clock(), s.text)))
        t.subscribe_landed_state(lambda s, _: (not lg.landed or lg.landed[-1][1] != getattr(s, "name", str(s)))
                                 and add(lg.landed, (self.clock(), getattr(s, "name", str(s)))))
        t.subscribe_in_air(lambda a, _: setattr(self, "_in_air", bool(a)))
        self.mission.subscribe_mission_progress(lambda p, _: add(lg.mission, (self.clock(), p.current, p.total)))

    # ---- state -------------------------------------------------------------------------------
    @property
    def in_air(self) -> bool:
        return self._in_air

    def position(self) -> tuple[float, float, float, float] | None:
        with self._lock:
            return self.log.positions[-1] if self.log.positions else None

    def mission_done(self) -> bool:
        with self._lock:
            return bool(self.log.mission) and self.log.mission[-1][1] >= self.log.mission[-1][2] > 0

    def wait(self, what: str, cond: Callable[[], bool], timeout_wall_s: float, idle: Callable[[], None] | None = None) -> None:
        """Wait (wall time) until ``cond``; ``idle`` runs in between (the camera loop keeps going)."""
        end = time.monotonic() + timeout_wall_s
        while not cond():
            if time.monotonic() > end:
                raise TimeoutError(f"vehicle: {what} not within {timeout_wall_s:g} s")
            if idle is not None:
                idle()
            else:
                time.sleep(0.1)

    # ---- commands ----------------------------------------------------------------------------
    def set_param(self, name: str, value: int) -> None:
        self.param.set_param_int(name, int(value))

    def set_param_float(self, name: str, value: float) -> None:
        self.param.set_param_float(name, float(value))

    def take_off(self, rel_alt_m: float, timeout_wall_s: float, idle=None) -> None:
        self.action.set_takeoff_altitude(float(rel_alt_m))
        for _ in range(30):  # pre-arm checks may need a few more seconds after the EKF is ready
            try:
                self.action.arm()
                break
            except Exception as e:  # ActionError: try again
                log.info("arm refused (%s), retrying", e)
                time.sleep(2.0)
        else:
            raise TimeoutError("vehicle: arming refused for 60 s; last texts: " + " | ".join(s for _, s in self.log.texts[-8:]))
        self.action.takeoff()
        home_alt = self.position()[3] if self.position() else None
        self.wait("climb to take-off altitude",
                  lambda: home_alt is not None and self.position() is not None and self.position()[3] - home_alt >= 0.9 * rel_alt_m,
                  timeout_wall_s, idle)

    def fly(self, waypoints_deg: list[tuple[float, float]], rel_alt_m: float, speed_mps: float) -> None:
        """Upload ``waypoints_deg`` (lat, lon) at ``rel_alt_m`` above home and start the mission. (The
        return home is commanded when it ends, ``return_home``: MAVSDK's return-after-mission item
        makes ArduPilot refuse the upload, INVALID_ARGUMENT.)"""
        from mavsdk.plugins.mission import MissionItem, MissionPlan

        items = [MissionItem(latitude_deg=lat, longitude_deg=lon, relative_altitude_m=rel_alt_m, speed_m_s=speed_mps,
                             is_fly_through=True, acceptance_radius_m=5.0) for lat, lon in waypoints_deg]
        self.mission.upload_mission(MissionPlan(items))
        # PX4 may refuse the mission mode for a moment after an upload ("Switching to Mission is
        # currently not available") while answering the command: believe the flight mode it reports
        for _ in range(15):
            try:
                self.mission.start_mission()
            except Exception as e:  # MissionError: try again
                log.info("start_mission: %s", e)
            end = time.monotonic() + 3.0
            while time.monotonic() < end:
                if self.mode() == "MISSION":
                    return
                time.sleep(0.1)
        raise TimeoutError(f"vehicle: mission mode refused; mode {self.mode()}, last texts: "
                           + " | ".join(s for _, s in self.log.texts[-8:]))

    def mode(self) -> str | None:
        with self._lock:
            return self.log.modes[-1][1] if self.log.modes else None

    def return_home(self) -> None:
        self.action.return_to_launch()

    def close(self) -> None:
        try:
            self._sdk.destroy()
        except Exception:  # closing a half-open MAVSDK instance must not hide the flight's outcome
            log.exception("closing MAVSDK")
