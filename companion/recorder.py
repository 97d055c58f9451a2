"""Flight recorder: what the pipeline is fed during `terraslam run`, written as a dataset
(docs/DATASET.md) that `terraslam replay DIR [--repeatable]` reads back.

A field trial is one flight; without its inputs a bad fix can be looked at only in the logs. The
recorder keeps what the hot path gave the pipeline, on the clock it used (the companion computer's
``time.monotonic()``, seconds):

    <recording.dir, default supervisor.state_dir/recordings>/flight-YYYYmmddTHHMMSSZ/
      dataset.yaml, site.yaml, camera.yaml, mount.yaml   the dataset's metadata (rewritten at close)
      images/frames.csv + images/NNNNNN.jpg|png          every frame the pipeline tracked, as delivered, numbered in order
                                                         (undistorted: camera.yaml is the delivered model)
      gnss.csv                                           every GNSS solution the bridge received
      attitude.csv                                       every ATTITUDE (+ barometer) the bridge received
      fixes.csv                                          what we computed per frame (not a replay input)
      mavlink.tlog                                       every MAVLink message received from and sent to the
                                                         autopilot (telemetry log: MAVExplorer, Mission Planner, QGC)

* The hot path only queues (``on_frame``); a writer thread encodes and writes. When the writer
  falls behind (slow SD card), frames are dropped from the recording, never delayed in the
  pipeline; ``dataset.yaml`` counts them and ``frames.csv`` keeps each frame's ``seq`` (gaps show).
* Rows are appended and flushed as they are written and fsync'ed every ``FSYNC_EVERY_S``; an image
  is on disk before its ``frames.csv`` row, so a recording cut by a kill or a power loss still reads.
* A full disk (free space under ``recording.min_free_mb``) or a write error stops the recording
  with a logged reason; the service goes on.
* ``site.yaml`` names the GIS model the service used by absolute path (copying a model of many
  km² on every flight is not the recorder's job), with the cache's content-addressed site id.

Samples whose time goes back (an autopilot's boot-time mapping that moved) are written at the
previous sample's time, as the dataset format needs, and counted.

``mavlink.tlog`` is the ground stations' telemetry log format (MAVProxy, Mission Planner and
QGroundControl write it, pymavlink and MAVExplorer read it): per message, its UNIX time in
microseconds as a big-endian uint64, then the message's wire bytes. It holds what the autopilot
made of our fixes (EKF status, its own position, STATUSTEXT) beside what we sent it; pymavlink's
own ``setup_logfile`` logs only received messages, hence the tap on both directions (Link).
``dataset.yaml`` gives ``unix_time_minus_clock_s`` to put it on the dataset's clock.
"""
from __future__ import annotations

import csv
import logging
import math
import os
import queue
import shutil
import struct
import threading
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import TextIO

import cv2
import numpy as np
import yaml

from companion.calibration import write_calibration
from companion.config import RecordingConfig
from companion.dataset import ATTITUDE_COLUMNS, FORMAT_VERSION, GNSS_COLUMNS, attitude_row, gnss_row, write_mount
from companion.evaluate import FIX_COLUMNS, fix_row
from companion.logs import log_event
from gis.geodesy import LocalFrame
from gis.types import GlobalFix
from mavlink_bridge.types import GnssSample, GpsFixType
from slam.types import CameraModel, Frame

log = logging.getLogger(__name__)

FSYNC_EVERY_S = 5.0        # how much a power loss may take (rows and images are flushed at once)
DISK_CHECK_EVERY_S = 2.0
NO_FIX_SIGMA_M = 10_000.0  # site.yaml rough position when no GNSS fix was recorded: the model origin, this unsure


@dataclass
class RecordingStats:
    frames: int = 0
    frames_dropped: int = 0          # the writer was behind: not in the recording (the pipeline had them)
    gnss: int = 0
    attitude: int = 0
    samples_retimed: int = 0         # written at the previous sample's time (their time went back)
    mavlink_messages: int = 0        # in mavlink.tlog
    stopped: str | None = None       # why the recording stopped before the service did


@dataclass
class _Csv:
    f: TextIO
    w: csv.writer
    last_t_s: float = -math.inf

    @classmethod
    def open(cls, path: Path, columns) -> "_Csv":
        f = path.open("w", newline="")
        w = csv.writer(f)
        w.writerow(columns)
        f.flush()
        return cls(f, w)

    def write(self, row: list) -> None:
        self.w.writerow(row)
        self.f.flush()


