"""Wiring: the demo, offline replay and the service, each reading top to bottom (run → evaluate → write).

- ``run_demo``: built-in simulated city + flight, a simulated autopilot on UDP loopback fed by the
  GNSS simulator, GNSS lost mid-flight. Everything shares one simulated clock so the demo runs as
  fast as the machine allows while every rate, timeout and hysteresis is judged in flight time.
- ``run_replay``: any dataset in the documented layout (docs/DATASET.md), offline, no autopilot.
- ``run_service``: the real thing (camera → SLAM → GIS alignment → MAVLink), supervised.
"""
from __future__ import annotations

import itertools
import logging
import math
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from companion.config import AppConfig
from companion.evaluate import GnssReference, gnss_ecef, write_report
from companion.fusion.gnss_fit import BootstrapCollector
from companion.pipeline import Localizer, PipelineInput, attitude_prior
from companion.run_log import RunLog, summarize, write_outputs
from gis.align.fine import FineTuner
from gis.align.journal import Journal, write_meta
from gis.geodesy import R_NED_ENU, LocalFrame, R_ecef_enu
from gis.globalizer import Globalizer
from gis.loaders import load_model
from gis.model import GisModel
from gis.types import Alignment, GlobalFix
from mavlink_bridge.monitor import GnssMonitor
from mavlink_bridge.types import GnssQuality, no_fix_sample
from slam.types import CameraModel

log = logging.getLogger(__name__)


class SimClock:
    """Monotonic simulated time in seconds, advanced by the frame loop (thread-safe reads)."""

    def __init__(self, t0_s: float = 0.0):
        self._t = t0_s
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            return self._t

    def advance_to(self, t_s: float) -> None:
        with self._lock:
            self._t = max(self._t, t_s)


#: Repeatable offline runs (``bench --repeatable``, ``replay --repeatable``; Localizer.settle):
#: a fine-tuning result is adopted at flight time submission + this, not whenever the worker
#: process happens to finish. 0.3 s is about twice a registration's wall time on a loaded 2-core
#: board (suite means 80–145 ms); bench counts the registrations that took longer.
REPEATABLE_LAG_S = 0.3
REPEATABLE_DELIVERY_TIMEOUT_S = 10.0  # fly_sim: how long a repeatable run waits for the autopilot's messages of a frame

#: Replay: a frame goes with the newest ATTITUDE up to this old, also when none arrived since the
#: previous frame (what the service asks of ``Bridge.attitude``).
ATTITUDE_MAX_AGE_S = 0.1


@dataclass(frozen=True)
class GnssDenial:
    """Replay only: GNSS withheld from the pipeline as if jammed, from ``from_s`` until ``until_s``
    seconds after the dataset's first frame (``t0_s``, bound by run_replay; open end: inf).

    Each withheld solution still reaches the GNSS monitor, as a no-fix report at its own time (what
    GPS_RAW_INT reads under jamming), so the takeover, the denied fine-tuning period and the return
    of GNSS run as in the service. The withheld 3D solutions are the reference the fixes sent
    meanwhile are judged against (evaluate.GnssReference): a recorded field flight, which has no
    truth, becomes a GNSS-denial trial with the receiver as its yardstick."""

    from_s: float
    until_s: float = math.inf
    t0_s: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.from_s) and self.from_s >= 0.0):
            raise ValueError(f"GNSS denial: start {self.from_s} s must be ≥ 0 s after the first frame")
        if not self.until_s > self.from_s:
            raise ValueError(f"GNSS denial: end {self.until_s} s must come after its start {self.from_s} s")

    @property
    def start_t_s(self) -> float:
        return self.t0_s + self.from_s

    @property
    def end_t_s(self) -> float:
        return self.t0_s + self.until_s

    def covers(self, t_s: float) -> bool:
        return self.start_t_s <= t_s < self.end_t_s


