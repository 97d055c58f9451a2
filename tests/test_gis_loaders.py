"""GIS model ingestion: every format from files written by real writers, plus corrupt inputs."""
from __future__ import annotations

import json
import struct

import laspy
import numpy as np
import open3d as o3d
import osmium
import pytest
import trimesh
from pyproj import CRS, Transformer
from scipy.spatial import cKDTree

from gis import loaders
from gis.geodesy import geodetic_to_ecef, msl_to_ellipsoid
from gis.loaders import DEFAULT_BUILDING_HEIGHT_M, LEVEL_HEIGHT_M, load_model
from gis.model import BUILDING, GROUND, GisFormatError
from gis.synthetic import box_city_mesh

UTM = "EPSG:32632"
OFFSET = np.array([465000.0, 5250000.0, 400.0])  # near Zurich-ish, UTM 32N


def _utm_to_ecef(p_utm: np.ndarray) -> np.ndarray:
    lon, lat, h = Transformer.from_crs(UTM, "EPSG:4979", always_xy=True).transform(*p_utm.T)
    return geodetic_to_ecef(lat, lon, h)


def _model_ecef(m):
    return m.origin.enu_to_ecef(m.points_enu)


def _sidecar(path, crs=UTM, offset=OFFSET, vertical="ellipsoid"):
    path.with_name(path.name + ".georef.json").write_text(
        json.dumps({"crs": crs, "offset_m": list(map(float, offset)), "vertical": vertical})
    )


@pytest.fixture(scope="module")
def city():
    return box_city_mesh(120.0, seed=3)


def _check_city(m, mesh, tol_m: float = 2e-3):
    """Points lie on the city (nearest-surface distance in the CRS) and the up axis is right."""
    tr = Transformer.from_crs("EPSG:4978", UTM, always_xy=True)
    x, y, z = tr.transform(*_model_ecef(m).T)
    p_file = np.stack([x, y, z], 1) - OFFSET
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    dist = scene.compute_distance(o3d.core.Tensor(p_file[::20].astype(np.float32))).numpy()
    assert np.max(dist) < tol_m
    assert abs(p_file[:, 2].max() - mesh.bounds[1, 2]) < 0.5  # roofs up, not sideways


def test_ply_mesh_with_sidecar_and_vertex_labels(tmp_path, city):
    mesh, face_labels = city
    m2 = mesh.copy()
    vlab = np.full(len(m2.vertices), BUILDING, np.uint8)
    vlab[np.unique(m2.faces[face_labels == GROUND])] = GROUND
    m2.vertex_attributes["classification"] = vlab
    path = tmp_path / "city.ply"
    path.write_bytes(trimesh.exchange.ply.export_ply(m2, encoding="binary", include_attributes=True))
    _sidecar(path)
    m = load_model(path, sample_spacing_m=2.0)
    _check_city(m, mesh)
    assert set(np.unique(m.labels)) == {GROUND, BUILDING}
    assert m.source_crs.endswith("32632")
    # ground normals point up in ENU
    g = m.labels == GROUND
    assert np.all(np.abs(m.normals_enu[g, 2]) > 0.99)


def test_obj_and_glb_meshes(tmp_path, city):
    mesh, _ = city
    obj = tmp_path / "city.obj"
    mesh.export(obj)
    _sidecar(obj)
    _check_city(load_model(obj, 2.0), mesh)
    # glTF is Y-up: write the Z-up city rotated into Y-up, as a glTF exporter would
    glb = tmp_path / "city.glb"
    yup = mesh.copy()
    yup.apply_transform(np.block([[np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0.0]]), np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
    glb.write_bytes(trimesh.Scene(yup).export(file_type="glb"))
    _sidecar(glb)
    _check_city(load_model(glb, 2.0), mesh)
    draco = tmp_path / "city_draco.glb"  # the same, Draco-compressed (KHR_draco_mesh_compression)
    draco.write_bytes(trimesh.Scene(yup).export(file_type="glb", extension_draco=True))
    _sidecar(draco)
    _check_city(load_model(draco, 2.0), mesh, tol_m=np.ptp(mesh.vertices) * 2.0**-14)  # Draco's 14-bit positions


def _assert_thinned(model_ecef: np.ndarray, file_ecef: np.ndarray, file_p: np.ndarray, voxel_m: float) -> np.ndarray:
    """The model holds file points only, exactly one per occupied voxel_m cube of the file's
    coordinates; returns the index of each model point in the file."""
    d, idx = cKDTree(file_ecef).query(model_ecef)
    assert np.max(d) < 2e-3
    keys = np.floor(file_p / voxel_m).astype(np.int64)
    assert len(np.unique(keys[idx], axis=0)) == len(idx) == len(np.unique(keys, axis=0))
    return idx


def test_ply_point_cloud_egm96_heights(tmp_path):
    rng = np.random.default_rng(0)
    p = rng.uniform([0, 0, 0], [50, 50, 1.0], (500, 3))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    path = tmp_path / "cloud.ply"
    o3d.io.write_point_cloud(str(path), pcd)
    _sidecar(path, vertical="egm96")
    m = load_model(path)
    lon, lat = Transformer.from_crs(UTM, "EPSG:4326", always_xy=True).transform(*(p + OFFSET)[:, :2].T)
    expect = geodetic_to_ecef(lat, lon, msl_to_ellipsoid(lat, lon, (p + OFFSET)[:, 2]))
    _assert_thinned(_model_ecef(m), expect, p.astype(np.float32).astype(float), 1.0)  # the file's float32 coordinates
    assert np.all(np.abs(np.linalg.norm(m.normals_enu, axis=1) - 1) < 1e-9)


def test_point_cloud_whose_heights_leave_the_earth_is_refused(tmp_path):
    """A sidecar whose offset puts the cloud 200 km up (heights in the wrong unit, a typo): inside
    the CRS's area horizontally, so only the on-Earth check catches it, by name."""
    p = np.random.default_rng(0).uniform([0, 0, 0], [50, 50, 1.0], (500, 3))
    path = tmp_path / "cloud.ply"
    o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)))
    path.with_name("cloud.ply.georef.json").write_text(json.dumps({"crs": UTM, "offset_m": [OFFSET[0], OFFSET[1], 2e5],
                                                                       "vertical": "ellipsoid"}))
    with pytest.raises(GisFormatError, match=r"cloud.ply: (\d+) of \1 points are not near the Earth.s surface"):
        load_model(path)


