"""Camera sources behind one interface: ``open_source(cfg, calibration) -> CameraSource``.

``camera.source`` selects the kind (``parse_source``):

========================  =====================================================================
``sim``                   the simulator: ``open_sim_source(steps, camera_model)`` (any iterable
                          of ``Frame`` or of objects with a ``.frame``, e.g. sim ``SimStep``)
``0`` / ``/dev/video0``   V4L2 device (OpenCV CAP_V4L2) with width/height/fps/fourcc requested
``rtsp://…``, ``http://…``  network stream through OpenCV's FFmpeg backend (open/read timeouts =
                          stall_timeout_s; RTSP transport via ``OPENCV_FFMPEG_CAPTURE_OPTIONS``)
``… ! … ! appsink``       GStreamer pipeline (needs an OpenCV built with GStreamer; refused with
                          a clear error otherwise — the pip wheel has none)
``flight.mp4``            video file (FFmpeg); timestamps = the frames' presentation times
``frames/``               image folder; timestamps from ``frames/frames.csv`` (columns ``t_s``,
                          ``filename``; rows in capture order) when present, else file-name order
                          at ``camera.fps`` (t = i / fps). File mtimes are not used: copying a
                          folder rewrites them.
========================  =====================================================================

Behaviour shared by every kind:

* A background grab thread keeps only the newest frame (latest-frame policy): a slow consumer drops
  frames (``stats().dropped``) instead of building latency. ``lossless=True`` (offline replay)
  makes file/sim sources wait for the consumer instead, so every frame is delivered.
* ``Frame.t_s`` is the source's own clock: ``time.monotonic()`` at grab for live sources; the file's
  timestamps for video/folder/sim (so they line up with the dataset's truth and GNSS logs). In
  realtime playback ``playback_epoch_s`` maps them onto the monotonic clock (t_s + epoch = when the
  frame was due), as ``terraslam run`` needs: the bridge and the autopilot's messages use that clock.
  ``capture_info(seq).grab_t_s`` is always the monotonic grab time (latency accounting).
  ``Frame.seq`` is the source's counter; gaps are dropped frames.
* File and sim sources play at their timestamps' pace when ``realtime=True`` (like a live camera)
  or as fast as they are read otherwise. Their end is ``eof`` — not a stall.
* Live sources (V4L2, streams, GStreamer) that deliver nothing for ``stall_timeout_s`` — or fail to
  read (unplugged) or end — are reopened with exponential backoff (``stats().stalls``,
  ``.reopens``); a device that is not there yet at boot is retried the same way.
* With a calibration, delivered images are undistorted to ``camera_model`` (dist = 0). An image of
  another size with the same aspect ratio is resized to the calibrated size first; a different
  aspect ratio is an error (the calibration cannot describe that camera).
"""
from __future__ import annotations

import csv
import logging
import re
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import cv2
import numpy as np

from companion.calibration import Calibration, load_calibration
from companion.config import CameraConfig
from companion.logs import log_event
from slam.types import CameraModel, Frame

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
FRAMES_CSV = "frames.csv"
REOPEN_BACKOFF_S = 0.25
REOPEN_BACKOFF_MAX_S = 8.0

RawFrames = Iterator[tuple[np.ndarray, float, Any]]  # (image, t_s, original item or None)


class CameraError(RuntimeError):
    """The camera source cannot work as configured (the message names the source and the problem)."""


@dataclass(frozen=True)
class SourceSpec:
    kind: str  # sim | v4l2 | stream | gstreamer | video | folder
    target: str | int

    @property
    def live(self) -> bool:
        return self.kind in ("v4l2", "stream", "gstreamer")


@dataclass
class SourceStats:
    grabbed: int = 0  # frames read from the device/file
    delivered: int = 0  # frames returned by read()
    dropped: int = 0  # grabbed but replaced by a newer frame before read()
    stalls: int = 0  # live source silent for stall_timeout_s
    reopens: int = 0
    read_failures: int = 0  # open/read errors of live sources (unplugged, refused, ended)
    eof: bool = False
    last_error: str | None = None