def build_localizer(cfg: AppConfig, camera: CameraModel, T_body_cam: np.ndarray, model: GisModel | None,
                    initial_alignment: Alignment | None = None, initial_map=None,
                    repeatable: bool = False, p_body_gnss_m=(0.0, 0.0, 0.0), reloc_timeout_s: float | None = None,
                    keep_loaded_map: bool = False) -> Localizer:
    """SLAM + fine-tuner + globalizer as configured; slam is imported here (torch is heavy).
    ``initial_map``: a slam.persist.LoadedMap to resume in (the service after a restart, or a
    site's survey map), relocalising in it within ``reloc_timeout_s`` of frame time (default
    ``persistence.reloc_timeout_s``); ``keep_loaded_map``: its keyframes are never forgotten by
    the memory cap (a survey map: slam.system.SlamSystem).
    ``repeatable``: offline runs only (Localizer.settle, REPEATABLE_LAG_S); never live.
    ``p_body_gnss_m``: the GNSS antenna, FRD metres from the body origin (BootstrapCollector)."""
    from slam.system import SlamSystem

    slam = SlamSystem(camera, cfg.slam, initial_map=initial_map,
                      reloc_timeout_s=cfg.persistence.reloc_timeout_s if reloc_timeout_s is None else reloc_timeout_s,
                      keep_loaded=keep_loaded_map, stepped=repeatable)
    tuner = FineTuner(model, cfg.alignment) if model is not None else None
    return Localizer(slam, tuner, Globalizer.from_config(T_body_cam, cfg.alignment), cfg.alignment.finetune_every_frames,
                     finetune_every_frames_denied=cfg.alignment.finetune_every_frames_denied,
                     finetune_min_parallax_deg=cfg.alignment.finetune_min_parallax_deg,
                     finetune_recent_keyframes=cfg.alignment.finetune_recent_keyframes,
                     denial_sigma_per_m=cfg.alignment.denial_sigma_per_m,
                     initial_alignment=initial_alignment,
                     repeatable_lag_s=REPEATABLE_LAG_S if repeatable else None,
                     bootstrap=BootstrapCollector(T_body_cam=T_body_cam, p_body_gnss_m=np.asarray(p_body_gnss_m, float))
                     if cfg.alignment.bootstrap_from_gnss
                     else BootstrapCollector(min_pairs=10**9))


# --------------------------------------------------------------------------------------------
# demo


@dataclass(frozen=True)
class DemoOptions:
    seed: int = 0
    n_frames: int = 800
    fps: float = 10.0
    gnss_loss_at_s: float = 40.0
    autopilot: str = "ardupilot"
    gnss_timeline: str | None = None  # e.g. "spoof_drift@40" (companion.sim.gnss.parse_timeline) instead of the loss
    receiver: str = "dgps"  # simulated receiver grade before the loss: dgps (SBAS/DGPS, ~0.8 m), standalone (~4 m), urban
    scenario: str = "gnss_loss"
    repeatable: bool = False  # fly_sim(repeatable=True)


@dataclass
class SimFlight:
    """What one simulated flight through the real pipeline produced (fly_sim)."""

    run: RunLog
    alignments: list[Alignment]        # every alignment the localizer adopted, in order
    map_points_slam: np.ndarray        # the final SLAM map
    last_map_key: tuple[int, int] | None  # (map_id, reset_counter) of the last tracked frame
    received: object                   # the simulated autopilot's counters (SimAutopilot.received())
    bridge_sent: dict


def open_journal(folder: Path, model_file: Path, cfg: AppConfig, origin: LocalFrame) -> Journal:
    """A registration journal in ``folder`` (gis.align.journal) with what a replay needs to load the
    same model (``model_file`` as ``cfg.gis`` loads it) and run the same alignment settings."""
    write_meta(folder, model_file, cfg.gis.sample_spacing_m, cfg.alignment.model_dump(mode="json"),
               (origin.lat0_deg, origin.lon0_deg, origin.h0_ellipsoid_m), cfg.gis.footprint_ground)
    return Journal(folder)


