"""`terraslam gis import|ls|fetch` and `align-offline` through the real entry point."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

TERRASLAM = [str(Path(sys.executable).with_name("terraslam"))]


def _run(*args, env: dict | None = None):
    return subprocess.run(TERRASLAM + list(args), capture_output=True, text=True, timeout=900, env=dict(os.environ, **(env or {})))


def _city_ply(tmp_path: Path) -> Path:
    from gis.synthetic import box_city_mesh

    mesh, _ = box_city_mesh(100.0, seed=1)
    path = tmp_path / "city.ply"
    mesh.export(path)
    path.with_name("city.ply.georef.json").write_text(
        json.dumps({"crs": "EPSG:32632", "offset_m": [465000, 5250000, 400], "vertical": "ellipsoid"}))
    return path


def test_gis_import_ls_fetch(tmp_path):
    cache = tmp_path / "cache"
    ply = _city_ply(tmp_path)
    r = _run("gis", "import", str(ply), "--site", "demo", "--cache-dir", str(cache))
    assert r.returncode == 0, r.stderr
    assert "site demo" in r.stdout and "EPSG:32632" in r.stdout
    from gis.cache import GisCache
    from gis.config import GisConfig
    from gis.loaders import source_key
    defaults = GisConfig()  # a service with this file as gis.model maps the import, not parsing the file again
    assert GisCache(cache).imported(source_key(ply, defaults.sample_spacing_m, defaults.footprint_ground)) == "demo"
    assert GisCache(cache).imported(source_key(ply, 2 * defaults.sample_spacing_m, None)) is None
    r = _run("gis", "ls", "--cache-dir", str(cache))
    assert r.returncode == 0 and "demo" in r.stdout
    # earlier flights' evidence on the model's georeference (gis.align.georef) shows in the listing
    from gis.align.georef import GeorefCheck

    chk = GeorefCheck(0.25)
    for k, d in enumerate([(2.4, 0.1, 0.0), (2.6, -0.2, 0.1), (2.5, 0.2, -0.1), (2.5, 0.0, 0.0)]):
        chk.add(20.0 * k, np.array(d), 0.25 * np.eye(3))
    GisCache(cache).save_georef("demo", chk.evidence)
    r = _run("gis", "ls", "--cache-dir", str(cache), env={"COLUMNS": "250"})
    assert r.returncode == 0 and "off 2.5 m, up +0.0 m" in r.stdout and "(4 registrations)" in r.stdout, r.stdout
    from pyproj import Transformer
    lon, lat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True).transform(465000, 5250000)
    r = _run("gis", "fetch", "--lat", str(lat), "--lon", str(lon), "--source", str(tmp_path), "--site", "near",
             "--cache-dir", str(cache))
    assert r.returncode == 0, r.stderr
    r = _run("gis", "fetch", "--lat", str(lat + 1), "--lon", str(lon), "--source", str(tmp_path), "--cache-dir", str(cache))
    assert r.returncode != 0 and "no GIS model within 10000 m" in r.stderr
    # rm: "near" holds the same content as "demo" (same file): forgetting it frees nothing; then demo frees the file
    f = GisCache(cache).model_file("demo")
    assert GisCache(cache).model_file("near") == f
    r = _run("gis", "rm", "near", "atlantis", "--cache-dir", str(cache))
    assert r.returncode != 0 and "no site 'atlantis'" in r.stderr and f.is_file()
    r = _run("gis", "rm", "near", "--cache-dir", str(cache))
    assert r.returncode == 0 and "shared" in r.stdout and f.is_file()
    r = _run("gis", "rm", "demo", "--cache-dir", str(cache))
    assert r.returncode == 0 and "MB freed" in r.stdout and not f.exists()
    assert GisCache(cache).entries() == [] and GisCache(cache).load_georef("demo") is None


def test_gis_import_and_align_offline_fail_clearly(tmp_path):
    bad = tmp_path / "broken.las"
    bad.write_bytes(b"LASF" + b"\x00" * 20)
    r = _run("gis", "import", str(bad), "--cache-dir", str(tmp_path / "c"))
    assert r.returncode == 2 and str(bad) in r.stderr and "LAS" in r.stderr
    r = _run("align-offline", str(tmp_path / "nope"), "--cache-dir", str(tmp_path / "c"))
    assert r.returncode == 2 and "nope" in r.stderr


def test_gis_import_osm_pbf_needs_and_takes_the_ground_height(tmp_path):
    from test_gis_loaders import _write_osm  # same module pytest collected (rootdir-relative import)

    pbf = tmp_path / "city.osm.pbf"
    _write_osm(pbf, 47.37, 8.54)
    r = _run("gis", "import", str(pbf), "--cache-dir", str(tmp_path / "c"))
    assert r.returncode == 2 and str(pbf) in r.stderr and "ground height" in r.stderr
    r = _run("gis", "import", str(pbf), "--site", "osm", "--ground-h-msl-m", "400", "--cache-dir", str(tmp_path / "c"))
    assert r.returncode == 0, r.stderr
    assert "site osm" in r.stdout and "EPSG:4979" in r.stdout


def _sim_dataset(tmp_path: Path, scenario: str, frames: int) -> Path:
    out = tmp_path / "ds"
    r = subprocess.run(TERRASLAM + ["sim", "generate", "-s", scenario, "-o", str(out), "-n", str(frames)],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    return out


def test_align_offline_with_given_survey_cloud_stores_t_rough(tmp_path):
    import numpy as np
    import open3d as o3d
    from scipy.spatial.transform import Rotation

    from companion.dataset import read_dataset
    from gis.align.fine import enu_sim3
    from gis.cache import GisCache
    from gis.loaders import load_model
    from gis.sim3 import Sim3, compose
    from gis.synthetic import slam_like_cloud

    ds_dir = _sim_dataset(tmp_path, "survey", 2)
    ds = read_dataset(ds_dir)
    m = load_model(ds.gis_files[0])
    rp = ds.rough_position
    c = m.origin.geodetic_to_enu(rp.lat_deg, rp.lon_deg, rp.h_ellipsoid_m) * np.array([1, 1, 0])
    T_enu_slam = Sim3(4.0, Rotation.from_euler("zyx", [130, 4, -6], degrees=True).as_matrix(), c + [3.0, -2.0, 1.0])
    p_slam = T_enu_slam.inverse().apply(slam_like_cloud(m, c, 90, 25000, 0.1, seed=3))
    cloud = tmp_path / "survey_cloud.ply"
    o3d.io.write_point_cloud(str(cloud), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p_slam)))
    r = _run("align-offline", str(ds_dir), "--cloud", str(cloud), "--cache-dir", str(tmp_path / "c"), "--site", "s1")
    assert r.returncode == 0, r.stderr
    assert "RANSAC" in r.stderr and "T_rough stored for site s1" in r.stdout
    T, meta = GisCache(tmp_path / "c").load_transform("s1", "rough")
    truth = compose(enu_sim3(m.origin), T_enu_slam)
    assert np.mean(np.linalg.norm(T.apply(p_slam) - truth.apply(p_slam), axis=1)) < 0.5
    assert meta["error_m"] < 0.5
    assert "no survey map" in r.stdout and GisCache(tmp_path / "c").survey_map("s1") is None
    ls = _run("gis", "ls", "--cache-dir", str(tmp_path / "c"), env={"COLUMNS": "250"})
    assert "cloud frame only" in ls.stdout, ls.stdout


@pytest.mark.slow
def test_align_offline_colmap_on_rendered_survey(tmp_path):
    """Full §4.3 path (many minutes): our SLAM maps a rendered survey (its first row and turn),
    COLMAP SfM reconstructs it, T_rough is found on the SfM cloud and carried into the survey map,
    which the cache then holds for the service; T_rough checked against the truth at the map's
    keyframes."""
    import numpy as np

    from companion.dataset import read_dataset
    from companion.persistence import load_survey
    from gis.cache import GisCache
    from slam.geometry import inv_T

    ds_dir = _sim_dataset(tmp_path, "survey", 1100)
    r = _run("align-offline", str(ds_dir), "--stride", "10", "--cache-dir", str(tmp_path / "c"), "--site", "s2")
    assert r.returncode == 0, r.stderr
    cache = GisCache(tmp_path / "c")
    _, meta = cache.load_transform("s2", "rough")
    assert meta["error_m"] < 0.6  # the SfM cloud itself sits ~0.44 m from the model (noise, trees)
    ds = read_dataset(ds_dir)
    survey = load_survey(cache.survey_map("s2"), ds.camera, "s2")
    kfs = survey.loaded.slam_map.keyframes.values()
    got = survey.alignment.T_ecef_slam.apply(np.array([inv_T(k.T_cam_slam)[:3, 3] for k in kfs]))
    err = np.linalg.norm(got - np.array([ds.truth[k.seq].p_ecef_m for k in kfs]), axis=1)
    print(f"survey map: {len(err)} keyframes, T_rough at them vs truth: mean {err.mean():.2f} m, max {err.max():.2f} m; "
          f"{meta}")
    assert "survey map" in r.stderr and "starts in its survey map" in r.stdout
    assert "survey map" in _run("gis", "ls", "--cache-dir", str(tmp_path / "c"), env={"COLUMNS": "250"}).stdout
    assert err.mean() < 2.0 and err.max() < 4.0
