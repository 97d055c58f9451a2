"""The SLAM map: keyframes and map points, guarded by one lock (held only by background threads
and for short snapshot copies)."""
from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from slam.geometry import camera_center
from slam.patches import ImageLevels

# What a forgotten keyframe keeps instead of its features: shared read-only empty arrays (a slice
# like ``desc[:0]`` would be a view that keeps the whole feature buffer alive).
_NO_UV = np.zeros((0, 2))
_NO_DESC = np.zeros((0, 32), np.uint8)
_NO_IDS = np.zeros(0, np.int64)
for _a in (_NO_UV, _NO_DESC, _NO_IDS):
    _a.flags.writeable = False


@dataclass
class Keyframe:
    kf_id: int
    t_s: float
    seq: int
    T_cam_slam: np.ndarray
    uv_px: np.ndarray  # (N,2) undistorted; a feature with a map point: where the point's reference patch aligned (slam.patches)
    desc: np.ndarray  # (N,32)
    point_ids: np.ndarray  # (N,) int64, -1 where the feature has no map point
    g_cam: np.ndarray | None = None  # (3,) unit gravity ("down") in the camera frame, autopilot prior
    gravity_sigma_rad: float | None = None  # its 1-sigma angle
    # the image (all levels) and the features' octaves, while local mapping may still cut reference
    # patches from it or align patches in it (slam.patches); dropped after a few keyframes, never saved
    levels: ImageLevels | None = None

    @property
    def center(self) -> np.ndarray:
        return camera_center(self.T_cam_slam)

    @property
    def has_features(self) -> bool:
        """False once the memory cap has forgotten it (only its pose is left, for the trajectory)."""
        return len(self.desc) > 0

    def feature_bytes(self) -> int:
        lv = 0 if self.levels is None else self.levels.atlas.nbytes + self.levels.octave.nbytes
        return self.uv_px.nbytes + self.desc.nbytes + self.point_ids.nbytes + lv


@dataclass
class MapPoint:
    point_id: int
    p_slam: np.ndarray
    desc: np.ndarray
    obs: dict[int, int] = field(default_factory=dict)  # kf_id -> feature index
    first_kf: int = 0
    patch: np.ndarray | None = None  # (slam.patches.STORED_PX,)*2 uint8 reference patch, None: none
    patch_octave: int = -1  # the pyramid level it was cut at

    def set_patch(self, patch: np.ndarray, octave: int) -> None:
        """Keep ``patch`` (a row of a batch of cut patches) as this point's reference patch, cut at
        pyramid level ``octave``. Stored as a copy: a row would keep the whole batch alive."""
        self.patch, self.patch_octave = patch.copy(), int(octave)


@dataclass(frozen=True)
class LocalMap:
    """Read-only arrays the tracking thread matches against (swapped atomically, never mutated)."""

    point_ids: np.ndarray
    p_slam: np.ndarray
    desc: np.ndarray
    version: int


@dataclass(frozen=True)
class MapSize:
    """Counts and bytes of what the map holds (companion.slam_bench --memory prints these)."""

    keyframes: int  # all, including forgotten ones (pose only)
    keyframes_with_features: int
    map_points: int
    observations: int
    feature_bytes: int  # keyframes' pixels + descriptors + point ids
    point_bytes: int  # map points' positions + descriptors + reference patches (arrays only)


class SlamMap:
    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.keyframes: dict[int, Keyframe] = {}
        self.points: dict[int, MapPoint] = {}
        self._next_kf = 0
        self._next_pt = 0
        # z is up: the map was levelled with the autopilot's gravity at initialisation, so its
        # keyframes may carry gravity priors for BA (a map without it, e.g. started before the
        # first prior or loaded from disk, gets none: they would fight its arbitrary frame)
        self.gravity_aligned = False

    @property
    def keyframes_created(self) -> int:
        """Keyframes ever added to this map (a cheap "has it grown" revision)."""
        return self._next_kf

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
        # copies: a row of a batch array would keep the whole batch (e.g. a keyframe's descriptors) alive
        self.points[pid] = MapPoint(pid, np.array(p_slam, float), np.array(desc, np.uint8), dict(obs), min(obs))
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

    def forget_keyframe(self, kf_id: int) -> None:
        """Drop a keyframe's features and its observations; points nobody observes any more go.
        The pose stays (trajectory); the keyframe can no longer be matched or optimised."""
        kf = self.keyframes[kf_id]
        for pid in kf.point_ids[kf.point_ids >= 0].tolist():
            mp = self.points.get(pid)
            if mp is not None:
                mp.obs.pop(kf_id, None)
                if not mp.obs:
                    del self.points[pid]
        kf.uv_px, kf.desc, kf.point_ids, kf.levels = _NO_UV, _NO_DESC, _NO_IDS, None

    def drop_keyframe(self, kf_id: int) -> None:
        """Remove a keyframe entirely (its features must already be forgotten)."""
        if self.keyframes[kf_id].has_features:
            self.forget_keyframe(kf_id)
        del self.keyframes[kf_id]

    def size(self) -> MapSize:
        kfs = self.keyframes.values()
        pts = self.points.values()
        return MapSize(len(self.keyframes), sum(k.has_features for k in kfs), len(self.points),
                       sum(len(p.obs) for p in pts), sum(k.feature_bytes() for k in kfs),
                       sum(p.p_slam.nbytes + p.desc.nbytes + (0 if p.patch is None else p.patch.nbytes) for p in pts))

    def kf_ids(self) -> list[int]:
        return sorted(self.keyframes)

    def covisible(self, point_ids, top: int) -> list[int]:
        """Up to ``top`` keyframes observing the most of ``point_ids`` (ORB-SLAM's covisibility,
        from the points' observations), most shared first. Caller holds the lock."""
        counts: dict[int, int] = {}
        for p in np.asarray(point_ids, np.int64).tolist():
            mp = self.points.get(p)
            if mp is not None:
                for k in mp.obs:
                    counts[k] = counts.get(k, 0) + 1
        return [k for k, _ in sorted(counts.items(), key=lambda kv: (-kv[1], -kv[0]))[:top] if k in self.keyframes]

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
