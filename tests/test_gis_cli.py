"""`terraslam gis import|ls|fetch` and `align-offline` through the real entry point."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import trimesh

TERRASLAM = [str(Path(sys.executable).with_name("terraslam"))]


def _run(*args):
    return subprocess.run(TERRASLAM + list(args), capture_output=True, text=True, timeout=180, env=dict(os.environ))


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
    r = _run("gis", "ls", "--cache-dir", str(cache))
    assert r.returncode == 0 and "demo" in r.stdout
    from pyproj import Transformer
    lon, lat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True).transform(465000, 5250000)
    r = _run("gis", "fetch", "--lat", str(lat), "--lon", str(lon), "--source", str(tmp_path), "--site", "near",
             "--cache-dir", str(cache))
    assert r.returncode == 0, r.stderr
    r = _run("gis", "fetch", "--lat", str(lat + 1), "--lon", str(lon), "--source", str(tmp_path), "--cache-dir", str(cache))
    assert r.returncode != 0 and "no GIS model within 10000 m" in r.stderr


def test_gis_import_and_align_offline_fail_clearly(tmp_path):
    bad = tmp_path / "broken.las"
    bad.write_bytes(b"LASF" + b"\x00" * 20)
    r = _run("gis", "import", str(bad), "--cache-dir", str(tmp_path / "c"))
    assert r.returncode == 2 and str(bad) in r.stderr and "LAS" in r.stderr
    r = _run("align-offline", str(tmp_path / "nope"), "--cache-dir", str(tmp_path / "c"))
    assert r.returncode == 2 and "nope" in r.stderr