@pytest.mark.parametrize("ext", ["las", "laz"])
def test_las_laz_with_crs_and_classification(tmp_path, ext, monkeypatch):
    """Read in chunks and thinned to one point per sampling voxel, labels kept with their points."""
    rng = np.random.default_rng(1)
    p = OFFSET + rng.uniform([0, 0, 0], [80, 80, 20], (2000, 3))
    hdr = laspy.LasHeader(point_format=6, version="1.4")
    hdr.add_crs(CRS.from_user_input(UTM))
    hdr.offsets, hdr.scales = OFFSET, [0.001] * 3
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = p.T
    las.classification = np.where(p[:, 2] - OFFSET[2] < 1, GROUND, BUILDING).astype(np.uint8)
    path = tmp_path / f"cloud.{ext}"
    las.write(path)
    path.with_name(path.name + ".georef.json").write_text(json.dumps({"vertical": "ellipsoid"}))  # (UTM is 2D)
    m = load_model(path)
    stored = laspy.read(path)
    p = np.column_stack([stored.x, stored.y, stored.z])  # voxels of the file's mm-quantised coordinates
    idx = _assert_thinned(_model_ecef(m), _utm_to_ecef(p), p, 1.0)
    np.testing.assert_array_equal(m.labels, np.asarray(las.classification)[idx])
    monkeypatch.setattr(loaders.las, "LAS_CHUNK_POINTS", 300)  # read in 7 chunks: voxels straddling chunks kept once
    chunked = load_model(path)
    _assert_thinned(_model_ecef(chunked), _utm_to_ecef(p), p, 1.0)
    dense = load_model(path, sample_spacing_m=0.1)  # a spacing finer than the cloud keeps every point
    np.testing.assert_allclose(np.sort(_model_ecef(dense), axis=0), np.sort(_utm_to_ecef(p), axis=0), atol=2e-3)
    las.classification[:100] = 7  # low noise, high noise and withheld points are no surface
    las.classification[100:200] = 18
    las.withheld = np.arange(len(p)) < 300
    las.write(path)
    kept = load_model(path, sample_spacing_m=0.1)
    np.testing.assert_allclose(np.sort(_model_ecef(kept), axis=0), np.sort(_utm_to_ecef(p[300:]), axis=0), atol=2e-3)


def _cityjson_cube(size=20.0, h=15.0):
    v = [[0, 0, 0], [size, 0, 0], [size, size, 0], [0, size, 0], [0, 0, h], [size, 0, h], [size, size, h], [0, size, h]]
    faces = [[[0, 3, 2, 1]], [[4, 5, 6, 7]], [[0, 1, 5, 4]], [[1, 2, 6, 5]], [[2, 3, 7, 6]], [[3, 0, 4, 7]]]
    return {
        "type": "CityJSON", "version": "2.0",
        "transform": {"scale": [0.001, 0.001, 0.001], "translate": list(OFFSET)},
        "metadata": {"referenceSystem": "https://www.opengis.net/def/crs/EPSG/0/32632"},
        "CityObjects": {"b1": {"type": "Building", "geometry": [{"type": "Solid", "lod": "2", "boundaries": [faces]}]}},
        "vertices": (np.asarray(v) * 1000).astype(int).tolist(),
    }


def _ellipsoidal(path):
    """The sidecar that states a file's heights (its CRS is 2D UTM) are WGS 84 ellipsoidal metres."""
    path.with_name(path.name + ".georef.json").write_text(json.dumps({"vertical": "ellipsoid"}))


def _write_dsm(path, crs="EPSG:32632", vertical="ellipsoid", res_m=0.5):
    """A 120 × 100 m digital surface model (rasterio, float32 GeoTIFF) at OFFSET's corner: ground at
    400 m, a 30 × 20 m building 12 m tall, a 10 × 10 m nodata hole; sidecar with the heights' datum."""
    import rasterio
    from rasterio.transform import from_origin
    h, w = int(100 / res_m), int(120 / res_m)
    yy, xx = np.mgrid[0:h, 0:w]
    e, n = (xx + 0.5) * res_m, 100.0 - (yy + 0.5) * res_m  # pixel centres, metres east / north of the corner
    z = np.where((e > 40) & (e < 70) & (n > 40) & (n < 60), 412.0, 400.0).astype(np.float32)
    z[(e > 100) & (n > 80)] = -9999.0
    with rasterio.open(path, "w", driver="GTiff", height=h, width=w, count=1, dtype="float32", crs=crs, nodata=-9999.0,
                       transform=from_origin(OFFSET[0], OFFSET[1] + 100.0, res_m, res_m)) as ds:
        ds.write(z, 1)
    if vertical:
        path.with_name(path.name + ".georef.json").write_text(json.dumps({"vertical": vertical}))
    return path


def test_geotiff_surface_model_roofs_walls_and_holes(tmp_path):
    """A DSM loads as the surface it describes: ground and roof at their heights, walls where the
    height jumps (normals level), nothing in the nodata hole, about one point per spacing² of
    ground; a 2D CRS without the heights' datum is refused, naming the sidecar."""
    m = load_model(_write_dsm(tmp_path / "dsm.tif"), sample_spacing_m=1.0)
    x, y, z = Transformer.from_crs("EPSG:4978", UTM, always_xy=True).transform(*_model_ecef(m).T)
    q = np.stack([x, y, z], 1) - OFFSET
    assert np.all(q[:, 2] > -0.01) and np.all(q[:, 2] < 12.01)
    roof = q[:, 2] > 11.99
    assert np.all((q[roof, 0] > 39) & (q[roof, 0] < 71) & (q[roof, 1] > 39) & (q[roof, 1] < 61))
    wall = (q[:, 2] > 0.5) & (q[:, 2] < 11.5)
    up = np.abs(m.normals_enu[:, 2])
    assert wall.sum() > 100 and np.median(up[wall]) < 0.2 and np.median(up[~wall]) > 0.99
    assert np.median(m.normals_enu[~wall, 2]) > 0  # roofs and ground face up
    assert not np.any((q[:, 0] > 101) & (q[:, 1] > 81))  # the hole
    flat = np.sum(~wall)
    assert 0.85 * (120 * 100 - 100) < flat < 1.15 * (120 * 100 - 100)
    bare = _write_dsm(tmp_path / "bare.tif", vertical=None)
    with pytest.raises(GisFormatError, match="bare.tif.georef.json"):
        load_model(bare)
    import rasterio  # the same DSM packed as int16 decimetres above 390 m (GDAL band scale / offset)
    with rasterio.open(tmp_path / "dsm.tif") as src:
        z, prof = src.read(1), src.profile
    prof.update(dtype="int16", nodata=-32768)
    with rasterio.open(tmp_path / "packed.tif", "w", **prof) as dst:
        dst.write(np.where(z == -9999.0, -32768, np.round((z - 390.0) * 10)).astype(np.int16), 1)
        dst.scales, dst.offsets = (0.1,), (390.0,)
    (tmp_path / "packed.tif.georef.json").write_text(json.dumps({"vertical": "ellipsoid"}))
    packed = load_model(tmp_path / "packed.tif", sample_spacing_m=1.0)
    np.testing.assert_allclose(np.sort(packed.origin.enu_to_geodetic(packed.points_enu)[2]),
                               np.sort(m.origin.enu_to_geodetic(m.points_enu)[2]), atol=0.02)


