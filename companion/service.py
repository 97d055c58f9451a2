"""`terraslam run`: the supervised service (camera → SLAM → GIS alignment → MAVLink).

One required stage runs the hot path (read the newest frame, track, globalise, hand the fix to the
bridge) and beats per frame, so systemd's watchdog is fed only while frames really flow. The
bridge runs its own receive thread; the fine-tuner its worker. Each accepted T_fine is written to
the GIS cache at once (a kill -9 runs no hooks) and again at clean shutdown.

Persistence (companion/persistence.py): a background thread saves the SLAM map with its current
alignment to ``<state_dir>/slam_map.npz`` every ``persistence.save_every_s``, soon after each
accepted alignment and at clean shutdown. On start, a saved map is loaded and SLAM relocalises in
it; its alignment (same map, same GIS site, not too old) is restored with an inflated covariance,
so fixes resume as soon as tracking does, also when GNSS is gone.

Recording (``recording.enabled``, companion/recorder.py): the frames the hot path tracked, every
GNSS and attitude message the bridge received and our fixes go to a dataset folder that
`terraslam replay` reads, for field trials.
"""
from __future__ import annotations

import logging
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from companion.config import AppConfig
from companion.logs import log_event, setup_logging
from companion.persistence import MapSaver, load_saved, load_survey, map_path, saved_site
from companion.pipeline import PipelineInput, SurveyArea, attitude_prior
from companion.supervisor import LatencyTracker, Stage, StageContext, Supervisor
from gis.types import AlignmentSource
from mavlink_bridge.types import GnssQuality, GnssStatus

if TYPE_CHECKING:
    from gis.cache import GisCache
    from gis.model import GisModel

log = logging.getLogger("terraslam.service")


def _open_camera(cfg: AppConfig):
    from companion.camera import open_sim_source, open_source

    if cfg.camera.source == "sim":
        from companion.sim import make_scenario

        scenario = make_scenario("nominal", fps=cfg.camera.fps)
        start = min(int(round(cfg.camera.sim_start_s * scenario.fps)), scenario.n_frames - 1)
        return open_sim_source(scenario.steps(start), scenario.camera, realtime=True), scenario.T_body_cam
    if cfg.camera.T_body_cam is None:
        raise ValueError("camera.T_body_cam (4x4 camera→body FRD mount) is required for a real camera")
    import numpy as np

    return open_source(cfg.camera), np.asarray(cfg.camera.T_body_cam, float)


def _accepted(a) -> tuple | None:
    """What identifies an accepted alignment (its source and acceptance time) across the copies
    that follow its points."""
    return None if a is None else (a.source, a.t_s)


def _survey_map(cache, camera, site_id: str):
    """The site's survey map with its T_rough (``terraslam align-offline``), or None: none stored,
    or one that cannot be used (logged with the reason; the service starts without it)."""
    from gis.cache import CacheCorrupt
    from slam.persist import MapFileError

    try:
        path = cache.survey_map(site_id)
        return None if path is None else load_survey(path, camera, site_id)
    except (CacheCorrupt, MapFileError) as e:
        log_event(log, "survey_map_unusable", f"not starting in the site's survey map: {e}", level=logging.WARNING)
        return None


def _restore_alignment(cfg: AppConfig, localizer, restored) -> None:
    h = restored.loaded.header
    if restored.survey:
        a = localizer.restore_alignment(restored.alignment, 0.0, cfg.persistence.restore_sigma_m, 0.0,
                                        source="from the site's survey map")
        m = restored.loaded.slam_map
        with m.lock:
            centres = np.array([kf.center for kf in m.keyframes.values()], float)
        localizer.watch_survey_area(SurveyArea(restored.alignment.T_ecef_slam.apply(centres), cfg.gis.survey_reach_m))
        log_event(log, "survey_map_loaded", f"starting in the site's survey map {restored.loaded.path} ({h.n_keyframes} "
                  f"keyframes, {h.n_points} points) with its T_rough (σ {restored.alignment.sigma_m:.2f} → {a.sigma_m:.2f} m); "
                  "relocalising", map_id=h.map_id, sigma_m=a.sigma_m)
        return
    what = (f"resuming in saved SLAM map {restored.loaded.path} ({h.n_keyframes} keyframes, {h.n_points} points, "
            f"saved {time.time() - h.created_wall_s:.0f} s ago); relocalising")
    if restored.alignment is None:
        log_event(log, "slam_map_resumed", f"{what}; alignment not restored: {restored.why_not}", map_id=h.map_id)
        return
    p = cfg.persistence
    a = localizer.restore_alignment(restored.alignment, restored.age_s, p.restore_sigma_m, p.restore_sigma_growth_mps)
    log_event(log, "slam_map_resumed", f"{what}; {a.source.value} alignment restored ({restored.age_s:.0f} s old, "
              f"σ {restored.alignment.sigma_m:.2f} → {a.sigma_m:.2f} m)", map_id=h.map_id, sigma_m=a.sigma_m)


