"""GIS alignment against the simulator: its exported GIS files (real writers: trimesh PLY +
sidecar, laspy LAZ with CRS VLR, GeoJSON) load onto the world, and the Globalizer tracks truth on
a simulated flight (SLAM stood in for by truth in a scaled/rotated frame with drift)."""
from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from companion.sim import make_scenario
from companion.sim.gis_export import export_gis
from gis.bench import replay_flight
from gis.loaders import load_model
from gis.model import BUILDING, GROUND, GisModel
from gis.synthetic import slam_like_cloud


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    sc = make_scenario("nominal", seed=0, n_frames=900)
    gis_world, _ = sc.gis
    files = export_gis(gis_world, tmp_path_factory.mktemp("gis"))
    return sc, gis_world, files


def _to_model_enu(sc, m: GisModel, p_enu_sim: np.ndarray) -> np.ndarray:
    return m.origin.ecef_to_enu(sc.origin.enu_to_ecef(p_enu_sim))


def _distance_to_world(sc, world, m: GisModel, n: int = 3000) -> np.ndarray:
    p_sim = sc.origin.ecef_to_enu(m.origin.enu_to_ecef(m.points_enu[:: max(1, len(m) // n)]))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(world.mesh.vertices.astype(np.float32)), o3d.core.Tensor(world.mesh.triangles.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(p_sim.astype(np.float32))).numpy()


@pytest.mark.parametrize("which", ["mesh_ply", "points_laz"])
def test_sim_gis_files_load_onto_the_world(sim, which):
    sc, world, files = sim
    m = load_model(getattr(files, which))
    assert {GROUND, BUILDING} <= set(np.unique(m.labels).tolist())
    d = _distance_to_world(sc, world, m)
    assert np.percentile(d, 99) < 0.02  # georeference through UTM and back is exact to mm


def test_sim_geojson_footprints_match_building_walls(sim):
    sc, world, files = sim
    m = load_model(files.buildings_geojson)
    walls = np.abs(m.normals_enu[:, 2]) < 0.1
    d = _distance_to_world(sc, world, GisModel(m.points_enu[walls], m.normals_enu[walls], m.labels[walls], m.origin, "", "x"))
    assert np.median(d) < 0.05  # walls of extruded footprints lie on the world's walls


def test_globalizer_on_simulated_flight_meets_targets(sim):
    sc, world, files = sim
    m = load_model(files.mesh_ply)
    pts, labels = world.gis_points_enu(0.7, labels=(1, 2, 5, 6, 11), seed=1)  # SLAM also sees trees/cars
    pw = _to_model_enu(sc, m, pts)
    world_model = GisModel(pw, np.tile([0.0, 0.0, 1.0], (len(pw), 1)), labels, m.origin, "sim world", "sim://world")
    T = sc.truth.T_enu_cam.copy()
    R = m.origin.R_ecef_enu.T @ sc.origin.R_ecef_enu
    T[:, :3, :3] = R @ T[:, :3, :3]
    T[:, :3, 3] = _to_model_enu(sc, m, T[:, :3, 3])
    f = replay_flight(m, T, lambda c, k, seed, r: slam_like_cloud(world_model, c, r, k, 0.05, seed), sc.T_body_cam, every_n=200)
    assert f.n_fixes == f.n_frames and f.n_rejected == 0
    assert f.mean_m <= 0.15 and f.p99_m <= 0.5
    assert f.integrity_fraction <= 0.01
