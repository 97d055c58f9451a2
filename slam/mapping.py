"""Background thread: local mapping (triangulation, culling, local BA with PLM) and loop closing
(place recognition, Sim(3) verification, full or recursive correction). Nothing here is called
from the tracking thread; results reach it through ``Shared`` by reference swap.

This module holds the thread, the keyframe's processing and the memory cap; the bundle adjustments are
slam.local_ba, loop closing slam.loop_closing (both mixed into LocalMapper), the operations on the
map's points slam.map_points."""
from __future__ import annotations

import bisect
import logging
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from slam.ba import ba_worker
from slam.config import SlamConfig
from slam.geometry import triangulate
from slam.local_ba import LocalBundleAdjustment
from slam.loop_closing import LoopClosing
from slam.map import Keyframe, MapSize, SlamMap
from slam.map_points import (
    LEVELS_KEYFRAMES,
    TRIANGULATION_LOOKBACK,
    align_observations,
    cut_patches,
    fuse_points,
    triangulation_partners,
)
from slam.matching import match_bf
from slam.patches import PatchAligner
from slam.place import PlaceIndex, place_index_of
from slam.tracking import Shared
from slam.types import MapUpdate

log = logging.getLogger(__name__)


#: per-keyframe timing histories keep the latest this many entries (about 100 bytes per keyframe)
STATS_HISTORY = 10_000


def _history() -> deque:
    return deque(maxlen=STATS_HISTORY)


@dataclass
class MappingStats:
    """Timings for benchmarks: the latest STATS_HISTORY entries of each, plus exact totals."""

    local_mapping_ms: deque = field(default_factory=_history)  # whole keyframe processing
    local_ba_ms: deque = field(default_factory=_history)
    local_ba_cpu_ms: deque = field(default_factory=_history)  # CPU time of the same BAs (BAResult.solve_cpu_ms)
    ba_window: deque = field(default_factory=_history)
    loop_ms: deque = field(default_factory=_history)  # loop correction (BA part), per closed loop
    loops: deque = field(default_factory=_history)  # (old kf id, current kf id)
    loop_ba_keyframes: deque = field(default_factory=_history)  # keyframes optimised per loop (all windows)
    n_keyframes: int = 0  # keyframes mapped, all of them
    n_loops: int = 0
    ba_timeouts: int = 0  # BAs abandoned after BA_TIMEOUT_S (their worker restarted)
    fused_observations: int = 0  # observations fuse_points joined to existing points
    fused_points: int = 0  # duplicate points fuse_points merged


class UpdateQueue:
    """MapUpdates for a consumer, at most ``max_len`` of them: when full the oldest is dropped
    (counted in ``dropped``), and a full snapshot supersedes everything queued before it. A consumer
    that fell behind re-reads the whole map with ``SlamSystem.map_points()``. Nothing grows when
    nobody polls (the pipeline does not). Same interface as queue.SimpleQueue for put/get_nowait."""

    def __init__(self, max_len: int) -> None:
        self._q: deque[MapUpdate] = deque(maxlen=max_len)
        self._lock = threading.Lock()
        self.dropped = 0

    def put(self, u: MapUpdate) -> None:
        with self._lock:
            if u.full:
                self.dropped += len(self._q)
                self._q.clear()
            elif len(self._q) == self._q.maxlen:
                self.dropped += 1
            self._q.append(u)

    def get_nowait(self) -> MapUpdate:
        with self._lock:
            if not self._q:
                raise queue.Empty
            return self._q.popleft()

    def __len__(self) -> int:
        return len(self._q)


@dataclass(frozen=True)
class MapMemory:
    """What local mapping holds, for the memory benchmark (companion.slam_bench --memory)."""

    map: MapSize
    loop_anchors: int  # old keyframes kept with features for loop closing
    place_entries: int  # keyframes in the place-recognition index
    place_bytes: int  # descriptors stored in the place index
    queued_keyframes: int
    queued_updates: int
    dropped_updates: int


