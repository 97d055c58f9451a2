"""Memory bounds of slam/ (issue 4): the map, place index, loop anchors and queues stay within
their caps over a long constructed flight, loop closing still finds an anchored place, and a
SlamSystem closed leaves no worker process or thread behind. RSS figures belong to
``python -m companion.slam_bench --memory`` (docs/BENCHMARKS.md), not to these tests."""
from __future__ import annotations

import threading
import time

import numpy as np
import psutil
import pytest

from slam.config import SlamConfig
from slam.map import Keyframe, SlamMap
from slam.mapping import LocalMapper, UpdateQueue
from slam.system import SlamSystem
from slam.tracking import Shared
from slam.types import CameraModel, Frame, MapUpdate

K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
W_PX, H_PX = 640, 480
HEIGHT_M = 50.0
STEP_M = 6.0
FEATURES = 300
N_OUT = 50  # keyframes out, then as many back


def nadir_T_cam_world(x_m: float) -> np.ndarray:
    """Camera looking straight down from (x, 0, HEIGHT_M): x_cam = x, y_cam = -y, z_cam = -z."""
    R_wc = np.diag([1.0, -1.0, -1.0])
    T = np.eye(4)
    T[:3, :3] = R_wc.T
    T[:3, 3] = -R_wc.T @ np.array([x_m, 0.0, HEIGHT_M])
    return T


