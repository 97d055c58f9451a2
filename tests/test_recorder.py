"""The flight recorder (companion/recorder.py): what `terraslam run` feeds the pipeline, written as a
dataset that `terraslam replay` reads back. Real parts: simulator frames, GNSS and attitude logs, real
PNG/JPEG files, the real dataset reader and the real replay pipeline. The service writing one over
real MAVLink is in test_service_e2e.py."""
from __future__ import annotations

import importlib
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.app import run_replay
from companion.config import RecordingConfig, load_config
from companion.dataset import read_dataset, write_dataset
from companion.recorder import open_recording
from companion.sim import make_scenario


def _record(ds, root: Path, cfg: RecordingConfig, steps=None):
    """Feed a dataset's steps to a recorder as the service does: the bridge hands over every GNSS
    and attitude message as it arrives, the hot path each frame it tracked."""
    rec = open_recording(root, cfg, ds.camera, ds.T_body_cam, ds.fps, ds.origin, ds.gis_files[:1], "site-test")
    for step in steps if steps is not None else ds.steps():
        for g in step.gnss:
            rec.on_gnss(g)
        for a in step.attitude:
            rec.on_attitude(a)
        rec.on_frame(step.frame, None)
    return rec, rec.close()


def test_a_recorded_flight_replays_to_the_same_fixes(tmp_path: Path) -> None:
    """Recorded losslessly, a flight replays (repeatable) to the same fixes, to the bit, as the
    flight it was recorded from: the recording holds everything the pipeline uses."""
    src = write_dataset(make_scenario("nominal", seed=0, n_frames=150, fps=10), tmp_path / "src", progress=False)
    ds = read_dataset(src)
    cfg = load_config(environ={})
    direct = run_replay(cfg, src, tmp_path / "direct", repeatable=True)

    rec, stats = _record(ds, tmp_path / "recordings", RecordingConfig(image_format="png", queue_frames=4096))
    assert (stats.frames, stats.frames_dropped, stats.gnss, stats.attitude) == (150, 0, len(ds.gnss), len(ds.attitude))
    assert rec.out.parent == tmp_path / "recordings" and rec.out.name.startswith("flight-")
    replayed = run_replay(cfg, rec.out, tmp_path / "replayed", repeatable=True)

    a = (tmp_path / "direct" / "trajectory.csv").read_text()
    b = (tmp_path / "replayed" / "trajectory.csv").read_text()
    assert direct["fix_ratio_all"] > 0.2, "the flight must be long enough to align and send fixes"
    assert a == b
    assert replayed["frames"] == direct["frames"] == 150

    meta = yaml.safe_load((rec.out / "dataset.yaml").read_text())
    assert meta["n_frames"] == 150 and meta["recording"]["complete"] and meta["recording"]["frames_dropped"] == 0
    site = yaml.safe_load((rec.out / "site.yaml").read_text())
    first_fix = next(g for g in ds.gnss if g.fix_type >= 3)
    assert (site["rough_position"]["lat_deg"], site["rough_position"]["lon_deg"]) == (first_fix.lat_deg, first_fix.lon_deg)
    assert site["gis"]["files"] == [str(ds.gis_files[0].resolve())] and site["gis"]["site_id"] == "site-test"


def test_a_slow_writer_drops_frames_from_the_recording_and_says_so(tmp_path: Path) -> None:
    """A writer behind the camera leaves frames out (the hot path never waits) and counts them; the
    frames it kept are the pipeline's, at their times, and attitude whose time went back is written
    at the previous time (the format needs time order) and counted."""
    src = write_dataset(make_scenario("nominal", seed=1, n_frames=40, fps=10), tmp_path / "src", progress=False)
    ds = read_dataset(src)
    steps = list(ds.steps())  # decoded before feeding: the feed is as fast as the hot path's put
    late = replace(ds.attitude[5], t_s=ds.attitude[5].t_s - 0.05, baro_alt_m=None)
    steps[1] = replace(steps[1], attitude=steps[1].attitude + [late])
    t0 = time.perf_counter()
    rec, stats = _record(ds, tmp_path / "rec", RecordingConfig(image_format="jpg", queue_frames=4), steps)
    print(f"40 frames: {stats.frames} recorded, {stats.frames_dropped} dropped, {time.perf_counter() - t0:.2f} s")
    assert stats.frames + stats.frames_dropped == 40 and stats.frames_dropped >= 1
    assert stats.samples_retimed == 1 and stats.attitude == len(ds.attitude) + 1

    back = read_dataset(rec.out)
    assert back.n_frames == stats.frames
    with open(rec.out / "images" / "frames.csv") as f:
        kept = [int(line.split(",")[0]) for line in f.read().splitlines()[1:]]  # the source's seq: gaps are the drops
    assert kept == sorted(kept) and set(kept) <= set(range(40)) and len(kept) == stats.frames
    np.testing.assert_array_equal(back.frame_t_s, ds.frame_t_s[kept])
    img, orig = back.image(0), ds.image(kept[0])
    assert img.shape == orig.shape and np.mean(np.abs(img.astype(float) - orig)) < 3.0  # JPEG q95
    meta = yaml.safe_load((rec.out / "dataset.yaml").read_text())["recording"]
    assert meta["frames_dropped"] == stats.frames_dropped and meta["samples_retimed"] == 1 and meta["complete"]
    assert [a.baro_alt_m for a in back.attitude].count(None) == 1


