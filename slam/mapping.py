"""Background thread: local mapping (triangulation, culling, local BA with PLM) and loop closing
(place recognition, Sim(3) verification, full or recursive correction). Nothing here is called
from the tracking thread; results reach it through ``Shared`` by reference swap."""
from __future__ import annotations

import bisect
import logging
import queue
import threading
import time
from collections import deque
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from itertools import chain

import numpy as np

from slam.ba import BAProblem, BAResult, ba_worker, bundle_adjust
from slam.config import SlamConfig
from slam.geometry import correct_pose_by_sim3, parallax_deg, project, ransac_sim3, sim3_share, triangulate
from slam.map import Keyframe, MapSize, SlamMap
from slam.matching import TH_LOW, candidates_by_projection, match_bf
from slam.patches import PatchAligner
from slam.place import PlaceIndex, place_index_of
from slam.plm import plm_window, recursive_loop_closing
from slam.tracking import Shared
from slam.types import MapUpdate

log = logging.getLogger(__name__)


#: per-keyframe timing histories keep the latest this many entries (about 100 bytes per keyframe)
STATS_HISTORY = 10_000
# A bundle adjustment not back from its worker process after this long is abandoned: the worker is
# restarted and mapping goes on without it. Measured BAs take 0.05-3.3 s on 2 cores (full-loop BA
# the longest, docs/BENCHMARKS.md); on 2026-12-04 a local BA's job never reached an idle worker
# under heavy load (3 processes on 2 cores), and with one local BA in flight at a time, mapping
# then ran without local BA for the rest of the flight (cause in ProcessPoolExecutor not found).
BA_TIMEOUT_S = 60.0
NEVER_SEEN_KF_AGE = np.iinfo(np.int32).max  # a map point no held keyframe observes (map_point_arrays)


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
    """What local mapping holds, for the memory benchmark (slam.bench --memory)."""

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


