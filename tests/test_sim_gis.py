"""GIS model export: real files with a CRS in standard readers, where the truth says; stale variants."""
from __future__ import annotations

import json

import laspy
import numpy as np
import open3d as o3d
import pytest
import trimesh
from pyproj import CRS, Transformer

from companion.sim.gis_export import export_gis
from companion.sim.stale import StaleSpec, stale_variant
from companion.sim.world import BUILDING, GROUND, ROAD, WorldSpec, make_world

SPEC = WorldSpec(n_buildings=12, extent_m=600.0)


@pytest.fixture(scope="module")
def world():
    return make_world(SPEC, seed=5, with_textures=False)


def _crs_to_enu(world, xyz, crs):
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(xyz[:, 0], xyz[:, 1])
    return world.origin.geodetic_to_enu(lat, lon, xyz[:, 2])


def _distance_to_world(world, p_enu):
    m = world.mesh
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(m.vertices.astype(np.float32)), o3d.core.Tensor(m.triangles.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor((p_enu).astype(np.float32))).numpy()


def test_fresh_model_files_open_with_crs_and_sit_on_the_world(world, tmp_path):
    gis, rep = stale_variant(world, StaleSpec(), seed=0)
    assert np.allclose(rep.T_model_world, np.eye(4))
    files = export_gis(gis, tmp_path, las_spacing_m=2.0)
    # LAZ: CRS VLR parsed by laspy, ASPRS classes, points on the world surface
    las = laspy.read(files.points_laz)
    crs = las.header.parse_crs()
    assert crs is not None and crs.equals(CRS.from_user_input(files.crs))
    assert set(np.unique(las.classification)) == {GROUND, BUILDING, ROAD}
    p = _crs_to_enu(world, np.asarray(las.xyz), files.crs)
    d = _distance_to_world(world, p[::20])
    assert np.percentile(d, 99) < 0.01, f"LAS points off the world surface: P99 {np.percentile(d, 99):.4f} m"
    # PLY + georef sidecar: trimesh reads per-face classification; vertices + offset in the CRS
    side = json.loads(files.mesh_ply.with_name("model.ply.georef.json").read_text())
    assert side["vertical"] == "ellipsoid" and CRS.from_user_input(side["crs"]).equals(CRS.from_user_input(files.crs))
    mesh = trimesh.load(files.mesh_ply, process=False)
    face = mesh.metadata["_ply_raw"]["face"]["data"]
    assert len(mesh.faces) == len(gis.mesh.triangles)
    assert np.array_equal(np.asarray(face["classification"]), gis.mesh.labels)
    v = _crs_to_enu(world, np.asarray(mesh.vertices) + side["offset_m"], side["crs"])
    assert np.abs(v - gis.mesh.vertices).max() < 0.005
    # GeoJSON footprints: lon/lat/h_ellipsoid back to ENU = the world's outlines and heights
    doc = json.loads(files.buildings_geojson.read_text())
    assert len(doc["features"]) == len(world.buildings)
    for f in doc["features"]:
        b = world.building(f["properties"]["id"])
        ring = np.asarray(f["geometry"]["coordinates"][0])
        enu = world.origin.geodetic_to_enu(ring[:, 1], ring[:, 0], ring[:, 2])
        assert np.abs(enu[:-1, :2] - b.outline_enu).max() < 0.005
        assert abs(enu[0, 2] - b.ground_z_m) < 0.005
        assert f["properties"]["height"] == pytest.approx(b.height_m, abs=1e-3)


def test_stale_variant_differs_by_the_configured_amount(world, tmp_path):
    spec = StaleSpec(changed_frac=0.25, change_m=2.5, n_new=2, n_demolished=1, registration_error_m=0.3)
    gis, rep = stale_variant(world, spec, seed=1)
    assert len(rep.missing_ids) == 2 and len(rep.changed_ids) == 3 and len(rep.demolished_ids) == 1
    assert np.hypot(*rep.T_model_world[:2, 3]) == pytest.approx(0.3)
    files = export_gis(gis, tmp_path, las_spacing_m=4.0)
    doc = json.loads(files.buildings_geojson.read_text())
    ids = {f["properties"]["id"] for f in doc["features"]}
    assert ids == ({b.id for b in world.buildings} - set(rep.missing_ids)) | set(rep.demolished_ids)
    for f in doc["features"]:
        bid = f["properties"]["id"]
        if bid in rep.demolished_ids:
            continue
        ring = np.asarray(f["geometry"]["coordinates"][0])
        enu = world.origin.geodetic_to_enu(ring[:, 1], ring[:, 0], ring[:, 2])[:-1, :2]
        shift = (enu - world.building(bid).outline_enu).mean(0)
        expected = 0.3 if bid not in rep.changed_ids else None
        if expected is not None:  # unchanged building: only the global registration error
            assert np.hypot(*shift) == pytest.approx(0.3, abs=0.01)
        else:  # changed outline: 2.5 m shift on top of the registration error
            assert abs(np.hypot(*(shift - rep.T_model_world[:2, 3])) - 2.5) < 0.05
    # the model's surface really is off the world: median distance of building points ≥ the error
    las = laspy.read(files.points_laz)
    p = _crs_to_enu(world, np.asarray(las.xyz), files.crs)[np.asarray(las.classification) == BUILDING]
    assert np.median(_distance_to_world(world, p)) > 0.1


def test_stale_spec_rejects_bad_values():
    with pytest.raises(ValueError, match="changed_frac"):
        StaleSpec(changed_frac=1.5)
    with pytest.raises(ValueError, match="n_buildings"):
        WorldSpec(n_buildings=0)


def test_world_labels_and_geometry_api(world):
    om, labels = world.mesh_o3d()
    assert len(labels) == len(om.triangles)
    assert {GROUND, BUILDING, ROAD, 5, 1} <= set(np.unique(labels))  # ground, building, road, vegetation, clutter
    pts, lab = world.gis_points_enu(2.0, labels=(BUILDING,))
    assert (lab == BUILDING).all() and len(pts) > 1000
    # buildings stand on the terrain, roofs at ground + height
    for b in world.buildings:
        gz = world.ground_height_m(b.outline_enu[:, 0], b.outline_enu[:, 1])
        assert b.ground_z_m == pytest.approx(gz.min()) and 10 <= b.height_m <= 60
