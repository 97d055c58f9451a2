"""A SITL bundle (start/stop scripts + autopilot builds, see docs/AUTOPILOTS.md) and one running
autopilot: where it listens, which system id it has, which parameters it booted with.

The bundle's layout is the one its README documents: ``start_arducopter.sh WORKDIR [INSTANCE]``
and ``start_px4.sh WORKDIR [INSTANCE]`` start the autopilot in the background and print ``PID=``;
``stop.sh PID`` stops it. Home, speed and boot parameters go in through their environment
(``AP_HOME``/``AP_SPEEDUP``/``AP_EXTRA_DEFAULTS``; ``PX4_HOME_*``/``PX4_SIM_SPEED_FACTOR``/``PX4_PARAM_*``).
"""
from __future__ import annotations

import os
import re
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

ENV_VAR = "TERRASLAM_SITL_DIR"
SCRIPTS = {"ardupilot": "start_arducopter.sh", "px4": "start_px4.sh"}

#: Boot parameters per output (docs/AUTOPILOTS.md): what our output needs, GNSS as the primary
#: source until we take over, no on-board logs (a SITL flight would write megabytes), and a
#: return altitude above the city's roofs (the buildings reach 60 m; the SITL knows no buildings).
PARAMS: dict[tuple[str, str], dict[str, float]] = {
    # GPS_INPUT carries no time: GPS2_DELAY_MS is our capture-to-wire latency (15–60 ms of SITL time at speed 0.5)
    ("ardupilot", "gps_input"): {"GPS2_TYPE": 14, "GPS_AUTO_SWITCH": 0, "GPS_PRIMARY": 0, "GPS2_DELAY_MS": 50},
    ("ardupilot", "odometry"): {"VISO_TYPE": 1, "VISO_DELAY_MS": 100, "EK3_SRC2_POSXY": 6, "EK3_SRC2_VELXY": 0,
                                "EK3_SRC2_POSZ": 1, "EK3_SRC2_VELZ": 0, "EK3_SRC2_YAW": 1},
    # ODOMETRY is stamped with the frame's capture time (PX4 maps it through TIMESYNC): no extra delay
    ("px4", "odometry"): {"EKF2_EV_CTRL": 1, "EKF2_EV_NOISE_MD": 0, "EKF2_EV_DELAY": 0},
    ("px4", "global_position_sensor"): {"EKF2_AGP0_ID": 1, "EKF2_AGP0_CTRL": 1, "EKF2_AGP0_DELAY": 100},
}
#: The heading follows the course and turns at most 20°/s, as a survey pilot flies a camera: a
#: monocular camera yawing on the spot at the autopilots' default 60°/s sees no parallax and loses track.
COMMON = {
    "ardupilot": {"LOG_BACKEND_TYPE": 0, "RTL_ALT": 8000, "WPNAV_SPEED_UP": 500, "PILOT_SPEED_UP": 500,
                  "WP_YAW_BEHAVIOR": 3, "ATC_SLEW_YAW": 2000},
    "px4": {"SDLOG_BACKEND": 0, "RTL_RETURN_ALT": 80, "RTL_DESCEND_ALT": 80, "MPC_Z_VEL_MAX_UP": 5,
            "COM_DISARM_LAND": 2, "MPC_YAW_MODE": 3, "MPC_YAWRAUTO_MAX": 20},
}
#: How old a SITL receiver's solution is when the autopilot stamps it (mavlink.gnss_delay_s): ArduPilot
#: SITL's SIM_GPS1_LAG_MS (default 100 ms); PX4 SIH's sensor_gps_sim publishes without lag
GNSS_DELAY_S = {"ardupilot": 0.1, "px4": 0.0}
#: GNSS off / on with the SITL's own receiver switch (docs/AUTOPILOTS.md)
GNSS_PARAM = {"ardupilot": ("SIM_GPS1_ENABLE", 0, 1), "px4": ("SIM_GPS_USED", 0, 10)}
#: A spoof: the SITL receiver's position moved north, in degrees of latitude (ArduPilot SIM_GPS1_GLTCH_X
#: adds it to the receiver's latitude). PX4 SIH's simulated receiver has no such offset.
SPOOF_PARAM = {"ardupilot": "SIM_GPS1_GLTCH_X"}
M_PER_DEG_LAT = 111_132.0  # metres per degree of latitude at mid latitudes (a spoof's size, ±0.5 %)


class SitlError(RuntimeError):
    """The bundle is missing or an autopilot did not start."""


def find_bundle(sitl_dir: Path | str | None = None) -> Path:
    """The bundle folder: ``sitl_dir``, else $TERRASLAM_SITL_DIR; it must hold both start scripts."""
    raw = sitl_dir if sitl_dir is not None else os.environ.get(ENV_VAR)
    if not raw:
        raise SitlError(f"no SITL bundle: pass --sitl-dir DIR or set {ENV_VAR} (a folder with "
                        f"{' and '.join(SCRIPTS.values())}, stop.sh and the autopilot builds)")
    path = Path(raw).expanduser()
    missing = [s for s in (*SCRIPTS.values(), "stop.sh") if not (path / s).is_file()]
    if missing:
        raise SitlError(f"SITL bundle {path}: missing {', '.join(missing)}")
    return path


@dataclass(frozen=True)
class Home:
    """Where the autopilot boots: WGS-84 degrees, MSL metres (what both SITLs take), heading."""

    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    yaw_deg: float = 0.0