def _gravity_arrays(kfs: list[Keyframe]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(P,3) g_cam (NaN rows without a prior) and (P,) sigmas for BAProblem; (None, None) when no
    keyframe has a gravity prior (slam.use_attitude_prior off)."""
    if all(kf.g_cam is None for kf in kfs):
        return None, None
    g = np.array([kf.g_cam if kf.g_cam is not None else np.full(3, np.nan) for kf in kfs], float)
    sigma = np.array([kf.gravity_sigma_rad if kf.g_cam is not None else np.nan for kf in kfs], float)
    return g, sigma


def map_point_arrays(m: SlamMap, pids: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(N,3) SLAM positions, (N,) observation counts, (N,) parallax (deg) and (N,) keyframe age of
    the points ``pids``.

    Parallax: the angle between the rays to a point from the first and the last keyframe that
    observe it (0 when one does). A point's depth error grows as 1/parallax (a feature's bearing
    noise of ~1 mrad gives ~0.5 m at 15° and 100–150 m range), so alignment can leave out the
    poorly triangulated ones. Keyframe age: how many keyframes were created after the newest one
    that observes the point (0: the newest keyframe sees it; a large sentinel when no keyframe the
    map still holds does), so alignment can keep to the part of the map the camera is in now.
    Vectorised over the flattened observations: a loop per point took
    80 % of a full map snapshot, which runs on the tracking thread (docs/BENCHMARKS.md,
    "Fine-tuning cost": "Map snapshot, vectorised parallax"). Call with m.lock held."""
    pts = [m.points[p] for p in pids]
    P = np.array([mp.p_slam for mp in pts], float).reshape(-1, 3)
    n_obs = np.fromiter((len(mp.obs) for mp in pts), np.int64, len(pts))
    kf = np.fromiter(chain.from_iterable(mp.obs for mp in pts), np.int64, int(n_obs.sum()))
    owner = np.repeat(np.arange(len(pts)), n_obs)
    # centres of the observing keyframes only: the map also holds up to max_trajectory_keyframes
    # forgotten ones (pose only), and this runs on the tracking thread
    ids = np.array([k for k in np.unique(kf).tolist() if k in m.keyframes], np.int64)
    known = np.isin(kf, ids)  # an observation of a keyframe the map no longer holds does not count
    kf, owner = kf[known], owner[known]
    first = np.full(len(pts), np.iinfo(np.int64).max)
    last = np.full(len(pts), -1)
    np.minimum.at(first, owner, kf)
    np.maximum.at(last, owner, kf)
    two = np.bincount(owner, minlength=len(pts)) >= 2
    centers = np.array([m.keyframes[k].center for k in ids.tolist()]).reshape(-1, 3)
    A, B = P.copy(), P.copy()  # a point without two observing keyframes: zero-length rays → 0°
    A[two] = centers[np.searchsorted(ids, first[two])]
    B[two] = centers[np.searchsorted(ids, last[two])]
    # keyframe ids are allocated in sequence (SlamMap.new_kf_id), so an id difference counts the
    # keyframes made since; the newest is the last id handed out, held whole by the map
    age = np.where(last >= 0, (m.keyframes_created - 1) - last, NEVER_SEEN_KF_AGE).astype(np.int64)
    return P, n_obs.astype(np.int32), parallax_deg(P, A, B), age


TRIANGULATION_LOOKBACK = 8  # earlier keyframes searched for a triangulation partner
STARVING_TRACKED = 100  # a new keyframe tracking fewer map points than this gets a third, nearer partner
STARVING_BASELINE_FRACTION = 0.4  # ... at least this share of the partners' baseline away


def triangulation_partners(m: SlamMap, kf: Keyframe, ids: list[int], min_baseline_ratio: float) -> list[int]:
    """Keyframe ids the new keyframe ``kf`` triangulates its unmatched features with: the 2 newest
    (newest first) of the last TRIANGULATION_LOOKBACK earlier ones whose centre is at least
    ``min_baseline_ratio`` × kf's median scene depth away (both in SLAM units: the ratio is
    scale-free); only the previous keyframe when none is. With 0, or with < 10 tracked points to
    measure the depth: the 2 previous keyframes, oldest first (the rule before this one).

    Why: in a turn the tracker adds a keyframe every ``keyframe_max_rotation_deg``, a few metres
    apart at 100+ m depth. Points triangulated between such neighbours have 1–2° of parallax, depth
    errors of ~5–10 %, and they carried the map's scale 4–8 % off through each turn (the error after
    a GNSS loss doubled; docs/BENCHMARKS.md). ORB-SLAM skips neighbours under 1 % of the depth
    (LocalMapping::CreateNewMapPoints); ours needs more because the turn keyframes are dense.
    ``ids`` is the map's keyframe ids in order, kf's last. Call with m.lock held.

    Only earlier keyframes that share a point with kf qualify (when kf's points are seen by any):
    a view of another place, which the baseline rule would prefer for its length, only triangulates
    chance descriptor matches. After a relocalisation into an older part of the map (a resumed or
    survey map) none of the newest keyframes does; the keyframes that share the most points with
    kf (``SlamMap.covisible``) are the earlier ones then."""
    earlier = ids[-TRIANGULATION_LOOKBACK - 1:-1]
    pids = [p for p in kf.point_ids.tolist() if p >= 0 and p in m.points]
    seen = {k for p in pids for k in m.points[p].obs} - {kf.kf_id}
    if seen:
        earlier = ([k for k in earlier if k in seen]
                   or sorted(k for k in m.covisible(pids, TRIANGULATION_LOOKBACK + 1) if k != kf.kf_id))
    if min_baseline_ratio <= 0:
        return earlier[-2:]
    if len(pids) < 10:  # no depth to compare with
        return earlier[-2:]
    P = np.array([m.points[p].p_slam for p in pids])
    depth_slam = float(np.median(P @ kf.T_cam_slam[2, :3] + kf.T_cam_slam[2, 3]))  # along the optical axis
    c = kf.center
    dist = {i: float(np.linalg.norm(m.keyframes[i].center - c)) for i in earlier}
    far = [i for i in reversed(earlier) if dist[i] >= min_baseline_ratio * depth_slam]
    parts = far[:2] or earlier[-1:]
    if len(pids) < STARVING_TRACKED:
        # the tracker is running out of points (a turn: keyframes every 10 deg, the partners far
        # enough away are the ones whose view is leaving); add the newest keyframe at a
        # STARVING_BASELINE_FRACTION of that baseline, whose view still overlaps
        near = [i for i in reversed(earlier) if i not in parts
                and dist[i] >= STARVING_BASELINE_FRACTION * min_baseline_ratio * depth_slam]
        parts += near[:1]
    return parts


FUSE_RADIUS_PX = 3.0  # a neighbour's point must project this close to a feature (ORB-SLAM Fuse, th=3)


def fuse_points(m: SlamMap, K: np.ndarray, kf: Keyframe, pids: list[int], protect_upto: int = -1,
                aligner: PatchAligner | None = None) -> tuple[int, int]:
    """Project map points ``pids`` into keyframe ``kf`` and join each to the feature it lands on
    (ORB-SLAM's Fuse in SearchInNeighbors): the closest descriptor within FUSE_RADIUS_PX and
    Hamming TH_LOW. A feature without a point gains the observation; a feature that holds another
    point is one physical point triangulated twice, and the two become one (the one with more
    observations stays; a point with id <= ``protect_upto``, a loaded map's, is never the one
    fused away). Without this a point the tracker missed for a frame or two was triangulated again
    beside itself, each copy seen by fewer keyframes (nominal, 900 frames: 6 360 keyframe views of a
    point landed on a feature that held another point; fusing merges a third of them and adds 18 %
    more observations, docs/BENCHMARKS.md). With ``aligner`` and kf's image still held, a joined
    observation is placed where the point's reference patch aligns (slam.patches). Caller holds
    m.lock. Returns (observations added, points fused)."""
    pids = [p for p in pids if p in m.points and kf.kf_id not in m.points[p].obs]
    if not pids or not kf.has_features:
        return 0, 0
    P = np.array([m.points[p].p_slam for p in pids])
    uv, z = project(K, kf.T_cam_slam, P)
    front = np.flatnonzero(z > 0)
    if len(front) == 0:
        return 0, 0
    desc = np.array([m.points[pids[j]].desc for j in front.tolist()])
    hd, idx = candidates_by_projection(uv[front], desc, kf.uv_px, kf.desc, FUSE_RADIUS_PX, k=8)
    b = np.argmin(hd, axis=1)
    rows = np.arange(len(front))
    d1, feat = hd[rows, b], idx[rows, b]
    ok = np.flatnonzero(d1 <= TH_LOW)
    ok = ok[np.argsort(d1[ok], kind="stable")]
    _, first = np.unique(feat[ok], return_index=True)  # each feature to its closest descriptor
    fused = 0
    joined: list[tuple[int, int]] = []  # (feature, point)
    for i in ok[first].tolist():
        f, pid = int(feat[i]), pids[int(front[i])]
        held = int(kf.point_ids[f])
        if pid not in m.points or kf.kf_id in m.points[pid].obs:
            continue  # fused away or joined earlier in this pass
        if held < 0 or held not in m.points:
            m.points[pid].obs[kf.kf_id] = f
            kf.point_ids[f] = pid
            joined.append((f, pid))
            continue
        keep, drop = (pid, held) if len(m.points[pid].obs) >= len(m.points[held].obs) else (held, pid)
        if drop <= protect_upto:
            keep, drop = drop, keep
            if drop <= protect_upto:
                continue  # both loaded: left as the map was saved
        m.replace_point(drop, keep)
        fused += 1
    if aligner is not None:
        align_observations(aligner, m, kf, [(f, p) for f, p in joined if p in m.points])
    return len(joined), fused


def loop_shares(m: SlamMap, loop: list[int], window: set[int], S: np.ndarray, center: np.ndarray,
                 loaded_upto: int) -> dict[int, np.ndarray]:
    """Loop correction for the keyframes inside the loop that the correction's window leaves
    out: keyframe ids ``loop`` run from the old keyframe (untouched) to the current one (moved by
    S with ``window``). Each of the others gets the share of S (slam.geometry.sim3_share, about
    ``center``) of its distance along the loop's camera path, so the loop's middle follows both
    ends. Without this only the window moved: the keyframes just before it kept the drifted
    coordinates beside the corrected ones, and on the `loop` flight's second lap the tracker
    met both, relocalised, and drifted off the first lap again (5-20 m, loops re-closed every
    10-20 s; docs/BENCHMARKS.md "Loop closing keeps the whole loop continuous"). A loaded map's
    keyframes (id <= loaded_upto) never move. Caller holds m.lock."""
    inner = [k for k in loop[1:-1] if k not in window and k > loaded_upto]
    if not inner:
        return {}
    C = np.array([m.keyframes[k].center for k in loop])
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(C, axis=0), axis=1))])
    if along[-1] <= 0:
        return {}
    share = dict(zip(loop, (along / along[-1]).tolist()))
    return {k: sim3_share(S, share[k], center) for k in inner}


