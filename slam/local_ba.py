"""Local bundle adjustment of local mapping (slam.mapping.LocalMapper): a keyframe's window submitted to the BA
worker process and applied when it is back, without holding up the next keyframe; synchronous BAs for loop
closing; a BA not back within BA_TIMEOUT_S abandoned (its worker restarted)."""
from __future__ import annotations

import logging
import time
from concurrent.futures.process import BrokenProcessPool

import numpy as np

from slam.ba import BAProblem, BAResult, bundle_adjust
from slam.map import Keyframe
from slam.plm import plm_window

log = logging.getLogger(__name__)

# A bundle adjustment not back from its worker process after this long is abandoned: the worker is
# restarted and mapping goes on without it. Measured BAs take 0.05-3.3 s on 2 cores (full-loop BA
# the longest, docs/BENCHMARKS.md); on 2026-12-04 a local BA's job never reached an idle worker
# under heavy load (3 processes on 2 cores), and with one local BA in flight at a time, mapping
# then ran without local BA for the rest of the flight (cause in ProcessPoolExecutor not found).
BA_TIMEOUT_S = 60.0


def _gravity_arrays(kfs: list[Keyframe]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(P,3) g_cam (NaN rows without a prior) and (P,) sigmas for BAProblem; (None, None) when no
    keyframe has a gravity prior (slam.use_attitude_prior off)."""
    if all(kf.g_cam is None for kf in kfs):
        return None, None
    g = np.array([kf.g_cam if kf.g_cam is not None else np.full(3, np.nan) for kf in kfs], float)
    sigma = np.array([kf.gravity_sigma_rad if kf.g_cam is not None else np.nan for kf in kfs], float)
    return g, sigma


class LocalBundleAdjustment:
    """LocalMapper's bundle adjustments (a mixin: the state is LocalMapper's, its ``map``, ``config``, ``K``,
    ``stats``, ``_ba`` worker and ``_pending_ba``)."""

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