def test_a_write_error_stops_the_recording_not_the_caller(tmp_path: Path) -> None:
    """The recording disk goes away mid-flight: the recorder stops with the reason, keeps taking
    (and ignoring) the hot path's calls, and closes with what it has said in dataset.yaml."""
    src = write_dataset(make_scenario("nominal", seed=2, n_frames=12, fps=10), tmp_path / "src", progress=False)
    ds = read_dataset(src)
    steps = list(ds.steps())
    rec = open_recording(tmp_path / "rec", RecordingConfig(queue_frames=64), ds.camera, ds.T_body_cam, ds.fps,
                         ds.origin, ds.gis_files[:1])
    for s in steps[:4]:
        rec.on_frame(s.frame, None)
    deadline = time.monotonic() + 10.0
    while rec.stats.frames < 4 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert rec.stats.frames == 4
    shutil.rmtree(rec.out / "images")
    for s in steps[4:]:
        rec.on_frame(s.frame, None)
        for g in s.gnss:
            rec.on_gnss(g)
    stats = rec.close()
    assert stats.stopped is not None and "write failed" in stats.stopped and stats.frames == 4
    meta = yaml.safe_load((rec.out / "dataset.yaml").read_text())["recording"]
    assert meta["stopped"] == stats.stopped and meta["complete"] is False


def test_no_recording_is_started_on_a_disk_under_min_free(tmp_path: Path) -> None:
    ds_cam = make_scenario("nominal", n_frames=1)
    with pytest.raises(OSError, match="min_free_mb"):
        open_recording(tmp_path / "rec", RecordingConfig(min_free_mb=1e12), ds_cam.camera, ds_cam.T_body_cam, 10.0,
                       ds_cam.origin, [])
    assert not any((tmp_path / "rec").glob("flight-*"))


def _dialect():
    """pymavlink's MAVLink 2 module of the bridge's dialect (mavlink_bridge.link sets MAVLINK20
    before pymavlink is imported)."""
    from mavlink_bridge.link import DIALECT

    return importlib.import_module(f"pymavlink.dialects.v20.{DIALECT}")


def _tlog_messages(path: Path) -> list:
    """Every message of a tlog as pymavlink's log reader gives it back (with its ``_timestamp``)."""
    from pymavlink import mavutil

    from mavlink_bridge.link import DIALECT  # sets MAVLINK20 before pymavlink is imported

    log = mavutil.mavlink_connection(str(path), dialect=DIALECT)
    out = []
    while (m := log.recv_match()) is not None:
        out.append(m)
    return out


def test_mavlink_traffic_is_kept_as_a_tlog_that_pymavlink_reads(tmp_path: Path) -> None:
    """Every message the bridge's link taps (received and sent) lands in mavlink.tlog, the ground
    stations' format: pymavlink's log reader gives them back with their UNIX times. The
    service's own tlog, over real UDP, is checked in test_service_e2e.py."""
    mavlink2 = _dialect()
    autopilot, us = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1), mavlink2.MAVLink(None, srcSystem=1, srcComponent=197)
    sent = [autopilot.heartbeat_encode(2, 3, 0, 0, 4).pack(autopilot),
            us.gps_input_encode(123456, 0, 0, 0, 0, 3, 473_769_000, 85_417_000, 541.0, 0.8, 1.1, 0, 0, 0, 0.3, 0.6, 0.8, 12).pack(us),
            autopilot.ekf_status_report_encode(0x1FF, 0.1, 0.2, 0.1, 0.0, 0.0).pack(autopilot)]
    cam = make_scenario("nominal", n_frames=1)
    rec = open_recording(tmp_path / "rec", RecordingConfig(), cam.camera, cam.T_body_cam, 10.0, cam.origin, [])
    t0 = time.time()
    for buf in sent:
        rec.on_mavlink(buf)
    t1 = time.time()
    stats = rec.close()
    assert stats.mavlink_messages == 3
    got = _tlog_messages(rec.out / "mavlink.tlog")
    assert [m.get_type() for m in got] == ["HEARTBEAT", "GPS_INPUT", "EKF_STATUS_REPORT"]
    assert got[1].lat == 473_769_000 and got[1].get_srcComponent() == 197 and got[2].flags == 0x1FF
    assert all(t0 - 1e-3 <= m._timestamp <= t1 + 1e-3 for m in got)
    meta = yaml.safe_load((rec.out / "dataset.yaml").read_text())["recording"]
    assert meta["mavlink_messages"] == 3 and abs(meta["unix_time_minus_clock_s"] - (time.time() - time.monotonic())) < 0.5


def test_the_tlog_keeps_the_frames_clock_when_the_wall_clock_steps(tmp_path: Path, monkeypatch) -> None:
    """A companion board without a real-time clock steps its wall clock mid-flight (NTP or GPS
    time arriving): the tlog's times stay on the recording's clock (dataset.yaml's UNIX offset plus
    time.monotonic()), in order, not an hour back with the wall clock."""
    mavlink2 = _dialect()
    autopilot = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    cam = make_scenario("nominal", n_frames=1)
    rec = open_recording(tmp_path / "rec", RecordingConfig(), cam.camera, cam.T_body_cam, 10.0, cam.origin, [])
    offset = yaml.safe_load((rec.out / "dataset.yaml").read_text())["recording"]["unix_time_minus_clock_s"]
    m0 = time.monotonic()
    rec.on_mavlink(autopilot.heartbeat_encode(2, 3, 0, 0, 4).pack(autopilot))
    real_time = time.time
    monkeypatch.setattr(time, "time", lambda: real_time() - 3600.0)  # the wall clock steps back an hour
    rec.on_mavlink(autopilot.heartbeat_encode(2, 3, 0, 0, 5).pack(autopilot))
    m1 = time.monotonic()
    monkeypatch.undo()
    rec.close()
    stamps = [m._timestamp for m in _tlog_messages(rec.out / "mavlink.tlog")]
    assert len(stamps) == 2 and stamps[0] <= stamps[1]
    assert all(offset + m0 - 1e-3 <= t <= offset + m1 + 1e-3 for t in stamps)
