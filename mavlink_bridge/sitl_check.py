"""Does a real PX4 / ArduPilot (SITL or vehicle) fuse our source? Observed with MAVSDK 4.x.

``collect`` listens through MAVSDK's native API (Telemetry, Param, MavlinkDirect) for a few
seconds; ``judge`` turns what it saw into a verdict with the evidence behind it. Nothing is
inferred that the autopilot does not report: where MAVLink does not expose the fact (PX4 has no
MAVLink flag for "EV fused"), the report says so and leaves the verdict open.
"""
from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import dataclass, field

from gis.geodesy import LocalFrame

ARDUPILOT_PARAMS = ("GPS1_TYPE", "GPS2_TYPE", "GPS_AUTO_SWITCH", "GPS_PRIMARY", "VISO_TYPE", "EK3_SRC1_POSXY", "EK3_SRC2_POSXY")
PX4_PARAMS = ("EKF2_EV_CTRL", "EKF2_GPS_CTRL", "EKF2_AGP0_ID", "EKF2_AGP0_CTRL", "MAV_USEHILGPS")
WATCHED = ("HEARTBEAT", "GPS_RAW_INT", "GPS2_RAW", "EKF_STATUS_REPORT", "ESTIMATOR_STATUS", "GLOBAL_POSITION_INT", "GPS_GLOBAL_ORIGIN")
EKF_POS_HORIZ_ABS = 16      # ArduPilot EKF_STATUS_REPORT / PX4 ESTIMATOR_STATUS: same bit
GPS_GLITCH_BITS = {"ardupilot": 32768, "px4": 1024}
AGREE_M = 3.0               # autopilot position this close to our fix counts as following it


@dataclass
class Observation:
    autopilot_type: str
    messages: dict = field(default_factory=dict)   # name → latest fields
    params: dict = field(default_factory=dict)     # name → value (missing when not readable)


@dataclass
class SitlReport:
    autopilot: str
    fusing: bool | None                 # None: the autopilot does not show it over MAVLink
    evidence: list[str]
    position: tuple[float, float] | None = None
    our_fix: tuple[float, float] | None = None
    distance_m: float | None = None


def collect(url: str, autopilot: str, seconds: float = 5.0, timeout_s: float = 10.0) -> Observation:
    """Connect with MAVSDK (e.g. ``udpin://0.0.0.0:14540`` for PX4, ``tcpout://127.0.0.1:5762`` for
    ArduPilot), record the watched messages for ``seconds`` and read the relevant parameters."""
    from mavsdk import ComponentType, Configuration, ConnectionResult, Mavsdk
    from mavsdk.plugins.mavlink_direct import MavlinkDirect
    from mavsdk.plugins.param import Param

    sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
    try:
        result = sdk.add_any_connection(url)
        if result != ConnectionResult.SUCCESS:
            raise ConnectionError(f"--connect {url}: {ConnectionResult(result).name}")
        system = sdk.first_autopilot(timeout_s)
        if system is None:
            raise TimeoutError(f"--connect {url}: no autopilot heartbeat within {timeout_s:g} s")
        obs = Observation(autopilot_type=system.autopilot_type().name.lower())
        lock = threading.Lock()

        def on_msg(msg, _ud):
            if msg.message_name in WATCHED and msg.component_id == 1:
                with lock:
                    obs.messages[msg.message_name] = json.loads(msg.fields_json)
        direct = MavlinkDirect(system)
        direct.subscribe_message("", on_msg)
        param = Param(system)
        for name in ARDUPILOT_PARAMS if autopilot == "ardupilot" else PX4_PARAMS:
            try:
                obs.params[name] = param.get_param_int(name)
            except Exception:  # wrong type or absent: try float, else leave it out
                try:
                    obs.params[name] = param.get_param_float(name)
                except Exception:
                    pass
        time.sleep(seconds)
        with lock:
            obs.messages = dict(obs.messages)
        return obs
    finally:
        sdk.destroy()


def _distance_m(a: tuple[float, float], b: tuple[float, float]) -> float:
    d = LocalFrame(a[0], a[1]).geodetic_to_ned(b[0], b[1], 0.0)
    return float(math.hypot(d[0], d[1]))


def _autopilot_position(obs: Observation) -> tuple[float, float] | None:
    g = obs.messages.get("GLOBAL_POSITION_INT")
    if not g or (g["lat"] == 0 and g["lon"] == 0):
        return None
    return g["lat"] * 1e-7, g["lon"] * 1e-7


