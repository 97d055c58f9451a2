"""The SLAM map: keyframes and map points, guarded by one lock (held only by background threads
and for short snapshot copies)."""
from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from slam.geometry import camera_center


@dataclass
class Keyframe:
    kf_id: int
    t_s: float
    seq: int
    T_cam_slam: np.ndarray
    uv_px: np.ndarray  # (N,2) undistorted
    desc: np.ndarray  # (N,32)
    point_ids: np.ndarray  # (N,) int64, -1 where the feature has no map point

    @property
    def center(self) -> np.ndarray:
        return camera_center(self.T_cam_slam)


@dataclass
class MapPoint:
    point_id: int
    p_slam: np.ndarray
    desc: np.ndarray
    obs: dict[int, int] = field(default_factory=dict)  # kf_id -> feature index
    first_kf: int = 0


@dataclass(frozen=True)
class LocalMap:
    """Read-only arrays the tracking thread matches against (swapped atomically, never mutated)."""

    point_ids: np.ndarray
    p_slam: np.ndarray
    desc: np.ndarray
    version: int


class SlamMap:
    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.keyframes: dict[int, Keyframe] = {}
        self.points: dict[int, MapPoint] = {}
        self._next_kf = 0
        self._next_pt = 0

    def new_kf_id(self) -> int:
        self._next_kf += 1
        return self._next_kf - 1

    def add_keyframe(self, kf: Keyframe) -> None:
        self.keyframes[kf.kf_id] = kf
        for i, pid in enumerate(kf.point_ids.tolist()):
            if pid >= 0:
                mp = self.points.get(pid)
                if mp is None:
                    kf.point_ids[i] = -1
                else:
                    mp.obs[kf.kf_id] = i

    def add_point(self, p_slam: np.ndarray, desc: np.ndarray, obs: dict[int, int]) -> int:
        pid = self._next_pt
        self._next_pt += 1
        self.points[pid] = MapPoint(pid, np.asarray(p_slam, float), desc, dict(obs), min(obs))
        for kf_id, i in obs.items():
            self.keyframes[kf_id].point_ids[i] = pid
        return pid

    def remove_point(self, pid: int) -> None:
        mp = self.points.pop(pid, None)
        if mp is None:
            return
        for kf_id, i in mp.obs.items():
            kf = self.keyframes.get(kf_id)
            if kf is not None and kf.point_ids[i] == pid:
                kf.point_ids[i] = -1

    def remove_observation(self, pid: int, kf_id: int) -> None:
        mp = self.points.get(pid)
        if mp is None or kf_id not in mp.obs:
            return
        i = mp.obs.pop(kf_id)
        kf = self.keyframes.get(kf_id)
        if kf is not None and kf.point_ids[i] == pid:
            kf.point_ids[i] = -1
        if len(mp.obs) < 2:
            self.remove_point(pid)

    def replace_point(self, old: int, new: int) -> None:
        """Fuse point ``old`` into ``new`` (loop fusion): observations move over."""
        if old == new or old not in self.points or new not in self.points:
            return
        mo, mn = self.points[old], self.points[new]
        for kf_id, i in list(mo.obs.items()):
            if kf_id not in mn.obs:
                mn.obs[kf_id] = i
                self.keyframes[kf_id].point_ids[i] = new
            else:
                self.keyframes[kf_id].point_ids[i] = -1
        mo.obs.clear()
        self.points.pop(old)

    def kf_ids(self) -> list[int]:
        return sorted(self.keyframes)

    def local_map(self, kf_ids: list[int], version: int) -> LocalMap:
        ids: set[int] = set()
        for k in kf_ids:
            kf = self.keyframes.get(k)
            if kf is not None:
                ids.update(kf.point_ids[kf.point_ids >= 0].tolist())
        pids = np.array(sorted(i for i in ids if i in self.points), dtype=np.int64)
        if len(pids) == 0:
            return LocalMap(pids, np.zeros((0, 3)), np.zeros((0, 32), np.uint8), version)
        P = np.array([self.points[i].p_slam for i in pids.tolist()])
        D = np.array([self.points[i].desc for i in pids.tolist()])
        return LocalMap(pids, P, D, version)
