"""The velocity a fix reports (gis.fix_velocity, through the Globalizer): the truth's velocity
within the claimed accuracy, across SLAM jumps and new alignments, none without enough positions."""
import numpy as np
import pytest

from gis import fix_velocity as fv
from gis.geodesy import LocalFrame
from gis.globalizer import Globalizer
from gis.sim3 import Sim3
from gis.types import Alignment, AlignmentSource
from slam.types import SlamPose, TrackingState

V0 = np.array([5.0, 3.0, -0.5])     # NED m/s
ACC = np.array([2.0, -1.0, 0.0])    # NED m/s², a turn's order of magnitude


def _track(rng, n=11, dt=0.1, jitter_m=0.1, jump_at=None, jump_m=(1.5, -2.0, 0.3)):
    t = np.arange(n) * dt
    p = V0 * t[:, None] + 0.5 * ACC * t[:, None] ** 2 + rng.normal(0, jitter_m, (n, 3))
    segment = np.zeros(n, int)
    if jump_at is not None:
        p[jump_at:] += jump_m
        segment[jump_at:] = 1
    return t, p, segment


@pytest.mark.parametrize("jump_at", [None, 7, 10])
def test_fit_recovers_the_velocity_within_its_sigma(jump_at):
    """Constant acceleration with 0.1 m of white jitter: the velocity at the newest position, its
    σ matching the error (RMS within 25 %), ~99.7 % within 3σ; a jump the segments absorb changes
    nothing, even in the newest position alone."""
    rng = np.random.default_rng(1)
    z, err, sig = [], [], []
    for _ in range(1000):
        t, p, seg = _track(rng, jump_at=jump_at)
        f = fv.fit_velocity(t, p, seg)
        e = f.v_ned_mps - (V0 + ACC * t[-1])
        z.append(np.max(np.abs(e)) / f.sigma_mps)
        err.append(e)
        sig.append(f.sigma_mps)
    rms = np.sqrt(np.mean(np.square(err), axis=0))
    assert np.all(rms < 1.25 * np.mean(sig)) and np.all(rms > 0.6 * np.mean(sig))
    assert np.mean(np.array(z) > 3.0) < 0.02


def test_a_jump_starts_a_segment_and_too_few_positions_give_no_velocity():
    rng = np.random.default_rng(2)
    t, p, seg = _track(rng)
    p_new = V0 * 1.1 + 0.5 * ACC * 1.1 ** 2
    assert not fv.breaks(t, p, seg, 1.1, p_new)
    assert fv.breaks(t, p, seg, 1.1, p_new + [2.0, 0.0, 0.0])
    assert fv.fit_velocity(t[:5], p[:5], seg[:5]) is None  # a quadratic needs 3 residual dof
    two_segments = np.r_[np.zeros(3, int), np.ones(3, int)]
    assert fv.fit_velocity(t[:6], p[:6], two_segments) is None


def test_window_takes_the_last_second_or_the_last_poses_at_a_low_rate():
    assert fv.window_start(np.arange(0, 5.01, 0.1)) == 40          # 10 Hz: the last second (11 positions)
    t2 = np.arange(0, 10.01, 0.5)                                    # 2 Hz: the last 8 (3.5 s) capped at 3 s
    assert t2[-1] - t2[fv.window_start(t2)] == pytest.approx(fv.MAX_WINDOW_S)


def _alignment(shift_m=0.0) -> Alignment:
    origin = LocalFrame(47.0, 8.0, 500.0)
    T = Sim3(1.0, origin.R_ecef_enu, origin.enu_to_ecef(np.array([shift_m, 0.0, 0.0])).reshape(3))
    return Alignment(T, AlignmentSource.FINE, 0.0, 0, np.eye(6) * 100, 0.1, center_slam=np.zeros(3))


def test_globalizer_velocity_across_a_jump_and_a_new_alignment():
    """SLAM = ENU at the origin, the vehicle flying east at 7 m/s, 10 fps, 5 cm of jitter: the fixes'
    velocity is 7 m/s east within their speed accuracy, also after a 2 m SLAM jump and after a new
    alignment that moves every fix 3 m (neither is motion); the first fixes have none."""
    rng = np.random.default_rng(3)
    g = Globalizer(np.eye(4), velocity_sigma_floor_mps=0.0)
    g.update_alignment(_alignment())
    out = []
    for k in range(60):
        T = np.eye(4)
        T[:3, 3] = [0.7 * k + (2.0 if k >= 30 else 0.0), 0.0, 80.0]
        T[:3, 3] += rng.normal(0, 0.05, 3)
        if k == 45:
            g.update_alignment(_alignment(3.0))
        f = g.fix(SlamPose(k / 10, k, T, TrackingState.OK, 0))
        out.append(f)
    assert out[0].v_ned_mps is None and out[4].v_ned_mps is None  # fewer than 6 positions
    with_v = [f for f in out if f.v_ned_mps is not None]
    assert len(with_v) >= 50
    for f in with_v:
        assert abs(f.v_ned_mps[1] - 7.0) < 3 * f.speed_acc_mps + 1e-9, (f.t_s, f.v_ned_mps, f.speed_acc_mps)
        assert abs(f.v_ned_mps[0]) < 3 * f.speed_acc_mps + 1e-9
    assert np.median([f.speed_acc_mps for f in with_v]) < 0.4
    floored = Globalizer(np.eye(4), velocity_sigma_floor_mps=0.3)
    floored.update_alignment(_alignment())
    for k in range(12):
        T = np.eye(4)
        T[:3, 3] = [0.7 * k, 0.0, 80.0]
        f = floored.fix(SlamPose(k / 10, k, T, TrackingState.OK, 0))
    assert f.speed_acc_mps == pytest.approx(0.3, abs=0.01)  # exact track: the floor alone