def judge(obs: Observation, autopilot: str, our_fix: tuple[float, float] | None = None) -> SitlReport:
    ev: list[str] = [f"autopilot reports itself as {obs.autopilot_type}"]
    pos = _autopilot_position(obs)
    status = obs.messages.get("EKF_STATUS_REPORT" if autopilot == "ardupilot" else "ESTIMATOR_STATUS")
    if status is not None:
        flags = status["flags"]
        ev.append(f"EKF flags 0x{flags:x}: horizontal absolute position {'valid' if flags & EKF_POS_HORIZ_ABS else 'NOT valid'}"
                  + (", GPS glitch" if flags & GPS_GLITCH_BITS[autopilot] else ""))
    else:
        ev.append("no EKF status message received (request EKF_STATUS_REPORT / ESTIMATOR_STATUS)")
    fusing: bool | None = None
    if autopilot == "ardupilot":
        fusing, ours = _judge_ardupilot(obs, ev)
        our_fix = our_fix or ours
    else:
        fusing = _judge_px4(obs, ev)
    dist = _distance_m(pos, our_fix) if pos and our_fix else None
    if dist is not None:
        ev.append(f"autopilot position is {dist:.2f} m from our fix")
        if fusing is not False and dist > AGREE_M:
            fusing = False
            ev.append(f"more than {AGREE_M:g} m apart: it is not following our fix")
        elif fusing is None and dist <= AGREE_M and not _gnss_ok(obs, autopilot):
            fusing = True
            ev.append("GNSS has no fix yet the autopilot holds a position within "
                      f"{AGREE_M:g} m of ours: it is fusing our source")
    elif pos is None:
        ev.append("autopilot reports no global position")
    return SitlReport(autopilot, fusing, ev, pos, our_fix, dist)


def _gnss_ok(obs: Observation, autopilot: str) -> bool:
    gps = obs.messages.get("GPS_RAW_INT")
    return gps is not None and gps["fix_type"] >= 3


def _judge_ardupilot(obs: Observation, ev: list[str]) -> tuple[bool | None, tuple[float, float] | None]:
    p = obs.params
    inst = 0 if p.get("GPS1_TYPE") == 14 else 1 if p.get("GPS2_TYPE") == 14 else None
    extnav = p.get("VISO_TYPE", 0) > 0 and 6 in (p.get("EK3_SRC1_POSXY"), p.get("EK3_SRC2_POSXY"))
    if inst is None and not extnav:
        ev.append("no GPSx_TYPE=14 instance and no ExternalNav source set: our messages cannot be used")
        return False, None
    if inst is None:
        ev.append("ExternalNav configured (VISO_TYPE>0, an EK3 source set with POSXY=6); the active source set is not reported over MAVLink")
        return None, None
    raw = obs.messages.get("GPS_RAW_INT" if inst == 0 else "GPS2_RAW")
    if raw is None:
        ev.append(f"GPS{inst + 1} (MAVLink GPS) not reported: request {'GPS_RAW_INT' if inst == 0 else 'GPS2_RAW'}")
        return None, None
    ev.append(f"GPS{inst + 1}_TYPE=14 (our GPS_INPUT, gps_id={inst}): fix_type {raw['fix_type']}, {raw['satellites_visible']} satellites")
    if raw["fix_type"] < 3:
        ev.append("the MAVLink GPS has no 3D fix: our GPS_INPUT is not arriving or not trusted")
        return False, None
    ours = (raw["lat"] * 1e-7, raw["lon"] * 1e-7)
    other = obs.messages.get("GPS2_RAW" if inst == 0 else "GPS_RAW_INT")
    if p.get("GPS_AUTO_SWITCH") == 0:
        primary = int(p.get("GPS_PRIMARY", 0))
        ev.append(f"GPS_AUTO_SWITCH=0, GPS_PRIMARY={primary}")
    else:  # ArduPilot's rule: higher fix type wins, ties to more satellites
        o = (other["fix_type"], other["satellites_visible"]) if other else (0, 0)
        primary = inst if (raw["fix_type"], raw["satellites_visible"]) > o else 1 - inst
        ev.append(f"GPS_AUTO_SWITCH=1: primary by fix type/satellites is GPS{primary + 1}")
    return primary == inst, ours


def _judge_px4(obs: Observation, ev: list[str]) -> bool | None:
    p = obs.params
    ev.append("PX4 ignores GPS_INPUT; sources: " + ", ".join(f"{k}={v}" for k, v in p.items()) if p else "PX4 parameters not readable")
    configured = (int(p.get("EKF2_EV_CTRL", 0)) & 1) or (int(p.get("EKF2_AGP0_CTRL", 0)) & 1) or p.get("MAV_USEHILGPS") == 1
    if p and not configured:
        ev.append("no external source enabled (EKF2_EV_CTRL bit 1, EKF2_AGP0_CTRL, MAV_USEHILGPS)")
        return False
    if _gnss_ok(obs, "px4"):
        ev.append("GNSS has a fix: EKF2 fuses EV relative to it, fusion of our source is not visible over MAVLink "
                  "(cut GNSS, e.g. `failure gps off` in the PX4 shell, and check again)")
    return None
