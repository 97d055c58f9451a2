"""Visualisation and records: a rerun-sdk recording (live viewer or .rrd file) and static PNG plots.

Rerun entity layout (one timeline ``t_s``, the pipeline's monotonic / dataset seconds):

=========================  ===============================================================
``camera/image``           the frame (BGR or grey) + ``camera/image/keypoints`` (Points2D)
``camera``                 Pinhole intrinsics, so the image can be shown in 3D too
``world/slam_map``         SLAM map points, already in the local ENU frame (metres)
``world/gis``              GIS model crop, coloured by ASPRS class (2 ground, 5 vegetation,
                           6 building, 11 road)
``world/tracks/<label>``   tracks (truth, gnss, ours...) as line strips + current position
``status/switch``          switch state text log + ``status/switch_source`` scalar
``errors/<label>``         horizontal error time series (metres)
=========================  ===============================================================

The world view is ENU, z up (``rr.ViewCoordinates.RIGHT_HAND_Z_UP``). Inputs are plain numpy arrays
and labels so demo, replay and bench can all use these functions.

PNG plots use matplotlib's Agg backend (headless): ``plot_track``, ``plot_error_over_time``,
``plot_error_cdf``, ``plot_latency_hist``. Each returns the path it wrote.
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")  # headless: no display on the drone or in CI
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import rerun as rr  # noqa: E402

from slam.types import CameraModel  # noqa: E402

APP_ID = "terraslam"
TIMELINE = "t_s"
ASPRS_CLASSES = {1: ("unclassified", (150, 150, 150)), 2: ("ground", (160, 120, 80)), 5: ("high vegetation", (40, 150, 40)),
                 6: ("building", (200, 60, 60)), 11: ("road surface", (70, 70, 90))}
TRACK_COLORS = {"truth": (40, 40, 40), "gnss": (230, 140, 20), "ours": (30, 110, 230), "slam": (30, 110, 230)}


class VizError(ValueError):
    """Bad input to a plot or recording (the message names the argument)."""


# --- rerun ---


def open_recording(mode: str, record_dir: Path | str | None = None, *, name: str = "run") -> rr.RecordingStream | None:
    """A rerun recording per ``logging.rerun``: off → None; save → ``<record_dir>/<name>.rrd``;
    serve → gRPC server for a remote viewer (``rerun --connect``); spawn → local viewer process."""
    if mode == "off":
        return None
    rec = rr.RecordingStream(APP_ID)
    if mode == "save":
        if record_dir is None:
            raise VizError("logging.rerun is 'save' but logging.record_dir is not set")
        path = Path(record_dir).expanduser() / f"{name}.rrd"
        path.parent.mkdir(parents=True, exist_ok=True)
        rec.save(path)
    elif mode == "serve":
        rec.serve_grpc()
    elif mode == "spawn":
        rec.spawn()
    else:
        raise VizError(f"logging.rerun: unknown mode {mode!r} (off | save | serve | spawn)")
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log("world/gis", rr.AnnotationContext([(cls, label, color) for cls, (label, color) in ASPRS_CLASSES.items()]), static=True)
    return rec


def close_recording(rec: rr.RecordingStream | None) -> None:
    """Flush and close the sink (the .rrd file is complete afterwards)."""
    if rec is not None:
        rec.flush()
        rec.disconnect()


def _points(name: str, a: np.ndarray, dims: int) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.ndim != 2 or a.shape[1] != dims:
        raise VizError(f"{name}: expected an (N, {dims}) array, got shape {a.shape}")
    return a


def log_camera(rec: rr.RecordingStream, camera: CameraModel) -> None:
    rec.log("camera", rr.Pinhole(image_from_camera=camera.K, resolution=[camera.width_px, camera.height_px]), static=True)


def log_frame(rec: rr.RecordingStream, t_s: float, image: np.ndarray, keypoints_px: np.ndarray | None = None) -> None:
    """The camera image (BGR colour or grey uint8) and optionally its (N, 2) feature positions."""
    rec.set_time(TIMELINE, duration=t_s)
    color = "BGR" if image.ndim == 3 else "L"
    rec.log("camera/image", rr.Image(image, color_model=color))
    if keypoints_px is not None:
        rec.log("camera/image/keypoints", rr.Points2D(_points("keypoints_px", keypoints_px, 2), radii=1.5, colors=(0, 255, 0)))


def log_map(rec: rr.RecordingStream, t_s: float, points_enu: np.ndarray) -> None:
    """SLAM map points in the local ENU frame (transform them with the current alignment first)."""
    rec.set_time(TIMELINE, duration=t_s)
    rec.log("world/slam_map", rr.Points3D(_points("points_enu", points_enu, 3), radii=0.3, colors=(30, 110, 230)))


def log_gis(rec: rr.RecordingStream, points_enu: np.ndarray, labels: np.ndarray | None = None, t_s: float | None = None) -> None:
    """The GIS model (crop) in ENU, coloured by ASPRS class; static when ``t_s`` is None."""
    pts = _points("points_enu", points_enu, 3)
    if labels is not None and len(labels) != len(pts):
        raise VizError(f"labels: {len(labels)} labels for {len(pts)} points")
    if t_s is not None:
        rec.set_time(TIMELINE, duration=t_s)
    rec.log("world/gis", rr.Points3D(pts, radii=0.2, class_ids=None if labels is None else np.asarray(labels, dtype=np.uint16)), static=t_s is None)


def log_tracks(rec: rr.RecordingStream, t_s: float, tracks_enu: Mapping[str, np.ndarray]) -> None:
    """Tracks so far per label (e.g. truth, gnss, ours), each (N, 3) ENU; the last row is 'now'."""
    rec.set_time(TIMELINE, duration=t_s)
    for label, track in tracks_enu.items():
        pts = _points(f"tracks_enu[{label!r}]", track, 3)
        if len(pts) == 0:
            continue
        color = TRACK_COLORS.get(label, (120, 120, 120))
        rec.log(f"world/tracks/{label}", rr.LineStrips3D([pts], colors=color, radii=0.15))
        rec.log(f"world/tracks/{label}/now", rr.Points3D(pts[-1:], colors=color, radii=1.0, labels=[label]))


def log_switch_state(rec: rr.RecordingStream, t_s: float, source: str, reason: str = "", source_code: int | None = None) -> None:
    """The position source the autopilot is fed from (e.g. gnss / slam / none) and why."""
    rec.set_time(TIMELINE, duration=t_s)
    rec.log("status/switch", rr.TextLog(f"{source}: {reason}" if reason else source, level="INFO"))
    if source_code is not None:
        rec.log("status/switch_source", rr.Scalars(float(source_code)))


def log_errors(rec: rr.RecordingStream, t_s: float, errors_m: Mapping[str, float]) -> None:
    """Current errors (metres) per label, e.g. {"ours": 2.1, "gnss": 35.0}."""
    rec.set_time(TIMELINE, duration=t_s)
    for label, err in errors_m.items():
        if np.isfinite(err):
            rec.log(f"errors/{label}", rr.Scalars(float(err)))


# --- PNG plots ---


def _save(fig: plt.Figure, path: Path | str) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_track(
    path: Path | str,
    tracks_en: Mapping[str, np.ndarray],
    *,
    map_points_en: np.ndarray | None = None,
    map_labels: np.ndarray | None = None,
    title: str = "Track on map",
) -> Path:
    """Top view (east/north metres) of each track over the map (GIS points coloured by class)."""
    if not tracks_en:
        raise VizError("tracks_en: no tracks to plot")
    fig, ax = plt.subplots(figsize=(7, 7))
    if map_points_en is not None:
        pts = np.asarray(map_points_en, dtype=float)[:, :2]
        if map_labels is None:
            ax.scatter(pts[:, 0], pts[:, 1], s=1, c="0.8", linewidths=0, label="map")
        else:
            labels = np.asarray(map_labels)
            for cls in np.unique(labels):
                name, rgb = ASPRS_CLASSES.get(int(cls), (f"class {cls}", (150, 150, 150)))
                sel = labels == cls
                ax.scatter(pts[sel, 0], pts[sel, 1], s=1, color=np.array(rgb) / 255, alpha=0.4, linewidths=0, label=name)
    for label, track in tracks_en.items():
        t = np.asarray(track, dtype=float)
        if t.ndim != 2 or t.shape[1] < 2:
            plt.close(fig)
            raise VizError(f"tracks_en[{label!r}]: expected (N, 2+) east/north metres, got shape {t.shape}")
        color = np.array(TRACK_COLORS[label]) / 255 if label in TRACK_COLORS else None
        ax.plot(t[:, 0], t[:, 1], "-", lw=1.5, label=label, color=color)
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(title)
    ax.legend(loc="best", markerscale=6, fontsize=8)
    ax.grid(True, alpha=0.3)
    return _save(fig, path)


def plot_error_over_time(
    path: Path | str,
    errors_by_label: Mapping[str, tuple[np.ndarray, np.ndarray]],
    *,
    events: Sequence[tuple[float, str]] = (),
    ylabel: str = "horizontal error [m]",
    title: str = "Error over time",
) -> Path:
    """Error series {label: (t_s, error_m)} with vertical lines at events [(t_s, text)] (switches)."""
    fig, ax = plt.subplots(figsize=(9, 4))
    for label, (t, e) in errors_by_label.items():
        t, e = np.asarray(t, dtype=float), np.asarray(e, dtype=float)
        if t.shape != e.shape:
            plt.close(fig)
            raise VizError(f"errors_by_label[{label!r}]: t_s has shape {t.shape}, errors {e.shape}")
        ax.plot(t, e, lw=1.2, label=label)
    for t_event, text in events:
        ax.axvline(t_event, color="0.3", ls="--", lw=0.8)
        ax.annotate(text, (t_event, 1.0), xycoords=("data", "axes fraction"), rotation=90, va="top", ha="right", fontsize=7)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    return _save(fig, path)


def plot_error_cdf(path: Path | str, errors_by_label: Mapping[str, np.ndarray], *, xlabel: str = "horizontal error [m]", title: str = "Error CDF") -> Path:
    """Empirical CDF per label; the legend carries P50 / P95 (NaNs — no fix — are left out)."""
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, errors in errors_by_label.items():
        e = np.sort(np.asarray(errors, dtype=float)[np.isfinite(errors)])
        if e.size == 0:
            continue
        p = np.arange(1, e.size + 1) / e.size
        ax.step(e, p, where="post", label=f"{label} (P50 {np.percentile(e, 50):.1f}, P95 {np.percentile(e, 95):.1f})")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("fraction ≤ x")
    ax.set_ylim(0, 1)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    return _save(fig, path)


def plot_latency_hist(path: Path | str, latencies_ms: Mapping[str, np.ndarray], *, title: str = "Latency") -> Path:
    """Histogram per stage/span (milliseconds), P50/P99 in the legend (e.g. LatencyTracker.samples_ms)."""
    fig, ax = plt.subplots(figsize=(7, 4))
    for label, values in latencies_ms.items():
        v = np.asarray(values, dtype=float)
        v = v[np.isfinite(v)]
        if v.size == 0:
            continue
        ax.hist(v, bins=50, alpha=0.6, label=f"{label} (P50 {np.percentile(v, 50):.1f}, P99 {np.percentile(v, 99):.1f} ms)")
    ax.set_xlabel("latency [ms]")
    ax.set_ylabel("frames")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    return _save(fig, path)
