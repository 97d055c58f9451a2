"""Records: a real .rrd written by rerun-sdk and read back, PNG plots, structured (JSON) logs."""
from __future__ import annotations

import io
import json
import logging

import cv2
import numpy as np
import pytest
import rerun.chunk as rrc

from companion import viz
from companion.config import LoggingConfig
from companion.logs import log_event, setup_logging
from slam.types import CameraModel


def _flight(n: int = 120):
    t = np.linspace(0, 60, n)
    truth = np.c_[100 * np.cos(t / 20), 100 * np.sin(t / 20), np.full(n, 80.0)]
    rng = np.random.default_rng(1)
    gnss = truth + rng.normal(0, 3, truth.shape)
    ours = truth + rng.normal(0, 1, truth.shape)
    return t, truth, gnss, ours


def test_rrd_recording_has_every_entity(tmp_path) -> None:
    t, truth, gnss, ours = _flight(30)
    cam = CameraModel(160, 120, np.array([[150.0, 0, 80], [0, 150, 60], [0, 0, 1]]))
    rec = viz.open_recording("save", tmp_path / "rec", name="trial")
    viz.log_camera(rec, cam)
    gis_pts = np.random.default_rng(0).uniform(-150, 150, (500, 3))
    viz.log_gis(rec, gis_pts, np.where(gis_pts[:, 2] > 0, 6, 2))
    image = np.zeros((120, 160, 3), np.uint8)
    cv2.rectangle(image, (40, 30), (120, 90), (255, 255, 255), -1)
    kps = cv2.goodFeaturesToTrack(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), 50, 0.01, 5).reshape(-1, 2)
    for i in range(len(t)):
        viz.log_frame(rec, t[i], image, kps)
        viz.log_map(rec, t[i], ours[: i + 1])
        viz.log_tracks(rec, t[i], {"truth": truth[: i + 1], "gnss": gnss[: i + 1], "ours": ours[: i + 1]})
        viz.log_errors(rec, t[i], {"ours": float(np.linalg.norm(ours[i] - truth[i])), "gnss": float("nan")})
    viz.log_switch_state(rec, t[10], "slam", reason="gnss jammed", source_code=1)
    viz.close_recording(rec)

    path = tmp_path / "rec" / "trial.rrd"
    store = rrc.RrdReader(path).store()
    entities = set(store.schema().entity_paths())
    expected = {"/camera", "/camera/image", "/camera/image/keypoints", "/world/slam_map", "/world/gis",
                "/world/tracks/truth", "/world/tracks/gnss/now", "/world/tracks/ours", "/status/switch",
                "/status/switch_source", "/errors/ours"}
    assert expected <= entities
    assert "/errors/gnss" not in entities  # NaN errors (no fix) are not logged as values
    summary = str(store.summary())
    assert "/camera/image rows=30" in summary.replace("  ", " ")


def test_recording_modes() -> None:
    assert viz.open_recording("off") is None
    with pytest.raises(viz.VizError, match="record_dir"):
        viz.open_recording("save", None)
    with pytest.raises(viz.VizError, match="unknown mode"):
        viz.open_recording("bogus")


def test_bad_arrays_are_named(tmp_path) -> None:
    rec = viz.open_recording("save", tmp_path)
    try:
        with pytest.raises(viz.VizError, match=r"points_enu: expected an \(N, 3\)"):
            viz.log_map(rec, 0.0, np.zeros((4, 2)))
        with pytest.raises(viz.VizError, match="3 labels for 4 points"):
            viz.log_gis(rec, np.zeros((4, 3)), np.array([2, 2, 6]))
    finally:
        viz.close_recording(rec)
    with pytest.raises(viz.VizError, match="tracks_en\\['ours'\\]"):
        viz.plot_track(tmp_path / "x.png", {"ours": np.zeros(5)})
    with pytest.raises(viz.VizError, match="no tracks"):
        viz.plot_track(tmp_path / "x.png", {})


def _png_ok(path) -> np.ndarray:
    img = cv2.imread(str(path))
    assert img is not None and img.shape[0] > 200 and img.shape[1] > 200
    assert img.std() > 5  # something was drawn, not a blank canvas
    return img


def test_png_plots(tmp_path) -> None:
    t, truth, gnss, ours = _flight()
    err_ours = np.linalg.norm(ours - truth, axis=1)
    err_gnss = np.linalg.norm(gnss - truth, axis=1)
    err_gnss[40:70] = np.nan  # jammed: no GNSS fix
    map_pts = np.random.default_rng(0).uniform(-120, 120, (2000, 3))
    labels = np.where(map_pts[:, 0] > 0, 6, 2)
    written = [
        viz.plot_track(tmp_path / "track.png", {"truth": truth, "gnss": gnss, "ours": ours}, map_points_en=map_pts, map_labels=labels),
        viz.plot_error_over_time(tmp_path / "err.png", {"ours": (t, err_ours), "gnss": (t, err_gnss)}, events=[(20.0, "→ slam"), (35.0, "→ gnss")]),
        viz.plot_error_cdf(tmp_path / "cdf.png", {"ours": err_ours, "gnss": err_gnss}),
        viz.plot_latency_hist(tmp_path / "sub" / "lat.png", {"capture→wire": np.random.default_rng(2).gamma(4, 5, 500)}),
    ]
    for path in written:
        _png_ok(path)
    with pytest.raises(viz.VizError, match="t_s has shape"):
        viz.plot_error_over_time(tmp_path / "bad.png", {"ours": (t, err_ours[:-1])})


def test_json_logs_carry_switch_events() -> None:
    stream = io.StringIO()
    handler = setup_logging(LoggingConfig(level="INFO", json=True), stream=stream)
    try:
        log = logging.getLogger("terraslam.switch")
        log_event(log, "switch", "switching to SLAM", source="slam", previous="gnss", reason="jammed", eph=np.float64(9.5))
        log.debug("not shown at INFO")
        try:
            raise RuntimeError("stage crashed")
        except RuntimeError:
            log.exception("tracking failed")
    finally:
        logging.getLogger().removeHandler(handler)
    lines = [json.loads(line) for line in stream.getvalue().splitlines()]
    assert len(lines) == 2
    ev = lines[0]
    assert (ev["event"], ev["source"], ev["previous"], ev["reason"], ev["eph"]) == ("switch", "slam", "gnss", "jammed", 9.5)
    assert ev["level"] == "INFO" and ev["logger"] == "terraslam.switch" and ev["msg"] == "switching to SLAM"
    assert ev["t_wall"].endswith("+00:00") and ev["t_mono_s"] > 0
    assert lines[1]["level"] == "ERROR" and "RuntimeError: stage crashed" in lines[1]["exc"]


def test_text_logs_append_event_fields() -> None:
    stream = io.StringIO()
    handler = setup_logging(LoggingConfig(level="DEBUG"), stream=stream)
    try:
        log_event(logging.getLogger("terraslam.camera"), "stall", level=logging.WARNING, source="/dev/video0", stalls=2)
    finally:
        logging.getLogger().removeHandler(handler)
    line = stream.getvalue().strip()
    assert "WARNING" in line and line.endswith("stall [stall] source=/dev/video0 stalls=2")