def fly_sim(cfg: AppConfig, steps: Iterable, n_frames: int, camera: CameraModel, T_body_cam: np.ndarray,
            model: GisModel | None, autopilot: str | None = None, output: str | None = None,
            progress: Callable[[int, int, str], None] | None = None, repeatable: bool = False,
            p_body_gnss_m=(0.0, 0.0, 0.0), journal: Journal | None = None) -> SimFlight:
    """Frames (SimStep-like: frame, gnss, attitude, truth) → Localizer → Bridge → simulated autopilot.

    The one loop behind ``demo`` and ``bench``: the autopilot (UDP 127.0.0.1) is fed the vehicle's
    GNSS and attitude, the bridge judges GNSS and relays the attitude, the localizer tracks and
    globalises, the fix goes back over MAVLink. A simulated clock advances with the frames, so every
    rate, timeout and hysteresis is judged in flight time while the loop runs as fast as it can.
    ``repeatable``: local mapping and fine-tuning keep step with the flight clock (Localizer.settle),
    so the same inputs give the same fixes to the bit; otherwise they run free, as live.
    ``journal``: every registration's inputs and outcome are written there (gis.align.journal).
    """
    from mavlink_bridge.bridge import Bridge
    from mavlink_bridge.sim_autopilot import SimAutopilot

    autopilot = autopilot or cfg.mavlink.autopilot
    output = output or (cfg.mavlink.output if autopilot == cfg.mavlink.autopilot
                        else ("gps_input" if autopilot == "ardupilot" else "odometry"))
    clock = SimClock()
    params = {"GPS_AUTO_SWITCH": 0, "GPS_PRIMARY": 0} if autopilot == "ardupilot" else {}
    ap = SimAutopilot(autopilot, params=params, clock=clock, heartbeat_on_new_peer=True).start()
    steps = iter(steps)
    first = next(steps, None)
    if first is not None:
        # The link comes up (the autopilot answers the bridge's first HEARTBEAT at once) at the first
        # frame's time and with its attitude, as when the flight starts: not at 0 with the link then
        # timing out across the jump to a later first frame, nor with a stale ATTITUDE streamed.
        for a in first.attitude:
            ap.feed_attitude(a.roll_rad, a.pitch_rad, a.yaw_rad)
        clock.advance_to(first.frame.t_s)
        steps = itertools.chain([first], steps)
    mav_cfg = cfg.mavlink.model_copy(update={"connect": f"udpout:127.0.0.1:{ap.port}", "autopilot": autopilot, "output": output})
    bridge = Bridge(mav_cfg, cfg.switching, clock=clock).start()
    localizer = build_localizer(cfg, camera, T_body_cam, model, repeatable=repeatable, p_body_gnss_m=p_body_gnss_m)
    if localizer.worker is not None:
        localizer.worker.journal = journal
    if repeatable:
        _wait_link(bridge, REPEATABLE_DELIVERY_TIMEOUT_S)
    out_msg = output.upper()  # the fix message; heartbeats etc. are not fixes
    run, alignments, last_key = RunLog(), [], None
    try:
        for k, step in enumerate(steps):
            if k >= n_frames:
                break
            for a in step.attitude:  # before the clock moves: ATTITUDE stamped at t carries the attitude at t
                ap.feed_attitude(a.roll_rad, a.pitch_rad, a.yaw_rad)
            clock.advance_to(step.frame.t_s)
            for s in step.gnss:
                ap.feed_gnss(s)
                run.gnss_ecef_m.append((s.t_s, gnss_ecef(s), s.fix_type >= 3))
            truth = step.truth
            if truth is not None:
                ap.set_truth(truth.lat_deg, truth.lon_deg, truth.h_msl_m)
            att = _wait_delivered(bridge, ap, step.frame.t_s, REPEATABLE_DELIVERY_TIMEOUT_S if repeatable else 0.05)
            status = bridge.gnss_status()
            localizer.settle(step.frame.t_s)  # may wait for the worker: not part of the frame's latency
            sent_before = bridge.sent_count(out_msg)
            t_capture = time.perf_counter()  # the frame exists (rendered / decoded) from here on
            rec = localizer.process(PipelineInput(step.frame, status.sample, status.quality is GnssQuality.GOOD, attitude_prior(att)))
            t_tracked = time.perf_counter()
            bridge.vision_check(localizer.gnss_inconsistency())
            bridge.submit_fix(rec.fix)
            t_wire = time.perf_counter()
            run.records.append(rec)
            run.wall_track_ms.append((t_tracked - t_capture) * 1e3)
            if bridge.sent_count(out_msg) > sent_before:  # this fix's bytes were written to the socket
                run.camera_to_wire_ms.append((t_wire - t_capture) * 1e3)
            if truth is not None:
                run.truth_ecef_m[rec.seq] = truth.p_body_ecef_m
                run.truth_cam_ecef_m[rec.seq] = truth.p_ecef_m
                est = ap.estimate()
                if est.valid:
                    run.autopilot_err_m.append((step.frame.t_s, horizontal_m(est.lat_deg, est.lon_deg, truth.lat_deg, truth.lon_deg), est.source))
            a = localizer.alignment
            if a is not None and (not alignments or a is not alignments[-1]):
                alignments.append(a)
            if rec.pose.state.has_pose:
                last_key = (rec.pose.map_id, rec.pose.reset_counter)
            if progress is not None:
                progress(k + 1, n_frames, bridge.state.value)
        time.sleep(0.2)  # let the last UDP messages land before reading the autopilot's counters
        run.switch_events = [(e.t_s, f"{e.from_state.value} → {e.to_state.value}: {e.reason}") for e in bridge.events()]
        active = [e for e in bridge.events() if e.to_state.value == "active"]
        run.takeover_t_s = active[0].t_s if active else None
        run.alignment_events = list(localizer.events)
        if localizer.bootstrap.last_refusal:
            run.alignment_events.append((run.records[-1].t_s if run.records else 0.0,
                                         f"last GNSS bootstrap refusal: {localizer.bootstrap.last_refusal}"))
        if localizer.worker is not None:  # let a registration in flight finish so its time counts
            localizer.settle(math.inf)
            deadline = time.monotonic() + 30.0
            while localizer.worker.busy.is_set() and time.monotonic() < deadline:
                time.sleep(0.05)
            run.finetune_ms, run.finetune_cpu_ms = list(localizer.worker.wall_ms), list(localizer.worker.cpu_ms)
        run.scale_checks = [c for _, c in localizer.scale_checks]
        map_points = np.asarray(localizer.slam.map_points().points_slam, float).reshape(-1, 3)
        received, sent = ap.received(), dict(bridge.stats().sent)
    finally:
        localizer.close()
        bridge.close()
        ap.close()
    return SimFlight(run, alignments, map_points, last_key, received, sent)


