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


@pytest.fixture(scope="module")
def periodic_city():
    """Identical boxes every 40 m: a survey of a few blocks fits in many places."""
    import trimesh

    from gis.loaders import sample_mesh
    from gis.model import BUILDING, GROUND, GisModel

    half = 200.0
    ground = trimesh.Trimesh(vertices=[[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]],
                             faces=[[0, 1, 2], [0, 2, 3]], process=False)
    boxes = []
    for cx in np.arange(-180.0, 181.0, 40.0):
        for cy in np.arange(-180.0, 181.0, 40.0):
            T = trimesh.transformations.rotation_matrix(0.3, [0, 0, 1])
            T[:3, 3] = [cx, cy, 10.0]
            boxes.append(trimesh.creation.box(extents=[18.0, 12.0, 20.0], transform=T))
    mesh = trimesh.util.concatenate([ground] + boxes)
    labels = np.concatenate([np.full(2, GROUND, np.uint8), np.full(12 * len(boxes), BUILDING, np.uint8)])
    p, n, f = sample_mesh(mesh, 1.0, seed=0)
    return GisModel(p, n, labels[f], ORIGIN, "synthetic ENU", "synthetic://periodic")


def test_rough_align_refuses_an_ambiguous_fit_and_the_start_position_settles_it(periodic_city):
    """A regular block fits in several places equally well: T_rough is refused rather than picked
    at random (a wrong one would be flown with confidence). Where the survey started (the dataset's
    rough position, here 5 m off with σ 5 m) rules out the placements a block away."""
    from gis.align.rough import StartPrior

    c = np.array([20.0, 20.0, 0.0])
    p_enu = slam_like_cloud(periodic_city, c, 55, 20000, noise_m=0.05, seed=2)
    T_enu_slam = Sim3(0.3, Rotation.from_euler("zyx", [70, 3, -2], degrees=True).as_matrix(), np.array([4.0, 9.0, 30.0]))
    p_slam = T_enu_slam.inverse().apply(p_enu)
    with pytest.raises(RoughAlignmentFailed, match="ambiguous: a placement"):
        rough_align(p_slam, periodic_city, c, radius_m=150.0, refine=False)
    start_enu = c + np.array([0.0, 0.0, 60.0])  # the survey's first camera, 60 m above c
    start = StartPrior(T_enu_slam.inverse().apply(start_enu[None])[0], start_enu + np.array([3.0, -4.0, 0.0]), 5.0)
    r = rough_align(p_slam, periodic_city, c, radius_m=150.0, start=start)
    truth = compose(enu_sim3(ORIGIN), T_enu_slam)
    assert np.linalg.norm(r.T_ecef_slam.apply(p_slam) - truth.apply(p_slam), axis=1).mean() < 0.5