def move_by_corrections(m: SlamMap, corrections: dict[int, np.ndarray], protect_upto: int = -1) -> None:
    """Move each keyframe of ``corrections`` (kf id → similarity, p_new = S p_old) and each of
    their points by its reference keyframe's correction (ORB-SLAM's CorrectLoop); a point whose
    reference keyframe has none stays, and so does a loaded map's (id <= ``protect_upto``).
    Caller holds m.lock."""
    moved: set[int] = set()
    for k, S_k in corrections.items():
        kfk = m.keyframes[k]
        kfk.T_cam_slam = correct_pose_by_sim3(kfk.T_cam_slam, S_k)
        for pid in kfk.point_ids[kfk.point_ids >= 0].tolist():
            if pid in moved or pid not in m.points or pid <= protect_upto:
                continue
            moved.add(pid)
            p = m.points[pid]
            S_p = corrections.get(p.first_kf)
            if S_p is not None:
                p.p_slam = S_p[:3, :3] @ p.p_slam + S_p[:3, 3]


def align_observations(aligner: PatchAligner, m: SlamMap, kf: Keyframe, obs: list[tuple[int, int]]) -> int:
    """Move kf's features ``obs`` ((feature, point) pairs) to where their points' reference patches
    align in kf's image (slam.patches); those without a patch, or kf without its image, stay.
    Caller holds m.lock. Returns how many moved."""
    obs = [(f, p) for f, p in obs if m.points[p].patch is not None]
    if kf.levels is None or not obs:
        return 0
    f = np.array([o[0] for o in obs])
    pts = [m.points[o[1]] for o in obs]
    uv, ok = aligner.align(kf.levels, np.array([p.patch for p in pts]), np.array([p.patch_octave for p in pts]), kf.uv_px[f])
    kf.uv_px[f[ok]] = uv[ok]
    return int(ok.sum())