@dataclass(frozen=True)
class CaptureInfo:
    grab_t_s: float  # time.monotonic() when the frame was grabbed
    item: Any = None  # the sim step the frame came from (sim sources), else None


def parse_source(source: str) -> SourceSpec:
    """Classify ``camera.source``; CameraError when it names nothing usable."""
    s = source.strip()
    if s == "sim":
        return SourceSpec("sim", s)
    if re.fullmatch(r"\d+", s):
        return SourceSpec("v4l2", int(s))
    if s.startswith("/dev/video") or s.startswith("/dev/v4l/"):
        return SourceSpec("v4l2", s)
    if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*://", s):
        return SourceSpec("stream", s)
    if "!" in s:
        return SourceSpec("gstreamer", s)
    p = Path(s).expanduser()
    if p.is_dir():
        return SourceSpec("folder", str(p))
    if p.is_file():
        return SourceSpec("video", str(p))
    raise CameraError(
        f"camera.source {source!r}: not 'sim', a V4L2 index or /dev/video path, a URL, a GStreamer "
        "pipeline, or an existing video file / image folder"
    )


# --- raw readers: generators of (image, t_s, item); they release their device in `finally` ---


def _capture_frames(open_cap: Callable[[], cv2.VideoCapture], name: str, live: bool) -> RawFrames:
    cap = open_cap()
    try:
        if not cap.isOpened():
            raise CameraError(f"camera source {name}: could not be opened")
        while True:
            ok, image = cap.read()
            t_grab = time.monotonic()
            if not ok or image is None:
                if live:
                    raise CameraError(f"camera source {name}: read failed (unplugged or stream ended)")
                return
            yield image, (t_grab if live else cap.get(cv2.CAP_PROP_POS_MSEC) / 1e3), None
    finally:
        cap.release()


def _gstreamer_available() -> bool:
    return bool(re.search(r"GStreamer:\s+YES", cv2.getBuildInformation()))


def _capture_opener(spec: SourceSpec, cfg: CameraConfig) -> Callable[[], cv2.VideoCapture]:
    timeout_ms = int(cfg.stall_timeout_s * 1000)
    if spec.kind == "v4l2":
        params = [cv2.CAP_PROP_BUFFERSIZE, 1]
        if cfg.fourcc:
            params += [cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*cfg.fourcc)]
        params += [cv2.CAP_PROP_FRAME_WIDTH, cfg.width_px, cv2.CAP_PROP_FRAME_HEIGHT, cfg.height_px, cv2.CAP_PROP_FPS, cfg.fps]
        return lambda: cv2.VideoCapture(spec.target, cv2.CAP_V4L2, params)
    if spec.kind == "stream":
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, timeout_ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, timeout_ms]
        return lambda: cv2.VideoCapture(spec.target, cv2.CAP_FFMPEG, params)
    if spec.kind == "gstreamer":
        return lambda: cv2.VideoCapture(spec.target, cv2.CAP_GSTREAMER)
    return lambda: cv2.VideoCapture(spec.target, cv2.CAP_FFMPEG)


def _read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise CameraError(f"image folder: cannot decode {path}")
    if image.dtype != np.uint8:
        raise CameraError(f"image folder: {path} is {image.dtype}, expected 8-bit")
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def folder_index(folder: Path | str, fps: float) -> list[tuple[float, Path]]:
    """(t_s, path) of every frame in ``folder``: from frames.csv when present, else name order at fps."""
    folder = Path(folder)
    index_file = folder / FRAMES_CSV
    if index_file.is_file():
        rows: list[tuple[float, Path]] = []
        with index_file.open(newline="") as f:
            reader = csv.DictReader(f)
            if reader.fieldnames is None or not {"t_s", "filename"} <= set(reader.fieldnames):
                raise CameraError(f"{index_file}: needs columns t_s,filename (got {reader.fieldnames})")
            for line, row in enumerate(reader, start=2):
                try:
                    t_s = float(row["t_s"])
                except (TypeError, ValueError):
                    raise CameraError(f"{index_file}:{line}: t_s {row['t_s']!r} is not a number") from None
                path = folder / row["filename"]
                if not path.is_file():
                    raise CameraError(f"{index_file}:{line}: {path} does not exist")
                if rows and t_s <= rows[-1][0]:
                    raise CameraError(f"{index_file}:{line}: t_s {t_s} is not after the previous row's {rows[-1][0]}")
                rows.append((t_s, path))
    else:
        files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        rows = [(i / fps, p) for i, p in enumerate(files)]
    if not rows:
        raise CameraError(f"image folder {folder}: no images ({', '.join(IMAGE_SUFFIXES)}) found")
    return rows


