"""Flights: multicopter-like kinematics, speed classes, loops that revisit, site survey."""
from __future__ import annotations

import numpy as np
import pytest

from companion.sim.flight import FlightSpec, make_trajectory
from companion.sim.scenario import SCENARIOS, T_body_cam_pitched


@pytest.mark.parametrize("name, lo, hi", [("slow", 0, 5), ("nominal", 5, 10), ("fast", 10, 20)])
def test_speed_classes(name, lo, hi):
    tr = make_trajectory(SCENARIOS[name].flight)
    t = np.arange(0, tr.duration_s, 0.1)
    _, v, a, R = tr.state(t)
    sp = np.linalg.norm(v, axis=1)
    assert lo <= np.median(sp) <= hi
    # smooth like a multicopter: bounded acceleration and jerk, tilt below 30°
    assert np.linalg.norm(a, axis=1).max() < 6.0
    jerk = np.linalg.norm(np.diff(a, axis=0), axis=1) / 0.1
    assert jerk.max() < 10.0
    tilt = np.degrees(np.arccos(-R[:, 2, 2]))
    assert tilt.max() < 30.0
    assert np.allclose(np.einsum("nji,njk->nik", R, R), np.eye(3), atol=1e-9)


def test_attitude_follows_thrust_and_heading():
    tr = make_trajectory(FlightSpec(kind="line", speed_mps=8.0, size_m=300))
    p, v, a, R = tr.state(np.array([20.0]))
    # cruising east: nose (body x) points east, pitched down to fight drag (nose below horizon)
    assert R[0, :, 0] @ [1, 0, 0] > 0.99
    assert R[0, 2, 0] < -0.01
    assert np.linalg.norm(v[0]) == pytest.approx(8.0, abs=0.1)


def test_loop_revisits_earlier_places():
    tr = make_trajectory(SCENARIOS["loop"].flight)
    t = np.arange(0, tr.duration_s, 0.5)
    p = tr.state(t)[0]
    first = p[t < tr.duration_s * 0.4]
    later = p[t > tr.duration_s * 0.6]
    d = np.linalg.norm(later[:, None, :2] - first[None, :, :2], axis=2).min(axis=1)
    assert (d < 3.0).mean() > 0.5  # most of the later flight retraces the first lap


def test_survey_covers_the_area_and_altitude_range():
    s = SCENARIOS["survey"].flight
    tr = make_trajectory(s)
    p = tr.state(np.arange(0, tr.duration_s, 1.0))[0]
    assert np.ptp(p[:, 0]) > 0.8 * s.size_m and np.ptp(p[:, 1]) > 0.8 * s.size_m
    assert np.allclose(p[:, 2], s.altitude_m, atol=0.5)
    with pytest.raises(ValueError, match="altitude_m"):
        FlightSpec(altitude_m=1000)


def test_camera_mount_nadir_and_oblique():
    T = T_body_cam_pitched(90.0)
    assert np.allclose(T[:3, 2], [0, 0, 1], atol=1e-12)  # camera z = body down
    assert np.allclose(T[:3, 1], [-1, 0, 0], atol=1e-12)  # image down = backwards
    T = T_body_cam_pitched(0.0)
    assert np.allclose(T[:3, 2], [1, 0, 0]) and np.allclose(T[:3, 0], [0, 1, 0])
    assert np.linalg.det(T_body_cam_pitched(37.0)[:3, :3]) == pytest.approx(1.0)