def test_geotiff_in_geographic_degrees_is_sampled_in_metres(tmp_path):
    """SRTM / Copernicus DEMs come in lon/lat degrees: the surface is meshed in ECEF, so it is sampled
    per square metre, not per square degree, and lands where the same DSM in UTM does."""
    import rasterio
    from rasterio.warp import Resampling, calculate_default_transform, reproject
    src = _write_dsm(tmp_path / "utm.tif", res_m=1.0)
    with rasterio.open(src) as s:
        T, w, h = calculate_default_transform(s.crs, "EPSG:4326", s.width, s.height, *s.bounds)
        z = np.full((h, w), -9999.0, np.float32)
        reproject(rasterio.band(s, 1), z, dst_transform=T, dst_crs="EPSG:4326", resampling=Resampling.nearest, dst_nodata=-9999.0)
        with rasterio.open(tmp_path / "ll.tif", "w", driver="GTiff", height=h, width=w, count=1, dtype="float32",
                           crs="EPSG:4326", transform=T, nodata=-9999.0) as d:
            d.write(z, 1)
    (tmp_path / "ll.tif.georef.json").write_text(json.dumps({"vertical": "ellipsoid"}))
    a, b = load_model(src, 1.0), load_model(tmp_path / "ll.tif", 1.0)
    assert 0.8 < len(b) / len(a) < 1.25
    pa, pb = _model_ecef(a), _model_ecef(b)
    assert np.linalg.norm(pa.mean(axis=0) - pb.mean(axis=0)) < 1.5
    assert np.percentile(cKDTree(pa).query(pb)[0], 90) < 1.5


def test_cityjson_geometry_instances_and_point_geometries(tmp_path):
    """A tree as a GeometryInstance (a 2×4×6 m box template, turned 90° about up, on a reference
    vertex 50 m east; template vertices not scaled by ``transform``) lands where the instance puts
    it; a MultiPoint geometry (no surfaces) is left out instead of failing the file."""
    from gis.model import HIGH_VEGETATION
    doc = _cityjson_cube()
    ref = len(doc["vertices"])
    doc["vertices"].append([50_000, 0, 0])  # scaled by transform: 50 m east of the cube's corner
    box = [[0, 0, 0], [2, 0, 0], [2, 4, 0], [0, 4, 0], [0, 0, 6], [2, 0, 6], [2, 4, 6], [0, 4, 6]]
    faces = [[[0, 3, 2, 1]], [[4, 5, 6, 7]], [[0, 1, 5, 4]], [[1, 2, 6, 5]], [[2, 3, 7, 6]], [[3, 0, 4, 7]]]
    doc["geometry-templates"] = {"templates": [{"type": "MultiSurface", "lod": "1", "boundaries": faces}],
                                 "vertices-templates": box}
    turn = [[0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]  # +90° about up: x → y, y → −x
    doc["CityObjects"]["tree"] = {"type": "SolitaryVegetationObject", "geometry": [
        {"type": "GeometryInstance", "template": 0, "boundaries": [ref], "transformationMatrix": sum(turn, [])}]}
    doc["CityObjects"]["lamp"] = {"type": "CityFurniture", "geometry": [{"type": "MultiPoint", "lod": "1", "boundaries": [ref]}]}
    path = tmp_path / "trees.city.json"
    path.write_text(json.dumps(doc))
    _ellipsoidal(path)
    m = load_model(path, sample_spacing_m=0.5)
    x, y, z = Transformer.from_crs("EPSG:4978", UTM, always_xy=True).transform(*_model_ecef(m)[m.labels == HIGH_VEGETATION].T)
    q = np.stack([x, y, z], 1) - OFFSET
    assert len(q) > 50
    np.testing.assert_allclose(q.min(axis=0), [46.0, 0.0, 0.0], atol=0.05)  # x ∈ [50−4, 50], y ∈ [0, 2]
    np.testing.assert_allclose(q.max(axis=0), [50.0, 2.0, 6.0], atol=0.05)
    assert np.sum(m.labels == BUILDING) > 2 * 20 * 20


def test_cityjson_seq_features_with_their_own_vertices(tmp_path):
    """CityJSONSeq: the header's transform applies to every feature's own vertex list; two cubes,
    the second 40 m north; a line that is not a CityJSONFeature is named."""
    cube = _cityjson_cube()
    header = {k: v for k, v in cube.items() if k not in ("CityObjects", "vertices")} | {"CityObjects": {}, "vertices": []}
    features = []
    for i, north_mm in enumerate((0, 40_000)):
        features.append({"type": "CityJSONFeature", "id": f"b{i}", "CityObjects": {f"b{i}": cube["CityObjects"]["b1"]},
                         "vertices": [[x, y + north_mm, z] for x, y, z in cube["vertices"]]})
    path = tmp_path / "tile.city.jsonl"
    path.write_text("\n".join(json.dumps(d) for d in [header, *features]) + "\n")
    _ellipsoidal(path)
    m = load_model(path, sample_spacing_m=1.0)
    x, y, z = Transformer.from_crs("EPSG:4978", UTM, always_xy=True).transform(*_model_ecef(m).T)
    q = np.stack([x, y, z], 1) - OFFSET
    assert np.all(m.labels == BUILDING)
    assert np.sum(q[:, 1] < 20.001) == pytest.approx(np.sum(q[:, 1] > 39.999), rel=0.05)  # one cube each
    np.testing.assert_allclose(q.max(axis=0), [20.0, 60.0, 15.0], atol=1e-3)
    path.write_text("\n".join(json.dumps(d) for d in [header, features[0], {"type": "CityJSON"}]))
    with pytest.raises(GisFormatError, match="line 3 is not a CityJSONFeature"):
        load_model(path)


def test_las_in_a_compound_crs_with_egm96_heights(tmp_path):
    """UTM 32N + EGM96 height (EPSG:32632+5773), as photogrammetry tools export clouds: heights are
    carried onto the ellipsoid by the geoid (the system's PROJ grid, Debian proj-data), the same N
    as gis.geodesy's; where no EGM96 grid is installed, the file is refused naming it."""
    from pyproj.transformer import TransformerGroup
    rng = np.random.default_rng(2)
    p = OFFSET + rng.uniform([0, 0, 0], [30, 30, 5], (300, 3))
    hdr = laspy.LasHeader(point_format=6, version="1.4")
    hdr.add_crs(CRS.from_user_input("EPSG:32632+5773"))
    hdr.offsets, hdr.scales = OFFSET, [0.001] * 3
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = p.T
    path = tmp_path / "msl.las"
    las.write(path)
    if TransformerGroup("EPSG:32632+5773", "EPSG:4979", allow_ballpark=False).best_available:
        m = load_model(path, sample_spacing_m=0.01)
        lon, lat = Transformer.from_crs(UTM, "EPSG:4326", always_xy=True).transform(*p[:, :2].T)
        expect = geodetic_to_ecef(lat, lon, msl_to_ellipsoid(lat, lon, p[:, 2]))  # N ≈ 47 m here
        np.testing.assert_allclose(np.sort(_model_ecef(m), axis=0), np.sort(expect, axis=0), atol=0.02)
    else:
        with pytest.raises(GisFormatError, match="egm96"):
            load_model(path)


def test_a_vertical_datum_without_its_grid_is_refused_not_guessed(tmp_path):
    """The Dutch 3D BAG's CRS, RD New + NAP height (EPSG:7415): NAP needs the nlgeo2018 geoid grid.
    Without it PROJ's ballpark fallback took NAP heights as ellipsoidal ones (a model ~43 m too
    low, loaded without a word); now the file is refused naming the grid. Where the grid is
    installed, NAP 0 m lands ~43 m above the ellipsoid."""
    from pyproj.transformer import TransformerGroup
    doc = _cityjson_cube()
    doc["transform"]["translate"] = [155000.0, 463000.0, 0.0]
    doc["metadata"]["referenceSystem"] = "https://www.opengis.net/def/crs/EPSG/0/7415"
    path = tmp_path / "bag.city.json"
    path.write_text(json.dumps(doc))
    if TransformerGroup("EPSG:7415", "EPSG:4979", allow_ballpark=False).best_available:
        m = load_model(path)
        h = m.origin.enu_to_geodetic(m.points_enu)[2]
        assert 40.0 < h.min() < 46.0, h.min()
    else:
        with pytest.raises(GisFormatError, match="nl_nsgi_nlgeo2018") as e:
            load_model(path)
        assert str(path) in str(e.value)


def test_cityjson_building(tmp_path):
    path = tmp_path / "city.json"
    path.write_text(json.dumps(_cityjson_cube()))
    _ellipsoidal(path)
    m = load_model(path, sample_spacing_m=1.0)
    assert np.all(m.labels == BUILDING)
    tr = Transformer.from_crs("EPSG:4978", UTM, always_xy=True)
    x, y, z = tr.transform(*_model_ecef(m).T)
    q = np.stack([x, y, z], 1) - OFFSET
    assert np.all(q > -1e-3) and np.all(q[:, :2] < 20 + 1e-3) and q[:, 2].max() == pytest.approx(15, abs=1e-3)
    # every sample lies on a cube face: at least one coordinate at a face plane
    on_face = np.isclose(q[:, 0], 0, atol=1e-3) | np.isclose(q[:, 0], 20, atol=1e-3) | np.isclose(q[:, 1], 0, atol=1e-3) | \
        np.isclose(q[:, 1], 20, atol=1e-3) | np.isclose(q[:, 2], 0, atol=1e-3) | np.isclose(q[:, 2], 15, atol=1e-3)
    assert on_face.all()
    assert len(m) > 2 * (20 * 20) + 4 * 20 * 15 * 0.9


def test_geojson_footprints_height_and_levels(tmp_path):
    lat0, lon0 = 47.37, 8.54
    d = 0.0002
    ring = [[lon0, lat0], [lon0 + d, lat0], [lon0 + d, lat0 + d], [lon0, lat0 + d], [lon0, lat0]]
    ring2 = [[x + 0.001, y, 410.0] for x, y in ring]
    fc = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"building": "yes", "building:levels": "4"}, "geometry": {"type": "Polygon", "coordinates": [ring]}},
        {"type": "Feature", "properties": {"height": 21.5}, "geometry": {"type": "Polygon", "coordinates": [ring2]}},
    ]}
    path = tmp_path / "buildings.geojson"
    path.write_text(json.dumps(fc))
    with pytest.raises(GisFormatError, match="no heights"):
        load_model(path)  # the first footprint has no z and no ground height was given
    m = load_model(path, sample_spacing_m=1.0, ground=400.0)
    assert np.all(m.labels == BUILDING)
    lat, lon, h = m.origin.enu_to_geodetic(m.points_enu)
    first = lon < lon0 + d + 1e-7
    n_geoid = float(msl_to_ellipsoid(lat0, lon0, 0.0))  # EGM96 undulation at the site (~48 m)
    assert h[first].max() == pytest.approx(400 + n_geoid + 4 * LEVEL_HEIGHT_M, abs=0.05)
    assert h[first].min() == pytest.approx(400 + n_geoid, abs=0.6)  # lowest wall sample: half a spacing up
    assert h[~first].max() == pytest.approx(410 + 21.5, abs=1e-3)  # polygon z is ellipsoidal: no ground needed
    assert h[~first].min() > 409.9


