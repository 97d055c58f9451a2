"""slam/ on short simulated flights (companion.sim renders the frames; truth from the simulator)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from companion.slam_bench.runs import run_sequence
from companion.slam_bench.sequence import render_sequence
from slam.config import SlamConfig
from slam.geometry import inv_T, project
from slam.system import SlamSystem
from slam.types import Frame, TrackingState

N = 150
# 3 s into the flight, the drone already flying. From rest the first ~2.5 s are the take-off's
# pitch-over: image motion from rotation, < 1.5 m of baseline at 80 m up, nothing to initialise a
# map from (test_takeoff_initialises_once_the_translation_shows below); the windows of these tests
# (initialised by frame 60, blackouts at 60 and 100, 90 frames for the API) assume a flying start.
START_FRAME = 90


@pytest.fixture(scope="session")
def seq_cache_dir(tmp_path_factory):
    return str(tmp_path_factory.mktemp("slam_seq"))


@pytest.fixture(scope="session")
def nominal(seq_cache_dir):
    return render_sequence("nominal", N, seed=0, cache_dir=seq_cache_dir, start=START_FRAME)


@pytest.fixture(scope="session")
def cpu_run(nominal):
    return run_sequence(nominal, SlamConfig(), "cpu")


def test_initializes_and_tracks_nominal_against_truth(cpu_run):
    r = cpu_run
    first = next(i for i, s in enumerate(r.states) if s != TrackingState.INITIALIZING)
    assert first < 60, f"initialization took {first} frames"
    assert r.ratio_after_init >= 0.97
    assert r.reset_counter == 0
    rmse_m, length_m, pct = r.ate()
    assert length_m > 10
    # camera ~80 m up: 1 m RMSE is ~2 px of pose jitter; the % target is measured on long flights
    # by companion.slam_bench (a 15 m path after initialization cannot show 0.5 %)
    assert rmse_m < 1.0, f"ATE {rmse_m:.2f} m = {pct:.2f} % of {length_m:.1f} m"
    assert len(r.local_mapping_ms) >= 4 and r.n_points > 300


def test_takeoff_initialises_once_the_translation_shows(seq_cache_dir):
    """From rest: the take-off's pitch-over moves the image ~80 px while the camera has moved
    centimetres. The map must not be initialised from that rotation (the earlier rule did, at frame
    16 from a 1 cm baseline with its translation 49 deg off), but once the drone has flown a few
    metres, along the true direction of flight."""
    from slam.features import make_extractor
    from slam.tracking import Tracker

    seq = render_sequence("nominal", 110, seed=0, cache_dir=seq_cache_dir)
    cfg = SlamConfig()
    tracker = Tracker(seq.camera.K, seq.camera.width_px, seq.camera.height_px, cfg, make_extractor(seq.camera, cfg))
    res = next((r for i in range(len(seq.images)) if (r := tracker.track(Frame(seq.images[i], float(seq.t_s[i]), i))).new_keyframe), None)
    assert res is not None, "no initialisation in 110 frames (3.7 s)"
    kf1, kf2 = (tracker.map.keyframes[k] for k in tracker.map.kf_ids())
    T_true = np.linalg.inv(seq.T_enu_cam[kf2.seq]) @ seq.T_enu_cam[kf1.seq]  # T_cam2_cam1
    baseline_m = np.linalg.norm(T_true[:3, 3])
    t_est = kf2.T_cam_slam[:3, 3] / np.linalg.norm(kf2.T_cam_slam[:3, 3])  # the SLAM frame is camera 1's
    # measured: frames 0 -> 68, 2.1 m, direction 16 deg off (the earlier rule: 0 -> 16, 7 mm, 49 deg)
    assert baseline_m > 1.5, (kf1.seq, kf2.seq, baseline_m)
    assert t_est @ T_true[:3, 3] / baseline_m > np.cos(np.deg2rad(22)), (kf1.seq, kf2.seq, t_est, T_true[:3, 3] / baseline_m)


def test_relocalizes_after_forced_loss(nominal):
    r = run_sequence(nominal, SlamConfig(), "loss", blackout=(100, 8))
    assert all(s == TrackingState.LOST for s in r.states[100:108])
    after = r.states[108:]
    assert TrackingState.RELOCALIZED in after[:10], [s.value for s in after[:10]]
    assert r.reset_counter == 0  # same map: the alignment downstream stays valid
    assert np.mean([s.has_pose for s in after]) > 0.9
    assert r.ate()[0] < 1.5


def test_map_updates_and_api(nominal):
    cfg = SlamConfig()
    with SlamSystem(nominal.camera, cfg) as s:
        poses = [s.track(Frame(nominal.images[i], i / 30, i)) for i in range(90)]
        tracked = s.tracked_points_slam()
        lm = s.tracked_local_map()
        s.wait_mapping()
        ups = s.poll_map_updates()
        snap = s.map_points()
        t_kf, T_kf = s.keyframe_poses()
        with pytest.raises(ValueError, match="seq must increase"):
            s.track(Frame(nominal.images[0], 0.0, 5))
        with pytest.raises(ValueError, match="640x480"):
            s.track(Frame(nominal.images[0][:100], 9.0, 1000))
    assert poses[-1].state.has_pose and np.isfinite(poses[-1].T_slam_cam).all()
    assert np.isnan(poses[0].T_slam_cam).all() and poses[0].state == TrackingState.INITIALIZING
    assert ups and all(len(u.points_slam) == len(u.point_ids) == len(u.n_obs) for u in ups)
    assert all((u.n_obs >= 2).all() for u in ups)
    assert snap.full and len(snap.points_slam) > 200
    assert len(t_kf) == len(T_kf) >= 3 and np.all(np.diff(t_kf) > 0)
    # the local map the last pose was solved against (what alignments follow, companion.pipeline):
    # it holds every inlier of that pose, at the position the pose used, ids sorted
    pos = dict(zip(lm.point_ids.tolist(), map(tuple, lm.p_slam)))
    assert np.all(np.diff(lm.point_ids) > 0) and {tuple(p) for p in tracked} <= set(pos.values())
    # the last frame's pose inliers (what the barometer check reads): in front of the camera, in the image
    assert len(tracked) == poses[-1].n_inliers >= 20
    uv, z = project(nominal.camera.K, inv_T(poses[-1].T_slam_cam), tracked)
    assert (z > 0).all() and (uv >= -1).all() and (uv[:, 0] <= 641).all() and (uv[:, 1] <= 481).all()


@pytest.mark.parametrize("stepped", [True, False])
def test_stepped_keyframes_reach_local_mapping_only_at_wait_mapping(nominal, stepped):
    """Repeatable offline runs (``stepped``): a frame's new keyframe waits for ``wait_mapping``, so
    what the caller reads from the map after ``track`` (a snapshot for fine-tuning) is the same
    however fast the mapping thread is. Not stepped, local mapping takes it at once."""
    import time

    def counts(s):  # (map points, keyframes) as a snapshot for fine-tuning sees them
        return len(s.map_points().point_ids), len(s.mapper.map.kf_ids())

    with SlamSystem(nominal.camera, SlamConfig(), stepped=stepped) as s:
        for i in range(N):
            before, created = counts(s), s.map_revision()[2]
            pose = s.track(Frame(nominal.images[i], i / 30, i))
            if before[1] >= 2 and s.map_revision()[2] > created:  # the tracker took a keyframe after initialisation
                break
            s.wait_mapping()
        else:
            pytest.fail("no keyframe after initialisation")
        assert pose.state.has_pose
        t_end = time.monotonic() + (0.5 if stepped else 10.0)
        while counts(s)[1] == before[1] and time.monotonic() < t_end:  # the mapping thread's time
            time.sleep(0.01)
        after = counts(s)
        assert s.wait_mapping()
        settled = counts(s)
    assert settled[1] == before[1] + 1 and settled[0] > before[0]
    if stepped:
        assert after == before
    else:
        assert after[1] == before[1] + 1

def test_torch_backend_tracks_as_well_as_cpu(nominal, cpu_run):
    pytest.importorskip("torch")
    short = replace(nominal, images=nominal.images[:110], T_enu_cam=nominal.T_enu_cam[:110], t_s=nominal.t_s[:110])
    r = run_sequence(short, SlamConfig(feature_backend="torch"), "torch")  # torch on a shared CPU is slow
    assert r.ratio_after_init >= 0.95
    assert r.ate()[0] < max(2 * cpu_run.ate()[0], 1.0), (r.ate(), cpu_run.ate())


def test_patch_alignment_makes_each_points_observations_agree(nominal, cpu_run):
    """With slam.patch_alignment (the default) every observation of a point is where the patch it
    was first seen with aligns, not where an ORB corner was detected again: the final map's
    observations reproject much closer to their points (measured: median 0.25 px against 0.59 px
    without)."""
    off = run_sequence(nominal, SlamConfig(patch_alignment=False), "cpu")
    on_px, off_px = np.median(cpu_run.reproj_px), np.median(off.reproj_px)
    assert len(cpu_run.reproj_px) > 1000 and len(off.reproj_px) > 1000
    assert on_px < 0.6 * off_px, (on_px, off_px)
    assert cpu_run.ate()[0] < 1.0


@pytest.mark.parametrize("mode", ["recursive", "full"])
def test_loop_closure_undoes_injected_drift(nominal, mode):
    """A drifted, disconnected revisit of earlier keyframes (copies with new points moved by a
    known Sim(3)) is found by place recognition, verified by Sim(3) RANSAC and corrected."""
    from companion.slam_bench.runs import inject_drifted_revisit
    from slam.geometry import camera_center, sim3_matrix

    cfg = SlamConfig(loop_closing=mode, loop_min_gap_keyframes=5, local_window=4)
    with SlamSystem(nominal.camera, cfg) as s:
        for i in range(N):
            s.track(Frame(nominal.images[i], i / 30, i))
        s.wait_mapping()
        mapper = s.mapper
        m = mapper.map
        ang = np.deg2rad(3.0)
        R = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
        depth = np.median([np.linalg.norm(p.p_slam) for p in m.points.values()])
        S_drift = sim3_matrix(1.08, R, np.array([0.03, -0.02, 0.01]) * depth)
        originals = m.kf_ids()[-3:]
        copies = inject_drifted_revisit(s, originals, S_drift)

        def gaps():
            return [np.linalg.norm(camera_center(c.T_cam_slam) - camera_center(m.keyframes[o].T_cam_slam))
                    for c, o in zip(copies, originals)]

        before = gaps()
        mapper._loop(copies[-1])
        assert len(mapper.stats.loops) == 1 and mapper.stats.loops[0][1] == copies[-1].kf_id
        assert mapper.stats.loops[0][0] in originals
        after = gaps()
        assert max(after) < 0.2 * min(before), (before, after)
        gen, S_corr = s.tracker.shared.correction
        assert gen == 1 and np.allclose(S_corr @ S_drift, np.eye(4), atol=0.05)


def test_long_loss_resets_the_map_and_reinitializes(nominal):
    r = run_sequence(nominal, SlamConfig(reset_after_lost_frames=15), "reset", blackout=(60, 25))
    assert r.reset_counter == 1  # a new SLAM frame: downstream must drop its alignment
    assert r.states[60] == TrackingState.LOST and r.states[80] == TrackingState.INITIALIZING
    assert any(s == TrackingState.OK for s in r.states[85:])


def test_periodic_larger_ba_runs_in_the_background(cpu_run):
    """Every periodic_ba_every_keyframes-th local BA covers periodic_ba_window keyframes (scale
    anchoring through turns); it runs in the worker, so tracking targets above still hold."""
    c = SlamConfig()
    r = cpu_run
    assert len(r.ba_window) >= c.periodic_ba_every_keyframes
    assert max(r.ba_window) == c.periodic_ba_window
    assert min(r.ba_window) <= c.local_window


# --- attitude (gravity) prior, issue 4 §5 ------------------------------------------------------

@pytest.fixture(scope="session")
def prior_run(nominal):
    """The same flight with the simulated autopilot's gravity direction (AHRS bias + noise)."""
    return run_sequence(nominal, SlamConfig(use_attitude_prior=True), "prior")


