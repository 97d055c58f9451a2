"""The service's SLAM map persistence: where the map lives, what goes with it, when it is saved,
and what is restored after a restart (docs/SERVICE.md "Restart during a GNSS outage").

One file, ``<supervisor.state_dir>/slam_map.npz`` (slam/persist.py: atomic write, verified load),
holds the SLAM map and, as an attachment covered by the same content hash, the alignment that maps
*that* map to ECEF (with the GIS site it was made for and its wall-clock acceptance time). The
alignment is attached only when its (map_id, reset_counter) is the saved map's, and restored only
when they still agree and the site is this run's, so a map and an alignment of another map can
never be paired.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from companion.config import AppConfig
from companion.logs import log_event
from gis.sim3 import Sim3
from gis.types import Alignment, AlignmentSource
from slam.persist import LoadedMap, MapFileError, MapHeader, clock_offset_s, load_map_file, read_map_header
from slam.types import CameraModel

log = logging.getLogger("terraslam.persistence")

MAP_FILE = "slam_map.npz"
SURVEY_ALIGNMENT = "survey_alignment"  # header attachment of a survey map: its T_rough (alignment_json)


def map_path(cfg: AppConfig) -> Path:
    return cfg.supervisor.state_dir.expanduser() / MAP_FILE


# --- the alignment as JSON -----------------------------------------------------------------------
def alignment_json(a: Alignment, site_id: str, now_mono_s: float | None = None, now_wall_s: float | None = None) -> dict:
    """``a`` as JSON, with the site and the wall-clock time it was accepted (its t_s is monotonic)."""
    mono = time.monotonic() if now_mono_s is None else now_mono_s
    wall = time.time() if now_wall_s is None else now_wall_s
    return {
        "site_id": site_id, "accepted_wall_s": wall - (mono - a.t_s),
        "T_ecef_slam": a.T_ecef_slam.matrix().tolist(), "source": a.source.value, "t_s": a.t_s,
        "reset_counter": a.reset_counter, "map_id": a.map_id, "information_6x6": np.asarray(a.information_6x6).tolist(),
        "sigma_m": a.sigma_m, "fitness": a.fitness, "rmse_m": a.rmse_m, "n_points": a.n_points,
        "center_slam": None if a.center_slam is None else np.asarray(a.center_slam, float).tolist(),
        "scale_sigma": a.scale_sigma, "drift_free_radius_m": a.drift_free_radius_m,
    }


def alignment_from_json(d: dict, t_offset_s: float = 0.0) -> Alignment:
    """The Alignment of ``alignment_json`` (t_s moved by ``t_offset_s`` onto this process's clock)."""
    info = np.asarray(d["information_6x6"], float)
    if info.shape != (6, 6) or not np.isfinite(info).all():
        raise ValueError("information_6x6 is not a finite 6x6 matrix")
    return Alignment(
        T_ecef_slam=Sim3.from_matrix(np.asarray(d["T_ecef_slam"], float)), source=AlignmentSource(d["source"]),
        t_s=float(d["t_s"]) + t_offset_s, reset_counter=int(d["reset_counter"]), information_6x6=info,
        sigma_m=float(d["sigma_m"]), fitness=float(d["fitness"]), rmse_m=float(d["rmse_m"]), n_points=int(d["n_points"]),
        map_id=int(d["map_id"]), center_slam=None if d["center_slam"] is None else np.asarray(d["center_slam"], float),
        scale_sigma=float(d["scale_sigma"]), drift_free_radius_m=float(d.get("drift_free_radius_m", 0.0)),
    )


# --- restore -------------------------------------------------------------------------------------
@dataclass
class Restored:
    """What a restart found: the map to resume in, and its alignment (None, with the reason, when
    the alignment cannot be used)."""

    loaded: LoadedMap
    alignment: Alignment | None
    age_s: float  # wall-clock seconds since the alignment was accepted (0 without one, or a survey's)
    why_not: str | None = None
    survey: bool = False  # the site's survey map (align-offline), not this service's own saved map


def load_saved(cfg: AppConfig, camera: CameraModel, site_id: str) -> Restored | None:
    """The saved map (keyframe times moved onto this clock) and its alignment if it is for this GIS
    site, this map and not older than ``persistence.max_restore_age_s``; None when there is no
    usable map: no file (first start), or a file that cannot be used (logged with the reason; the
    file is kept as ``slam_map.npz.bad`` for inspection and a fresh map starts)."""
    path = map_path(cfg)
    if not path.exists():
        return None
    try:
        loaded = load_map_file(path, camera)
    except MapFileError as e:
        bad = path.with_name(path.name + ".bad")
        try:
            path.replace(bad)
            kept = f"file moved to {bad}"
        except OSError as oe:
            kept = f"could not move it aside: {oe}"
        log_event(log, "slam_map_unusable", f"{e}; starting a fresh SLAM map ({kept})",
                  level=logging.WARNING, path=str(path))
        return None
    offset_s = clock_offset_s(loaded.header)
    loaded.rebase_times(offset_s)
    d = loaded.header.attachments.get("alignment")
    if d is None:
        return Restored(loaded, None, 0.0, "no alignment was saved with the map")
    age_s = time.time() - float(d["accepted_wall_s"])
    try:
        a = alignment_from_json(d, offset_s)
    except (KeyError, TypeError, ValueError) as e:
        return Restored(loaded, None, age_s, f"saved alignment unreadable ({e})")
    if d.get("site_id") != site_id:
        return Restored(loaded, None, age_s, f"saved alignment is for GIS site {d.get('site_id')!r}, this run uses {site_id!r}")
    why_not = _not_restorable(cfg, loaded.header, a.map_id, a.reset_counter, age_s)
    return Restored(loaded, a if why_not is None else None, age_s, why_not)


def _not_restorable(cfg: AppConfig, header: MapHeader, map_id: int, reset_counter: int, age_s: float) -> str | None:
    """Why an alignment saved with the map in ``header`` (of map ``map_id``/``reset_counter``,
    accepted ``age_s`` ago) is not restored whatever the site; None when it is."""
    if (map_id, reset_counter) != (header.map_id, header.reset_counter):
        return "saved alignment belongs to another map"
    if age_s > cfg.persistence.max_restore_age_s:
        return f"saved alignment is {age_s:.0f} s old (persistence.max_restore_age_s {cfg.persistence.max_restore_age_s:g} s)"
    return None


def saved_site(cfg: AppConfig) -> tuple[str, float] | None:
    """(GIS site, age s) of the alignment saved with the map when ``load_saved`` would restore it
    for that site (its map's, not older than ``persistence.max_restore_age_s``); None otherwise,
    also for an unreadable file (``load_saved`` reports that). Reads the header only: no camera
    needed."""
    try:
        h = read_map_header(map_path(cfg))
        d = h.attachments["alignment"]
        age_s = time.time() - float(d["accepted_wall_s"])
        ok = isinstance(d["site_id"], str) and _not_restorable(cfg, h, int(d["map_id"]), int(d["reset_counter"]), age_s) is None
    except (MapFileError, KeyError, TypeError, ValueError):
        return None
    return (d["site_id"], age_s) if ok else None


def load_survey(path: Path, camera: CameraModel, site_id: str) -> Restored:
    """A site's survey SLAM map (``terraslam align-offline``, stored in the GIS cache) with its
    T_rough, to start in without GNSS. The alignment has no age: it registers the survey map to the
    GIS model, which does not drift with time. Raises MapFileError when the file cannot be used or
    carries no T_rough for this site and map (the caller logs it and starts without it)."""
    loaded = load_map_file(path, camera)
    d = loaded.header.attachments.get(SURVEY_ALIGNMENT)
    if d is None:
        raise MapFileError(path, "no T_rough attached (not a survey map of align-offline)")
    try:
        a = alignment_from_json(d)
    except (KeyError, TypeError, ValueError) as e:
        raise MapFileError(path, f"its T_rough is unreadable ({e})") from None
    if d.get("site_id") != site_id:
        raise MapFileError(path, f"its T_rough is for GIS site {d.get('site_id')!r}, this run uses {site_id!r}")
    if (a.map_id, a.reset_counter) != (loaded.header.map_id, loaded.header.reset_counter):
        raise MapFileError(path, "its T_rough belongs to another map")
    # The survey's keyframe times are its dataset's clock: moved so that the newest is a second
    # ago on this process's monotonic clock (the camera's), as a map saved by this service would
    # be. (Keyframe times later than the frames' had the pose 45 m off within 20 s.)
    now_s = time.monotonic()
    loaded.rebase_times(now_s - 1.0 - max(kf.t_s for kf in loaded.slam_map.keyframes.values()))
    return Restored(loaded, replace(a, t_s=now_s - 1.0), 0.0, survey=True)


# --- save ----------------------------------------------------------------------------------------
class MapSaver:
    """Saves the SLAM map (with its current alignment) in a background thread: every
    ``save_every_s``, soon after ``request()`` (an alignment was accepted), and once more on
    ``close()``. Never on the hot path: SlamSystem.save_map copies the map under its lock (local
    mapping waits a few ms) and writes without it. A failed save is logged and retried next time.
    Nothing is written while neither the map has new keyframes nor the alignment changed (a
    hovering or grounded vehicle does not rewrite tens of MB of flash every period)."""

    def __init__(self, slam, localizer, path: Path, site_id: str, save_every_s: float) -> None:
        self.slam, self.localizer, self.path, self.site_id = slam, localizer, path, site_id
        self.save_every_s = save_every_s
        self.saves: deque = deque(maxlen=100)  # SavedMap of the latest saves (sizes and times)
        self._saved_revision: tuple | None = None  # (map revision, alignment) of the file on disk
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()  # one save at a time (thread vs close)
        self._thread = threading.Thread(target=self._run, name="map-saver", daemon=True)

    def start(self) -> "MapSaver":
        self._thread.start()
        return self

    def request(self) -> None:
        self._wake.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(self.save_every_s)
            self._wake.clear()
            if not self._stop.is_set():
                self.save()

    def attachments(self) -> dict:
        a = self.localizer.alignment
        if a is None or (a.map_id, a.reset_counter) != self.slam.current_map_key():
            return {}
        return {"alignment": alignment_json(a, self.site_id)}

    def save(self):
        """Write the map (with its alignment) unless the file on disk already holds this state;
        returns the SavedMap, or None when nothing was written."""
        with self._lock:
            atts = self.attachments()
            a = atts.get("alignment")
            revision = (self.slam.map_revision(), None if a is None else (a["t_s"], a["sigma_m"]))
            if revision == self._saved_revision:
                return None
            try:
                info = self.slam.save_map(self.path, atts)
            except Exception:  # disk full, permissions...: keep flying, try again next period
                log.exception("saving the SLAM map to %s failed", self.path)
                return None
            if info is not None:
                self._saved_revision = revision
        if info is not None:
            self.saves.append(info)
            log_event(log, "slam_map_saved", f"SLAM map saved to {info.path}: {info.n_keyframes} keyframes, {info.n_points} "
                      f"points, {info.n_bytes / 1e6:.1f} MB, lock {info.snapshot_ms:.0f} ms, write {info.write_ms:.0f} ms",
                      keyframes=info.n_keyframes, points=info.n_points, bytes=info.n_bytes,
                      with_alignment="alignment" in atts)
        return info

    def close(self) -> None:
        """Stop the thread and save once more (clean shutdown)."""
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=30)
        self.save()