def _open_recorder(cfg: AppConfig, camera, T_body_cam, model, site_id: str, model_file: Path):
    """The flight recorder when ``recording.enabled`` (companion/recorder.py); None, logged, when its
    folder cannot be made: a recorder problem never stops the service."""
    if not cfg.recording.enabled:
        return None
    from companion.recorder import open_recording

    root = cfg.recording.dir or cfg.supervisor.state_dir / "recordings"
    try:
        return open_recording(root, cfg.recording, camera, T_body_cam, cfg.camera.fps, model.origin,
                              [model_file], site_id, cfg.mavlink.gnss_antenna_m)
    except OSError as e:
        log_event(log, "recording_unavailable", f"flight recorder off for this run: {e}", level=logging.ERROR)
        return None


def _restore_georef(cache, site_id: str, localizer) -> int:
    """Earlier flights' evidence on this model's georeference (gis.align.georef) into the
    localizer; returns how many registrations it holds. Corrupt evidence is logged and left out:
    the flight starts as if it were the first at the site (the model as configured)."""
    from gis.cache import CacheCorrupt

    try:
        ev = cache.load_georef(site_id)
    except CacheCorrupt as e:
        log_event(log, "georef_unreadable", f"{e}; starting without it", level=logging.ERROR)
        return -1
    if ev is None:
        return 0
    c = localizer.restore_georef(ev)
    log_event(log, "georef_restored", f"GIS model georeference evidence of earlier flights at site {site_id}: {ev.n} registrations vs GNSS; "
              + (c.describe() + ": corrected" if c is not None else "model as configured"), n=ev.n)
    return ev.n


class NoPositionError(RuntimeError):
    """gis.site: auto found no rough position to look the site up at."""


ORIGIN_GRACE_S = 5.0  # the EKF origin stands in for a position once known this long without trusted GNSS


def wait_for_position(bridge, timeout_s: float, poll_s: float = 0.2,
                      origin_grace_s: float = ORIGIN_GRACE_S) -> tuple[tuple[float, float, str] | None, GnssStatus]:
    """Where the autopilot is, roughly enough to choose a GIS site: (lat, lon, what it is) and the
    GNSS monitor's last verdict. Its first GNSS position the monitor trusts; else, once its EKF
    origin (GPS_GLOBAL_ORIGIN) has been known for ``origin_grace_s`` with GNSS still not trusted
    (jammed at a restart in flight: the autopilot keeps the origin it started with), that origin;
    None when neither came within ``timeout_s`` (systemd is told each 10 s that startup goes on,
    and why)."""
    from companion import notify

    deadline = time.monotonic() + timeout_s
    next_note, origin_since = 0.0, None
    while True:
        st = bridge.gnss_status()
        now = time.monotonic()
        if st.trusted and st.sample is not None:
            return (st.sample.lat_deg, st.sample.lon_deg, "trusted GNSS"), st
        origin = bridge.ekf_origin()
        origin_since = None if origin is None else (origin_since or now)
        if origin is not None and now - origin_since >= origin_grace_s:
            return (origin.lat0_deg, origin.lon0_deg, f"the autopilot's EKF origin, GNSS {_why(st)}"), st
        if now >= deadline:
            return None, st
        if now >= next_note:
            notify.status(f"gis.site auto: waiting for a trusted GNSS position ({_why(st)}); {deadline - now:.0f} s left")
            notify.extend_timeout(30.0)
            next_note = now + 10.0
        time.sleep(poll_s)


def _why(st: GnssStatus) -> str:
    return "; ".join(st.reasons) or st.quality.value


