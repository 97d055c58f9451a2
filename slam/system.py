"""SlamSystem: the public face of slam/ (issue 4 §6). Frames in, SlamPose out, MapUpdates polled.

``track`` runs in the caller's (tracking) thread and never waits on local mapping or loop
closing, which run in a background thread (BA in a worker process, see slam/ba.py).

Map identity: ``map_id`` (random, 62 bits) names one map for its whole life, across save/load;
``reset_counter`` counts resets within this lineage. Both go into every SlamPose / MapUpdate, and
downstream alignments are keyed on the pair. ``save_map`` writes the current map (slam/persist.py)
from any thread; ``SlamSystem(camera, config, initial_map=load_map_file(...))`` starts in a saved
map with the same identity, relocalising into it (Tracker.resume) or, after ``reloc_timeout_s``
without success, resetting to a fresh map (new map_id, reset_counter + 1).
"""
from __future__ import annotations

import functools
import queue
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from slam.config import SlamConfig
from slam.features import make_extractor
from slam.geometry import inv_T
from slam.map import LocalMap
from slam.mapping import LocalMapper
from slam.patches import PatchAligner
from slam.persist import LoadedMap, MapFileError, SavedMap, new_map_id, save_map_file, snapshot_map
from slam.tracking import Gravity, Tracker
from slam.types import AttitudePrior, CameraModel, Frame, MapUpdate, SlamPose, TrackingState