def _slam_frame_tilt_deg(r) -> np.ndarray:
    """Per keyframe: angle between its true gravity direction, rotated into the SLAM frame by the
    estimated pose, and the SLAM frame's down axis (no alignment to truth at all)."""
    from slam.geometry import tilt_rad

    down_enu = np.array([0.0, 0.0, -1.0])
    return np.degrees([tilt_rad(T[:3, :3], Tt[:3, :3].T @ down_enu) for T, Tt in zip(r.kf_T_slam_cam, r.kf_T_enu_cam)])


def test_attitude_prior_gives_a_gravity_aligned_map(prior_run, cpu_run):
    """The new map is levelled at initialisation and stays level: every keyframe's true gravity
    points along the SLAM frame's -z within the AHRS bias (0.2° per axis) plus noise."""
    tilt = _slam_frame_tilt_deg(prior_run)
    assert len(tilt) >= 4
    assert tilt.max() < 1.0, tilt
    assert _slam_frame_tilt_deg(cpu_run).min() > 10  # without the prior the SLAM frame is the first camera's


def test_attitude_prior_agrees_with_the_vision_only_path(prior_run, cpu_run):
    """Same tracking and accuracy as without the prior on this short flight (the prior must not
    fight the images); the longer before/after comparison is companion.slam_bench --attitude-prior both."""
    assert prior_run.ratio_after_init >= 0.97 and prior_run.reset_counter == 0
    rmse_on, rmse_off = prior_run.ate()[0], cpu_run.ate()[0]
    assert rmse_on < 1.0 and abs(rmse_on - rmse_off) < 0.3, (rmse_on, rmse_off)
    assert abs(len(prior_run.kf_T_slam_cam) - len(cpu_run.kf_T_slam_cam)) <= 0.3 * len(cpu_run.kf_T_slam_cam)


