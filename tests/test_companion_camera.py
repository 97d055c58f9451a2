"""Camera sources and calibration against real files and a real network stream.

- video files written by OpenCV's VideoWriter (MJPG/AVI), read back through FFmpeg;
- image folders with and without frames.csv;
- a live MJPEG-over-HTTP stream (multipart/x-mixed-replace, what IP cameras serve) from a server on
  127.0.0.1, read through OpenCV's FFmpeg backend — the same path as rtsp:// URLs. The server can be
  paused (stall) and can drop the connection (unplug); the source must notice and reconnect.
- V4L2 and GStreamer need a device / a GStreamer-enabled OpenCV: not available here (see
  docs/SERVICE.md); the GStreamer refusal is tested.
"""
from __future__ import annotations

import http.server
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.calibration import CalibrationError, load_calibration, read_camera_model, write_calibration
from companion.camera import CameraError, folder_index, open_sim_source, open_source, parse_source
from companion.config import CameraConfig
from slam.types import CameraModel, Frame

W, H = 160, 120
K = np.array([[150.0, 0, 80.0], [0, 150.0, 60.0], [0, 0, 1]])


def _pattern(i: int, w: int = W, h: int = H) -> np.ndarray:
    """A frame whose index can be read back after JPEG compression: mean grey level = 4*i."""
    return np.full((h, w, 3), 4 * i, np.uint8)


def _index_of(image: np.ndarray) -> int:
    return int(round(float(image.mean()) / 4))


@pytest.fixture
def calib_path(tmp_path: Path) -> Path:
    path = tmp_path / "cam.yaml"
    write_calibration(path, CameraModel(W, H, K, np.array([-0.2, 0.05, 0.001, -0.001, 0.0])))
    return path


@pytest.fixture
def video_path(tmp_path: Path) -> Path:
    path = tmp_path / "flight.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 20.0, (W, H))
    assert writer.isOpened()
    for i in range(40):
        writer.write(_pattern(i))
    writer.release()
    return path


def _drain(src, timeout_s: float = 5.0) -> list[Frame]:
    frames: list[Frame] = []
    deadline = time.monotonic() + timeout_s
    while not src.eof and time.monotonic() < deadline:
        f = src.read(0.5)
        if f is not None:
            frames.append(f)
    return frames


# --- calibration ---


def test_calibration_opencv_yaml_roundtrip_and_undistortion(calib_path: Path) -> None:
    cal = load_calibration(calib_path)
    np.testing.assert_allclose(cal.raw.K, K)
    np.testing.assert_allclose(cal.raw.dist, [-0.2, 0.05, 0.001, -0.001, 0.0])
    assert not cal.model.is_distorted and (cal.model.width_px, cal.model.height_px) == (W, H)
    # the undistorted image of a distorted point lands where the new K projects the undistorted ray
    src = np.zeros((H, W), np.uint8)
    u, v = 140.0, 100.0  # near the corner: large barrel displacement
    cv2.circle(src, (int(u), int(v)), 2, 255, -1)
    out = cal.undistort(src)
    ys, xs = np.nonzero(out > 100)
    expected = cv2.undistortPoints(np.array([[[u, v]]]), cal.raw.K, cal.raw.dist, P=cal.model.K)[0, 0]
    assert np.hypot(xs.mean() - expected[0], ys.mean() - expected[1]) < 1.0
    same_k = cv2.undistortPoints(np.array([[[u, v]]]), cal.raw.K, cal.raw.dist, P=cal.raw.K)[0, 0]
    assert np.hypot(same_k[0] - u, same_k[1] - v) > 3.0  # the lens distortion at this point is substantial


