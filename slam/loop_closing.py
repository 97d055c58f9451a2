"""Loop closing of local mapping (slam.mapping.LocalMapper): place recognition, Sim(3) verification, and the
correction of the loop (full or recursive BA), published as a full map snapshot."""
from __future__ import annotations

import logging
import time

import numpy as np

from slam.geometry import correct_pose_by_sim3, ransac_sim3, sim3_share
from slam.map import Keyframe, SlamMap
from slam.map_points import map_point_arrays
from slam.matching import match_bf
from slam.plm import recursive_loop_closing
from slam.types import MapUpdate

log = logging.getLogger(__name__)


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


class LoopClosing:
    """LocalMapper's loop closing (a mixin: the state is LocalMapper's, its ``map``, ``config``, ``_place``,
    ``stats`` and loop cooldown)."""

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