def run_demo(cfg: AppConfig, out_dir: Path, opts: DemoOptions = DemoOptions(),
             progress: Callable[[int, int, str], None] | None = None) -> dict:
    """The embedded default: simulated flight, GNSS lost mid-flight, our fixes take over."""
    from companion.sim import make_scenario
    from companion.sim.gis_export import export_gis
    from companion.sim.gnss import GnssEvent, GnssSpec, parse_timeline

    out_dir.mkdir(parents=True, exist_ok=True)
    scenario = make_scenario(opts.scenario, opts.seed, opts.n_frames, fps=opts.fps,
                             gnss=GnssSpec(base=opts.receiver,
                                           events=parse_timeline(opts.gnss_timeline) if opts.gnss_timeline
                                           else (GnssEvent("dropout", opts.gnss_loss_at_s),)))
    gis_world, _ = scenario.gis
    files = export_gis(gis_world, out_dir / "gis", seed=opts.seed)
    model = load_model(files.mesh_ply, sample_spacing_m=cfg.gis.sample_spacing_m)
    flight = fly_sim(cfg, scenario.steps(), scenario.n_frames, scenario.camera, scenario.T_body_cam, model,
                     autopilot=opts.autopilot, progress=progress, repeatable=opts.repeatable,
                     p_body_gnss_m=scenario.spec.gnss_antenna_m)
    run, received = flight.run, flight.received
    summary = summarize(run, name=f"demo ({opts.scenario}, {opts.receiver} receiver, {opts.autopilot})")
    summary["autopilot"] = {
        "personality": opts.autopilot,
        "received": dict(received.counts),
        "accepted": dict(received.accepted),
        "rejections": [f"{t:.1f}s {m}: {r}" for t, m, r in received.rejections[:10]],
        "sources_after_takeover": sorted({s for t, _, s in run.autopilot_err_m if run.takeover_t_s is not None and t >= run.takeover_t_s}),
    }
    summary["bridge_sent"] = flight.bridge_sent
    summary["outputs"] = [str(p) for p in write_outputs(run, summary, out_dir, scenario.origin, "TerraSLAM demo")]
    write_report(summary, out_dir / "report.json", out_dir / "report.md", title="TerraSLAM demo")
    return summary