@dataclass
class _FrameItem:
    frame: Frame
    fix: GlobalFix | None


def _unique_dir(root: Path, stem: str) -> Path:
    out, k = root / stem, 1
    while out.exists():
        k += 1
        out = root / f"{stem}-{k}"
    return out


def _disk_short(path: Path, min_free_mb: float) -> str | None:
    """Why the disk holding ``path`` is too full to record on, or None."""
    free_mb = shutil.disk_usage(path).free / 2**20
    return f"{path}: {free_mb:.0f} MB free, under recording.min_free_mb {min_free_mb:g}" if free_mb < min_free_mb else None


def _write_yaml(path: Path, doc: dict) -> None:
    """Written whole or not at all (a cut write must not leave half a YAML file)."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(yaml.safe_dump(doc, sort_keys=False))
    os.replace(tmp, path)


class FlightRecorder:
    """One recording: ``open_recording`` → ``on_frame`` / ``on_gnss`` / ``on_attitude`` → ``close``."""

    def __init__(self, out: Path, cfg: RecordingConfig, fps: float, origin: LocalFrame, gis_files: list[Path],
                 site_id: str | None):
        self.out, self.cfg, self.fps, self.origin = out, cfg, fps, origin
        self.gis_files, self.site_id = [Path(p).resolve() for p in gis_files], site_id
        self.stats = RecordingStats()
        self._ext = "." + cfg.image_format
        self._params = [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality] if cfg.image_format == "jpg" else [cv2.IMWRITE_PNG_COMPRESSION, 1]
        self._frames: queue.Queue[_FrameItem | None] = queue.Queue(maxsize=cfg.queue_frames)
        self._samples: list[GnssSample | object] = []
        self._mavlink: list[tuple[float, bytes]] = []   # (UNIX time s, wire bytes)
        self._lock = threading.Lock()        # _samples, _mavlink, stats
        self._unix_minus_clock_s = time.time() - time.monotonic()
        self._first_fix: GnssSample | None = None
        self._started_utc = datetime.now(timezone.utc)
        self._last_drop_log_s = -math.inf
        (out / "images").mkdir(parents=True)
        self._csv_frames = _Csv.open(out / "images" / "frames.csv", ("seq", "t_s", "filename"))
        self._csv_gnss = _Csv.open(out / "gnss.csv", GNSS_COLUMNS)
        self._csv_att = _Csv.open(out / "attitude.csv", ATTITUDE_COLUMNS)
        self._csv_fix = _Csv.open(out / "fixes.csv", ("seq",) + FIX_COLUMNS)
        self._tlog = (out / "mavlink.tlog").open("wb")
        self._files = (self._csv_frames.f, self._csv_gnss.f, self._csv_att.f, self._csv_fix.f, self._tlog)
        self._thread = threading.Thread(target=self._run, name="flight-recorder", daemon=True)

    # ---- any thread ----------------------------------------------------------------------
    def on_frame(self, frame: Frame, fix: GlobalFix | None) -> None:
        """Hot path: queue the frame the pipeline just processed (and its fix); never blocks."""
        if self.stats.stopped is not None:
            return
        try:
            self._frames.put_nowait(_FrameItem(frame, fix))
        except queue.Full:
            with self._lock:
                self.stats.frames_dropped += 1
                n = self.stats.frames_dropped
            now = time.monotonic()
            if now - self._last_drop_log_s > 10.0:
                self._last_drop_log_s = now
                log_event(log, "recording_behind", f"flight recorder behind the camera: {n} frames not recorded so far "
                          f"(the pipeline had them); a faster disk, image_format jpg or a lower jpeg_quality helps",
                          level=logging.WARNING, frames_dropped=n)

    def on_gnss(self, sample: GnssSample) -> None:
        """Every GNSS solution the bridge received (its receive thread)."""
        if self.stats.stopped is None:
            with self._lock:
                self._samples.append(sample)

    def on_attitude(self, attitude) -> None:
        """Every attitude (VehicleAttitude) the bridge received (its receive thread)."""
        if self.stats.stopped is None:
            with self._lock:
                self._samples.append(attitude)

    def on_mavlink(self, buf: bytes) -> None:
        """The wire bytes of a MAVLink message received or sent (Link's tap: the receive thread,
        or whichever thread sent it)."""
        if self.stats.stopped is None:
            # UNIX time as the recording began plus the monotonic clock since, not time.time(): a
            # board without a real-time clock (Raspberry Pi class) steps its wall clock when NTP or
            # GPS time arrives, which would tear the log's times away from the frames' (and send
            # them backwards); this way they stay on the frames' clock, offset as dataset.yaml says.
            with self._lock:  # stamped under the lock: the log's times never go back between threads
                self._mavlink.append((self._unix_minus_clock_s + time.monotonic(), bytes(buf)))

    # ---- lifecycle -----------------------------------------------------------------------
    def start(self) -> "FlightRecorder":
        self._write_meta(final=False)
        self._thread.start()
        log_event(log, "recording_started", f"recording the flight to {self.out}", path=str(self.out))
        return self

    def close(self) -> RecordingStats:
        """Write what is queued, then the final metadata. Idempotent."""
        if self._thread.is_alive():
            self._frames.put(None)
            self._thread.join()
        try:
            for f in self._files:
                if not f.closed:
                    f.flush()
                    os.fsync(f.fileno())
                    f.close()
            self._write_meta(final=True)
        except OSError as e:  # the disk went away: what was written stays readable up to its last fsync
            log.error("flight recorder: closing %s failed: %s", self.out, e)
        s = self.stats
        log_event(log, "recording_closed", f"recording {self.out}: {s.frames} frames ({s.frames_dropped} dropped), "
                  f"{s.gnss} GNSS, {s.attitude} attitude samples, {s.mavlink_messages} MAVLink messages"
                  + (f"; stopped early: {s.stopped}" if s.stopped else ""),
                  path=str(self.out), frames=s.frames, frames_dropped=s.frames_dropped)
        return s

    # ---- writer thread -------------------------------------------------------------------
    def _run(self) -> None:
        last_sync = last_disk = time.monotonic()
        while True:
            try:
                item = self._frames.get(timeout=0.2)
            except queue.Empty:
                item = False
            try:
                self._write_samples()
                if item:
                    self._write_frame(item)
                now = time.monotonic()
                if now - last_disk >= DISK_CHECK_EVERY_S:
                    last_disk = now
                    self._check_disk()
                if now - last_sync >= FSYNC_EVERY_S:
                    last_sync = now
                    for f in self._files:
                        os.fsync(f.fileno())
            except OSError as e:  # ENOSPC, EIO, a pulled USB stick: the recording ends, the service goes on
                self._stop(f"write failed: {e}")
            except Exception as e:  # noqa: BLE001 — e.g. cv2.error on an image it cannot encode: the same
                log.exception("flight recorder failed")
                self._stop(f"{type(e).__name__}: {e}")
            if item is None or self.stats.stopped is not None:
                return

    def _write_samples(self) -> None:
        if self.stats.stopped is not None:
            return
        with self._lock:
            batch, self._samples = self._samples, []
            tlog, self._mavlink = self._mavlink, []
        if tlog:
            self._tlog.write(b"".join(struct.pack(">Q", int(t * 1e6)) + buf for t, buf in tlog))
            self._tlog.flush()
            self.stats.mavlink_messages += len(tlog)
        for s in batch:
            is_gnss = isinstance(s, GnssSample)
            c = self._csv_gnss if is_gnss else self._csv_att
            row = gnss_row(s) if is_gnss else attitude_row(s)
            if s.t_s < c.last_t_s:
                row[0] = f"{c.last_t_s:.6f}"
                self.stats.samples_retimed += 1
            c.last_t_s = max(c.last_t_s, s.t_s)
            c.write(row)
            if is_gnss:
                self.stats.gnss += 1
                if self._first_fix is None and s.fix_type >= GpsFixType.FIX_3D:
                    self._first_fix = s
                    self._write_meta(final=False)
            else:
                self.stats.attitude += 1

    def _write_frame(self, item: _FrameItem) -> None:
        f = item.frame
        if f.t_s <= self._csv_frames.last_t_s:  # the dataset needs strictly increasing frame times
            log.warning("frame %d at %.6f s not after the previous recorded frame: not recorded", f.seq, f.t_s)
            return
        name = f"{self.stats.frames:06d}{self._ext}"  # the recorder's own count: names never depend on the source's counter
        ok, buf = cv2.imencode(self._ext, np.ascontiguousarray(f.image), self._params)
        if not ok:
            raise OSError(f"cannot encode frame {f.seq} as {self._ext}")
        (self.out / "images" / name).write_bytes(buf.tobytes())
        self._csv_frames.write([f.seq, f"{f.t_s:.6f}", name])
        self._csv_frames.last_t_s = f.t_s
        if item.fix is not None:
            self._csv_fix.write([f.seq, *fix_row(item.fix)])
        self.stats.frames += 1

    def _check_disk(self) -> None:
        short = _disk_short(self.out, self.cfg.min_free_mb)
        if short:
            self._stop(short)

    def _stop(self, why: str) -> None:
        self.stats.stopped = why
        log_event(log, "recording_stopped", f"flight recorder stopped ({self.out}): {why}; the service goes on",
                  level=logging.ERROR, path=str(self.out), reason=why)
        while True:  # free what the hot path queued
            try:
                self._frames.get_nowait()
            except queue.Empty:
                break

    # ---- metadata ------------------------------------------------------------------------
    def _write_meta(self, final: bool) -> None:
        s, o, g = self.stats, self.origin, self._first_fix
        if g is not None:
            rough = {"lat_deg": g.lat_deg, "lon_deg": g.lon_deg, "h_ellipsoid_m": g.h_ellipsoid_m,
                     "sigma_m": float(g.h_acc_m) if math.isfinite(g.h_acc_m) and g.h_acc_m > 0 else 10.0,
                     "note": f"the first 3D GNSS fix recorded (t_s {g.t_s:.3f})"}
        else:
            rough = {"lat_deg": o.lat0_deg, "lon_deg": o.lon0_deg, "h_ellipsoid_m": o.h0_ellipsoid_m,
                     "sigma_m": NO_FIX_SIGMA_M, "note": "no GNSS fix recorded: the GIS model's origin"}
        _write_yaml(self.out / "site.yaml", {
            "origin": {"lat_deg": o.lat0_deg, "lon_deg": o.lon0_deg, "h_ellipsoid_m": o.h0_ellipsoid_m},
            "rough_position": rough,
            "gis": {"files": [str(p) for p in self.gis_files], "site_id": self.site_id,
                    "note": "the model the service used, by absolute path; copy it next to the recording to move it"},
        })
        _write_yaml(self.out / "dataset.yaml", {
            "format_version": FORMAT_VERSION, "name": self.out.name, "fps": float(self.fps), "n_frames": s.frames,
            "generator": "terraslam run (flight recorder)",
            "recording": {
                "clock": "time.monotonic() of the companion computer, seconds",
                "started_utc": self._started_utc.isoformat(timespec="seconds"),
                "ended_utc": datetime.now(timezone.utc).isoformat(timespec="seconds") if final else None,
                "complete": final and s.stopped is None,
                "frames_dropped": s.frames_dropped, "gnss_samples": s.gnss, "attitude_samples": s.attitude,
                "samples_retimed": s.samples_retimed, "stopped": s.stopped, "image_format": self.cfg.image_format,
                "mavlink_tlog": "mavlink.tlog", "mavlink_messages": s.mavlink_messages,
                "unix_time_minus_clock_s": round(self._unix_minus_clock_s, 6),
            },
        })


def open_recording(root: Path, cfg: RecordingConfig, camera: CameraModel, T_body_cam: np.ndarray, fps: float,
                   origin: LocalFrame, gis_files: list[Path], site_id: str | None = None,
                   p_body_gnss_m=(0.0, 0.0, 0.0)) -> FlightRecorder:
    """A started recorder in a new ``flight-<UTC time>`` folder under ``root``. Raises OSError when
    the folder cannot be made or the disk is already under ``min_free_mb`` (the caller logs and
    runs without)."""
    root = Path(root).expanduser()
    root.mkdir(parents=True, exist_ok=True)
    short = _disk_short(root, cfg.min_free_mb)
    if short:
        raise OSError(short)
    out = _unique_dir(root, "flight-" + datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ"))
    rec = FlightRecorder(out, cfg, fps, origin, gis_files, site_id)
    write_calibration(out / "camera.yaml", camera)
    write_mount(out / "mount.yaml", T_body_cam, p_body_gnss_m)
    return rec.start()