LEVELS_KEYFRAMES = 10  # the newest keyframes keep their image for patch alignment (~1 MB each at 640x480)


def cut_patches(aligner: PatchAligner, m: SlamMap, kf: Keyframe) -> int:
    """Give every point kf observes that has no reference patch one, cut from kf's image at its
    observation (slam.patches). Caller holds m.lock. Returns how many were given one."""
    if kf.levels is None:
        return 0
    f = np.array([i for i, p in enumerate(kf.point_ids.tolist()) if p >= 0 and p in m.points and m.points[p].patch is None], int)
    if len(f) == 0:
        return 0
    octave = kf.levels.octave[f]
    patches, ok = aligner.cut(kf.levels, kf.uv_px[f], octave)
    for j in np.flatnonzero(ok).tolist():
        m.points[int(kf.point_ids[f[j]])].set_patch(patches[j], octave[j])
    return int(ok.sum())


class LocalMapper:
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

    def _local_ba(self, kf: Keyframe, ids: list[int]) -> None:
        c = self.config
        w = c.local_window
        prev = [self.map.keyframes[i].center for i in ids[:-1][-w:]]
        prev_t = np.array([self.map.keyframes[i].t_s for i in ids[:-1][-w:]])
        win = (plm_window(np.array(prev), kf.center, w, prev_t, kf.t_s)
               if c.progressive_local_mapping and len(prev) >= 2 else w)
        if self._pending_ba is not None:
            return  # one local BA in flight at a time; this keyframe's points are mapped already
        n_fixed = c.ba_fixed_keyframes or max(2, w // 2)
        self._n_local_ba += 1
        if c.periodic_ba_every_keyframes and self._n_local_ba % c.periodic_ba_every_keyframes == 0:
            # occasional larger window (still in the worker process); PLM halves it as well while
            # the motion is reliable (Eq. 4), so straight stretches do not pay for the turns
            win = max(win, c.periodic_ba_window if win >= w else c.periodic_ba_window // 2)
        job = self._build_ba(ids[-win:], max_fixed=n_fixed)
        if job is not None:
            self.stats.ba_window.append(win)
            self._pending_ba = (self._ba.submit(bundle_adjust, job[0]), job, kf, time.monotonic())

    def _finish_ba(self, wait: bool) -> None:
        """Apply the in-flight local BA once it is done (BA never holds up new keyframes' mapping)."""
        if self._pending_ba is None:
            return
        fut, job, kf, t_submit = self._pending_ba
        late = time.monotonic() - t_submit > BA_TIMEOUT_S
        if not (wait or fut.done() or late):
            return
        try:  # pending until applied and published (wait_idle)
            try:
                res: BAResult = fut.result(timeout=max(0.0, t_submit + BA_TIMEOUT_S - time.monotonic()))
            except TimeoutError:
                self.stats.ba_timeouts += 1
                self._ba.restart(f"a local BA was not back after {BA_TIMEOUT_S:.0f} s: skipped")
                return
            except BrokenProcessPool:
                log.error("bundle-adjustment worker died during a local BA: that BA is skipped")
                return
            except Exception:
                log.exception("bundle adjustment failed")
                return
            self._apply_ba(res, job)
            self.stats.local_ba_ms.append(res.solve_ms)
            self.stats.local_ba_cpu_ms.append(res.solve_cpu_ms)
            with self.map.lock:
                ids = self.map.kf_ids()
            if ids:
                self._publish(ids, kf)
        finally:
            self._pending_ba = None

    def _run_ba(self, kf_ids: list[int], max_fixed: int) -> BAResult | None:
        """Synchronous BA (loop closing): build, solve in the worker process, write back."""
        job = self._build_ba(kf_ids, max_fixed)
        if job is None:
            return None
        try:
            res: BAResult = self._ba.submit(bundle_adjust, job[0]).result(timeout=BA_TIMEOUT_S)
        except TimeoutError:
            self.stats.ba_timeouts += 1
            self._ba.restart(f"a loop-closing BA was not back after {BA_TIMEOUT_S:.0f} s: skipped")
            return None
        except BrokenProcessPool:
            log.error("bundle-adjustment worker died during a loop-closing BA: that BA is skipped")
            return None
        except Exception:
            log.exception("bundle adjustment failed")
            return None
        self._apply_ba(res, job)
        return res

    def _build_ba(self, kf_ids: list[int], max_fixed: int):
        """BA problem for these keyframes (+ fixed neighbours that see their points)."""
        m = self.map
        c = self.config
        with m.lock:
            kf_ids = [k for k in kf_ids if k in m.keyframes and m.keyframes[k].has_features]
            pids = sorted({int(p) for k in kf_ids for p in m.keyframes[k].point_ids if p >= 0})
            pids = [p for p in pids if p in m.points]
            if len(pids) < 10:
                return None
            win = set(kf_ids)
            border = {k for p in pids for k in m.points[p].obs if k not in win and k in m.keyframes}
            # hold the border keyframes closest (in keyframe order) to the window; a local window's
            # border is all older, so these are the newest; a loop window with two ends (RLC, Alg. 1
            # line 1) gets anchors at both ends instead of a free-floating old end
            fixed_ids = sorted(sorted(border, key=lambda k: (min(abs(k - w) for w in win), -k))[:max_fixed])
            all_ids = fixed_ids + kf_ids
            fixed = np.array([k in fixed_ids or k <= self._loaded_upto for k in all_ids])
            if fixed.sum() < 2:  # gauge: monocular BA needs >= 2 held poses (7 DoF)
                fixed[: 2] = True
            pose_idx = {k: i for i, k in enumerate(all_ids)}
            pt_idx = {p: j for j, p in enumerate(pids)}
            o_pose, o_pt, o_uv = [], [], []
            for p in pids:
                for k, f in m.points[p].obs.items():
                    if k in pose_idx:
                        o_pose.append(pose_idx[k])
                        o_pt.append(pt_idx[p])
                        o_uv.append(m.keyframes[k].uv_px[f])
            g_cam, g_sigma = _gravity_arrays([m.keyframes[k] for k in all_ids])
            prob = BAProblem(self.K, np.array([m.keyframes[k].T_cam_slam for k in all_ids]), fixed,
                             np.array([m.points[p].p_slam for p in pids]), np.array(o_pose), np.array(o_pt),
                             np.array(o_uv), max_iterations=c.ba_iterations, g_cam=g_cam, gravity_sigma_rad=g_sigma,
                             fixed_points=np.array(pids) <= self._loaded_pt_upto if self._loaded_pt_upto >= 0 else None)
        return prob, m, all_ids, fixed, pose_idx, pids, o_pt, o_pose

    def _apply_ba(self, res: BAResult, job) -> None:
        """Write BA results back (skipping what was removed meanwhile) and drop bad observations."""
        _, m, all_ids, fixed, pose_idx, pids, o_pt, o_pose = job
        c = self.config
        with m.lock:
            if m is not self.map:
                return
            levelled = job[0].levelled_anchors  # fixed by their centres only: re-oriented by BA
            for k, T in zip(all_ids, res.T_cam_slam):
                if k in m.keyframes and (not fixed[pose_idx[k]] or levelled[pose_idx[k]]):
                    m.keyframes[k].T_cam_slam = T
            for p, X in zip(pids, res.points_slam):
                if p in m.points:
                    m.points[p].p_slam = X
            bad = np.flatnonzero(~(res.residual_px < c.max_reproj_px))
            for b in bad:
                m.remove_observation(pids[o_pt[b]], all_ids[o_pose[b]])
        self._changed = pids

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

    # --- loop closing ---------------------------------------------------------------------------
    def _loop(self, kf: Keyframe) -> None:
        c = self.config
        cands = self._place.query(kf.desc, exclude_after_kf_id=kf.kf_id - c.loop_min_gap_keyframes)
        self._place.add(kf.kf_id, kf.desc)
        if kf.kf_id < self._loop_cooldown_until:
            return
        with self.map.lock:
            own = set(kf.point_ids[kf.point_ids >= 0].tolist())
            shared = {cand.kf_id: len(own & set(self.map.keyframes[cand.kf_id].point_ids.tolist()))
                      for cand in cands if cand.kf_id in self.map.keyframes}
        for cand in cands[:2]:
            if cand.score < c.loop_min_score:
                break
            log.debug("loop candidate %d score %.3f shared %d", cand.kf_id, cand.score, shared.get(cand.kf_id, 0))
            if shared.get(cand.kf_id, 0) >= c.loop_min_inliers // 2:
                continue  # already connected through common map points: nothing to close
            S = self._verify(kf, cand.kf_id)
            if S is not None and self._correct(kf, cand.kf_id, S):
                self._loop_cooldown_until = kf.kf_id + c.local_window
                return

    def _verify(self, kf: Keyframe, old_id: int):
        """Sim(3) between the current keyframe's points and the candidate's (3D-3D RANSAC)."""
        m = self.map
        with m.lock:
            old = m.keyframes.get(old_id)
            if old is None or len(old.desc) == 0:
                return None
            a = np.flatnonzero(kf.point_ids >= 0)
            b = np.flatnonzero(old.point_ids >= 0)
            a = a[[int(kf.point_ids[i]) in m.points for i in a]]
            b = b[[int(old.point_ids[i]) in m.points for i in b]]
            pairs = match_bf(kf.desc[a], old.desc[b], ratio=0.8, max_dist=64)
            if len(pairs) < self.config.loop_min_inliers:
                return None
            pa = [int(kf.point_ids[a[i]]) for i in pairs[:, 0]]
            pb = [int(old.point_ids[b[j]]) for j in pairs[:, 1]]
            src = np.array([m.points[p].p_slam for p in pa])
            dst = np.array([m.points[p].p_slam for p in pb])
            depth = np.median(np.linalg.norm(src - kf.center, axis=1))
        S, inl = ransac_sim3(src, dst, thresh=0.03 * depth)
        if S is None or inl.sum() < self.config.loop_min_inliers:
            return None
        self._loop_pairs = [(pa[i], pb[i]) for i in np.flatnonzero(inl)]
        return S

    def _correct(self, kf: Keyframe, old_id: int, S: np.ndarray) -> bool:
        """Move the current keyframe and its covisible recent keyframes by S (ORB-SLAM's loop
        correction neighbourhood) and the keyframes between them and the old one by a share of S
        (``loop_shares``), each point with its reference keyframe; fuse the matched points, then
        BA: Algorithm 1 (recursive) or the whole loop at once (full) — same starting state, so the
        two are comparable. With a map loaded from disk, its keyframes and points never move (its
        alignment registers them where they are): they stay out of the moved window and survive
        every fusion, and a loop from a keyframe that sees them to one of the flight's own is not
        closed (False): the current keyframe is held by the loaded map already, and the correction
        would pull it towards the flight's drifted part, off the map its alignment registers."""
        c = self.config
        w = c.local_window
        m = self.map
        with m.lock:
            sees_loaded = bool(np.any((kf.point_ids >= 0) & (kf.point_ids <= self._loaded_pt_upto)))
            if 0 <= self._loaded_upto < old_id and sees_loaded:
                log.info("loop %d -> %d not closed: keyframe %d is held by the loaded map's points", kf.kf_id, old_id, kf.kf_id)
                return False
        self._finish_ba(wait=True)
        t0 = time.perf_counter()
        with m.lock:
            ids = m.kf_ids()
            start, cur = ids.index(old_id), ids.index(kf.kf_id)
            own = set(kf.point_ids[kf.point_ids >= 0].tolist())
            # (never a loaded map's keyframes: its alignment registers them where they are)
            window = {k for k in ids[max(cur - w, start + 1):cur]
                      if k > self._loaded_upto and len(own & set(m.keyframes[k].point_ids.tolist())) >= c.loop_min_inliers // 2}
            window.add(kf.kf_id)
            corrections = {k: S for k in window}
            corrections.update(loop_shares(m, ids[start:cur + 1], window, S, kf.center, self._loaded_upto))
            move_by_corrections(m, corrections, self._loaded_pt_upto)
            for new_pid, old_pid in self._loop_pairs:
                if new_pid > self._loaded_pt_upto:  # (a loaded point is never the one fused away)
                    m.replace_point(new_pid, old_pid)
        self._correction_gen += 1
        self.shared.correction = (self._correction_gen, S)

        def ba(idx: list[int]) -> None:
            self._run_ba([ids[i] for i in idx], max_fixed=w)

        def centers():
            with m.lock:
                return [m.keyframes[k].center for k in ids]

        if c.loop_closing == "recursive":
            with m.lock:
                times = [m.keyframes[k].t_s for k in ids]
            windows = recursive_loop_closing(start, cur, w, ba, centers, times)
        else:
            windows = [list(range(start, cur + 1))]
            ba(windows[0])
        self.stats.loop_ba_keyframes.append(sum(len(x) for x in windows))
        self.stats.loop_ms.append((time.perf_counter() - t0) * 1e3)
        self.stats.loops.append((old_id, kf.kf_id))
        self.stats.n_loops += 1
        self._publish_full()
        return True

    def _publish_full(self) -> None:
        with self.map.lock:
            self._publish_local_map(self.map.kf_ids())
            self.updates.put(self._snapshot(full=True))

    def _snapshot(self, full: bool) -> MapUpdate:
        m = self.map
        with m.lock:
            pids = sorted(m.points)
            ids = m.kf_ids()[-self.config.local_window:]
            P, n_obs, parallax, age = map_point_arrays(m, pids)
            return MapUpdate(
                t_s=m.keyframes[ids[-1]].t_s if ids else 0.0,
                points_slam=P, point_ids=np.array(pids, np.int64), n_obs=n_obs,
                keyframe_t_s=np.array([m.keyframes[k].t_s for k in ids]),
                keyframe_centers_slam=np.array([m.keyframes[k].center for k in ids]).reshape(-1, 3),
                reset_counter=self.reset_counter, full=full, map_id=self.reset_counter,
                parallax_deg=parallax, last_seen_kf_age=age)