def choose_site(cfg: AppConfig, cache: GisCache, bridge) -> str:
    """``gis.site: auto``: the GIS site this flight uses (TerraSLAM §6: Pre-fetch the cached site
    covering the rough position, else Fetch it from ``gis.fetch_sources`` and SaveCache). The rough
    position is, in this order: ``gis.rough_position_deg``; else, with no position needed, the
    site of the saved SLAM map when its alignment is fresh enough to restore (a restart in flight,
    GNSS perhaps jammed); else the autopilot's first trusted GNSS position, or its EKF origin when
    GNSS stays untrusted (wait_for_position; the bridge starts here for it), within
    ``gis.position_wait_s``. Raises NoPositionError, gis.providers.NoSiteError,
    FetchError or GisFormatError."""
    from companion import notify
    from gis.providers import site_at

    g = cfg.gis
    saved = saved_site(cfg) if cfg.persistence.enabled and g.rough_position_deg is None else None
    if g.rough_position_deg is not None:
        (lat, lon), where = g.rough_position_deg, "gis.rough_position_deg"
    elif saved is not None and _cached(cache, saved[0]):
        log_event(log, "gis_site", f"GIS site {saved[0]}: the saved SLAM map's (its alignment is {saved[1]:.0f} s old)",
                  site=saved[0])
        return saved[0]
    else:
        found, st = wait_for_position(bridge.start(), g.position_wait_s)
        if found is None:
            raise NoPositionError(f"gis.site auto: no trusted GNSS position or EKF origin from the autopilot within "
                                  f"gis.position_wait_s ({g.position_wait_s:g} s; GNSS {_why(st)}) and no "
                                  "gis.rough_position_deg: cannot choose the GIS site")
        lat, lon, where = found

    def progress(line: str) -> None:
        log.info("fetching the GIS site: %s", line)
        notify.status(f"gis.site auto: fetching ({line})")
        notify.extend_timeout(120.0)

    site_id, how = site_at(cache, lat, lon, g, progress)
    log_event(log, "gis_site", f"GIS site {site_id} ({how}) covers {lat:.6f}, {lon:.6f} ({where})", site=site_id)
    return site_id


def _cached(cache: GisCache, site_id: str) -> bool:
    try:
        cache.model_file(site_id)
    except KeyError:
        return False
    return True


class _RecorderTaps:
    """What the bridge hands the flight recorder. The bridge may start before the recorder opens
    (gis.site: auto waits for its GNSS to choose the site the recording names); what comes before
    that, before any frame, has nothing to be recorded with."""

    def __init__(self) -> None:
        self.recorder = None

    def gnss(self, sample) -> None:
        if self.recorder is not None:
            self.recorder.on_gnss(sample)

    def attitude(self, att) -> None:
        if self.recorder is not None:
            self.recorder.on_attitude(att)

    def mavlink(self, data: bytes) -> None:
        if self.recorder is not None:
            self.recorder.on_mavlink(data)


def load_gis_model(cfg: AppConfig, cache: GisCache, site_id: str | None = None) -> tuple[GisModel, str, Path]:
    """The GIS model, mapped from the GIS cache (gis.cache: paged in only where it is cropped; a
    model larger than the board's RAM works), its site id and the file a replay loads it from.
    ``site_id`` (``gis.site``, or the one ``choose_site`` chose): that site as `gis import` / `gis
    fetch` stored it (GisFormatError when it is not there or fails its hash). ``gis.model``: a file
    already imported unchanged with the same settings is not parsed again (a LAZ or a tileset takes
    minutes); else it is loaded, saved and mapped back, so the parsed copy is freed; a cached copy
    that fails its hash check is imported again."""
    from gis.cache import CacheCorrupt
    from gis.loaders import load_model, source_key
    from gis.model import GisFormatError

    site_id = site_id if site_id is not None else cfg.gis.site
    if site_id is not None:
        try:
            return cache.load_model(site_id), site_id, cache.model_file(site_id)
        except KeyError:
            raise GisFormatError(cache.root, f"no site {site_id!r} in the GIS cache (`terraslam gis ls` lists them)") from None
        except CacheCorrupt as e:
            raise GisFormatError(cache.root, str(e)) from None
    path, spacing, ground = cfg.gis.model.expanduser(), cfg.gis.sample_spacing_m, cfg.gis.footprint_ground
    key = source_key(path, spacing, ground)
    site_id = cache.imported(key)
    if site_id is not None:
        try:
            model = cache.load_model(site_id)
            log_event(log, "gis_model", f"{path}: unchanged since imported as site {site_id}; mapped from the cache")
            return model, site_id, path
        except CacheCorrupt as e:
            log_event(log, "gis_cache_corrupt", f"{e}; importing {path} again", level=logging.WARNING)
    site_id = cache.save_model(load_model(path, spacing, ground), source_key=key)
    return cache.load_model(site_id), site_id, path