def test_footprints_stand_on_a_terrain_model(tmp_path, caplog):
    """OSM-style footprints without heights on a DTM (GeoTIFF, EGM96 heights, ground rising 1 m per
    10 m eastwards): each building's walls start at the terrain under its outline's lowest vertex,
    turned ellipsoidal; a footprint beyond the DTM is left out with a warning; one ground source only."""
    import rasterio
    from rasterio.transform import from_origin

    from gis.config import GisConfig
    from gis.loaders import dem_heights_ellipsoid_m
    h, w = 200, 200  # 1 m pixels, 200 × 200 m from OFFSET's corner
    e = np.arange(w) + 0.5
    z = np.tile(400.0 + 0.1 * e, (h, 1)).astype(np.float32)
    dem = tmp_path / "dtm.tif"
    with rasterio.open(dem, "w", driver="GTiff", height=h, width=w, count=1, dtype="float32", crs=UTM,
                       transform=from_origin(OFFSET[0], OFFSET[1] + 200.0, 1.0, 1.0)) as ds:
        ds.write(z, 1)
    dem.with_name("dtm.tif.georef.json").write_text(json.dumps({"vertical": "egm96"}))
    to_ll = Transformer.from_crs(UTM, "EPSG:4326", always_xy=True)

    def square(e0, n0, side=20.0):
        ring = [(e0, n0), (e0 + side, n0), (e0 + side, n0 + side), (e0, n0 + side), (e0, n0)]
        return [[*to_ll.transform(OFFSET[0] + x, OFFSET[1] + y)] for x, y in ring]
    feats = [{"type": "Feature", "properties": {"height": 10.0}, "geometry": {"type": "Polygon", "coordinates": [square(e0, 50.0)]}}
             for e0 in (20.0, 150.0, 400.0)]  # the third is beyond the DTM
    path = tmp_path / "osm.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    with caplog.at_level("WARNING"):
        m = load_model(path, sample_spacing_m=1.0, ground=dem)
    assert "1 footprints outside the terrain model" in caplog.text
    lat, lon, hgt = m.origin.enu_to_geodetic(m.points_enu)
    x, _ = Transformer.from_crs("EPSG:4326", UTM, always_xy=True).transform(lon, lat)
    for e0 in (20.0, 150.0):
        mine = np.abs(x - OFFSET[0] - e0 - 10.0) <= 10.5
        lo_lon, lo_lat = to_ll.transform(OFFSET[0] + e0, OFFSET[1] + 50.0)
        n_geoid = float(msl_to_ellipsoid(lo_lat, lo_lon, 0.0))
        assert hgt[mine].min() == pytest.approx(400.0 + 0.1 * (np.floor(e0) + 0.5) + n_geoid, abs=0.6)  # lowest wall sample: ≤ half a spacing up
        assert hgt[mine].max() == pytest.approx(hgt[mine].min() + 10.0, abs=0.6)
    assert not np.any(x - OFFSET[0] > 300)
    assert np.isnan(dem_heights_ellipsoid_m(dem, np.array([0.0]), np.array([0.0]))[0])
    with pytest.raises(ValueError, match="not both"):
        GisConfig(footprint_ground_h_msl_m=400.0, footprint_ground_dem=dem)


