"""SlamSystem: the public face of slam/ (issue 4 §6). Frames in, SlamPose out, MapUpdates polled.

``track`` runs in the caller's (tracking) thread and never waits on local mapping or loop
closing, which run in a background thread (BA in a worker process, see slam/ba.py).
"""
from __future__ import annotations

import queue
import time

import numpy as np

from slam.config import SlamConfig
from slam.features import make_extractor
from slam.geometry import inv_T
from slam.mapping import LocalMapper
from slam.tracking import Tracker
from slam.types import AttitudePrior, CameraModel, Frame, MapUpdate, SlamPose, TrackingState


class SlamSystem:
    def __init__(self, camera: CameraModel, config: SlamConfig | None = None) -> None:
        self.camera = camera
        self.config = config or SlamConfig()
        if self.config.use_attitude_prior:
            raise ValueError("slam.use_attitude_prior: attitude/baro priors are not implemented yet; set it to false")
        K = np.asarray(camera.K, float)
        if K.shape != (3, 3) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"camera.K must be a 3x3 intrinsics matrix with positive focal lengths, got {K!r}")
        self.tracker = Tracker(K, camera.width_px, camera.height_px, self.config, make_extractor(camera, self.config))
        self.mapper = LocalMapper(K, self.config, self.tracker.shared, self.tracker.map)
        self.reset_counter = 0
        self._last_seq: int | None = None

    def track(self, frame: Frame, prior: AttitudePrior | None = None) -> SlamPose:
        """Track one frame (hot path). ``prior`` is accepted for the API; it is ignored while
        ``use_attitude_prior`` is off (the only supported setting for now)."""
        t0 = time.perf_counter()
        img = frame.image
        if img.shape[:2] != (self.camera.height_px, self.camera.width_px):
            raise ValueError(f"frame {frame.seq}: image is {img.shape[1]}x{img.shape[0]} px, camera is "
                             f"{self.camera.width_px}x{self.camera.height_px} px")
        if self._last_seq is not None and frame.seq <= self._last_seq:
            raise ValueError(f"frame seq must increase: got {frame.seq} after {self._last_seq}")
        self._last_seq = frame.seq
        self.tracker.shared.pending_keyframes = self.mapper.pending()
        res = self.tracker.track(frame)
        if res.reset_map is not None:
            self.reset_counter += 1
            self.mapper.reset(res.reset_map)
        if res.new_keyframe is not None:
            self.mapper.insert_keyframe(res.new_keyframe)
        T_slam_cam = inv_T(res.T_cam_slam) if res.state.has_pose else np.full((4, 4), np.nan)
        return SlamPose(t_s=frame.t_s, seq=frame.seq, T_slam_cam=T_slam_cam, state=res.state,
                        reset_counter=self.reset_counter, n_inliers=res.n_inliers,
                        tracking_ms=(time.perf_counter() - t0) * 1e3, map_id=self.reset_counter)

    def poll_map_updates(self) -> list[MapUpdate]:
        out = []
        while True:
            try:
                out.append(self.mapper.updates.get_nowait())
            except queue.Empty:
                return out

    def map_points(self) -> MapUpdate:
        """Snapshot of all current map points (and the latest keyframe window)."""
        return self.mapper._snapshot(full=True)

    def keyframe_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(K,) keyframe times and (K,4,4) T_slam_cam of every keyframe of the current map."""
        m = self.mapper.map
        with m.lock:
            ids = m.kf_ids()
            return (np.array([m.keyframes[k].t_s for k in ids]),
                    np.array([inv_T(m.keyframes[k].T_cam_slam) for k in ids]).reshape(-1, 4, 4))

    @property
    def state(self) -> TrackingState:
        return self.tracker.state

    def wait_mapping(self, timeout_s: float = 60.0) -> bool:
        """Offline/tests only: block until queued keyframes are mapped."""
        return self.mapper.wait_idle(timeout_s)

    def close(self) -> None:
        self.mapper.close()

    def __enter__(self) -> "SlamSystem":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