class StripWorld:
    """Ground points along a 360 m strip, each with its own random ORB-like descriptor; keyframes
    are exact nadir views (the tracker's job is done by ``associate``: features of world points
    that a recent keyframe maps get that map point, as the tracker's local-map matching would)."""

    def __init__(self, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        n = 15000
        self.p = np.c_[rng.uniform(-60, 360, n), rng.uniform(-30, 30, n), rng.normal(0, 1.5, n)]
        self.desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
        self.world_of: dict[tuple[int, int], int] = {}  # (kf id, feature) -> world point

    def keyframe(self, m: SlamMap, x_m: float, t_s: float, recent: int = 10) -> Keyframe:
        T = nadir_T_cam_world(x_m)
        pc = self.p @ T[:3, :3].T + T[:3, 3]
        uv = pc[:, :2] / pc[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
        vis = np.flatnonzero((uv[:, 0] > 0) & (uv[:, 0] < W_PX) & (uv[:, 1] > 0) & (uv[:, 1] < H_PX))[:FEATURES]
        pids = np.full(len(vis), -1, np.int64)
        with m.lock:
            by_world = {}
            for k in m.kf_ids()[-recent:]:
                for f, pid in enumerate(m.keyframes[k].point_ids.tolist()):
                    if pid >= 0 and pid in m.points:
                        by_world[self.world_of[(k, f)]] = pid
        for f, w in enumerate(vis):
            pids[f] = by_world.get(int(w), -1)
        kf = Keyframe(m.new_kf_id(), t_s, int(t_s * 10), T, uv[vis], self.desc[vis].copy(), pids)
        for f, w in enumerate(vis):
            self.world_of[(kf.kf_id, f)] = int(w)
        return kf


def fly(config: SlamConfig, xs_m: np.ndarray) -> tuple[LocalMapper, list]:
    """Feed a LocalMapper (real thread, real BA worker, real place index) one keyframe per x."""
    world = StripWorld()
    m = SlamMap()
    shared = Shared(active_map=m)
    mapper = LocalMapper(K, config, shared, m)
    sizes = []
    first = world.keyframe(m, xs_m[0], 0.0)
    with m.lock:
        m.add_keyframe(first)
    for n, x in enumerate(xs_m[1:], 1):
        mapper.insert_keyframe(world.keyframe(m, x, n * 0.5))
        assert mapper.wait_idle(60)
        sizes.append(mapper.memory())
    return mapper, sizes


CAPS = dict(max_keyframes=20, loop_anchor_every=5, max_loop_anchors=6, max_trajectory_keyframes=40,
            loop_min_gap_keyframes=30, max_queued_map_updates=8, local_window=6, periodic_ba_every_keyframes=0,
            ba_iterations=3)


@pytest.fixture(scope="module")
def out_and_back():
    """N_OUT keyframes out along the strip, as many back over the same ground (a revisit beyond
    the 20-keyframe window: only the loop anchors remember the start)."""
    xs = np.r_[np.arange(N_OUT) * STEP_M, np.arange(N_OUT - 1, -1, -1) * STEP_M + 1.0]
    mapper, sizes = fly(SlamConfig(**CAPS), xs)
    yield mapper, sizes
    mapper.close()


def test_map_place_index_and_queues_stay_within_caps(out_and_back):
    mapper, sizes = out_and_back
    c = mapper.config
    most_whole = c.max_keyframes + c.max_loop_anchors
    assert len(sizes) == 2 * N_OUT - 1
    for s in sizes:
        assert s.map.keyframes_with_features <= most_whole
        assert s.loop_anchors <= c.max_loop_anchors
        assert s.place_entries <= most_whole
        assert s.map.keyframes <= most_whole + c.max_trajectory_keyframes
        assert s.queued_updates <= c.max_queued_map_updates
    late = sizes[N_OUT:]
    # bounded, not merely slow: the second half holds no more than the first half's peak
    assert max(s.map.map_points for s in late) <= 1.2 * max(s.map.map_points for s in sizes[:N_OUT])
    assert max(s.map.feature_bytes for s in late) <= most_whole * FEATURES * (16 + 32 + 8)
    assert max(s.place_bytes for s in late) <= most_whole * 400 * 32
    assert sizes[-1].dropped_updates > 0  # nobody polled: the queue dropped instead of growing
    m = mapper.map
    with m.lock:  # no point is held by a forgotten keyframe's observation
        featured = {k for k, kf in m.keyframes.items() if kf.has_features}
        assert all(set(p.obs) <= featured for p in m.points.values())
        assert all(p.desc.base is None for p in m.points.values())  # own copies, no views of keyframes


def test_loop_closes_on_an_anchor_beyond_the_keyframe_window(out_and_back):
    mapper, _ = out_and_back
    loops = list(mapper.stats.loops)
    assert loops, "the return over the start found no loop"
    old, cur = loops[0]
    assert cur - old > mapper.config.max_keyframes  # the old keyframe had left the whole-keyframe window


def test_update_queue_is_bounded_and_a_full_snapshot_supersedes():
    def upd(full: bool) -> MapUpdate:
        return MapUpdate(0.0, np.zeros((5, 3)), np.arange(5), np.full(5, 2, np.int32), np.zeros(1), np.zeros((1, 3)),
                         0, full=full, map_id=0)

    q = UpdateQueue(4)
    for _ in range(10):
        q.put(upd(False))
    assert len(q) == 4 and q.dropped == 6
    q.put(upd(True))
    assert len(q) == 1 and q.dropped == 10 and q.get_nowait().full


def _slam_threads() -> set[threading.Thread]:
    """Mapping threads and BA pools' manager threads alive now."""
    return {t for t in threading.enumerate() if t.name == "slam-mapping" or type(t).__name__ == "_ExecutorManagerThread"}


def test_slam_system_close_leaves_no_worker_process_or_thread():
    cam = CameraModel(W_PX, H_PX, K, np.zeros(5))
    proc = psutil.Process()
    before = {c.pid for c in proc.children(recursive=True)}
    threads_before = _slam_threads()  # another test's mapper may still be open
    rng = np.random.default_rng(1)
    for _ in range(3):
        with SlamSystem(cam, SlamConfig()) as s:
            for i in range(3):
                s.track(Frame(rng.integers(0, 255, (H_PX, W_PX), dtype=np.uint8), i / 10, i))
            assert s.mapper._thread.is_alive()
        assert not s.mapper._thread.is_alive()
    s.close()  # closing twice is harmless
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and ({c.pid for c in proc.children(recursive=True)} - before
                                           or _slam_threads() - threads_before):
        time.sleep(0.05)
    assert {c.pid for c in proc.children(recursive=True)} - before == set()
    assert _slam_threads() - threads_before == set()


def test_place_index_drops_removed_entries():
    from slam.place import PlaceIndex

    rng = np.random.default_rng(3)
    descs = [rng.integers(0, 256, (300, 32), dtype=np.uint8) for _ in range(20)]
    idx, without_7 = PlaceIndex(), PlaceIndex()
    for k, d in enumerate(descs):
        idx.add(k, d)
        if k != 7:
            without_7.add(k, d)
    assert idx.query(descs[7])[0].kf_id == 7
    idx.remove([7])
    assert len(idx) == 19 and 0 < idx.nbytes() == without_7.nbytes() < 300 * 32 * 19
    assert all(c.kf_id != 7 for c in idx.query(descs[7]))
    assert idx.query(descs[8])[0].kf_id == 8


def _surveyed_strip(n_keyframes: int, config: SlamConfig) -> tuple[StripWorld, SlamMap]:
    """A map of the strip's first n keyframes (STEP_M apart, keyframe k at x = k * STEP_M) made
    by a LocalMapper that is closed again: what a later flight loads from disk."""
    world, m = StripWorld(), SlamMap()
    survey = LocalMapper(K, config, Shared(active_map=m), m)
    try:
        with m.lock:
            m.add_keyframe(world.keyframe(m, 0.0, 0.0))
        for n in range(1, n_keyframes):
            survey.insert_keyframe(world.keyframe(m, n * STEP_M, n * 0.5))
            assert survey.wait_idle(60)
    finally:
        survey.close()
    return world, m


@pytest.mark.parametrize("keep_loaded", [True, False])
def test_a_survey_maps_keyframes_are_outside_the_memory_cap(keep_loaded):
    """A loaded map kept whole (a site's survey map, SlamSystem keep_loaded) keeps every keyframe
    while the flight's own keyframes go through the cap; a map saved by the service itself
    (keep_loaded off) is capped as a whole, or it would grow with every restart."""
    world, m = _surveyed_strip(30, SlamConfig(**{**CAPS, "max_keyframes": 40}))
    with m.lock:
        loaded = m.kf_ids()
        assert len(loaded) == 30 and all(m.keyframes[k].has_features for k in loaded)
    mapper = LocalMapper(K, SlamConfig(**CAPS), Shared(active_map=m), m, keep_loaded=keep_loaded)
    try:
        for n in range(30, 60):
            mapper.insert_keyframe(world.keyframe(m, n * STEP_M, n * 0.5))
            assert mapper.wait_idle(60)
        mem = mapper.memory()
    finally:
        mapper.close()
    with m.lock:
        whole_loaded = sum(m.keyframes[k].has_features for k in loaded if k in m.keyframes)
        whole_new = sum(kf.has_features for k, kf in m.keyframes.items() if k > loaded[-1])
    c = mapper.config
    assert whole_new <= c.max_keyframes + c.max_loop_anchors
    if keep_loaded:
        assert whole_loaded == 30 and mem.place_entries >= 30 + c.max_keyframes
    else:
        assert whole_loaded <= 10, whole_loaded  # all but the loop anchors forgotten
        assert mem.map.keyframes_with_features <= c.max_keyframes + c.max_loop_anchors


def test_a_loop_correction_never_moves_a_loaded_map():
    """A loaded map (restart or survey) is what its alignment registers: a loop correction moves
    the flight's keyframes onto it, never its keyframes or points (none fused away either), and a
    loop from a keyframe that sees its points to one of the flight's own is not closed."""
    from slam.geometry import make_T

    world, m = _surveyed_strip(15, SlamConfig(**CAPS))
    with m.lock:
        loaded_kf = {k: kf.T_cam_slam.copy() for k, kf in m.keyframes.items()}
        loaded_pt = {p: mp.p_slam.copy() for p, mp in m.points.items()}
    mapper = LocalMapper(K, SlamConfig(**CAPS), Shared(active_map=m), m, keep_loaded=True)
    try:
        for n in range(15, 23):  # on along the strip: the first of these see the survey's points
            mapper.insert_keyframe(world.keyframe(m, n * STEP_M, n * 0.5))
            assert mapper.wait_idle(60)
        with m.lock:
            flight = sorted(k for k in m.keyframes if k not in loaded_kf)
            sees = [k for k in flight if any(0 <= p <= max(loaded_pt) for p in m.keyframes[k].point_ids.tolist())]
            before = {k: kf.T_cam_slam.copy() for k, kf in m.keyframes.items()}
        assert sees and sees[0] == flight[0], (flight, sees)
        S = make_T(np.eye(3), np.array([0.0, 2.0, 0.0]))  # a 2 m "loop correction"

        # from a keyframe held by the survey's points to one of the flight's own: not closed, nothing moves
        mapper._loop_pairs = []
        assert not mapper._correct(m.keyframes[sees[-1]], flight[0] if sees[-1] != flight[0] else flight[1], S)
        with m.lock:
            assert all(np.array_equal(m.keyframes[k].T_cam_slam, T) for k, T in before.items())

        # to a survey keyframe, from a flight keyframe whose correction window (the 6 keyframes before
        # it that share its points) holds survey keyframes: only the flight's move, and BA brings
        # them back onto the held survey
        assert flight[2] in sees
        a, b = sorted(loaded_pt)[:2]
        mapper._loop_pairs = [(a, b)]  # a pair whose "new" point is the survey's: kept, not fused away
        assert mapper._correct(m.keyframes[flight[2]], 5, S) and mapper.stats.n_loops == 1
        with m.lock:
            assert all(np.array_equal(m.keyframes[k].T_cam_slam, T) for k, T in loaded_kf.items())
            assert all(p in m.points and np.array_equal(m.points[p].p_slam, P) for p, P in loaded_pt.items())
            # (keyframe ids are the strip positions' indices: kf k was taken at x = k * STEP_M)
            off_m = [np.linalg.norm(m.keyframes[k].center - [k * STEP_M, 0.0, HEIGHT_M]) for k in flight]
    finally:
        mapper.close()
    print(f"flight keyframes after the 2 m correction and loop BA: {np.round(off_m, 3).tolist()} m off")
    assert max(off_m) < 1.0, off_m