def _folder_frames(rows: list[tuple[float, Path]]) -> RawFrames:
    for t_s, path in rows:
        yield _read_image(path), t_s, None


def _sim_frames(steps: Iterable[Any]) -> RawFrames:
    for item in steps:
        frame = item if isinstance(item, Frame) else getattr(item, "frame", None)
        if not isinstance(frame, Frame):
            raise CameraError(f"sim source: expected Frame or an object with .frame, got {type(item).__name__}")
        yield frame.image, frame.t_s, (None if item is frame else item)


# --- the source: grab thread, latest-frame slot, stall watch, reopen ---


@dataclass
class _Slot:
    image: np.ndarray
    t_s: float
    seq: int
    grab_t_s: float
    item: Any


@dataclass
class CameraSource:
    """Use ``open_source`` / ``open_sim_source``; then ``read()`` until ``eof``, and ``close()``."""

    name: str
    open_frames: Callable[[], RawFrames]
    live: bool
    camera_model: CameraModel | None  # what delivered frames follow (undistorted when calibrated)
    calibration: Calibration | None = None
    stall_timeout_s: float = 2.0
    realtime: bool = False
    lossless: bool = False
    backoff_s: float = REOPEN_BACKOFF_S
    backoff_max_s: float = REOPEN_BACKOFF_MAX_S
    history: int = 256
    _stats: SourceStats = field(default_factory=SourceStats)
    _cond: threading.Condition = field(default_factory=threading.Condition)
    _slot: _Slot | None = None
    _seq: int = 0
    _gen: int = 0
    _closed: bool = False
    _fatal: str | None = None
    _last_activity_s: float = 0.0
    _info: OrderedDict[int, CaptureInfo] = field(default_factory=OrderedDict)
    _manager: threading.Thread | None = None
    _size_warned: bool = False
    _epoch_s: float | None = None

    def start(self) -> CameraSource:
        self._manager = threading.Thread(target=self._manage, name=f"camera-{self.name}", daemon=True)
        self._manager.start()
        return self

    # consumer side

    def read(self, timeout_s: float | None = None) -> Frame | None:
        """The newest frame not yet returned; waits up to ``timeout_s`` (None: stall_timeout_s).

        None when no new frame came in time (check ``eof`` / ``stats()``). CameraError when the
        source failed for good (unreadable file, bad image size, GStreamer unavailable...).
        """
        timeout_s = self.stall_timeout_s if timeout_s is None else timeout_s
        with self._cond:
            self._cond.wait_for(lambda: self._slot is not None or self._stats.eof or self._fatal or self._closed, timeout_s)
            slot, self._slot = self._slot, None
            if slot is None:
                if self._fatal:  # after the frames grabbed before the failure were delivered
                    raise CameraError(self._fatal)
                return None
            self._stats.delivered += 1
            self._cond.notify_all()  # a lossless producer waits for the slot to empty
        return Frame(image=self._prepare(slot.image), t_s=slot.t_s, seq=slot.seq)

    def _prepare(self, image: np.ndarray) -> np.ndarray:
        if self.calibration is None:
            return image
        raw = self.calibration.raw
        h, w = image.shape[:2]
        if (w, h) != (raw.width_px, raw.height_px):
            if abs(w * raw.height_px - h * raw.width_px) > max(w, h) // 100:
                msg = f"camera source {self.name}: images are {w}x{h} px, calibration is {raw.width_px}x{raw.height_px} px (different aspect ratio)"
                with self._cond:
                    self._fatal = msg
                raise CameraError(msg)
            if not self._size_warned:
                log.warning("camera source %s: resizing %dx%d px images to the calibrated %dx%d px", self.name, w, h, raw.width_px, raw.height_px)
                self._size_warned = True
            image = cv2.resize(image, (raw.width_px, raw.height_px), interpolation=cv2.INTER_AREA)
        return self.calibration.undistort(image)

    @property
    def eof(self) -> bool:
        """The file/sim source is exhausted and its last frame was read."""
        with self._cond:
            return self._stats.eof and self._slot is None

    @property
    def playback_epoch_s(self) -> float | None:
        """Realtime file/sim playback: the monotonic time at which source time 0 s plays, so a frame's
        ``t_s`` + this is when it was due on the monotonic clock. None for live sources (their ``t_s``
        is monotonic already), for playback that is not realtime, and before the first frame."""
        with self._cond:
            return self._epoch_s

    def stats(self) -> SourceStats:
        with self._cond:
            return replace(self._stats)

    def capture_info(self, seq: int) -> CaptureInfo | None:
        with self._cond:
            return self._info.get(seq)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._gen += 1
            self._cond.notify_all()
        if self._manager is not None:
            self._manager.join(self.stall_timeout_s + 1.0)

    def __enter__(self) -> CameraSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # producer side

    def _publish(self, gen: int, image: np.ndarray, t_s: float, item: Any) -> bool:
        grab_t_s = t_s if self.live else time.monotonic()  # live readers stamp t_s right after the grab
        with self._cond:
            if self.lossless:
                self._cond.wait_for(lambda: self._slot is None or self._closed or gen != self._gen)
            if self._closed or gen != self._gen:
                return False
            self._stats.grabbed += 1
            if self._slot is not None:
                self._stats.dropped += 1
            self._slot = _Slot(image, t_s, self._seq, grab_t_s, item)
            self._info[self._seq] = CaptureInfo(grab_t_s, item)
            while len(self._info) > self.history:
                self._info.popitem(last=False)
            self._seq += 1
            self._last_activity_s = time.monotonic()
            self._cond.notify_all()
        return True

    def _pace(self, gen: int, t_s: float, clock: list[float]) -> None:
        """Realtime file playback: wait until t_s (file time) is due on the monotonic clock."""
        if not clock:
            clock.extend((time.monotonic(), t_s))
            epoch = clock[0] - clock[1]
            with self._cond:
                self._epoch_s = epoch
            log_event(log, "playback_start", f"camera source {self.name}: realtime playback, source time 0 s plays at "
                      f"monotonic {epoch:.6f} s", source=self.name, epoch_mono_s=round(epoch, 6))
            return
        due = clock[0] + (t_s - clock[1])
        with self._cond:
            self._cond.wait_for(lambda: self._closed or gen != self._gen, max(0.0, due - time.monotonic()))

    def _connection(self, gen: int) -> None:
        frames: RawFrames | None = None
        clock: list[float] = []
        try:
            frames = self.open_frames()
            for image, t_s, item in frames:
                if self.realtime and not self.live:
                    self._pace(gen, t_s, clock)
                if not self._publish(gen, image, t_s, item):
                    return
            with self._cond:
                if not self.live and gen == self._gen:
                    self._stats.eof = True
                    self._cond.notify_all()
        except Exception as e:  # noqa: BLE001 — reported to the manager / the consumer
            msg = str(e) if isinstance(e, CameraError) else f"camera source {self.name}: {type(e).__name__}: {e}"
            with self._cond:
                if gen == self._gen:
                    self._stats.last_error = msg
                    if self.live:
                        self._stats.read_failures += 1
                    else:
                        self._fatal = msg
                    self._cond.notify_all()
        finally:
            if frames is not None:
                frames.close()

    def _manage(self) -> None:
        failures = 0
        while True:
            with self._cond:
                if self._closed:
                    return
                self._gen += 1
                gen = self._gen
                self._last_activity_s = time.monotonic()
                grabbed_before = self._stats.grabbed
            conn = threading.Thread(target=self._connection, args=(gen,), name=f"camera-{self.name}-{gen}", daemon=True)
            conn.start()
            if not self.live:
                conn.join()
                return
            stalled = False
            while conn.is_alive():
                with self._cond:
                    if self._closed:
                        return
                    self._cond.wait(min(0.1, self.stall_timeout_s / 4))
                    if time.monotonic() - self._last_activity_s > self.stall_timeout_s:
                        stalled = True
                        self._stats.stalls += 1
                        self._gen += 1  # abandon the blocked reader; it releases the device when it returns
                        break
            with self._cond:
                if self._closed:
                    return
                got_frames = self._stats.grabbed > grabbed_before
                if stalled:
                    self._stats.last_error = f"camera source {self.name}: no frame for {self.stall_timeout_s:.1f} s (stall)"
                log_event(log, "camera_reopen", f"{self._stats.last_error or f'camera source {self.name} ended'}; reopening",
                          level=logging.WARNING, source=self.name, stalls=self._stats.stalls, read_failures=self._stats.read_failures)
            failures = 0 if got_frames else failures + 1
            delay = min(self.backoff_max_s, self.backoff_s * 2 ** max(0, failures - 1))
            with self._cond:
                if self._cond.wait_for(lambda: self._closed, delay):
                    return
                self._stats.reopens += 1