def _wait_link(bridge, timeout_s: float) -> None:
    """Repeatable simulated flight: before the first frame the link is up and the autopilot has
    answered the bridge's last request of the link-up (REQUEST_MESSAGE, after the stream
    intervals; one UDP socket, handled in order), so the first frame's GNSS is streamed whatever
    the two threads' speed."""
    from pymavlink.dialects.v20.ardupilotmega import MAV_CMD_REQUEST_MESSAGE

    t_end = time.monotonic() + timeout_s
    while True:
        try:  # the bridge's thread adds to the counter meanwhile
            if any(cmd == MAV_CMD_REQUEST_MESSAGE for cmd, _ in list(bridge.stats().acks)):
                return
        except RuntimeError:  # changed size while copied: look again
            pass
        if time.monotonic() >= t_end:
            log.warning("repeatable run: the simulated autopilot did not answer the link-up after %.0f s; going on", timeout_s)
            return
        time.sleep(0.001)


def _wait_delivered(bridge, ap, t_s: float, timeout_s: float):
    """Simulated flight only: the autopilot's ATTITUDE for simulated time t_s, and whatever else it
    sent for it (GPS_RAW_INT, the barometer), are on their way over UDP when the frame is processed:
    wait (real time) until the bridge has the attitude and the autopilot's last message
    (MAVLink sequence number) instead of using the previous ones. Free-running, briefly, as a live
    pipeline would not wait; repeatable, as long as it takes (what the frame sees must not depend
    on how loaded this machine is)."""
    t_end = time.monotonic() + timeout_s
    while True:
        att = bridge.attitude(max_age_s=0.1)
        if att is not None and att.t_s >= t_s - 1e-3 and bridge.stats().last_seq == ap.last_sent_seq():
            return att
        if time.monotonic() >= t_end:
            if timeout_s >= REPEATABLE_DELIVERY_TIMEOUT_S:
                log.warning("repeatable run: the simulated autopilot's messages for %.2f s not all at the bridge "
                            "after %.0f s; going on", t_s, timeout_s)
            return att
        time.sleep(0.001)


def horizontal_m(lat1, lon1, lat2, lon2) -> float:
    """Horizontal distance (m) of point 1 from point 2, WGS-84 degrees."""
    ned = LocalFrame(lat2, lon2, 0.0).geodetic_to_ned(lat1, lon1, 0.0)
    return float(np.hypot(ned[0], ned[1]))


# --------------------------------------------------------------------------------------------
# replay


def antenna_to_body(p_antenna_ecef_m: np.ndarray, fix: GlobalFix, p_body_gnss_m: np.ndarray) -> np.ndarray:
    """The body origin where the receiver's antenna (``p_body_gnss_m``, FRD metres from it) is at
    ``p_antenna_ecef_m``, turned by the fix's own attitude (a degree off moves a 0.3 m lever arm
    5 mm); the antenna's position as it is when the fix has no attitude."""
    lever = np.asarray(p_body_gnss_m, float)
    if not lever.any() or fix.q_ned_body is None:
        return p_antenna_ecef_m
    return p_antenna_ecef_m - R_ecef_enu(fix.lat_deg, fix.lon_deg) @ R_NED_ENU.T @ fix.R_ned_body @ lever