def test_geojson_in_a_projected_crs_named_by_a_legacy_crs_member(tmp_path):
    """GeoJSON as QGIS/GDAL write projected data (the 2008 spec's ``crs`` member, UTM 32N here) lands
    where the same footprint in lon/lat does; without the member those numbers are refused, not
    read as degrees."""
    lat0, lon0, d = 47.37, 8.54, 0.0002
    ring = [[lon0, lat0], [lon0 + d, lat0], [lon0 + d, lat0 + d], [lon0, lat0 + d], [lon0, lat0]]
    to_utm = Transformer.from_crs("EPSG:4326", UTM, always_xy=True)
    utm = [[*to_utm.transform(x, y), 410.0] for x, y in ring]
    feature = {"type": "Feature", "properties": {"height": 12.0}, "geometry": {"type": "Polygon", "coordinates": [utm]}}
    projected = {"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::32632"}},
                 "features": [feature]}
    lonlat = {"type": "FeatureCollection", "features": [
        {**feature, "geometry": {"type": "Polygon", "coordinates": [[[x, y, 410.0] for x, y in ring]]}}]}
    (tmp_path / "utm.geojson").write_text(json.dumps(projected))
    (tmp_path / "ll.geojson").write_text(json.dumps(lonlat))
    a, b = load_model(tmp_path / "utm.geojson"), load_model(tmp_path / "ll.geojson")
    np.testing.assert_allclose(_model_ecef(a), _model_ecef(b), atol=1e-3)
    del projected["crs"]
    (tmp_path / "utm.geojson").write_text(json.dumps(projected))
    with pytest.raises(GisFormatError, match="not WGS 84 lon/lat"):
        load_model(tmp_path / "utm.geojson")


def _write_osm(path, lat0: float, lon0: float) -> float:
    """A real .osm.pbf (pyosmium's writer): a 4-level way, a multipolygon relation with a courtyard
    (height 21.5 m, min_height 3 m), a building with an unreadable height, and a tagged road.
    Returns the footprint side in degrees."""
    d = 0.0002
    mut = osmium.osm.mutable
    w = osmium.SimpleWriter(str(path))
    nid = iter(range(1, 1000))

    def square(lon, lat, side):
        ids = [next(nid) for _ in range(4)]
        for i, (x, y) in zip(ids, [(lon, lat), (lon + side, lat), (lon + side, lat + side), (lon, lat + side)]):
            w.add_node(mut.Node(id=i, location=(x, y), version=1))
        return ids + ids[:1]

    a = square(lon0, lat0, d)
    outer = square(lon0 + 0.001, lat0, d)
    inner = square(lon0 + 0.001 + d / 4, lat0 + d / 4, d / 2)
    c = square(lon0 + 0.002, lat0, d)
    road = square(lon0, lat0 + 0.001, d)
    w.add_way(mut.Way(id=1, nodes=a, tags={"building": "yes", "building:levels": "4"}, version=1))
    w.add_way(mut.Way(id=2, nodes=outer, version=1))
    w.add_way(mut.Way(id=3, nodes=inner, version=1))
    w.add_way(mut.Way(id=4, nodes=c, tags={"building": "yes", "height": "about 12"}, version=1))
    w.add_way(mut.Way(id=5, nodes=road, tags={"highway": "pedestrian", "area": "yes"}, version=1))
    w.add_relation(mut.Relation(id=1, members=[("w", 2, "outer"), ("w", 3, "inner")], version=1,
                                tags={"type": "multipolygon", "building": "yes", "height": "21.5 m", "min_height": "3"}))
    w.close()
    return d


def test_osm_pbf_buildings_ways_multipolygons_and_bad_tags(tmp_path, caplog):
    lat0, lon0 = 47.37, 8.54
    path = tmp_path / "city.osm.pbf"
    d = _write_osm(path, lat0, lon0)
    m = load_model(path, sample_spacing_m=1.0, ground=400.0)
    assert np.all(m.labels == BUILDING)
    lat, lon, h = m.origin.enu_to_geodetic(m.points_enu)
    g = 400.0 + float(msl_to_ellipsoid(lat0, lon0, 0.0))  # ground, ellipsoidal
    first = lon < lon0 + d + 1e-7
    second = (lon > lon0 + 0.001 - 1e-7) & (lon < lon0 + 0.001 + d + 1e-7)
    third = lon > lon0 + 0.002 - 1e-7
    assert first.sum() + second.sum() + third.sum() == len(m)  # the road area is not a building
    assert lat.max() < lat0 + d + 1e-6
    assert h[first].max() == pytest.approx(g + 4 * LEVEL_HEIGHT_M, abs=0.05)
    # OSM height is the top above ground; min_height lifts the base (a building part on pillars)
    assert h[second].max() == pytest.approx(g + 21.5, abs=0.05) and h[second].min() > g + 3 - 0.05
    assert h[third].max() == pytest.approx(g + DEFAULT_BUILDING_HEIGHT_M, abs=0.05)
    assert "1 unreadable OSM height tags" in caplog.text and "about 12" in caplog.text
    # the courtyard (inner ring) has walls but no roof: no roof sample inside it
    roof = second & (h > g + 21.5 - 0.1)
    cx, cy = lon0 + 0.001 + d / 2, lat0 + d / 2
    inside = (np.abs(lon[roof] - cx) < d / 4 - 1e-5) & (np.abs(lat[roof] - cy) < d / 4 - 1e-5)
    assert roof.sum() > 100 and not inside.any()


def test_osm_without_buildings_fails_clearly(tmp_path):
    path = tmp_path / "roads.osm.pbf"
    w = osmium.SimpleWriter(str(path))
    for i in range(1, 4):
        w.add_node(osmium.osm.mutable.Node(id=i, location=(8.54 + i * 1e-4, 47.37), version=1))
    w.add_way(osmium.osm.mutable.Way(id=1, nodes=[1, 2, 3], tags={"highway": "residential"}, version=1))
    w.close()
    with pytest.raises(GisFormatError, match="no building areas") as e:
        load_model(path)
    assert str(path) in str(e.value)


def _b3dm(glb: bytes, rtc: np.ndarray) -> bytes:
    ft = json.dumps({"BATCH_LENGTH": 0, "RTC_CENTER": list(map(float, rtc))}).encode()
    ft += b" " * ((8 - (28 + len(ft)) % 8) % 8)
    total = 28 + len(ft) + len(glb)
    return struct.pack("<4sIIIIII", b"b3dm", 1, total, len(ft), 0, 0, 0) + ft + glb