def open_source(
    cfg: CameraConfig,
    calibration: Calibration | None = None,
    *,
    realtime: bool = True,
    lossless: bool = False,
) -> CameraSource:
    """Open and start the source named by ``cfg.source`` (not ``sim``: see ``open_sim_source``).

    ``calibration`` defaults to ``cfg.calibration`` loaded from disk; a real camera without one is
    an error (SLAM needs intrinsics). ``realtime``/``lossless`` apply to video files and folders.
    """
    spec = parse_source(cfg.source)
    if spec.kind == "sim":
        raise CameraError("camera.source 'sim': use open_sim_source(steps, camera_model) with the simulator's frames")
    if spec.kind == "gstreamer" and not _gstreamer_available():
        raise CameraError(f"camera.source {cfg.source!r} is a GStreamer pipeline but this OpenCV build has no GStreamer support")
    if calibration is None:
        if cfg.calibration is None:
            raise CameraError(f"camera.calibration is required for camera.source {cfg.source!r} (OpenCV/ROS calibration YAML)")
        calibration = load_calibration(cfg.calibration)
    if spec.kind == "folder":
        rows = folder_index(spec.target, cfg.fps)
        opener: Callable[[], RawFrames] = lambda: _folder_frames(rows)  # noqa: E731
    else:
        if spec.kind == "video":
            probe = cv2.VideoCapture(spec.target, cv2.CAP_FFMPEG)
            ok = probe.isOpened()
            probe.release()
            if not ok:
                raise CameraError(f"camera.source {cfg.source!r}: not a video file OpenCV/FFmpeg can decode")
        open_cap = _capture_opener(spec, cfg)
        name = str(spec.target)
        opener = lambda: _capture_frames(open_cap, name, spec.live)  # noqa: E731
    return CameraSource(
        name=str(spec.target),
        open_frames=opener,
        live=spec.live,
        camera_model=calibration.model,
        calibration=calibration,
        stall_timeout_s=cfg.stall_timeout_s,
        realtime=realtime,
        lossless=lossless and not spec.live,
    ).start()


def open_sim_source(
    steps: Iterable[Any],
    camera_model: CameraModel,
    *,
    realtime: bool = True,
    lossless: bool = False,
) -> CameraSource:
    """Wrap simulator output (Frames, or objects with ``.frame`` such as SimStep) as a source.

    Frames pass through unchanged (the renderer's camera has no distortion); ``capture_info(seq).item``
    returns the step the frame came from so ground truth stays attached to it.
    """
    return CameraSource(
        name="sim",
        open_frames=lambda: _sim_frames(steps),
        live=False,
        camera_model=camera_model,
        realtime=realtime,
        lossless=lossless,
    ).start()