def run_replay(cfg: AppConfig, dataset_dir: Path, out_dir: Path, max_frames: int | None = None,
               progress: Callable[[int, int, str], None] | None = None, repeatable: bool = False,
               deny: GnssDenial | None = None, gis_model: Path | None = None, realtime: bool = False) -> dict:
    """Offline replay of a dataset: GNSS judged by the same monitor as live, no autopilot.
    ``repeatable``: as in fly_sim. ``deny``: GNSS withheld over a span (GnssDenial), and the
    fixes sent meanwhile judged against it (summary ``against_withheld_gnss``). ``gis_model``:
    the GIS model to use instead of the files site.yaml names. ``realtime``: each frame goes to
    the pipeline no earlier than its recorded time after the first frame (wall clock), as a
    camera delivers them, so mapping and fine-tuning get the idle time they would get in flight
    (without it the loop runs as fast as it can and they compete with it for the cores); a frame
    reached late is still processed, and summary ``realtime`` counts those more than one frame
    interval late. Not with ``repeatable`` (which waits for mapping and fine-tuning instead)."""
    from companion.dataset import read_dataset

    if realtime and repeatable:
        raise ValueError("realtime and repeatable replays exclude each other: a repeatable replay waits "
                         "for local mapping and fine-tuning at every frame, a real-time one never waits for them")
    ds = read_dataset(dataset_dir, None if gis_model is None else [gis_model])
    if not ds.gis_files:
        raise ValueError(f"dataset {dataset_dir} lists no GIS model file (site.yaml gis)")
    n = ds.n_frames if max_frames is None else min(ds.n_frames, max_frames)
    if deny is not None:
        deny = replace(deny, t0_s=float(ds.frame_t_s[0]))
        last_s = float(ds.frame_t_s[n - 1] - ds.frame_t_s[0])
        if deny.from_s >= last_s:
            raise ValueError(f"GNSS denial from {deny.from_s:g} s: the replayed frames end {last_s:.1f} s after the first")
    model = _load_first_model(ds.gis_files, cfg)
    localizer = build_localizer(cfg, ds.camera, ds.T_body_cam, model, repeatable=repeatable, p_body_gnss_m=ds.p_body_gnss_m)
    monitor = GnssMonitor(cfg.switching)
    run = RunLog(denial=deny)
    lost_since: float | None = None
    last_att = None
    late_ms: list[float] = []  # realtime: how late each frame reached the pipeline
    t_wall0: float | None = None
    t_loop0 = time.perf_counter()
    try:
        for k, step in enumerate(ds.steps()):
            if k >= n:
                break
            if realtime:
                now = time.perf_counter()
                if t_wall0 is None:
                    t_wall0 = now
                due = t_wall0 + float(step.frame.t_s - ds.frame_t_s[0])
                if due > now:
                    time.sleep(due - now)
                late_ms.append(max(0.0, (time.perf_counter() - due) * 1e3))
            for s in step.gnss:
                run.gnss_ecef_m.append((s.t_s, gnss_ecef(s), s.fix_type >= 3))
                monitor.on_sample(no_fix_sample(s.t_s) if deny is not None and deny.covers(s.t_s) else s)
            status = monitor.status(step.frame.t_s)
            good = status.quality is GnssQuality.GOOD
            if not good and lost_since is None:
                lost_since = step.frame.t_s
                run.takeover_t_s = run.takeover_t_s or step.frame.t_s
                run.switch_events.append((step.frame.t_s, f"GNSS {status.quality.value}: {'; '.join(status.reasons)}"))
            elif good and lost_since is not None:
                lost_since = None
                run.switch_events.append((step.frame.t_s, "GNSS good again"))
            localizer.settle(step.frame.t_s)
            t0 = time.perf_counter()
            # the newest attitude up to 0.1 s old, as the service asks the bridge for it: a camera
            # faster than the autopilot's ATTITUDE stream has frames with no sample of their own
            last_att = step.attitude[-1] if step.attitude else last_att
            fresh = last_att is not None and step.frame.t_s - last_att.t_s <= ATTITUDE_MAX_AGE_S
            prior = attitude_prior(last_att) if fresh else None
            rec = localizer.process(PipelineInput(step.frame, status.sample, good, prior))
            monitor.on_vision_check(localizer.gnss_inconsistency())
            run.wall_track_ms.append((time.perf_counter() - t0) * 1e3)
            monitor.on_fix(rec.fix)
            run.records.append(rec)
            if step.truth is not None:
                run.truth_ecef_m[rec.seq] = step.truth.p_body_ecef_m
                run.truth_cam_ecef_m[rec.seq] = step.truth.p_ecef_m
            if progress is not None:
                progress(k + 1, n, "")
        localizer.settle(math.inf)
        run.alignment_events = list(localizer.events)
        if localizer.bootstrap.last_refusal:
            run.alignment_events.append((run.records[-1].t_s if run.records else 0.0,
                                         f"last GNSS bootstrap refusal: {localizer.bootstrap.last_refusal}"))
        run.finetune_ms = list(localizer.worker.wall_ms) if localizer.worker else []
        run.finetune_cpu_ms = list(localizer.worker.cpu_ms) if localizer.worker else []
        loop_s = time.perf_counter() - t_loop0
    finally:
        localizer.close()
    if deny is not None:
        ref = GnssReference.from_samples(ds.gnss)  # the whole track: a fix just before the end lies between two solutions
        for r in run.records:
            at = ref.at(r.fix.t_s) if r.fix is not None and deny.covers(r.fix.t_s) else None
            if at is not None:
                run.reference[r.seq] = (antenna_to_body(at[0], r.fix, ds.p_body_gnss_m), at[1])
    summary = summarize(run, name=f"replay {ds.name}")
    summary["pace"] = _pace("realtime" if realtime else "repeatable" if repeatable else "unpaced",
                            run.records[-1].t_s - run.records[0].t_s if run.records else 0.0, loop_s)
    if realtime:
        summary["realtime"] = _lateness(late_ms, 1.0 / ds.fps)
    summary["outputs"] = [str(p) for p in write_outputs(run, summary, out_dir, ds.origin, f"TerraSLAM replay of {ds.name}")]
    write_report(summary, out_dir / "report.json", out_dir / "report.md", title=f"TerraSLAM replay of {ds.name}")
    return summary


