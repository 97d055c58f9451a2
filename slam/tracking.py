"""Tracking thread: features, motion-model prediction, matching against the local map, PnP +
pose-only refinement, keyframe decisions and the tracking state machine (issue 4 §1)."""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np
from scipy.spatial import cKDTree

from slam.config import SlamConfig
from slam.features import Features
from slam.geometry import R_slam_cam_levelled, T_from_rvec, initialize_two_view, inv_T, make_T, project, rvec_from_T
from slam.map import Keyframe, LocalMap, SlamMap
from slam.matching import TH_LOW, match_bf, match_by_projection
from slam.patches import ImageLevels, image_levels
from slam.types import Frame, TrackingState


@dataclass
class PoseEstimate:
    T_cam_slam: np.ndarray
    inlier_feat: np.ndarray  # feature indices
    inlier_pid: np.ndarray  # their map point ids
    inlier_p_slam: np.ndarray  # (N, 3) their positions in the SLAM frame, as the pose was solved with them
    local_map: LocalMap  # the map the pose was solved against


def solve_pnp(K: np.ndarray, p_slam: np.ndarray, uv_px: np.ndarray, T_guess: np.ndarray | None,
              reproj_px: float, min_inliers: int) -> tuple[np.ndarray, np.ndarray] | None:
    """RANSAC PnP (OpenCV, EPnP minimal sets) then pose-only Levenberg-Marquardt refinement on the
    inliers, re-gated once (motion-only BA). Returns (T_cam_slam, inlier mask) or None."""
    if len(p_slam) < max(6, min_inliers):
        return None
    obj = np.ascontiguousarray(p_slam, np.float64)
    img = np.ascontiguousarray(uv_px, np.float64)
    if T_guess is not None:
        rvec, tvec = rvec_from_T(T_guess)
        uv, z = project(K, T_guess, obj)
        err = np.linalg.norm(uv - img, axis=1)
        inl = (z > 0) & (err < 2 * reproj_px)
        ok = inl.sum() >= min_inliers
    else:
        ok = False
    if not ok:
        ok, rvec, tvec, idx = cv2.solvePnPRansac(obj, img, K, None, iterationsCount=100,
                                                 reprojectionError=reproj_px, confidence=0.99,
                                                 flags=cv2.SOLVEPNP_EPNP)
        if not ok or idx is None or len(idx) < min_inliers:
            return None
        inl = np.zeros(len(obj), bool)
        inl[idx.ravel()] = True
    for gate in (2 * reproj_px, reproj_px):
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
        T = T_from_rvec(rvec, tvec)
        uv, z = project(K, T, obj)
        inl = (z > 0) & (np.linalg.norm(uv - img, axis=1) < gate)
        if inl.sum() < min_inliers:
            return None
    return T, inl


@dataclass
class Shared:
    """State the background threads publish to the tracker by reference swap (no locks needed)."""

    local_map: LocalMap | None = None
    correction: tuple[int, np.ndarray] = (0, np.eye(4))  # (generation, S_new_old) from loop closing
    mapping_busy: bool = False
    pending_keyframes: int = 0  # keyframes queued for local mapping (set by the system)
    active_map: object = None  # the tracker's current SlamMap; mapping publishes only for this one
    place: tuple[object, object] | None = None  # (SlamMap, its slam.place.PlaceIndex), set by mapping


@dataclass
class TrackResult:
    state: TrackingState
    T_cam_slam: np.ndarray
    n_inliers: int
    new_keyframe: Keyframe | None = None
    reset_map: SlamMap | None = None


@dataclass(frozen=True)
class Gravity:
    """The autopilot's gravity direction for one frame: unit "down" in the camera, 1-sigma angle."""

    g_cam: np.ndarray
    sigma_rad: float


@dataclass
class _Init:
    frame: Frame
    feats: Features
    gravity: Gravity | None = None
    levels: ImageLevels | None = None


def reloc_keyframes(kf_ids: list[int], place_ids: list[int], n_recent: int, n_neighbours: int = 2) -> list[int]:
    """Keyframes whose points relocalisation searches: the ``n_recent`` newest of ``kf_ids``
    (sorted) and each place-recognition candidate with up to ``n_neighbours`` keyframes either side
    of it in id order (a place seen once is covered by its neighbours' points too)."""
    chosen = set(kf_ids[-n_recent:])
    for k in place_ids:
        i = bisect.bisect_left(kf_ids, k)
        if i < len(kf_ids) and kf_ids[i] == k:
            chosen.update(kf_ids[max(0, i - n_neighbours): i + n_neighbours + 1])
    return sorted(chosen)


