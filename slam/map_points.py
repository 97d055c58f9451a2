"""What local mapping does with a SlamMap's points: the partners a new keyframe triangulates with, fusion of
duplicate points, sub-pixel observations from reference patches, and the point arrays of a map snapshot
(parallax, keyframe age). Callers hold the map's lock."""
from __future__ import annotations

from itertools import chain

import numpy as np

from slam.geometry import parallax_deg, project
from slam.map import Keyframe, SlamMap
from slam.matching import TH_LOW, candidates_by_projection
from slam.patches import PatchAligner

NEVER_SEEN_KF_AGE = np.iinfo(np.int32).max  # a map point no held keyframe observes (map_point_arrays)


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
