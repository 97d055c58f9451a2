"""``terraslam sitl``: a closed-loop flight with a real autopilot SITL, our camera and SLAM in it.

Reads top to bottom (run_sitl): build the simulated city and its GIS model → start the autopilot
with its home at the city's origin and our output's parameters → connect the truth link, the
mission client and the bridge → take off and start the mission → every camera period of SITL
time, render the frame from the autopilot's simulated truth, run the pipeline, hand the fix to the
bridge → switch the SITL's GNSS off (and on) with its own command → land → report our fixes, the
autopilot's estimate and the vehicle's track against the truth.

The camera and pipeline run on the SITL's clock (truth.TruthFeed.clock). When a frame's processing
takes longer than a camera period of SITL time, the frames due meanwhile are skipped, as a live
camera pipeline drops them; run the SITL slower (``speed``) on a small machine to avoid it.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from companion.app import build_localizer, horizontal_m
from companion.config import AppConfig
from companion.evaluate import write_report
from companion.pipeline import PipelineInput, attitude_prior
from companion.run_log import RunLog, summarize, write_outputs
from companion.sitl import bundle as sitl_bundle
from companion.sitl.truth import TruthFeed, TruthState
from companion.sitl.vehicle import Vehicle
from gis.geodesy import R_NED_ENU, LocalFrame, R_ecef_enu, ellipsoid_to_msl, msl_to_ellipsoid
from gis.loaders import load_model
from mavlink_bridge.types import GnssQuality
from slam.types import Frame

log = logging.getLogger(__name__)

DEFAULT_OUTPUT = {"ardupilot": "gps_input", "px4": "odometry"}
READY_TIMEOUT_S = 120.0       # SITL time for the autopilot to be ready to arm on GNSS (ArduPilot's EKF: ~40 s)
#: ArduPilot boots (EKF start, GNSS lock, origin) at this speed-up before the camera runs, then takes
#: ``SitlOptions.speed`` (SIM_SPEEDUP can change in flight); PX4 SIH keeps its start speed (~10 s to ready)
BOOT_SPEEDUP = 4.0
HANDBACK_WINDOW_S = 3.0       # the autopilot's estimate around the hand-back, for its jump
#: the camera starts once the vehicle cruises: moving at least this fast, its heading settled (the
#: first turn towards the route is a yaw on the spot, which no monocular SLAM initialises on)
CAMERA_START_MPS = 3.0
CAMERA_START_YAW_RATE_DPS = 8.0


@dataclass(frozen=True)
class SitlOptions:
    autopilot: str = "ardupilot"
    output: str | None = None            # default per autopilot: DEFAULT_OUTPUT
    seed: int = 0                        # the simulated city
    fps: float = 10.0                    # camera frames per second of SITL time
    speed: float = 0.5                   # SITL speed against real time (ArduPilot --speedup, PX4 speed factor)
    altitude_m: float = 80.0             # mission height above home (the city's roofs reach 60 m)
    speed_mps: float = 7.0
    size_m: float = 200.0                # side of the square flown over the city's centre
    laps: float = 1.75
    gnss_off_after_s: float = 40.0       # SITL time after the camera starts (the GNSS fits and first registrations need ~20 s)
    gnss_off_for_s: float | None = 120.0  # None: GNSS stays off to the end
    max_flight_s: float | None = None    # end this long after the camera starts (None: fly to the landing)
    offset_probe_m: float = 0.0          # add this much east to our fixes over the denial's last 10 s (is the EKF following us?)
    spoof_m: float = 0.0                 # instead of switching GNSS off, move the SITL receiver this far north (a spoof)
    instance: int = 0

    def __post_init__(self):
        if self.autopilot not in DEFAULT_OUTPUT:
            raise ValueError(f"autopilot must be ardupilot or px4, got {self.autopilot!r}")
        if not 0.05 <= self.speed <= 4.0:
            raise ValueError(f"speed must be in [0.05, 4], got {self.speed}")
        if not 1.0 <= self.fps <= 30.0:
            raise ValueError(f"fps must be in [1, 30], got {self.fps}")
        sitl_bundle.boot_params(self.autopilot, self.out)  # raises for an output without a SITL set-up
        if self.spoof_m and self.autopilot not in sitl_bundle.SPOOF_PARAM:
            raise ValueError(f"no spoof for {self.autopilot}: its SITL receiver has no position offset parameter")

    @property
    def out(self) -> str:
        return self.output or DEFAULT_OUTPUT[self.autopilot]


@dataclass
class Timeline:
    """SITL times of what happened (s since the autopilot's boot)."""

    ready_s: float | None = None
    mission_start_s: float | None = None
    camera_on_s: float | None = None
    gnss_off_s: float | None = None
    gnss_on_s: float | None = None
    return_s: float | None = None
    landed_s: float | None = None
    events: list[tuple[float, str]] = field(default_factory=list)

    def add(self, t_s: float, text: str) -> None:
        self.events.append((t_s, text))
        log.info("t=%.1f s %s", t_s, text)


def home_of(origin: LocalFrame, ground_h_m: float) -> sitl_bundle.Home:
    """The world's origin on its ground, as both SITLs take a home: MSL (EGM96) height."""
    h_ell = origin.h0_ellipsoid_m + ground_h_m
    return sitl_bundle.Home(origin.lat0_deg, origin.lon0_deg, float(ellipsoid_to_msl(origin.lat0_deg, origin.lon0_deg, h_ell)))


def T_enu_body(origin: LocalFrame, s: TruthState) -> np.ndarray:
    """The body pose in the world's ENU frame; SITL heights are MSL (EGM96), as its home was given.
    The vehicle's NED is turned into the origin's ENU through ECEF (earth curvature, ~3" per 100 m)."""
    h_ell = float(msl_to_ellipsoid(s.lat_deg, s.lon_deg, s.alt_msl_m))
    T = np.eye(4)
    T[:3, 3] = origin.geodetic_to_enu(s.lat_deg, s.lon_deg, h_ell).reshape(3)
    R_enu0_enu = origin.R_ecef_enu.T @ R_ecef_enu(s.lat_deg, s.lon_deg)
    T[:3, :3] = R_enu0_enu @ R_NED_ENU.T @ s.R_ned_body
    return T


def body_ecef(origin: LocalFrame, s: TruthState) -> np.ndarray:
    return origin.enu_to_ecef(T_enu_body(origin, s)[:3, 3])


def run_sitl(cfg: AppConfig, sitl_dir: Path | None, out_dir: Path, opts: SitlOptions = SitlOptions(),
             progress: Callable[[float, str], None] | None = None) -> dict:
    """Fly one closed-loop SITL mission (module docstring); returns the summary written to out_dir."""
    from companion.sim import make_scenario
    from companion.sim.flight import FlightSpec, waypoints
    from companion.sim.gis_export import export_gis
    from mavlink_bridge.bridge import Bridge

    bundle = sitl_bundle.find_bundle(sitl_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    # the city, its GIS model, the camera and its mount: the demo's (make_scenario "nominal")
    scenario = make_scenario("nominal", opts.seed, n_frames=1)
    world, origin = scenario.world, scenario.origin
    model = load_model(export_gis(scenario.gis[0], out_dir / "gis", seed=opts.seed).mesh_ply,
                       sample_spacing_m=cfg.gis.sample_spacing_m)
    home = home_of(origin, float(world.ground_height_m(0.0, 0.0)))
    route_enu = waypoints(FlightSpec(kind="loop", size_m=opts.size_m, altitude_m=opts.altitude_m, laps=opts.laps))
    route_deg = [(float(la), float(lo)) for la, lo, _ in zip(*origin.enu_to_geodetic(route_enu))]

    boot_speed = BOOT_SPEEDUP if opts.autopilot == "ardupilot" else opts.speed
    sitl = sitl_bundle.start(bundle, opts.autopilot, opts.out, out_dir / "sitl", home, boot_speed, opts.instance)
    tl, run = Timeline(), RunLog()
    truth = vehicle = bridge = localizer = None
    try:
        truth = _connect_truth(sitl, opts, boot_speed)
        vehicle = Vehicle(sitl.mission_url, truth.clock)
        mav_cfg = cfg.mavlink.model_copy(update={
            "connect": sitl.bridge_url, "autopilot": opts.autopilot, "output": opts.out, "gps_id": 1,
            "target_system": sitl.system_id, "source_system": sitl.system_id, "rate_hz": max(opts.fps, 1.0),
            "gnss_delay_s": sitl_bundle.GNSS_DELAY_S[opts.autopilot], "estimate_stream_hz": 10.0})
        bridge = Bridge(mav_cfg, cfg.switching, clock=truth.clock).start()
        # ready to fly on GNSS: the receiver trusted and the EKF's absolute position, as the autopilot
        # tells the bridge (EKF_STATUS_REPORT / ESTIMATOR_STATUS; MAVSDK's health needs SYS_STATUS
        # streams that ArduPilot does not send unasked)
        vehicle.wait("ready to fly on GNSS", lambda: bridge.gnss_status().trusted and bridge.ekf_absolute_position(),
                     READY_TIMEOUT_S / min(boot_speed, 1.0))
        tl.ready_s = truth.clock()
        tl.add(tl.ready_s, "ready to arm on GNSS")
        if boot_speed != opts.speed:
            vehicle.set_param_float("SIM_SPEEDUP", opts.speed)
            truth.speed = opts.speed
        vehicle.take_off(opts.altitude_m, 120.0 / opts.speed)
        localizer = build_localizer(cfg, scenario.camera, scenario.T_body_cam, model)
        renderer = scenario.renderer
        vehicle.fly(route_deg, opts.altitude_m, opts.speed_mps)
        tl.mission_start_s = truth.clock()
        tl.add(tl.mission_start_s, f"mission started ({len(route_deg)} waypoints, {opts.laps:g} laps of {opts.size_m:g} m at {opts.altitude_m:g} m)")
        gnss_name, gnss_off, gnss_on = sitl_bundle.GNSS_PARAM[opts.autopilot]
        set_gnss = vehicle.set_param
        if opts.spoof_m:  # the receiver keeps its fix but moves: "off" is the offset, "on" none
            gnss_name, gnss_off, gnss_on = sitl_bundle.SPOOF_PARAM[opts.autopilot], opts.spoof_m / sitl_bundle.M_PER_DEG_LAT, 0.0
            set_gnss = vehicle.set_param_float
        vehicle.wait("cruising on the route", lambda: _cruising(truth), 60.0 / opts.speed)
        tl.camera_on_s = t0 = truth.clock()
        tl.add(t0, "camera on: cruising on the route")
        t_frame, seq, dropped = math.ceil(t0 * opts.fps) / opts.fps, 0, 0
        out_msg = opts.out.upper()
        wall_end = time.monotonic() + _wall_budget_s(opts)
        while time.monotonic() < wall_end:
            now = truth.clock()
            # ---- GNSS off / on with the SITL's own command, at their SITL times
            if tl.gnss_off_s is None and now >= t0 + opts.gnss_off_after_s:
                set_gnss(gnss_name, gnss_off)
                tl.gnss_off_s = truth.clock()
                tl.add(tl.gnss_off_s, f"GNSS spoofed {opts.spoof_m:+g} m north ({gnss_name}={gnss_off:.7f})" if opts.spoof_m
                       else f"GNSS off ({gnss_name}={gnss_off})")
            if (tl.gnss_off_s is not None and tl.gnss_on_s is None and opts.gnss_off_for_s is not None
                    and now >= tl.gnss_off_s + opts.gnss_off_for_s):
                set_gnss(gnss_name, gnss_on)
                tl.gnss_on_s = truth.clock()
                tl.add(tl.gnss_on_s, f"GNSS on ({gnss_name}={gnss_on})")
            # ---- the end: time's up, or landed after the mission
            if opts.max_flight_s is not None and now >= t0 + opts.max_flight_s:
                break
            if opts.max_flight_s is None and tl.return_s is None and vehicle.mission_done():
                vehicle.return_home()
                tl.return_s = truth.clock()
                tl.add(tl.return_s, "mission done: return home and land")
            if not vehicle.in_air and now > t0 + 5.0:  # on the ground: returned, or a failsafe landed it
                tl.landed_s = now
                tl.add(now, "landed" if tl.return_s is not None else f"landed before the mission's end (mode {vehicle.mode()})")
                break
            # ---- the camera: the next frame due, rendered from the truth at its time
            if not truth.wait_until(t_frame, timeout_s=5.0):
                raise TimeoutError(f"SITL truth stopped at {truth.clock():.1f} s")
            newest = truth.latest().t_s
            if newest - t_frame > 1.0 / opts.fps:  # behind: frames due meanwhile are dropped
                late = math.floor((newest - t_frame) * opts.fps)
                dropped += late
                t_frame += late / opts.fps
            state = truth.at(t_frame)
            T_enu_cam = T_enu_body(origin, state) @ scenario.T_body_cam
            image = renderer.render(T_enu_cam).image_bgr
            status = bridge.gnss_status()
            att = bridge.attitude(max_age_s=0.1)
            t_capture = time.perf_counter()
            rec = localizer.process(PipelineInput(Frame(image, t_frame, seq), status.sample,
                                                  status.quality is GnssQuality.GOOD, attitude_prior(att)))
            run.wall_track_ms.append((time.perf_counter() - t_capture) * 1e3)
            bridge.vision_check(localizer.gnss_inconsistency())
            fix = rec.fix
            if fix is not None and opts.offset_probe_m and _in_probe_window(tl, opts, t_frame):
                fix = _shifted_east(fix, opts.offset_probe_m)
            sent_before = bridge.sent_count(out_msg)
            bridge.submit_fix(fix)
            if bridge.sent_count(out_msg) > sent_before:
                run.camera_to_wire_ms.append((time.perf_counter() - t_capture) * 1e3)
            run.records.append(rec)
            run.truth_ecef_m[rec.seq] = body_ecef(origin, state)
            run.truth_cam_ecef_m[rec.seq] = origin.enu_to_ecef(T_enu_cam[:3, 3])
            est = bridge.autopilot_estimate()  # stamped with the autopilot's boot time, the truth's clock
            s_est = truth.at(est[0]) if est is not None else None
            if s_est is not None and (not run.autopilot_err_m or est[0] > run.autopilot_err_m[-1][0]):
                run.autopilot_err_m.append((est[0], horizontal_m(est[1], est[2], s_est.lat_deg, s_est.lon_deg), "ekf"))
            if progress is not None:
                progress(t_frame - t0, f"{bridge.state.value} {rec.pose.state.value}")
            seq += 1
            t_frame += 1.0 / opts.fps
        else:
            tl.add(truth.clock(), f"wall-time budget of {_wall_budget_s(opts):.0f} s spent")
        run.switch_events = [(e.t_s, f"{e.from_state.value} → {e.to_state.value}: {e.reason}") for e in bridge.events()]
        # the takeover that answers the GNSS loss (a companion started before the receiver's first fix takes over at boot too)
        active = [e for e in bridge.events() if e.to_state.value == "active" and tl.gnss_off_s is not None and e.t_s >= tl.gnss_off_s]
        run.takeover_t_s = active[0].t_s if active else None
        run.alignment_events = list(localizer.events)
        run.finetune_ms = list(localizer.worker.wall_ms) if localizer.worker else []
        run.finetune_cpu_ms = list(localizer.worker.cpu_ms) if localizer.worker else []
        final = truth.latest()
        summary = _summary(run, tl, opts, sitl, bridge, vehicle, origin, home, final, dropped)
    finally:
        for closer in (localizer, bridge, vehicle, truth):
            if closer is not None:
                closer.close()
        sitl_bundle.stop(sitl)
    summary["outputs"] = [str(p) for p in write_outputs(run, summary, out_dir, origin, f"TerraSLAM SITL flight ({opts.autopilot})")]
    write_report(summary, out_dir / "report.json", out_dir / "report.md", title=f"TerraSLAM closed-loop SITL flight ({opts.autopilot}, {opts.out})")
    return summary


def _connect_truth(sitl: sitl_bundle.Sitl, opts: SitlOptions, speed: float) -> TruthFeed:
    """The truth link, once the SITL serves it (ArduPilot opens its TCP ports a moment after start)."""
    deadline = time.monotonic() + 30.0
    while True:
        try:
            feed = TruthFeed(sitl.truth_url, opts.autopilot, speed, sitl.system_id).start()
            break
        except OSError as e:
            if time.monotonic() > deadline:
                raise sitl_bundle.SitlError(f"truth link {sitl.truth_url}: {e}\n{sitl.log_tail()}") from e
            time.sleep(0.5)
    if not feed.wait_until(0.0, timeout_s=30.0):
        feed.close()
        raise sitl_bundle.SitlError(f"no simulator truth on {sitl.truth_url} within 30 s\n{sitl.log_tail()}")
    return feed


def _cruising(truth: TruthFeed) -> bool:
    """Moving at CAMERA_START_MPS or more with a heading that turned less than CAMERA_START_YAW_RATE_DPS over the last second."""
    s1 = truth.latest()
    s0 = truth.at(s1.t_s - 1.0) if s1 is not None else None
    if s0 is None or math.hypot(s1.v_ned_mps[0], s1.v_ned_mps[1]) < CAMERA_START_MPS:
        return False
    fwd0, fwd1 = s0.R_ned_body[:2, 0], s1.R_ned_body[:2, 0]
    turn = math.degrees(abs(math.atan2(fwd0[0] * fwd1[1] - fwd0[1] * fwd1[0], float(fwd0 @ fwd1))))
    return turn / max(s1.t_s - s0.t_s, 1e-3) < CAMERA_START_YAW_RATE_DPS


def _wall_budget_s(opts: SitlOptions) -> float:
    """Wall time the camera loop may take: the mission's SITL time at the SITL's speed, twice over."""
    route_s = 4 * opts.laps * opts.size_m / opts.speed_mps + 2 * opts.altitude_m / 1.5 + 60.0
    sitl_s = opts.max_flight_s if opts.max_flight_s is not None else route_s
    return 2.0 * sitl_s / opts.speed + 60.0


def _in_probe_window(tl: Timeline, opts: SitlOptions, t_s: float) -> bool:
    if tl.gnss_off_s is None or tl.gnss_on_s is not None:
        return False
    end = tl.gnss_off_s + (opts.gnss_off_for_s if opts.gnss_off_for_s is not None else math.inf)
    if not math.isfinite(end):
        end = tl.camera_on_s + (opts.max_flight_s or math.inf)
    return end - 10.0 <= t_s < end


def _shifted_east(fix, east_m: float):
    """The fix moved ``east_m`` east (the known offset the autopilot's estimate must follow)."""
    frame = LocalFrame(fix.lat_deg, fix.lon_deg, fix.h_ellipsoid_m)
    east = np.array([east_m, 0.0, 0.0])
    lat, lon, _ = frame.enu_to_geodetic(east)
    return replace(fix, p_ecef_m=np.asarray(frame.enu_to_ecef(east), float).reshape(3), lat_deg=float(lat), lon_deg=float(lon))


def _summary(run: RunLog, tl: Timeline, opts: SitlOptions, sitl, bridge, vehicle, origin: LocalFrame,
             home: sitl_bundle.Home, final: TruthState | None, dropped: int) -> dict:
    s = summarize(run, name=f"sitl ({opts.autopilot}, {opts.out})")
    denial_end = tl.gnss_on_s if tl.gnss_on_s is not None else math.inf
    in_denial = [(t, e) for t, e, _ in run.autopilot_err_m if tl.gnss_off_s is not None and tl.gnss_off_s + 1.0 <= t < denial_end
                 and not (opts.offset_probe_m and _in_probe_window(tl, opts, t))]
    e = np.array([x for _, x in in_denial])
    handback = [ev for ev in bridge.events() if ev.to_state.value == "standby" and tl.gnss_on_s is not None and ev.t_s >= tl.gnss_on_s]
    jump = None
    if handback:
        h = handback[0].t_s
        around = [x for t, x, _ in run.autopilot_err_m if h - HANDBACK_WINDOW_S <= t <= h + HANDBACK_WINDOW_S]
        jump = float(np.max(np.abs(np.diff(around)))) if len(around) > 1 else None
    landed_from_home = None
    if final is not None and tl.landed_s is not None:
        landed_from_home = horizontal_m(final.lat_deg, final.lon_deg, home.lat_deg, home.lon_deg)
    st = bridge.stats()
    s["sitl"] = {
        "autopilot": opts.autopilot, "output": opts.out, "system_id": sitl.system_id, "speed": opts.speed,
        "spoof_m": opts.spoof_m,
        "boot_params": sitl.params, "fps": opts.fps, "frames_dropped": dropped,
        "timeline": {k: getattr(tl, k) for k in ("ready_s", "mission_start_s", "camera_on_s", "gnss_off_s", "gnss_on_s", "return_s", "landed_s")},
        "events": tl.events,
        "takeover_after_gnss_off_s": (run.takeover_t_s - tl.gnss_off_s) if run.takeover_t_s is not None and tl.gnss_off_s is not None else None,
        "handback_after_gnss_on_s": (handback[0].t_s - tl.gnss_on_s) if handback else None,
        "autopilot_jump_at_handback_m": jump,
        "autopilot_error_in_denial_m": {"n": int(e.size), "mean": float(e.mean()) if e.size else None,
                                        "max": float(e.max()) if e.size else None},
        "failsafes": vehicle.log.failsafes(),
        "flight_modes": vehicle.log.modes,
        "autopilot_texts": vehicle.log.texts[-40:],
        "mission_completed": tl.return_s is not None or vehicle.mission_done(),
        "landed_from_home_m": landed_from_home,
        "source_switch": st.source_switch,
        "bridge_sent": dict(st.sent),
        "bridge_acks": {f"{c}:{r}": n for (c, r), n in st.acks.items()},
        "origin_sent": st.origin_sent,
        "ekf_origin": st.origin,
    }
    if opts.offset_probe_m:
        s["sitl"]["offset_probe"] = _probe_result(run, tl, opts)
    return s


def _probe_result(run: RunLog, tl: Timeline, opts: SitlOptions) -> dict:
    """How far the autopilot's estimate moved east while our fixes carried the known offset: its
    error east component over the probe's last 5 s against the 5 s before the probe."""
    inside = [x for t, x, _ in run.autopilot_err_m if _in_probe_window(tl, opts, t) and _in_probe_window(tl, opts, t - 5.0)]
    before = [x for t, x, _ in run.autopilot_err_m if _in_probe_window(tl, opts, t + 10.0) and not _in_probe_window(tl, opts, t)]
    return {"offset_m": opts.offset_probe_m, "error_before_m": float(np.mean(before)) if before else None,
            "error_during_m": float(np.mean(inside)) if inside else None}