@dataclass
class Tracker:
    K: np.ndarray
    width_px: int
    height_px: int
    config: SlamConfig
    extract: Callable[[np.ndarray], Features]
    map: SlamMap = field(default_factory=SlamMap)
    shared: Shared = field(default_factory=Shared)
    state: TrackingState = TrackingState.INITIALIZING
    T_last: np.ndarray = field(default_factory=lambda: np.eye(4))
    T_vel: np.ndarray = field(default_factory=lambda: np.eye(4))  # T_cur_prev of the last step
    frames_since_kf: int = 0
    most_tracked_since_kf: int = 0  # the inlier-ratio keyframe rule's reference (_accept)
    R_kf_cam_slam: np.ndarray = field(default_factory=lambda: np.eye(3))  # orientation of the last keyframe
    lost_frames: int = 0
    _init: _Init | None = None
    _correction_gen: int = 0
    _reloc_map: LocalMap | None = None
    _reloc_age: int = 0
    _reloc_queried: bool = False  # the relocalisation map was built with a place query of a usable frame
    _reloc_timeout_s: float | None = None  # set by resume(): relocalise within this much frame time or reset
    _reloc_deadline_t_s: float | None = None
    _gravity: Gravity | None = None  # of the frame being tracked (slam.use_attitude_prior)
    tracked_p_slam: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # the last frame's pose inliers (SLAM frame)
    pose_map: LocalMap | None = None  # the local map the last frame's pose was solved against (None: no pose)

    # --- public ---------------------------------------------------------------------------------
    def resume(self, timeout_s: float) -> None:
        """Start in ``self.map`` (a map loaded from disk) as lost: the first frames relocalise against
        its most recent keyframes (where the vehicle was when the map was saved). If none succeeds
        within ``timeout_s`` of frame time from the first frame, the map is abandoned (a reset, as
        after a long loss) instead of the ``reset_after_lost_frames`` rule."""
        with self.map.lock:
            ids = self.map.kf_ids()
            if not ids:
                raise ValueError("cannot resume in an empty map")
            self.shared.local_map = self.map.local_map(ids[-self.config.local_map_keyframes:], 0)
            self.T_last = self.map.keyframes[ids[-1]].T_cam_slam.copy()
        self.state = TrackingState.LOST
        self.lost_frames = 0
        self._reloc_map = None
        self._reloc_timeout_s, self._reloc_deadline_t_s = float(timeout_s), None

    @property
    def resuming(self) -> bool:
        """Started in a loaded map (``resume``) and not relocalised in it yet."""
        return self._reloc_timeout_s is not None

    def abandon_resume(self) -> None:
        """Give the loaded map up: the next frame starts a fresh map, as when ``resume``'s time
        budget runs out. No effect once relocalised."""
        if self._reloc_timeout_s is not None:
            self._reloc_deadline_t_s = -math.inf

    def track(self, frame: Frame, gravity: Gravity | None = None) -> TrackResult:
        """``gravity``: the autopilot's gravity direction at this frame (None: no prior); new
        keyframes carry it to bundle adjustment and a new map is levelled with it."""
        self._gravity = gravity
        self.tracked_p_slam = np.zeros((0, 3))
        self.pose_map = None
        feats = self.extract(frame.image)
        if self.state == TrackingState.INITIALIZING:
            return self._initialize(frame, feats)
        self._apply_correction()
        if self.state == TrackingState.LOST:
            return self._relocalize(frame, feats)
        est = self._track_local_map(feats, self.T_vel @ self.T_last)
        if est is None:  # lost: try relocalization on this very frame before reporting it
            self.state = TrackingState.LOST
            self.lost_frames = 0
            return self._relocalize(frame, feats)
        return self._accept(frame, feats, est, TrackingState.OK)

    # --- steps ----------------------------------------------------------------------------------
    def _accept(self, frame: Frame, feats: Features, est: PoseEstimate, state: TrackingState) -> TrackResult:
        self.T_vel = est.T_cam_slam @ inv_T(self.T_last) if self.state == TrackingState.OK else np.eye(4)
        self.T_last = est.T_cam_slam
        self.state = state
        self.lost_frames = 0
        self.frames_since_kf += 1
        self.tracked_p_slam = est.inlier_p_slam
        self.pose_map = est.local_map
        kf = None
        n = len(est.inlier_pid)
        # The inlier-ratio rule's reference is the most points tracked since the last keyframe
        # (ORB-SLAM compares with the reference keyframe's tracked map points). The frame that
        # makes a keyframe is tracked on the older map alone; the keyframe's own new points reach
        # the tracker one mapping step later. Its count was the reference before, so the rule fired
        # only after the inliers had fallen to 3/4 of an already depleted count, and the
        # 20-frame rule made most keyframes: on the demo flight 30 keyframes in 45 s, inliers
        # sagging from ~150 to ~50 before each, and pose steps of 1-2.5 m when the next local map
        # arrived (docs/BENCHMARKS.md, "Keyframe reference").
        self.most_tracked_since_kf = max(self.most_tracked_since_kf, n)
        if self._need_keyframe(est.T_cam_slam, n):
            pids = np.full(len(feats), -1, np.int64)
            pids[est.inlier_feat] = est.inlier_pid
            # its image goes with it: local mapping moves the tracked points' observations to where
            # their patches align (slam.map_points.align_observations), off this thread
            kf = self._keyframe(frame, est.T_cam_slam.copy(), feats, pids, self._gravity, self._levels_of(frame, feats))
            self._keyed(est.T_cam_slam, n)
        return TrackResult(state, est.T_cam_slam, n, new_keyframe=kf)

    def _need_keyframe(self, T_cam_slam: np.ndarray, n_inliers: int) -> bool:
        """ORB-SLAM-like keyframe rules, plus one for turns: a keyframe once the camera has turned
        ``keyframe_max_rotation_deg`` since the last one. At 10 fps a 30 deg/s turn leaves the last
        keyframe's view within a second, and the points the tracker needs there come only from
        keyframes; without it the turn was crossed with keyframes 20+ deg apart, tracked on few
        points, and the pose errors made there bent the map (docs/BENCHMARKS.md)."""
        c = self.config
        k = self.frames_since_kf
        rotated_deg = np.degrees(np.arccos(np.clip((np.trace(T_cam_slam[:3, :3] @ self.R_kf_cam_slam.T) - 1) / 2, -1, 1)))
        return (k >= c.max_frames_between_keyframes
                or (n_inliers < c.keyframe_inlier_ratio * self.most_tracked_since_kf
                    and k >= c.min_frames_between_keyframes and not self.shared.mapping_busy)
                or (rotated_deg > c.keyframe_max_rotation_deg and k >= 1 and self.shared.pending_keyframes < 2)
                or (n_inliers < 2 * c.min_inliers and k >= 1 and self.shared.pending_keyframes < 2))

    def _keyed(self, T_cam_slam: np.ndarray, n_inliers: int) -> None:
        """Bookkeeping after a keyframe was made at pose T_cam_slam."""
        self.frames_since_kf = 0
        self.most_tracked_since_kf = n_inliers
        self.R_kf_cam_slam = T_cam_slam[:3, :3].copy()
        self.shared.mapping_busy = True

    def _keyframe(self, frame: Frame, T_cam_slam: np.ndarray, feats: Features, point_ids: np.ndarray,
                  gravity: Gravity | None, levels: ImageLevels | None = None) -> Keyframe:
        """levels: the frame's image, for local mapping's patch alignment (slam.patches)."""
        use = gravity is not None and self.map.gravity_aligned
        g, sigma = (gravity.g_cam, gravity.sigma_rad) if use else (None, None)
        return Keyframe(self.map.new_kf_id(), frame.t_s, frame.seq, T_cam_slam, feats.uv_px.copy(), feats.desc, point_ids,
                        g, sigma, levels)

    def _track_local_map(self, feats: Features, T_pred: np.ndarray) -> PoseEstimate | None:
        lm = self.shared.local_map
        if lm is None or len(lm.point_ids) == 0 or len(feats) < self.config.min_inliers:
            return None
        tree = cKDTree(feats.uv_px)
        for radius in (self.config.search_radius_px, 3 * self.config.search_radius_px):
            est = self._match_and_solve(feats, lm, T_pred, radius, tree)
            if est is not None:
                return est
        return None

    def _visible(self, lm: LocalMap, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        uv, z = project(self.K, T, lm.p_slam)
        vis = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < self.width_px) & (uv[:, 1] >= 0) & (uv[:, 1] < self.height_px)
        idx = np.flatnonzero(vis)
        return idx, uv[idx]

    def _match_and_solve(self, feats: Features, lm: LocalMap, T_pred: np.ndarray, radius: float,
                         tree: cKDTree) -> PoseEstimate | None:
        c = self.config
        idx, uv = self._visible(lm, T_pred)
        pairs = match_by_projection(uv, lm.desc[idx], feats.uv_px, feats.desc, radius, tree=tree)
        if len(pairs) < c.min_inliers:
            return None
        pts = idx[pairs[:, 0]]
        sol = solve_pnp(self.K, lm.p_slam[pts], feats.uv_px[pairs[:, 1]], T_pred, c.pnp_reproj_px, c.min_inliers)
        if sol is None:
            return None
        T, inl = sol
        # second pass (ORB-SLAM TrackLocalMap): re-project with the refined pose, tight radius
        idx, uv = self._visible(lm, T)
        pairs2 = match_by_projection(uv, lm.desc[idx], feats.uv_px, feats.desc, c.refine_radius_px, tree=tree)
        if len(pairs2) >= c.min_inliers:
            pts2 = idx[pairs2[:, 0]]
            sol2 = solve_pnp(self.K, lm.p_slam[pts2], feats.uv_px[pairs2[:, 1]], T, c.pnp_reproj_px, c.min_inliers)
            if sol2 is not None and sol2[1].sum() >= inl.sum():
                T, inl = sol2
                pts, pairs = pts2, pairs2
        return PoseEstimate(T, pairs[inl, 1], lm.point_ids[pts[inl]], lm.p_slam[pts[inl]], lm)

    def _levels_of(self, frame: Frame, feats: Features) -> ImageLevels | None:
        """The frame's image levels for local mapping's patch alignment (slam.patches); None
        without ``slam.patch_alignment``."""
        return image_levels(frame.image, feats.octave) if self.config.patch_alignment else None

    def _apply_correction(self) -> None:
        gen, S = self.shared.correction
        if gen != self._correction_gen:
            from slam.geometry import correct_pose_by_sim3

            self._correction_gen = gen
            self.T_last = correct_pose_by_sim3(self.T_last, S)
            self.T_vel = np.eye(4)

    def _relocalize(self, frame: Frame, feats: Features) -> TrackResult:
        """Match against the points of the recent keyframes and of those the place index finds most
        like this frame (brute force, no pose prior) + PnP. The set is rebuilt every 15 lost frames,
        and at once when the last one could not query the place index (e.g. built on a black frame)."""
        self.lost_frames += 1
        c = self.config
        if self._reloc_timeout_s is not None:  # resumed in a loaded map: a time budget
            if self._reloc_deadline_t_s is None:
                self._reloc_deadline_t_s = frame.t_s + self._reloc_timeout_s
            give_up = frame.t_s > self._reloc_deadline_t_s
        else:
            give_up = self.lost_frames > c.reset_after_lost_frames
        if give_up:
            return self._reset(frame, feats)
        place = self.shared.place[1] if self.shared.place is not None and self.shared.place[0] is self.map else None
        if (self._reloc_map is None or self._reloc_age >= 15
                or (not self._reloc_queried and place is not None and len(feats) >= c.min_inliers)):
            cands = place.query(feats.desc, top=c.reloc_place_candidates) if place is not None else []
            with self.map.lock:
                ids = reloc_keyframes(self.map.kf_ids(), [p.kf_id for p in cands], c.reloc_keyframes)
                self._reloc_map = self.map.local_map(ids, -1)
            self._reloc_age, self._reloc_queried = 0, place is not None and len(feats) >= c.min_inliers
        self._reloc_age += 1
        lm = self._reloc_map
        if len(feats) >= c.min_inliers and len(lm.point_ids) >= c.min_inliers:
            pairs = match_bf(feats.desc, lm.desc, ratio=0.8, max_dist=TH_LOW + 14)
            if len(pairs) >= c.min_inliers:
                sol = solve_pnp(self.K, lm.p_slam[pairs[:, 1]], feats.uv_px[pairs[:, 0]], None,
                                c.pnp_reproj_px, c.reloc_min_inliers)
                if sol is not None:
                    # confirm with a projection-guided pass around the found pose: the local map,
                    # else the relocalisation map (the pose may lie outside the newest keyframes')
                    est = self._track_local_map(feats, sol[0])
                    if est is None or len(est.inlier_pid) < c.reloc_min_inliers:
                        est = self._match_and_solve(feats, lm, sol[0], c.search_radius_px, cKDTree(feats.uv_px))
                    if est is not None and len(est.inlier_pid) >= c.reloc_min_inliers:
                        with self.map.lock:  # track on against the map found here until mapping publishes
                            near = self.map.covisible(est.inlier_pid, c.local_map_keyframes)
                            self.shared.local_map = self.map.local_map(near, -1)
                        self._reloc_map = None
                        self._reloc_timeout_s = self._reloc_deadline_t_s = None
                        self.T_vel = np.eye(4)
                        self.frames_since_kf = c.max_frames_between_keyframes  # key the first good frame
                        return self._accept(frame, feats, est, TrackingState.RELOCALIZED)
        return TrackResult(TrackingState.LOST, self.T_last, 0)

    def __post_init__(self) -> None:
        self.shared.active_map = self.map

    def _reset(self, frame: Frame, feats: Features) -> TrackResult:
        self.map = SlamMap()
        self.shared.active_map = self.map
        self.shared.local_map = None
        self.state = TrackingState.INITIALIZING
        self._init = None
        self._reloc_map = None
        self._reloc_timeout_s = self._reloc_deadline_t_s = None
        self.lost_frames = 0
        res = self._initialize(frame, feats)
        return TrackResult(res.state, res.T_cam_slam, res.n_inliers, reset_map=self.map)

    def _initialize(self, frame: Frame, feats: Features) -> TrackResult:
        """Two-view monocular initialization once the reference frame has enough parallax."""
        c = self.config
        if self._init is None or len(self._init.feats) < c.init_min_matches:
            self._init = _Init(frame, feats, self._gravity, self._levels_of(frame, feats))
            return TrackResult(TrackingState.INITIALIZING, np.eye(4), 0)
        ref = self._init.feats
        pairs = match_bf(ref.desc, feats.desc, ratio=0.75, max_dist=TH_LOW + 14)
        if len(pairs) < c.init_min_matches:
            self._init = _Init(frame, feats, self._gravity, self._levels_of(frame, feats))  # too much changed: restart from this frame
            return TrackResult(TrackingState.INITIALIZING, np.eye(4), 0)
        uv1, uv2 = ref.uv_px[pairs[:, 0]], feats.uv_px[pairs[:, 1]]
        if np.median(np.linalg.norm(uv2 - uv1, axis=1)) < c.init_min_flow_px:
            return TrackResult(TrackingState.INITIALIZING, np.eye(4), 0)
        init = initialize_two_view(self.K, uv1, uv2, min_points=c.init_min_matches // 2)
        if init is None:
            return TrackResult(TrackingState.INITIALIZING, np.eye(4), 0)
        # scale: median scene depth of the first view = 1 (ORB-SLAM convention)
        s = 1.0 / np.median(init.points_cam1[init.good, 2])
        T2 = init.T_cam2_cam1.copy()
        T2[:3, 3] *= s
        pts = init.points_cam1[init.good] * s
        good = np.flatnonzero(init.good)
        # the SLAM frame: the first camera's, or with its gravity prior the first camera's levelled
        # (z up; yaw and origin those of the first camera). Only the first view's prior: the
        # second one would come through the two-view rotation, which is degrees off at times.
        g1 = self._init.gravity
        T_cam1_slam = np.eye(4) if g1 is None else make_T(R_slam_cam_levelled(g1.g_cam).T, np.zeros(3))
        T2 = T2 @ T_cam1_slam
        pts = pts @ T_cam1_slam[:3, :3]  # p_slam = R_slam_cam1 p_cam1
        m = self.map
        with m.lock:
            m.gravity_aligned = g1 is not None
            kf1 = self._keyframe(self._init.frame, T_cam1_slam, ref, np.full(len(ref), -1, np.int64), self._init.gravity,
                                 levels=self._init.levels)
            kf2 = self._keyframe(frame, T2, feats, np.full(len(feats), -1, np.int64), self._gravity,
                                 levels=self._levels_of(frame, feats))
            m.add_keyframe(kf1)
            m.add_keyframe(kf2)
            for p, i1, i2 in zip(pts, pairs[good, 0], pairs[good, 1]):
                m.add_point(p, feats.desc[i2], {kf1.kf_id: int(i1), kf2.kf_id: int(i2)})
            self.shared.local_map = m.local_map([kf1.kf_id, kf2.kf_id], 0)
        self._init = None
        self.T_last = T2
        self.T_vel = np.eye(4)
        self.state = TrackingState.OK
        self._keyed(T2, len(pts))
        # kf2 goes to local mapping for its first BA (kf1 is already in the map)
        return TrackResult(TrackingState.OK, T2, len(pts), new_keyframe=kf2)