@dataclass
class _Reset:
    new_map: SlamMap


_STOP = object()


class LocalMapper(LocalBundleAdjustment, LoopClosing):
    def __init__(self, K: np.ndarray, config: SlamConfig, shared: Shared, slam_map: SlamMap,
                 reset_counter: int = 0, keep_loaded: bool = False, aligner: PatchAligner | None = None) -> None:
        self.K = K
        self.aligner = aligner  # reference patches for new points, sub-pixel observations (slam.patches)
        self.config = config
        self.shared = shared
        self.map = slam_map
        self.reset_counter = reset_counter
        self.stats = MappingStats()
        self.updates = UpdateQueue(config.max_queued_map_updates)
        self._inbox: queue.SimpleQueue = queue.SimpleQueue()
        with slam_map.lock:  # a map loaded from disk: its keyframes are places to close loops with
            self._place = place_index_of([slam_map.keyframes[k] for k in slam_map.kf_ids()])
        shared.place = (slam_map, self._place)
        self._anchors: list[int] = []  # loop anchors: old keyframes kept with features (see _forget_old)
        # A map loaded from disk (a restart, a survey map) is the reference its saved alignment
        # registers: its keyframes (ids up to this) are held in every BA, and as the camera may be
        # anywhere in it, a keyframe's neighbourhood is its covisible keyframes, not the newest
        # ones (_neighbourhood). -1: a map this process started.
        self._loaded_upto = max(slam_map.keyframes, default=-1)
        self._loaded_pt_upto = max(slam_map.points, default=-1)  # ... and its points, held in every BA too
        self._keep_loaded = keep_loaded  # ... and kept whole, outside the memory cap (a survey map: SlamSystem)
        self._retired_upto = -1  # keyframes with ids up to this one have left the active window
        self._n_retired = 0
        self._ba = ba_worker(config.ba_nice)
        self._lm_version = 0
        self._correction_gen = 0
        self._loop_cooldown_until = 0
        self._pending_ba = None
        self._n_local_ba = 0
        self._thread = threading.Thread(target=self._run, name="slam-mapping", daemon=True)
        self._thread.start()

    # --- called from the tracking thread (non-blocking) -----------------------------------------
    def insert_keyframe(self, kf: Keyframe) -> None:
        self._n_put += 1
        self._inbox.put(kf)

    def reset(self, new_map: SlamMap) -> None:
        self._n_put += 1
        self._inbox.put(_Reset(new_map))

    def close(self) -> None:
        self._inbox.put(_STOP)
        self._thread.join(timeout=30)
        self._ba.close()

    def pending(self) -> int:
        return self._inbox.qsize()

    def wait_idle(self, timeout_s: float = 60.0) -> bool:
        """For offline use/tests: wait until every keyframe put so far is processed and its local
        BA applied and published (counted, so a keyframe just taken off the queue is not missed)."""
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if self._n_done == self._n_put and self._pending_ba is None:
                return True
            time.sleep(0.001)
        return False

    # --- thread ---------------------------------------------------------------------------------
    _n_put = 0   # items put in the inbox (tracking thread)
    _n_done = 0  # items processed (mapping thread)

    def _run(self) -> None:
        while True:
            try:
                item = self._inbox.get(timeout=0.005 if self._pending_ba is not None else None)
            except queue.Empty:
                self._finish_ba(wait=False)
                continue
            if item is _STOP:
                return
            try:
                if isinstance(item, _Reset):
                    self._finish_ba(wait=True)
                    self.map = item.new_map
                    self._place = PlaceIndex()
                    self.shared.place = (item.new_map, self._place)
                    self._anchors, self._retired_upto, self._n_retired = [], -1, 0
                    self._loaded_upto = self._loaded_pt_upto = -1
                    self.reset_counter += 1
                else:
                    self._process(item)
            except Exception:  # keep mapping alive; tracking continues on the last local map
                log.exception("local mapping failed on a keyframe")
            finally:
                self.shared.mapping_busy = not self._inbox.empty()
                self._n_done += 1

    def _process(self, kf: Keyframe) -> None:
        t0 = time.perf_counter()
        m = self.map
        c = self.config
        with m.lock:
            m.add_keyframe(kf)
            tracked = []
            for i, pid in enumerate(kf.point_ids.tolist()):  # freshest appearance for matching
                if pid >= 0:
                    m.points[pid].desc = kf.desc[i].copy()  # a row view would keep kf.desc alive
                    tracked.append((i, pid))
            if self.aligner is not None:  # the tracker's matches observed where their patches align
                align_observations(self.aligner, m, kf, tracked)
            ids = self._neighbourhood(kf, m.kf_ids()) if self._loaded_upto >= 0 else m.kf_ids()
        self._finish_ba(wait=False)
        self._triangulate(kf, ids)
        if self.aligner is not None:
            with m.lock:
                cut_patches(self.aligner, m, kf)
        self._fuse(kf)
        self._cull(kf, ids)
        self._local_ba(kf, ids)  # submitted to the worker; applied when done (_finish_ba)
        self._publish(ids, kf)
        self.stats.local_mapping_ms.append((time.perf_counter() - t0) * 1e3)
        self.stats.n_keyframes += 1
        if c.loop_closing != "off":
            self._loop(kf)  # waits for the in-flight local BA before moving the map
        self._forget_old()
        with m.lock:
            for k in m.kf_ids()[:-LEVELS_KEYFRAMES]:
                m.keyframes[k].levels = None

    # --- local mapping --------------------------------------------------------------------------
    def _neighbourhood(self, kf: Keyframe, ids: list[int]) -> list[int]:
        """The keyframes (in id order, kf last) that share the most points with ``kf``: its window
        for triangulation, local BA and the tracker's local map in a map loaded from disk. There the
        newest keyframes can be a survey's far end, and a local BA over them with kf would leave kf
        and the points it shares with the old keyframes around it without anchor (they are only
        the fixed border, chosen by id nearness), so the pose jumped metres at each keyframe
        (ORB-SLAM's local mapping is covisibility-based for this reason). Call with m.lock held."""
        m, c = self.map, self.config
        top = max(c.local_window, c.periodic_ba_window, c.local_map_keyframes, TRIANGULATION_LOOKBACK + 1)
        near = set(m.covisible(kf.point_ids[kf.point_ids >= 0], top)) | {kf.kf_id}
        # and the loaded keyframes nearest to kf: the new keyframes observe fewer of the loaded
        # points each time (new points are triangulated beside them), so covisibility alone lets
        # the loaded map fall out of the tracker's local map and the pose drift off it
        loaded = [k for k in ids if k <= self._loaded_upto]
        if loaded:
            d = np.linalg.norm(np.array([m.keyframes[k].center for k in loaded]) - kf.center, axis=1)
            near.update(loaded[i] for i in np.argsort(d)[:c.local_map_keyframes])
        return [k for k in ids if k in near]

    def _triangulate(self, kf: Keyframe, ids: list[int]) -> None:
        """New points from the new keyframe's unmatched features and those of up to 2 earlier
        keyframes with enough baseline (triangulation_partners)."""
        m = self.map
        with m.lock:
            partners = triangulation_partners(m, kf, ids, self.config.triangulation_min_baseline_ratio)
        for other_id in partners:
            other = m.keyframes[other_id]
            a = np.flatnonzero(kf.point_ids < 0)
            b = np.flatnonzero(other.point_ids < 0)
            pairs = match_bf(kf.desc[a], other.desc[b], ratio=0.7, max_dist=60)
            if len(pairs) == 0:
                continue
            ia, ib = a[pairs[:, 0]], b[pairs[:, 1]]
            uv_b, patches, octave = self._partner_observations(kf, other, ia, ib)
            p, good = triangulate(self.K, kf.T_cam_slam, other.T_cam_slam, kf.uv_px[ia], uv_b,
                                  max_reproj_px=2.0, min_parallax_deg=1.0)
            with m.lock:
                for k in np.flatnonzero(good):
                    i, j = int(ia[k]), int(ib[k])
                    if kf.point_ids[i] < 0 and other.point_ids[j] < 0:
                        pid = m.add_point(p[k], kf.desc[i], {kf.kf_id: i, other.kf_id: j})
                        other.uv_px[j] = uv_b[k]
                        if octave[k] >= 0:
                            m.points[pid].set_patch(patches[k], octave[k])

    def _partner_observations(self, kf: Keyframe, other: Keyframe, ia: np.ndarray,
                              ib: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For new points between kf's features ia and other's ib: other's observations placed where
        kf's patches align in other's image (slam.patches), the patches, and their levels (-1: no
        patch). Without the images: other's features as detected."""
        uv_b = other.uv_px[ib]
        if self.aligner is None or kf.levels is None:
            return uv_b, np.zeros((len(ia), 0, 0), np.uint8), np.full(len(ia), -1)
        octave = kf.levels.octave[ia].astype(int)
        patches, ok = self.aligner.cut(kf.levels, kf.uv_px[ia], octave)
        octave = np.where(ok, octave, -1)
        if other.levels is not None:
            uv_b = self.aligner.align(other.levels, patches, octave, uv_b)[0]
        return uv_b, patches, octave

    def _fuse(self, kf: Keyframe) -> None:
        """The new keyframe's points into its ``fuse_keyframes`` most covisible keyframes, and
        theirs into it (fuse_points)."""
        n = self.config.fuse_keyframes
        if n == 0:
            return
        m = self.map
        with m.lock:
            own = kf.point_ids[kf.point_ids >= 0].tolist()
            nbrs = [m.keyframes[k] for k in m.covisible(own, n + 1) if k != kf.kf_id and m.keyframes[k].has_features]
            done = [fuse_points(m, self.K, o, kf.point_ids[kf.point_ids >= 0].tolist(), self._loaded_pt_upto, self.aligner)
                    for o in nbrs]
            theirs = {int(p) for o in nbrs for p in o.point_ids if p >= 0}
            done.append(fuse_points(m, self.K, kf, sorted(theirs), self._loaded_pt_upto, self.aligner))
        self.stats.fused_observations += sum(a for a, _ in done)
        self.stats.fused_points += sum(f for _, f in done)

    def _cull(self, kf: Keyframe, ids: list[int]) -> None:
        """Drop points created >= 3 keyframes ago that are seen by fewer than 3 keyframes (ORB-SLAM)."""
        if len(ids) < 4 or ids[-4] <= self._loaded_upto:  # never a loaded map's points (its window holds old keyframes)
            return
        old = ids[-4]
        m = self.map
        with m.lock:
            for pid in [p.point_id for p in m.points.values() if p.first_kf == old and len(p.obs) < 3]:
                m.remove_point(pid)

    def _publish_local_map(self, ids: list[int], kf: Keyframe | None = None) -> None:
        """The tracker's local map. In a map loaded from disk: ``ids`` whole, kf's neighbourhood
        (``_neighbourhood``: its covisible keyframes and the nearest loaded ones). Else the newest
        ``local_map_keyframes`` keyframes and, with ``kf``, the keyframes that share the most
        points with it: in a flight these are the newest ones anyway; after a loop closure or a
        relocalisation into an older part of the map they are the old keyframes there, so tracking
        goes on against the map it found instead of only the points it triangulates anew."""
        if self.shared.active_map is not self.map:
            return  # the tracker has already reset to a new map
        n = self.config.local_map_keyframes
        with self.map.lock:
            local = ids if self._loaded_upto >= 0 else ids[-n:]
            if kf is not None and self._loaded_upto < 0:  # (the neighbourhood holds kf's covisible keyframes already)
                newest = set(local)
                local = [k for k in self.map.covisible(kf.point_ids[kf.point_ids >= 0], n) if k not in newest] + local
            self._lm_version += 1
            self.shared.local_map = self.map.local_map(local, self._lm_version)

    def _publish(self, ids: list[int], kf: Keyframe) -> None:
        m = self.map
        c = self.config
        self._publish_local_map(ids, kf)
        with m.lock:
            upd_ids = [p for p in getattr(self, "_changed", []) if p in m.points]
            upd_ids += [int(p) for p in kf.point_ids if p >= 0 and p in m.points]
            upd_ids = sorted(set(upd_ids))
            win = ids[-c.local_window:]
            self.updates.put(MapUpdate(
                t_s=kf.t_s,
                points_slam=np.array([m.points[p].p_slam for p in upd_ids]).reshape(-1, 3),
                point_ids=np.array(upd_ids, np.int64),
                n_obs=np.array([len(m.points[p].obs) for p in upd_ids], np.int32),
                keyframe_t_s=np.array([m.keyframes[k].t_s for k in win]),
                keyframe_centers_slam=np.array([m.keyframes[k].center for k in win]).reshape(-1, 3),
                reset_counter=self.reset_counter, full=False, map_id=self.reset_counter))
        self._changed = []

    def _forget_old(self) -> None:
        """Memory cap (slam.max_keyframes, loop_anchor_every, max_loop_anchors, max_trajectory_keyframes).

        The newest ``max_keyframes`` keyframes are kept whole. A keyframe leaving that window becomes
        a loop anchor if it is the ``loop_anchor_every``-th to leave (it keeps its features, its
        points and its place-index entry, so a revisit of that place can still close a loop), else
        it is forgotten: features, observations, place-index entry and the points only it observed
        go; its pose stays for the trajectory. Beyond ``max_loop_anchors`` every second anchor is
        forgotten (older places keep a thinner coverage). Beyond ``max_trajectory_keyframes``
        forgotten keyframes the oldest poses are dropped too. A loaded map's keyframes kept whole
        (``keep_loaded``) are outside all of this.
        """
        c = self.config
        m = self.map
        forgotten: list[int] = []
        with m.lock:
            ids = m.kf_ids()
            n_kept = bisect.bisect_right(ids, self._loaded_upto) if self._keep_loaded else 0
            ids = ids[n_kept:]
            first_active = ids[-c.max_keyframes] if len(ids) > c.max_keyframes else None
            if first_active is not None:
                lo = bisect.bisect_right(ids, self._retired_upto)
                hi = bisect.bisect_left(ids, first_active)
                for k in ids[lo:hi]:
                    self._n_retired += 1
                    if c.max_loop_anchors and self._n_retired % c.loop_anchor_every == 0 and m.keyframes[k].has_features:
                        self._anchors.append(k)
                    elif m.keyframes[k].has_features:
                        m.forget_keyframe(k)
                        forgotten.append(k)
                    self._retired_upto = k
            if len(self._anchors) > c.max_loop_anchors:
                for k in self._anchors[1::2]:
                    m.forget_keyframe(k)
                    forgotten.append(k)
                self._anchors = self._anchors[::2]
            n_poses_only = len(m.keyframes) - n_kept - min(len(ids), c.max_keyframes) - len(self._anchors)
            if n_poses_only > c.max_trajectory_keyframes:  # trimmed to 90 % of the cap (amortised)
                anchors = set(self._anchors)
                old = [k for k in ids if k <= self._retired_upto and k not in anchors]
                for k in old[: n_poses_only - int(0.9 * c.max_trajectory_keyframes)]:
                    m.drop_keyframe(k)
        if forgotten:
            self._place.remove(forgotten)

    def memory(self) -> MapMemory:
        """Sizes of the map, loop anchors, place index and queues (takes the map lock briefly)."""
        with self.map.lock:
            size = self.map.size()
        return MapMemory(size, len(self._anchors), len(self._place), self._place.nbytes(), self._inbox.qsize(),
                         len(self.updates), self.updates.dropped)
