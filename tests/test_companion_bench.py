"""Benchmarks of the companion building blocks (figures printed, nothing timed is asserted).

Run: pytest tests/test_companion_bench.py -m slow -s
"""
from __future__ import annotations

import time

import numpy as np
import pytest

from companion.calibration import make_calibration
from companion.camera import open_sim_source
from companion.supervisor import LatencyTracker
from slam.types import CameraModel, Frame

pytestmark = pytest.mark.slow


def test_bench_undistort_and_latest_frame_latency() -> None:
    w, h = 640, 480
    raw = CameraModel(w, h, np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), np.array([-0.25, 0.08, 0.001, -0.001, 0.0]))
    cal = make_calibration(raw)
    image = np.random.default_rng(0).integers(0, 255, (h, w, 3), dtype=np.uint8)
    t0 = time.perf_counter()
    for _ in range(200):
        cal.undistort(image)
    undistort_ms = (time.perf_counter() - t0) / 200 * 1e3

    # a 30 fps "camera" (realtime-paced frames) read by a consumer that needs 50 ms per frame:
    # latest-frame policy → grab-to-read latency stays bounded, frames are dropped instead of queued
    frames = (Frame(image=image, t_s=i / 30.0, seq=i) for i in range(150))
    tracker = LatencyTracker()
    with open_sim_source(frames, raw, realtime=True) as src:
        while not src.eof:
            f = src.read(0.5)
            if f is None:
                continue
            tracker.start(f.seq, src.capture_info(f.seq).grab_t_s)
            tracker.mark(f.seq, "read")
            time.sleep(0.05)
            tracker.mark(f.seq, "processed")
            tracker.finish(f.seq)
        stats = src.stats()
    s = tracker.summary()
    print(f"\nundistort {w}x{h} BGR: {undistort_ms:.2f} ms/frame")
    print(f"latest-frame, 30 fps source, 50 ms consumer: grabbed {stats.grabbed}, delivered {stats.delivered}, dropped {stats.dropped}")
    print(f"grab→read p50 {s['capture→read'].p50_ms:.1f} ms p99 {s['capture→read'].p99_ms:.1f} ms; "
          f"grab→processed p50 {s['capture→processed'].p50_ms:.1f} ms p99 {s['capture→processed'].p99_ms:.1f} ms")
    assert stats.grabbed == 150 and stats.delivered + stats.dropped == 150