def test_3dtiles_b3dm_tileset(tmp_path):
    box = trimesh.creation.box(extents=[30, 12, 20])  # Y-up inside the glb: 12 m tall
    rtc = geodetic_to_ecef(47.37, 8.54, 420.0)
    (tmp_path / "tiles").mkdir()
    (tmp_path / "tiles" / "a.b3dm").write_bytes(_b3dm(trimesh.Scene(box).export(file_type="glb"), rtc))
    # tile transform: rotation so the tile's local z is ECEF up at the site (ENU at rtc)
    from gis.geodesy import R_ecef_enu
    T = np.eye(4)
    T[:3, :3] = R_ecef_enu(47.37, 8.54)
    T[:3, 3] = rtc - T[:3, :3] @ rtc  # rotate about the RTC centre
    ts = {"asset": {"version": "1.0"}, "geometricError": 100,
          "root": {"boundingVolume": {"sphere": [*rtc, 50]}, "geometricError": 10, "refine": "REPLACE",
                   "transform": T.T.reshape(-1).tolist(),
                   "children": [{"boundingVolume": {"sphere": [*rtc, 50]}, "geometricError": 0, "content": {"uri": "tiles/a.b3dm"}}]}}
    (tmp_path / "tileset.json").write_text(json.dumps(ts))
    m = load_model(tmp_path, sample_spacing_m=1.0)
    lat, lon, h = m.origin.enu_to_geodetic(m.points_enu)
    enu = m.origin.geodetic_to_enu(lat, lon, h)
    assert np.ptp(enu[:, 2]) == pytest.approx(12.0, abs=0.05)  # glTF Y became up
    assert abs(np.mean(lat) - 47.37) < 1e-3 and abs(np.mean(lon) - 8.54) < 1e-3


def _cmpt(*tiles: bytes) -> bytes:
    return struct.pack("<4sIII", b"cmpt", 1, 16 + sum(map(len, tiles)), len(tiles)) + b"".join(tiles)


def test_3dtiles_composite_tiles(tmp_path):
    """cmpt content (a composite of b3dm / pnts / nested cmpt tiles, 3D Tiles 1.0): every inner tile
    is loaded in the tile's frame; a truncated composite is refused by name."""
    from gis.geodesy import LocalFrame, R_ecef_enu
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_ecef_enu(47.37, 8.54), geodetic_to_ecef(47.37, 8.54, 420.0)

    def box_b3dm(east_m: float, height_m: float) -> bytes:
        box = trimesh.creation.box(extents=[10, height_m, 10])
        box.apply_translation([east_m, height_m / 2, 0.0])  # glTF Y-up: standing on the ground
        return _b3dm(trimesh.Scene(box).export(file_type="glb"), np.zeros(3))

    rng = np.random.default_rng(0)
    ground = np.column_stack([rng.uniform(-60, -40, 4000), rng.uniform(-10, 10, 4000), np.zeros(4000)])
    data = _cmpt(box_b3dm(0.0, 6.0), _pnts(ground, False, np.zeros(3)), _cmpt(box_b3dm(40.0, 14.0)))
    (tmp_path / "c.cmpt").write_bytes(data)
    (tmp_path / "tileset.json").write_text(json.dumps({"asset": {"version": "1.0"}, "geometricError": 10, "root": {
        "boundingVolume": {"sphere": [0, 0, 0, 80]}, "geometricError": 0, "transform": T.T.reshape(-1).tolist(),
        "content": {"uri": "c.cmpt"}}}))
    m = load_model(tmp_path, sample_spacing_m=1.0)
    enu = LocalFrame(47.37, 8.54, 420.0).ecef_to_enu(m.origin.enu_to_ecef(m.points_enu))
    near = lambda e: np.abs(enu[:, 0] - e) < 5.5  # noqa: E731
    assert enu[near(0.0), 2].max() == pytest.approx(6.0, abs=0.05)    # the b3dm
    assert enu[near(40.0), 2].max() == pytest.approx(14.0, abs=0.05)  # the nested composite's b3dm
    assert np.sum(enu[:, 0] < -39) > 200 and np.allclose(enu[enu[:, 0] < -39, 2], 0.0, atol=0.01)  # the pnts
    (tmp_path / "c.cmpt").write_bytes(data[: len(data) - 50])
    with pytest.raises(GisFormatError, match="c.cmpt.*inner tile 2 of 3"):
        load_model(tmp_path, sample_spacing_m=1.0)


def _oct16(v: np.ndarray) -> np.ndarray:
    """Unit vectors → 16-bit oct encoding (the inverse of the loader's decode; Cigolle et al. 2014)."""
    v = v / np.abs(v).sum(axis=1, keepdims=True)
    x, y = v[:, 0], v[:, 1]
    sx, sy = np.where(x >= 0, 1.0, -1.0), np.where(y >= 0, 1.0, -1.0)
    x, y = np.where(v[:, 2] < 0, (1 - np.abs(v[:, 1])) * sx, x), np.where(v[:, 2] < 0, (1 - np.abs(v[:, 0])) * sy, y)
    return np.round((np.column_stack([x, y]) + 1) / 2 * 65535).astype("<u2")


def _i3dm(ft: dict, body: bytes, glb_or_uri: bytes, gltf_format: int = 1) -> bytes:
    js = json.dumps(ft).encode()
    js += b" " * ((8 - (32 + len(js)) % 8) % 8)
    body += b"\x00" * (-len(body) % 8)
    total = 32 + len(js) + len(body) + len(glb_or_uri)
    return struct.pack("<4sIIIIIII", b"i3dm", 1, total, len(js), len(body), 0, 0, gltf_format) + js + body + glb_or_uri