class SlamSystem:
    def __init__(self, camera: CameraModel, config: SlamConfig | None = None, initial_map: LoadedMap | None = None,
                 reloc_timeout_s: float = 15.0, keep_loaded: bool = False, stepped: bool = False) -> None:
        """``keep_loaded``: the keyframes of ``initial_map`` are a reference (a site's survey map):
        the memory cap (``slam.max_keyframes``) never forgets them and applies to the keyframes
        this run adds. Off for a map this service saved itself, which would otherwise grow with
        every restart.
        ``stepped`` (offline, repeatable runs only; never live): a frame's new keyframe (or map
        reset) goes to local mapping at the next ``wait_mapping``, not at once. Otherwise local
        mapping starts on it while the caller still reads the map for the same frame (a
        ``map_points`` snapshot for fine-tuning), and what that read sees depends on how far this
        machine ran the mapping thread meanwhile."""
        self.camera = camera
        self.config = config or SlamConfig()
        K = np.asarray(camera.K, float)
        if K.shape != (3, 3) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"camera.K must be a 3x3 intrinsics matrix with positive focal lengths, got {K!r}")
        extract = make_extractor(camera, self.config)
        aligner = PatchAligner(camera) if self.config.patch_alignment else None
        if initial_map is None:
            self.tracker = Tracker(K, camera.width_px, camera.height_px, self.config, extract)
            self.map_id, self.reset_counter = new_map_id(), 0
        else:
            if not initial_map.slam_map.keyframes:
                raise MapFileError(initial_map.path, "the map has no keyframes")
            self.tracker = Tracker(K, camera.width_px, camera.height_px, self.config, extract, map=initial_map.slam_map)
            self.tracker.resume(reloc_timeout_s)
            self.map_id, self.reset_counter = initial_map.header.map_id, initial_map.header.reset_counter
        self._map_ids = {self.reset_counter: self.map_id}  # reset_counter -> map_id, for MapUpdates
        self._current = (self.tracker.map, self.map_id, self.reset_counter)  # swapped as one (save_map reads it)
        self.mapper = LocalMapper(K, self.config, self.tracker.shared, self.tracker.map, reset_counter=self.reset_counter,
                                  keep_loaded=keep_loaded, aligner=aligner)
        self.restored = initial_map is not None
        self._last_seq: int | None = None
        self._stepped = stepped
        self._deferred: list[Callable[[], None]] = []  # stepped: hand-overs to local mapping, in order

    def track(self, frame: Frame, prior: AttitudePrior | None = None) -> SlamPose:
        """Track one frame (hot path). ``prior``: the autopilot's attitude at the frame's capture
        time; with ``slam.use_attitude_prior`` its ``gravity_cam`` levels a new map and enters
        bundle adjustment (ignored otherwise, and when it has no gravity_cam)."""
        t0 = time.perf_counter()
        img = frame.image
        if img.shape[:2] != (self.camera.height_px, self.camera.width_px):
            raise ValueError(f"frame {frame.seq}: image is {img.shape[1]}x{img.shape[0]} px, camera is "
                             f"{self.camera.width_px}x{self.camera.height_px} px")
        if self._last_seq is not None and frame.seq <= self._last_seq:
            raise ValueError(f"frame seq must increase: got {frame.seq} after {self._last_seq}")
        self._last_seq = frame.seq
        self.tracker.shared.pending_keyframes = self.mapper.pending()
        res = self.tracker.track(frame, self._gravity(prior))
        if res.reset_map is not None:
            self.reset_counter += 1
            self.map_id = new_map_id()
            self._map_ids[self.reset_counter] = self.map_id
            self._current = (res.reset_map, self.map_id, self.reset_counter)
            self._to_mapping(functools.partial(self.mapper.reset, res.reset_map))
        if res.new_keyframe is not None:
            self._to_mapping(functools.partial(self.mapper.insert_keyframe, res.new_keyframe))
        T_slam_cam = inv_T(res.T_cam_slam) if res.state.has_pose else np.full((4, 4), np.nan)
        return SlamPose(t_s=frame.t_s, seq=frame.seq, T_slam_cam=T_slam_cam, state=res.state,
                        reset_counter=self.reset_counter, n_inliers=res.n_inliers,
                        tracking_ms=(time.perf_counter() - t0) * 1e3, map_id=self.map_id)

    def _to_mapping(self, hand_over: Callable[[], None]) -> None:
        if self._stepped:
            self._deferred.append(hand_over)
        else:
            hand_over()

    def _gravity(self, prior: AttitudePrior | None) -> Gravity | None:
        if not self.config.use_attitude_prior or prior is None or prior.gravity_cam is None:
            return None
        g_cam = np.asarray(prior.gravity_cam, float).reshape(3)
        n = np.linalg.norm(g_cam)
        if not (np.isfinite(n) and n > 0):
            return None
        sigma = prior.gravity_sigma_rad if prior.gravity_sigma_rad is not None else np.radians(self.config.attitude_prior_sigma_deg)
        return Gravity(g_cam / n, float(sigma))

    def _with_map_id(self, u: MapUpdate) -> MapUpdate:
        # local mapping knows its map by reset_counter only; the id goes with it
        return replace(u, map_id=self._map_ids.get(u.reset_counter, -1))

    def poll_map_updates(self) -> list[MapUpdate]:
        out = []
        while True:
            try:
                out.append(self._with_map_id(self.mapper.updates.get_nowait()))
            except queue.Empty:
                return out

    def map_points(self) -> MapUpdate:
        """Snapshot of all current map points (and the latest keyframe window)."""
        return self._with_map_id(self.mapper._snapshot(full=True))

    def tracked_points_slam(self) -> np.ndarray:
        """(N, 3) SLAM-frame positions of the map points the last frame's pose was solved from
        (its PnP inliers: what the camera sees now); empty when that frame had no tracked pose.
        Call from the thread that calls ``track``."""
        return self.tracker.tracked_p_slam

    def tracked_local_map(self) -> LocalMap | None:
        """The local map (point ids and SLAM positions, as local mapping last published them) the
        last frame's pose was solved against, or None when that frame had no pose. Lock-free and
        read-only: call from the thread that calls ``track``. Its positions change when local
        mapping or loop closing moves the points, in the same frame as the tracked pose follows."""
        return self.tracker.pose_map

    @property
    def resuming(self) -> bool:
        """Started in a loaded map and not relocalised in it yet (fresh map after reloc_timeout_s)."""
        return self.tracker.resuming

    def abandon_loaded_map(self) -> None:
        """Stop waiting to relocalise in the loaded map: the next frame starts a fresh map (new
        map_id, reset_counter + 1). No effect once relocalised. Call from the thread that calls
        ``track``."""
        self.tracker.abandon_resume()

    def current_map_key(self) -> tuple[int, int]:
        """(map_id, reset_counter) of the map being tracked now (as in SlamPose)."""
        _, map_id, reset_counter = self._current
        return map_id, reset_counter

    def map_revision(self) -> tuple[int, int, int]:
        """(map_id, reset_counter, keyframes created): changes when the map grows or is replaced."""
        slam_map, map_id, reset_counter = self._current
        return map_id, reset_counter, slam_map.keyframes_created

    def save_map(self, path: Path | str, attachments: dict | None = None) -> SavedMap | None:
        """Write the current map to ``path`` atomically (slam/persist.py); None while the map has
        no keyframes yet (initialising). Safe from any thread: the map is copied under its lock
        (which only local mapping / loop closing hold; tracking does not wait for it) and written
        without it. ``attachments`` (JSON) travel in the same file, e.g. the map's alignment."""
        slam_map, map_id, reset_counter = self._current
        t0 = time.perf_counter()
        snap = snapshot_map(slam_map)
        snapshot_ms = (time.perf_counter() - t0) * 1e3
        if snap.n_keyframes == 0:
            return None
        return save_map_file(path, snap, self.camera, map_id, reset_counter, attachments, snapshot_ms=snapshot_ms)

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
        """Offline/tests only: block until queued keyframes are mapped (``stepped``: hand over the
        keyframes tracked since the last call first)."""
        for hand_over in self._deferred:
            hand_over()
        self._deferred.clear()
        return self.mapper.wait_idle(timeout_s)

    def close(self) -> None:
        self.mapper.close()

    def __enter__(self) -> "SlamSystem":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