def test_calibration_ros_camera_info(tmp_path: Path) -> None:
    path = tmp_path / "ost.yaml"
    path.write_text(
        "image_width: 640\nimage_height: 480\ncamera_name: narrow_stereo\n"
        "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [500.5, 0, 321.0, 0, 501.5, 239.0, 0, 0, 1]\n"
        "distortion_model: plumb_bob\n"
        "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0.1, -0.05, 0.0, 0.0, 0.0]\n"
    )
    cam = read_camera_model(path)
    assert (cam.width_px, cam.height_px, cam.fx, cam.fy, cam.cx, cam.cy) == (640, 480, 500.5, 501.5, 321.0, 239.0)
    np.testing.assert_allclose(cam.dist, [0.1, -0.05, 0, 0, 0])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("image_width: 640\nimage_height: 480\n", "missing key 'camera_matrix'"),
        ("image_width: 640\ncamera_matrix: {rows: 3, cols: 3, data: [1,0,0,0,1,0,0,0,1]}\n", "image_height"),
        ("image_width: 640\nimage_height: 480\ncamera_matrix: {rows: 3, cols: 3, data: [1,0,0,0,1,0,0]}\n"
         "distortion_coefficients: {rows: 1, cols: 5, data: [0,0,0,0,0]}\n", "rows=3 cols=3 but 7 data values"),
        ("image_width: 640\nimage_height: 480\ncamera_matrix: {rows: 3, cols: 3, data: [-5,0,0,0,1,0,0,0,1]}\n"
         "distortion_coefficients: {rows: 1, cols: 5, data: [0,0,0,0,0]}\n", "not an intrinsics matrix"),
        ("image_width: 640\nimage_height: 480\ndistortion_model: equidistant\n", "'equidistant' is not supported"),
        ("image_width: [1, 2\n", "not a readable"),
    ],
)
def test_calibration_malformed_files_name_file_and_key(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(CalibrationError) as err:
        read_camera_model(path)
    assert message in str(err.value) and str(path) in str(err.value)


def test_calibration_missing_file(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="not found"):
        load_calibration(tmp_path / "nope.yaml")


# --- source parsing ---


def test_parse_source_kinds(tmp_path: Path, video_path: Path) -> None:
    assert parse_source("sim").kind == "sim"
    assert parse_source("0").target == 0 and parse_source("/dev/video2").kind == "v4l2"
    assert parse_source("rtsp://10.0.0.2:8554/cam").kind == "stream"
    assert parse_source("v4l2src ! videoconvert ! appsink").kind == "gstreamer"
    assert parse_source(str(tmp_path)).kind == "folder"
    assert parse_source(str(video_path)).kind == "video"
    with pytest.raises(CameraError, match="not 'sim'"):
        parse_source(str(tmp_path / "missing.mp4"))


def test_gstreamer_refused_without_support(calib_path: Path) -> None:
    if "GStreamer:                   YES" in cv2.getBuildInformation():
        pytest.skip("this OpenCV has GStreamer")
    with pytest.raises(CameraError, match="no GStreamer support"):
        open_source(CameraConfig(source="videotestsrc ! appsink", calibration=calib_path))


def test_real_camera_needs_calibration(video_path: Path) -> None:
    with pytest.raises(CameraError, match="camera.calibration is required"):
        open_source(CameraConfig(source=str(video_path)))


# --- video file ---


def test_video_file_lossless_delivers_every_frame_undistorted(video_path: Path, calib_path: Path) -> None:
    cal = load_calibration(calib_path)
    with open_source(CameraConfig(source=str(video_path), calibration=calib_path), realtime=False, lossless=True) as src:
        frames = _drain(src)
        stats = src.stats()
        assert src.camera_model is not None and not src.camera_model.is_distorted
    assert len(frames) == 40 and stats.eof and stats.dropped == 0 and stats.stalls == 0
    assert [f.seq for f in frames] == list(range(40))
    np.testing.assert_allclose([f.t_s for f in frames], np.arange(40) / 20.0, atol=1e-6)  # PTS at 20 fps
    # the delivered image is the undistorted one (compare with undistorting the decoded file frame)
    cap = cv2.VideoCapture(str(video_path))
    _, first = cap.read()
    cap.release()
    np.testing.assert_array_equal(frames[0].image, cal.undistort(first))


def test_video_file_latest_frame_policy_drops_for_slow_consumer(video_path: Path, calib_path: Path) -> None:
    with open_source(CameraConfig(source=str(video_path), calibration=calib_path), realtime=False) as src:
        time.sleep(1.0)  # a consumer far slower than the decoder
        frame = src.read(1.0)
        stats = src.stats()
        assert frame is not None and src.read(0.2) is None and src.eof
    # only the newest frame survived; everything in between was dropped, not queued
    assert frame.seq == 39 and _index_of(frame.image) == 39
    assert stats.grabbed == 40 and stats.dropped == 39 and stats.delivered == 1


def test_video_file_size_mismatch(video_path: Path, tmp_path: Path) -> None:
    # same aspect ratio: resized to the calibration; different aspect: clear error
    half = tmp_path / "half.yaml"
    write_calibration(half, CameraModel(W // 2, H // 2, K / 2 + np.diag([0, 0, 0.5]), np.zeros(5)))
    with open_source(CameraConfig(source=str(video_path), calibration=half), realtime=False, lossless=True) as src:
        f = src.read(2.0)
        assert f is not None and f.image.shape[:2] == (H // 2, W // 2)
    square = tmp_path / "square.yaml"
    write_calibration(square, CameraModel(W, W, K, np.zeros(5)))
    with open_source(CameraConfig(source=str(video_path), calibration=square), realtime=False, lossless=True) as src:
        with pytest.raises(CameraError, match="different aspect ratio"):
            src.read(2.0)


def test_undecodable_video_is_a_clear_error(tmp_path: Path, calib_path: Path) -> None:
    bogus = tmp_path / "broken.mp4"
    bogus.write_bytes(b"this is not a video" * 100)
    with pytest.raises(CameraError, match="broken.mp4"):
        open_source(CameraConfig(source=str(bogus), calibration=calib_path))


# --- image folder ---


def _write_folder(folder: Path, n: int) -> list[str]:
    folder.mkdir()
    names = [f"img_{i:04d}.png" for i in range(n)]
    for i, name in enumerate(names):
        cv2.imwrite(str(folder / name), _pattern(i))
    return names


def test_image_folder_with_frames_csv(tmp_path: Path, calib_path: Path) -> None:
    folder = tmp_path / "frames"
    names = _write_folder(folder, 12)
    times = 100.0 + np.cumsum(np.full(12, 0.05))
    (folder / "frames.csv").write_text("t_s,filename\n" + "".join(f"{t:.3f},{n}\n" for t, n in zip(times, names)))
    with open_source(CameraConfig(source=str(folder), calibration=calib_path), realtime=True, lossless=True) as src:
        t0 = time.monotonic()
        frames = _drain(src)
        elapsed = time.monotonic() - t0
    assert [round(f.t_s, 3) for f in frames] == [round(t, 3) for t in times]
    assert elapsed >= 0.5  # realtime pacing: 11 intervals of 50 ms cannot arrive sooner (a lower bound only)
    assert [_index_of(f.image) for f in frames] == list(range(12))  # csv order, uniform grey survives undistortion


def test_image_folder_without_csv_uses_name_order_and_fps(tmp_path: Path, calib_path: Path) -> None:
    folder = tmp_path / "frames"
    _write_folder(folder, 5)
    rows = folder_index(folder, fps=10.0)
    assert [p.name for _, p in rows] == [f"img_{i:04d}.png" for i in range(5)]
    np.testing.assert_allclose([t for t, _ in rows], [0.0, 0.1, 0.2, 0.3, 0.4])
    with open_source(CameraConfig(source=str(folder), calibration=calib_path, fps=10.0), realtime=False, lossless=True) as src:
        assert len(_drain(src)) == 5


@pytest.mark.parametrize(
    ("csv_text", "message"),
    [
        ("time,file\n0,img_0000.png\n", "needs columns t_s,filename"),
        ("t_s,filename\n0.0,img_0000.png\n0.0,img_0001.png\n", "is not after"),
        ("t_s,filename\nabc,img_0000.png\n", "is not a number"),
        ("t_s,filename\n0.0,missing.png\n", "does not exist"),
    ],
)
def test_image_folder_bad_csv(tmp_path: Path, csv_text: str, message: str) -> None:
    folder = tmp_path / "frames"
    _write_folder(folder, 2)
    (folder / "frames.csv").write_text(csv_text)
    with pytest.raises(CameraError, match=message):
        folder_index(folder, fps=10.0)


def test_image_folder_corrupt_image_is_reported(tmp_path: Path, calib_path: Path) -> None:
    folder = tmp_path / "frames"
    _write_folder(folder, 3)
    (folder / "img_0001.png").write_bytes(b"not a png")
    with open_source(CameraConfig(source=str(folder), calibration=calib_path), realtime=False, lossless=True) as src:
        assert src.read(2.0) is not None
        with pytest.raises(CameraError, match="cannot decode .*img_0001.png"):
            src.read(2.0)


# --- simulator frames ---


def test_sim_source_keeps_steps_attached(tmp_path: Path) -> None:
    class Step:  # the shape of companion.sim's SimStep as far as the source cares: a .frame
        def __init__(self, i: int) -> None:
            self.frame = Frame(image=_pattern(i), t_s=10.0 + i * 0.1, seq=i)
            self.truth = ("truth", i)

    cam = CameraModel(W, H, K)
    with open_sim_source((Step(i) for i in range(6)), cam, realtime=False, lossless=True) as src:
        frames = _drain(src)
        items = [src.capture_info(f.seq).item for f in frames]
    assert [f.t_s for f in frames] == pytest.approx([10.0 + i * 0.1 for i in range(6)])
    assert [it.truth for it in items] == [("truth", i) for i in range(6)]
    with open_sim_source([object()], cam, realtime=False) as src:
        with pytest.raises(CameraError, match="expected Frame"):
            src.read(2.0)


# --- live network stream (MJPEG over HTTP on loopback) ---


class _MjpegServer:
    """A live MJPEG camera on 127.0.0.1: counts frames, can pause (stall) or cut connections (unplug)."""

    def __init__(self, fps: float = 30.0) -> None:
        self.running = threading.Event()
        self.running.set()
        self.cut = threading.Event()
        self.connections = 0
        self.i = 0
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 — http.server API
                server.connections += 1
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace;boundary=frame")
                self.end_headers()
                try:
                    while not server.cut.is_set():
                        if not server.running.is_set():
                            time.sleep(0.02)
                            continue
                        ok, buf = cv2.imencode(".jpg", _pattern(server.i % 60))
                        server.i += 1
                        self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n" % len(buf) + buf.tobytes() + b"\r\n")
                        time.sleep(1.0 / fps)
                except (BrokenPipeError, ConnectionResetError):
                    pass

            def log_message(self, *args: object) -> None:
                pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/stream.mjpg"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.cut.set()
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def mjpeg():
    server = _MjpegServer()
    yield server
    server.close()


def _wait_frame(src, timeout_s: float) -> Frame | None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        f = src.read(0.2)
        if f is not None:
            return f
    return None


def _stream_cfg(url: str, calib_path: Path) -> CameraConfig:
    return CameraConfig(source=url, calibration=calib_path, stall_timeout_s=0.8)


def test_stream_live_frames_have_monotonic_capture_times(mjpeg: _MjpegServer, calib_path: Path) -> None:
    with open_source(_stream_cfg(mjpeg.url, calib_path)) as src:
        frames = [f for f in (_wait_frame(src, 5.0) for _ in range(5)) if f is not None]
        infos = [src.capture_info(f.seq) for f in frames]
    assert len(frames) == 5
    assert all(b.t_s > a.t_s for a, b in zip(frames, frames[1:]))
    assert all(info.grab_t_s == f.t_s for f, info in zip(frames, infos))  # live: t_s is the grab time
    assert all(f.t_s <= time.monotonic() for f in frames)


def test_stream_stall_is_detected_and_recovered(mjpeg: _MjpegServer, calib_path: Path) -> None:
    with open_source(_stream_cfg(mjpeg.url, calib_path)) as src:
        assert _wait_frame(src, 5.0) is not None
        mjpeg.running.clear()  # camera freezes, connection stays open
        time.sleep(2.0)
        stalled = src.stats()
        mjpeg.running.set()
        after = _wait_frame(src, 10.0)
        recovered = src.stats()
    assert stalled.stalls >= 1 and stalled.last_error is not None and "stall" in stalled.last_error
    assert after is not None and recovered.reopens >= 1 and mjpeg.connections >= 2


def test_stream_unplug_is_detected_and_recovered(mjpeg: _MjpegServer, calib_path: Path) -> None:
    with open_source(_stream_cfg(mjpeg.url, calib_path)) as src:
        first = _wait_frame(src, 5.0)
        mjpeg.cut.set()  # drop every connection (cable pulled)
        time.sleep(1.0)
        mjpeg.cut.clear()
        after = _wait_frame(src, 10.0)
        stats = src.stats()
    assert first is not None and after is not None and after.seq > first.seq
    assert stats.reopens >= 1 and mjpeg.connections >= 2


def test_stream_absent_at_start_is_retried(calib_path: Path) -> None:
    # the camera is not there yet at boot: the source keeps retrying with backoff, then gets frames
    probe = _MjpegServer()
    url = probe.url
    probe.close()
    with open_source(_stream_cfg(url, calib_path)) as src:
        time.sleep(1.5)
        before = src.stats()
        assert src.read(0.1) is None
    assert before.read_failures >= 1 and before.grabbed == 0 and before.reopens >= 1


def test_sim_source_with_the_real_simulator() -> None:
    sim = pytest.importorskip("companion.sim")
    scenario = sim.make_scenario("nominal", n_frames=4)
    with open_sim_source(scenario.steps(), scenario.camera, realtime=False, lossless=True) as src:
        frames = _drain(src, timeout_s=120.0)
        steps = [src.capture_info(f.seq).item for f in frames]
    assert len(frames) == 4 and src.camera_model is scenario.camera
    assert all(f.image.shape[:2] == (scenario.camera.height_px, scenario.camera.width_px) for f in frames)
    assert [f.t_s for f in frames] == [s.frame.t_s for s in steps]  # truth/GNSS stay attached to their frame
    assert all(s.truth is not None for s in steps)