@pytest.mark.parametrize("orientation", ["normals", "oct32p", "east_north_up"])
def test_3dtiles_instanced_models(tmp_path, orientation):
    """i3dm content (trees as instances of one glTF): each instance stands upright at its position
    however the orientation is given (NORMAL_UP = north, NORMAL_RIGHT = east, as exporters write
    for Cesium's composition; their oct encoding; EAST_NORTH_UP), scaled by SCALE; positions
    about RTC_CENTER in ECEF; the glTF by URI too. A truncated i3dm is refused by name."""
    from gis.geodesy import LocalFrame, R_ecef_enu
    site = LocalFrame(47.37, 8.54, 420.0)
    tree = trimesh.creation.box(extents=[2.0, 8.0, 2.0])  # glTF Y-up: 8 m tall, standing on y = 0
    tree.apply_translation([0.0, 4.0, 0.0])
    glb = trimesh.Scene(tree).export(file_type="glb")
    enu = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [0.0, 30.0, 0.0]])  # three trees on the ground
    ecef = site.enu_to_ecef(enu)
    rtc = site.origin_ecef_m
    R = np.stack([R_ecef_enu(*site.enu_to_geodetic(p)[:2]) for p in enu])  # columns east, north, up
    scale = np.array([1.0, 2.0, 1.0], "<f4")
    ft = {"INSTANCES_LENGTH": 3, "RTC_CENTER": rtc.tolist(), "POSITION": {"byteOffset": 0}, "SCALE": {"byteOffset": 36}}
    body = (ecef - rtc).astype("<f4").tobytes() + scale.tobytes()
    if orientation == "normals":
        ft.update(NORMAL_UP={"byteOffset": 48}, NORMAL_RIGHT={"byteOffset": 84})
        body += R[:, :, 1].astype("<f4").tobytes() + R[:, :, 0].astype("<f4").tobytes()
    elif orientation == "oct32p":
        ft.update(NORMAL_UP_OCT32P={"byteOffset": 48}, NORMAL_RIGHT_OCT32P={"byteOffset": 60})
        body += _oct16(R[:, :, 1]).tobytes() + _oct16(R[:, :, 0]).tobytes()
    else:
        ft["EAST_NORTH_UP"] = True
    (tmp_path / "trees.i3dm").write_bytes(_i3dm(ft, body, glb))
    (tmp_path / "tileset.json").write_text(json.dumps({"asset": {"version": "1.0"}, "geometricError": 10, "root": {
        "boundingVolume": {"sphere": [*rtc, 80]}, "geometricError": 0, "content": {"uri": "trees.i3dm"}}}))
    m = load_model(tmp_path, sample_spacing_m=0.5)
    p = site.ecef_to_enu(m.origin.enu_to_ecef(m.points_enu))
    for (e, n, _), s in zip(enu, scale):
        at = np.hypot(p[:, 0] - e, p[:, 1] - n) < 3.0 * s
        assert at.sum() > 50
        assert p[at, 2].min() == pytest.approx(0.0, abs=0.05) and p[at, 2].max() == pytest.approx(8.0 * s, abs=0.05)
        assert np.ptp(p[at, 0]) == pytest.approx(2.0 * s, abs=0.6) and np.ptp(p[at, 1]) == pytest.approx(2.0 * s, abs=0.6)
    if orientation == "normals":  # the same glTF by URI beside the tile
        (tmp_path / "tree.glb").write_bytes(glb)
        (tmp_path / "trees.i3dm").write_bytes(_i3dm(ft, body, b"tree.glb", gltf_format=0))
        assert len(load_model(tmp_path, sample_spacing_m=0.5)) == len(m)
        (tmp_path / "tree.glb").unlink()
        with pytest.raises(GisFormatError, match="trees.i3dm: its glTF tree.glb is missing"):
            load_model(tmp_path, sample_spacing_m=0.5)
    (tmp_path / "trees.i3dm").write_bytes(_i3dm(ft, body, glb)[:200])
    with pytest.raises(GisFormatError, match="trees.i3dm.*(truncated|byteLength)"):
        load_model(tmp_path, sample_spacing_m=0.5)


def _hlod_tileset(tmp_path, refine: str, content_uri_0: str = "tiles/coarse.glb"):
    """A tileset at the site, tile frame ENU: a coarse 60×60×4 m slab (geometric error 5 m), refined
    by two 10 m cubes 40 m apart (error 0), glTF Y-up content."""
    from gis.geodesy import R_ecef_enu
    (tmp_path / "tiles").mkdir(exist_ok=True)
    (tmp_path / "tiles" / "coarse.glb").write_bytes(trimesh.Scene(trimesh.creation.box(extents=[60, 4, 60])).export(file_type="glb"))
    for i, x in enumerate((-20.0, 20.0)):
        cube = trimesh.creation.box(extents=[10, 10, 10])
        cube.apply_translation([x, 20.0, 0.0])  # 20 m up (glTF Y)
        (tmp_path / "tiles" / f"fine_{i}.glb").write_bytes(trimesh.Scene(cube).export(file_type="glb"))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_ecef_enu(47.37, 8.54), geodetic_to_ecef(47.37, 8.54, 420.0)
    ts = {"asset": {"version": "1.1"}, "geometricError": 100, "root": {
        "boundingVolume": {"sphere": [0, 0, 0, 60]}, "geometricError": 5, "refine": refine, "transform": T.T.reshape(-1).tolist(),
        "content": {"uri": content_uri_0},
        "children": [{"boundingVolume": {"sphere": [0, 0, 0, 60]}, "geometricError": 0, "content": {"uri": f"tiles/fine_{i}.glb?v=2"}}
                     for i in range(2)]}}
    path = tmp_path / "tileset.json"
    path.write_text(json.dumps(ts))
    return path


def _pnts(p_tile: np.ndarray, quantized: bool, rtc: np.ndarray) -> bytes:
    """A pnts tile as 3D Tiles 1.0 lays it out (written here to the spec: no kept Python writer
    runs on this numpy): header, feature table JSON padded to 8 bytes, then the binary body."""
    local = p_tile - rtc
    if quantized:
        lo, span = local.min(axis=0), np.ptp(local, axis=0)
        body = np.round((local - lo) / span * 65535).astype("<u2").tobytes()
        ft = {"POINTS_LENGTH": len(p_tile), "POSITION_QUANTIZED": {"byteOffset": 0},
              "QUANTIZED_VOLUME_OFFSET": lo.tolist(), "QUANTIZED_VOLUME_SCALE": span.tolist(), "RTC_CENTER": rtc.tolist()}
    else:
        body = local.astype("<f4").tobytes()
        ft = {"POINTS_LENGTH": len(p_tile), "POSITION": {"byteOffset": 0}, "RTC_CENTER": rtc.tolist()}
    js = json.dumps(ft).encode()
    js += b" " * ((8 - (28 + len(js)) % 8) % 8)
    body += b"\x00" * (-len(body) % 8)
    return struct.pack("<4sIIIIII", b"pnts", 1, 28 + len(js) + len(body), len(js), len(body), 0, 0) + js + body


@pytest.mark.parametrize("quantized", [False, True])
def test_3dtiles_point_cloud_tiles(tmp_path, quantized):
    """pnts content (LiDAR served as 3D Tiles): float or quantized positions about an RTC centre, the
    tile transform applied, Z-up as stored (no glTF rotation), thinned to the spacing."""
    from gis.geodesy import LocalFrame, R_ecef_enu
    rng = np.random.default_rng(4)
    e, n = rng.uniform(0, 40, (2, 20000))
    p_tile = np.column_stack([e, n, np.where(e < 20, 0.0, 8.0)])  # a ground plane and an 8 m step, ENU metres
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "c.pnts").write_bytes(_pnts(p_tile, quantized, np.array([20.0, 20.0, 0.0])))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_ecef_enu(47.37, 8.54), geodetic_to_ecef(47.37, 8.54, 420.0)
    (tmp_path / "tileset.json").write_text(json.dumps({"asset": {"version": "1.0"}, "geometricError": 10, "root": {
        "boundingVolume": {"sphere": [0, 0, 0, 60]}, "geometricError": 0, "transform": T.T.reshape(-1).tolist(),
        "content": {"uri": "t/c.pnts"}}}))
    m = load_model(tmp_path, sample_spacing_m=1.0)
    enu = LocalFrame(47.37, 8.54, 420.0).ecef_to_enu(m.origin.enu_to_ecef(m.points_enu))
    low = enu[:, 0] < 20
    assert np.allclose(enu[low, 2], 0.0, atol=0.01) and np.allclose(enu[~low, 2], 8.0, atol=0.01)
    assert 0.0 <= enu[:, :2].min() and enu[:, :2].max() <= 40.0
    assert 1400 < len(m) < 2 * 1700  # ~one per m² of 1600 m², a voxel holding both faces of the step edge or not
    assert np.median(np.abs(m.normals_enu[:, 2])) > 0.99