KERNEL_COMPILE_TIMEOUT_S = 600.0  # start-up time granted to compile fine-tuning's kernels (8.5 s on a 2-core x86 VM)


def _compile_kernels() -> None:
    """Fine-tuning's numba kernels, compiled (the first start; NUMBA_CACHE_DIR keeps them) or
    loaded from numba's cache (0.3 s) before the localizer is built, with the start timeout
    extended meanwhile: a small board compiles for much longer than the x86 VM's 8.5 s, and with
    the GIS model's loading that could pass TimeoutStartSec (120 s) on the first start."""
    from companion import notify
    from gis.align.fine import compile_kernels

    notify.status("starting: fine-tuning kernels (numba: compiled at the first start, cached after)")
    notify.extend_timeout(KERNEL_COMPILE_TIMEOUT_S)
    t0 = time.monotonic()
    compile_kernels()
    log.info("fine-tuning kernels ready in %.1f s", time.monotonic() - t0)


def run_service(cfg: AppConfig) -> int:
    """Run until SIGTERM/SIGINT or a required stage fails; returns the process exit code."""
    from companion.app import build_localizer, open_journal
    from gis.cache import CacheCorrupt, GisCache
    from gis.config import AUTO_SITE
    from gis.model import GisFormatError
    from gis.providers import FetchError, NoSiteError
    from mavlink_bridge.bridge import Bridge

    setup_logging(cfg.logging)
    if cfg.gis.model is None and cfg.gis.site is None:
        log.error("neither gis.model nor gis.site is set: the service needs a GIS model file (any supported format), "
                  "a site of the GIS cache or gis.site: auto")
        return 2
    cache = GisCache(cfg.gis.cache_dir.expanduser())
    taps = _RecorderTaps() if cfg.recording.enabled else None
    bridge = Bridge(cfg.mavlink, cfg.switching, on_gnss=taps and taps.gnss, on_attitude=taps and taps.attitude,
                    on_mavlink=taps and taps.mavlink)  # started once the site is known, or by choose_site for its GNSS
    try:
        site = choose_site(cfg, cache, bridge) if cfg.gis.site == AUTO_SITE else None
        model, site_id, model_file = load_gis_model(cfg, cache, site)
    except (GisFormatError, OSError, NoSiteError, CacheCorrupt) as e:  # missing, unreadable or corrupt: a config problem, not a crash
        log.error("cannot load the GIS model (gis.%s): %s", "site" if cfg.gis.site else "model", e)
        bridge.close()
        return 2
    except (NoPositionError, FetchError) as e:  # GNSS or the network may be there after a restart
        log.error("cannot choose the GIS site: %s", e)
        bridge.close()
        return 1
    if model is not None:
        _compile_kernels()
    source, T_body_cam = _open_camera(cfg)
    restored = load_saved(cfg, source.camera_model, site_id) if cfg.persistence.enabled else None
    if cfg.gis.use_survey_map and (restored is None or restored.alignment is None):
        restored = _survey_map(cache, source.camera_model, site_id) or restored
    localizer = build_localizer(cfg, source.camera_model, T_body_cam, model,
                                initial_map=restored.loaded if restored else None, p_body_gnss_m=cfg.mavlink.gnss_antenna_m,
                                reloc_timeout_s=cfg.gis.survey_reloc_timeout_s if restored and restored.survey else None,
                                keep_loaded_map=bool(restored and restored.survey))
    # the alignment timeline (accepted, rejected, dropped, withheld, survey map given up) in the journal
    localizer.on_event = lambda t_s, text: log_event(log, "alignment", text, t_s=round(t_s, 3))
    if restored is not None:
        _restore_alignment(cfg, localizer, restored)
    georef_n = _restore_georef(cache, site_id, localizer)
    saver = (MapSaver(localizer.slam, localizer, map_path(cfg), site_id, cfg.persistence.save_every_s).start()
             if cfg.persistence.enabled else None)
    recorder = _open_recorder(cfg, source.camera_model, T_body_cam, model, site_id, model_file)
    if taps is not None:
        taps.recorder = recorder
    if recorder is not None and localizer.worker is not None:  # the registrations too, for gis.align.replay
        try:
            localizer.worker.journal = open_journal(recorder.out / "registrations", model_file, cfg, model.origin)
        except OSError as e:
            log_event(log, "recording_unavailable", f"registration journal off for this run: {e}", level=logging.ERROR)
    bridge.start()
    latency = LatencyTracker()
    saved = {"t": None, "alignment": _accepted(localizer.alignment)}

    def save_fine() -> None:
        a = localizer.alignment
        if a is not None and a.source is AlignmentSource.FINE and a.t_s != saved["t"]:
            cache.save_transform(site_id, "fine", a.T_ecef_slam, {"t_s": a.t_s, "sigma_m": a.sigma_m, "fitness": a.fitness})
            saved["t"] = a.t_s
            log_event(log, "t_fine_saved", f"T_fine saved to the GIS cache (site {site_id})", sigma_m=a.sigma_m)

    def save_georef() -> None:
        """The evidence on the model's georeference, whenever a registration added to it."""
        nonlocal georef_n
        if localizer.georef is None or localizer.georef.n == georef_n:  # (every frame: no copy unless it grew)
            return
        ev = localizer.georef_evidence()
        cache.save_georef(site_id, ev)
        georef_n = ev.n
        log_event(log, "georef_saved", f"GIS model georeference evidence saved ({ev.n} registrations vs GNSS, site {site_id})",
                  n=ev.n)

    def alignment_changed() -> None:
        """A newly accepted alignment goes to disk with the map soon (by the saver thread). One that
        only follows its points (re-expressed after local mapping moved them, several times a
        second) waits for the periodic save: requesting one each time rewrote the whole map
        (4-5 MB at a survey site) about every second."""
        key = _accepted(localizer.alignment)
        if key != saved["alignment"]:
            saved["alignment"] = key
            if key is not None and saver is not None:
                saver.request()

    def hot_path(ctx: StageContext) -> None:
        while not ctx.stop.is_set():
            frame = source.read(timeout_s=0.5)
            if frame is None:
                if source.eof:
                    return
                continue
            epoch = source.playback_epoch_s
            if not source.live and epoch is not None:
                # sim/file playback stamps frames with the file's time; the bridge (fix age), the GNSS
                # monitor and the attitude prior all run on the monotonic clock, as a live camera does
                frame = replace(frame, t_s=frame.t_s + epoch)
            grab = source.capture_info(frame.seq)
            latency.start(frame.seq, grab.grab_t_s if grab else frame.t_s)
            status = bridge.gnss_status()
            prior = attitude_prior(bridge.attitude(max_age_s=0.1))
            rec = localizer.process(PipelineInput(frame, status.sample, status.quality is GnssQuality.GOOD, prior))
            bridge.vision_check(localizer.gnss_inconsistency())
            latency.mark(frame.seq, "track")
            bridge.submit_fix(rec.fix)
            latency.mark(frame.seq, "wire")
            latency.finish(frame.seq)
            if recorder is not None:
                recorder.on_frame(frame, rec.fix)
            save_fine()
            save_georef()
            alignment_changed()
            ctx.beat()

    stage = Stage("hot-path", hot_path, deadline_s=max(2.0, 3 * cfg.camera.stall_timeout_s),
                  restart_limit=cfg.supervisor.stage_restart_limit)
    sup = Supervisor([stage], watchdog=cfg.supervisor.watchdog)
    if recorder is not None:
        sup.on_shutdown("close recording", recorder.close)  # hooks run newest first: this one last
    sup.on_shutdown("close camera", source.close)
    sup.on_shutdown("close bridge", bridge.close)
    sup.on_shutdown("close localizer", localizer.close)
    sup.on_shutdown("save T_fine", save_fine)
    sup.on_shutdown("save georeference evidence", save_georef)
    if saver is not None:
        sup.on_shutdown("save SLAM map", saver.close)
    sup.install_signal_handlers()
    sup.start("tracking")
    log_event(log, "ready", "service ready", source=cfg.camera.source, mavlink=cfg.mavlink.connect)
    last_log = [time.monotonic()]

    def status() -> str:
        now = time.monotonic()
        a = localizer.alignment
        off = localizer.gnss_offset_m(now)
        text = (f"{bridge.state.value}; GNSS {bridge.gnss_status().quality.value}; alignment {a.source.value if a else 'none'}"
                + ("" if off is None else f"; GNSS {off:.1f} m from ours"))
        if now - last_log[0] > 10.0:
            log.info("%s; latency: %s", text, latency.format())
            last_log[0] = now
        return text

    return sup.run(status=status)