def _ba_that_never_returns(problem):
    import time

    time.sleep(3600)


def test_a_bundle_adjustment_that_never_returns_is_abandoned_and_mapping_goes_on(nominal, monkeypatch):
    """A BA job that does not come back from its worker (seen once under heavy load: the job never
    reached the idle worker) no longer stops local BA for the rest of the flight: after BA_TIMEOUT_S
    the worker is restarted and mapping goes on; tracking never waits for it."""
    import slam.local_ba

    monkeypatch.setattr(slam.local_ba, "BA_TIMEOUT_S", 1.0)
    monkeypatch.setattr(slam.local_ba, "bundle_adjust", _ba_that_never_returns)
    states = []
    with SlamSystem(nominal.camera, SlamConfig()) as s:
        for i in range(100):
            states.append(s.track(Frame(nominal.images[i], float(nominal.t_s[i]), i)).state)
            assert s.wait_mapping(timeout_s=10.0), f"mapping stuck at frame {i}"
        stats = s.mapper.stats
        assert stats.n_keyframes >= 5 and stats.ba_timeouts >= 2, (stats.n_keyframes, stats.ba_timeouts)
        assert len(stats.local_ba_ms) == 0  # none came back, and none was waited for beyond the timeout
    first = next(i for i, st in enumerate(states) if st != TrackingState.INITIALIZING)
    assert first < 70 and np.mean([st.has_pose for st in states[first:]]) > 0.9