def test_3dtiles_content_off_the_earth_is_refused(tmp_path):
    """A tile whose points are not ECEF (a tileset without its transform: local metres about the
    Earth's centre) is refused by name instead of becoming a model, or a crop index, a continent wide."""
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "c.pnts").write_bytes(_pnts(np.random.default_rng(0).uniform(0, 40, (500, 3)), False, np.zeros(3)))
    (tmp_path / "tileset.json").write_text(json.dumps({"asset": {"version": "1.0"}, "geometricError": 10, "root": {
        "boundingVolume": {"sphere": [0, 0, 0, 60]}, "geometricError": 0, "content": {"uri": "t/c.pnts"}}}))
    with pytest.raises(GisFormatError, match=r"c.pnts: \d+ of \d+ points are not near the Earth's surface"):
        load_model(tmp_path)


@pytest.mark.parametrize("refine,spacing_m,expect", [
    ("REPLACE", 1.0, "cubes"),   # 5 m of error is too coarse for 1 m sampling: the children replace the slab
    ("REPLACE", 8.0, "slab"),    # coarse sampling: the slab is fine enough, the children are not loaded
    ("ADD", 1.0, "both"),        # ADD: the children add to the slab
])
def test_3dtiles_level_of_detail_and_refinement(tmp_path, refine, spacing_m, expect):
    from gis.geodesy import LocalFrame
    m = load_model(_hlod_tileset(tmp_path, refine), sample_spacing_m=spacing_m)
    enu = LocalFrame(47.37, 8.54, 420.0).ecef_to_enu(m.origin.enu_to_ecef(m.points_enu))
    slab = np.abs(enu[:, 2]) <= 2.01
    cubes = (enu[:, 2] >= 14.99) & (enu[:, 2] <= 25.01)
    assert np.all(slab | cubes)
    assert slab.any() == (expect in ("slab", "both")) and cubes.any() == (expect in ("cubes", "both"))


def test_3dtiles_uri_and_extension_errors_name_the_problem(tmp_path):
    with pytest.raises(GisFormatError, match="not relative to the tileset"):  # a server's absolute path, not mirrored
        load_model(_hlod_tileset(tmp_path, "REPLACE", "/v1/3dtiles/datasets/x/coarse.glb"), sample_spacing_m=8.0)
    ts = _hlod_tileset(tmp_path, "REPLACE")
    doc = json.loads(ts.read_text())
    doc["root"]["children"][0]["transform"] = [1, 0, 0]
    ts.write_text(json.dumps(doc))
    with pytest.raises(GisFormatError, match="malformed tile"):
        load_model(ts)
    del doc["root"]["children"][0]["transform"]  # the tile well-formed again
    # implicit tiling (tests/test_gis_implicit_tiles.py) over a sphere: not defined by 3D Tiles 1.1
    doc["root"]["children"][0]["implicitTiling"] = {"subdivisionScheme": "QUADTREE", "subtreeLevels": 4,
                                                   "availableLevels": 8, "subtrees": {"uri": "subtrees/{level}.{x}.{y}.subtree"}}
    ts.write_text(json.dumps(doc))
    with pytest.raises(GisFormatError, match=r"implicit tiling over a \['sphere'\] bounding volume"):
        load_model(ts)
    del doc["root"]["children"][0]["implicitTiling"]
    # a glb that requires meshopt compression: trimesh would load zeros, so it is refused by name
    glb = tmp_path / "tiles" / "fine_0.glb"
    data = glb.read_bytes()
    jlen = struct.unpack("<I", data[12:16])[0]
    gltf = json.loads(data[20:20 + jlen])
    gltf["extensionsUsed"] = gltf["extensionsRequired"] = ["EXT_meshopt_compression", "KHR_materials_unlit"]
    chunk = json.dumps(gltf).encode()
    chunk += b" " * (-len(chunk) % 4)
    rest = data[20 + jlen:]
    glb.write_bytes(struct.pack("<4sIIII", b"glTF", 2, 20 + len(chunk) + len(rest), len(chunk), 0x4E4F534A) + chunk + rest)
    ts.write_text(json.dumps(doc))  # the tiles well-formed: now a content is the problem
    with pytest.raises(GisFormatError, match="EXT_meshopt_compression") as e:
        load_model(ts)
    assert "fine_0.glb" in str(e.value) and "KHR_materials_unlit" not in str(e.value)


@pytest.mark.parametrize("name,content,problem", [
    ("bad.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\nend_header\n\x00\x01", ""),
    ("bad.las", b"LASF" + b"\x00" * 50, "LAS"),
    ("bad.laz", b"not a laz file at all", "LASF"),
    ("bad.json", b"{\"type\": \"CityJSON\", ", "JSON"),
    ("bad.geojson", b"{\"type\": \"FeatureCollection\", \"features\": [{\"geometry\": {\"type\": \"Polygon\", \"coordinates\": [[[8, 47]]]}}]}", "feature 0"),
    ("x.xyz", b"1 2 3\n", "unsupported"),
    ("x.osm.pbf", b"\x00\x00\x00\x0d\x0a\x09OSMHeader", "not a readable OSM file"),
    ("lone.b3dm", b"b3dm" + b"\x00" * 40, "tileset"),
    ("bad.tif", b"II*\x00" + b"\x07" * 60, "cannot read GeoTIFF"),
    ("bad.npz", b"PK\x03\x04" + b"\x00" * 60, "not a GIS model .npz"),
    ("bad.city.jsonl", b'{"type": "CityJSON", "metadata": {"referenceSystem": "EPSG:32632"}}\n'
                       b'{"type": "CityJSONFeature", "CityObjects": {}, "vertices": [[1, 2]]}\n', "malformed CityJSON"),
])
def test_corrupt_or_unsupported_files_fail_clearly(tmp_path, name, content, problem):
    path = tmp_path / name
    path.write_bytes(content)
    if name.endswith(".ply"):
        _sidecar(path)
    with pytest.raises(GisFormatError) as e:
        load_model(path)
    assert str(path) in str(e.value) and problem in str(e.value)


def test_missing_georeference_and_crs(tmp_path, city):
    mesh, _ = city
    path = tmp_path / "city.ply"
    mesh.export(path)
    with pytest.raises(GisFormatError, match="georef.json sidecar missing"):
        load_model(path)
    hdr = laspy.LasHeader(point_format=6, version="1.4")
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = np.random.default_rng(0).uniform(0, 10, (3, 10))
    lp = tmp_path / "nocrs.las"
    las.write(lp)
    with pytest.raises(GisFormatError, match="no CRS"):
        load_model(lp)
    doc = _cityjson_cube()
    del doc["metadata"]
    cj = tmp_path / "nocrs.city.json"
    cj.write_text(json.dumps(doc))
    with pytest.raises(GisFormatError, match="referenceSystem"):
        load_model(cj)
