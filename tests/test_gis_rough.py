"""Offline initialization T_rough (TerraSLAM §4.3): recover an unknown Sim(3) incl. scale and tilt."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gis.align.fine import enu_sim3
from gis.align.rough import RoughAlignmentFailed, rough_align
from gis.geodesy import LocalFrame
from gis.sim3 import Sim3, compose
from gis.synthetic import box_city_model, slam_like_cloud

ORIGIN = LocalFrame(47.3769, 8.5417, 450.0)


@pytest.fixture(scope="module")
def city():
    return box_city_model(500.0, ORIGIN, seed=4, spacing_m=1.0)


def test_rough_align_recovers_sim3_from_survey_cloud(city):
    c = np.array([10.0, 25.0, 0.0])
    p_enu = slam_like_cloud(city, c, 100, 30000, noise_m=0.05, seed=5)
    T_enu_slam = Sim3(0.2, Rotation.from_euler("zyx", [-110, 15, 8], degrees=True).as_matrix(), np.array([5.0, -7.0, 12.0]))
    p_slam = T_enu_slam.inverse().apply(p_enu)
    msgs = []
    # rough position 50 m off the survey centre
    r = rough_align(p_slam, city, c + np.array([35.0, -35.0, 0.0]), radius_m=180.0, progress=msgs.append)
    truth = compose(enu_sim3(ORIGIN), T_enu_slam)
    err = np.linalg.norm(r.T_ecef_slam.apply(p_slam) - truth.apply(p_slam), axis=1)
    assert err.mean() < 0.5
    assert r.error_m < 0.5 and r.n_inliers >= 8
    assert r.T_ecef_slam.scale == pytest.approx(0.2, rel=0.01)
    assert any("RANSAC" in m for m in msgs)


def test_rough_align_fails_clearly_on_flat_ground(city):
    rng = np.random.default_rng(0)
    flat = np.hstack([rng.uniform(0, 50, (2000, 2)), rng.normal(0, 0.01, (2000, 1))])
    with pytest.raises(RoughAlignmentFailed, match="buildings found"):
        rough_align(flat, city, np.zeros(3), radius_m=150.0)