def _pace(mode: str, recorded_s: float, wall_s: float) -> dict:
    """How fast a replay ran against its recording: ``speed_x`` = recorded span / wall time of the
    loop. An ``unpaced`` replay faster than real time gives local mapping and fine-tuning less time
    per frame than in flight (docs/DATASET.md, "Will this board keep up?")."""
    return {"mode": mode, "recorded_s": float(recorded_s), "wall_s": float(wall_s),
            "speed_x": float(recorded_s / wall_s) if wall_s > 0 else float("nan")}


def _lateness(late_ms: list[float], frame_interval_s: float) -> dict:
    """A real-time replay's pacing: frames more than one frame interval late (the pipeline did
    not keep up with the camera there), the mean and largest lateness."""
    late = np.asarray(late_ms, float)
    return {"frames": int(late.size), "frame_interval_ms": 1e3 * frame_interval_s,
            "late_frames": int(np.sum(late > 1e3 * frame_interval_s)),
            "late_ms_mean": float(late.mean()) if late.size else 0.0, "late_ms_max": float(late.max(initial=0.0))}


def _load_first_model(paths: Iterable[Path], cfg: AppConfig) -> GisModel:
    errors = []
    for p in paths:
        try:
            return load_model(p, cfg.gis.sample_spacing_m, cfg.gis.footprint_ground)
        except Exception as e:  # try the next listed format; report all if none loads
            errors.append(f"{p}: {e}")
    raise ValueError("no GIS model could be loaded:\n  " + "\n  ".join(errors))