@dataclass
class Sitl:
    """One running autopilot."""

    autopilot: str
    bundle: Path
    workdir: Path
    pid: int
    instance: int
    params: dict[str, float] = field(default_factory=dict)

    @property
    def system_id(self) -> int:
        """PX4 SITL instance N is MAVLink system N+1; ArduPilot's is 1 (MAV_SYSID) for every instance."""
        return self.instance + 1 if self.autopilot == "px4" else 1

    @property
    def bridge_url(self) -> str:
        """The companion's link (pymavlink URL): ArduPilot SERIAL1 (TCP), PX4's onboard link (UDP)."""
        if self.autopilot == "ardupilot":
            return f"tcp:127.0.0.1:{5762 + 10 * self.instance}"
        return f"udpin:127.0.0.1:{14540 + self.instance}"

    @property
    def mission_url(self) -> str:
        """The ground station's link (MAVSDK URL): ArduPilot SERIAL0, PX4's GCS link."""
        if self.autopilot == "ardupilot":
            return f"tcpout://127.0.0.1:{5760 + 10 * self.instance}"
        return "udpin://127.0.0.1:14550"  # PX4 sends its GCS link to 14550 for every instance

    @property
    def truth_url(self) -> str:
        """The simulator's truth (pymavlink URL): ArduPilot SERIAL2 (SIM_STATE), PX4 SIH's display link
        (HIL_STATE_QUATERNION)."""
        if self.autopilot == "ardupilot":
            return f"tcp:127.0.0.1:{5763 + 10 * self.instance}"
        return f"udpin:127.0.0.1:{19410 + self.instance}"

    def log_tail(self, n: int = 20) -> str:
        log = self.workdir / ("arducopter.log" if self.autopilot == "ardupilot" else "px4.log")
        try:
            return "\n".join(log.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return f"(no {log})"


def boot_params(autopilot: str, output: str) -> dict[str, float]:
    if (autopilot, output) not in PARAMS:
        supported = ", ".join(f"{a}/{o}" for a, o in PARAMS)
        raise SitlError(f"{autopilot} with output {output}: no SITL set-up for it (supported: {supported})")
    return {**COMMON[autopilot], **PARAMS[(autopilot, output)]}


def px4_runnable(bundle: Path, scratch: Path) -> Path:
    """The bundle, or where its PX4 clients are missing, a copy made of links in ``scratch``.

    PX4's start-up script runs its commands as ``px4-<module>`` links to the ``px4`` binary beside
    it; a copy of the bundle that kept those links as plain files (a read-only mount, an archive
    without symlinks) cannot start. The copy links everything back to the bundle and makes each
    ``px4-<module>`` a link to ``px4`` again; nothing of the bundle is copied."""
    bin_dir = bundle / "px4" / "bin"
    clients = [p for p in bin_dir.glob("px4-*") if p.suffix != ".sh"]
    if all(p.is_symlink() or os.access(p, os.X_OK) for p in clients):
        return bundle
    shadow = scratch / "sitl-bundle"
    (shadow / "px4" / "bin").mkdir(parents=True, exist_ok=True)
    for entry in bundle.iterdir():
        if entry.name != "px4":
            _link(shadow / entry.name, entry)
    for entry in (bundle / "px4").iterdir():
        if entry.name != "bin":
            _link(shadow / "px4" / entry.name, entry)
    for entry in bin_dir.iterdir():
        _link(shadow / "px4" / "bin" / entry.name, Path("px4") if entry in clients else entry)
    return shadow


def _link(at: Path, to: Path) -> None:
    if at.is_symlink() or at.exists():
        at.unlink()
    at.symlink_to(to)


def start(bundle: Path, autopilot: str, output: str, workdir: Path, home: Home, speed: float = 1.0,
          instance: int = 0, extra_params: dict[str, float] | None = None) -> Sitl:
    """Start the autopilot from factory defaults (its WORKDIR wiped) with our output's parameters."""
    params = {**boot_params(autopilot, output), **(extra_params or {})}
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    if autopilot == "ardupilot":
        defaults = workdir / "terraslam.parm"
        defaults.write_text("".join(f"{k} {v:g}\n" for k, v in params.items()))
        env.update(AP_HOME=f"{home.lat_deg:.8f},{home.lon_deg:.8f},{home.alt_msl_m:.2f},{home.yaw_deg:.1f}",
                   AP_SPEEDUP=f"{speed:g}", AP_WIPE="1", AP_EXTRA_DEFAULTS=str(defaults))
    else:
        env.update(PX4_HOME_LAT=f"{home.lat_deg:.8f}", PX4_HOME_LON=f"{home.lon_deg:.8f}",
                   PX4_HOME_ALT=f"{home.alt_msl_m:.2f}", PX4_SIM_SPEED_FACTOR=f"{speed:g}", PX4_WIPE="1",
                   **{f"PX4_PARAM_{k}": f"{v:g}" for k, v in params.items()})
    if autopilot == "px4":
        bundle = px4_runnable(bundle, workdir.parent)
    script = bundle / SCRIPTS[autopilot]
    r = subprocess.run(["bash", str(script), str(workdir), str(instance)], env=env, capture_output=True,
                       text=True, timeout=60)
    m = re.search(r"^PID=(\d+)", r.stdout, re.M)
    if r.returncode != 0 or m is None:
        raise SitlError(f"{script} failed (exit {r.returncode}):\n{r.stdout}\n{r.stderr}")
    return Sitl(autopilot, bundle, workdir, int(m.group(1)), instance, params)


def stop(sitl: Sitl) -> None:
    subprocess.run(["bash", str(sitl.bundle / "stop.sh"), str(sitl.pid)], capture_output=True, timeout=30)
