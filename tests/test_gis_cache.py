"""GIS cache round trip with hash checks; providers (local files, 3D Tiles over HTTP on 127.0.0.1)."""
from __future__ import annotations

import functools
import hashlib
import http.server
import json
import threading

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from gis.cache import CacheCorrupt, GisCache
from gis.geodesy import LocalFrame, R_ecef_enu, geodetic_to_ecef
from gis.model import GisModel
from gis.providers import FetchError, HttpTilesProvider, LocalProvider, fetch_model
from gis.sim3 import Sim3
from gis.synthetic import box_city_model
from test_gis_loaders import _b3dm

ORIGIN = LocalFrame(47.3769, 8.5417, 450.0)


@pytest.fixture(scope="module")
def model():
    return box_city_model(200.0, ORIGIN, seed=2, spacing_m=2.0)


def test_cache_round_trip_prefetch_and_hash_checks(tmp_path, model):
    cache = GisCache(tmp_path / "cache")
    site = cache.save_model(model, "zurich")
    T_rough = Sim3(2.5, Rotation.from_euler("z", 33, degrees=True).as_matrix(), ORIGIN.origin_ecef_m)
    T_fine = Sim3(2.51, Rotation.from_euler("z", 33.2, degrees=True).as_matrix(), ORIGIN.origin_ecef_m + 0.3)
    cache.save_transform(site, "rough", T_rough, {"error_m": 0.4})
    cache.save_transform(site, "fine", T_rough)
    cache.save_transform(site, "fine", T_fine, {"t_s": 12.0})  # latest replaces
    # a fresh cache object (new process) sees the same content
    cache2 = GisCache(tmp_path / "cache")
    m2 = cache2.load_model(site)
    stored = model.sorted_by_cell  # the cache keeps the points cell by cell of the crop index
    assert stored is not model and sorted(map(tuple, stored.points_enu)) == sorted(map(tuple, model.points_enu))
    fresh = GisModel(stored.points_enu, stored.normals_enu, stored.labels, stored.origin, "", "x")  # its index, built anew
    assert fresh._grid[0] is None and all(np.array_equal(a, b) for a, b in zip(fresh._grid[1:3], stored._grid[1:3]))
    assert fresh._grid[3] == stored._grid[3]
    np.testing.assert_array_equal(m2.points_enu, stored.points_enu)
    np.testing.assert_array_equal(m2.normals_enu, stored.normals_enu)
    np.testing.assert_array_equal(m2.labels, stored.labels)
    assert m2.origin == model.origin
    # mapped from the file, not read into memory; its index holds no per-point order
    assert isinstance(m2.points_enu.base, np.memmap) and not m2.points_enu.flags.writeable
    assert m2._grid[0] is None
    c = np.array([30.0, -40.0])
    np.testing.assert_array_equal(np.sort(m2.points_enu[m2.crop(c, 150.0)], axis=0),
                                  np.sort(model.points_enu[model.crop(c, 150.0)], axis=0))
    e = cache2.prefetch(*ORIGIN.enu_to_geodetic(np.array([30.0, -40.0, 0]))[:2])
    assert e is not None and e.site_id == "zurich"
    np.testing.assert_allclose(e.T_rough.matrix(), T_rough.matrix(), atol=1e-9)
    np.testing.assert_allclose(e.T_fine.matrix(), T_fine.matrix(), atol=1e-9)
    assert e.meta == {"rough": {"error_m": 0.4}, "fine": {"t_s": 12.0}}
    assert cache2.prefetch(*ORIGIN.enu_to_geodetic(np.array([3000.0, 0, 0]))[:2]) is None
    with pytest.raises(ValueError, match="kind"):
        cache2.save_transform(site, "medium", T_fine)
    # corrupt the model file: load refuses, naming the site and file
    f = e.model_file
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0xFF
    f.write_bytes(bytes(data))
    with pytest.raises(CacheCorrupt, match="zurich.*SHA-256"):
        cache2.load_model(site)
    # tamper with a stored transform row
    import sqlite3
    with sqlite3.connect(cache2.db_path) as db:
        db.execute("UPDATE transforms SET matrix_json=replace(matrix_json, '2.5', '2.6') WHERE kind='rough'")
    with pytest.raises(CacheCorrupt, match="T_rough"):
        cache2.load_transform(site, "rough")


def test_georeference_evidence_round_trips_and_a_tampered_row_is_refused(tmp_path, model):
    """The evidence on a model's georeference (gis.align.georef) is stored per site, comes back
    exactly in a fresh cache object (prefetch too), and a row that no longer matches its hash or
    holds no valid evidence raises CacheCorrupt naming the site."""
    import sqlite3

    from gis.align.georef import GeorefEvidence

    cache = GisCache(tmp_path / "cache")
    site = cache.save_model(model, "zurich")
    assert cache.load_georef(site) is None
    ev = GeorefEvidence(np.array([[2.0, 0.1, 0.0], [0.1, 3.0, 0.0], [0.0, 0.0, 1.0]]), np.array([5.5, -3.25, 0.5]), 17.75, 4)
    cache.save_georef(site, ev)
    back = GisCache(tmp_path / "cache").load_georef(site)
    np.testing.assert_array_equal(back.info, ev.info)
    np.testing.assert_array_equal(back.info_d, ev.info_d)
    assert (back.dWd, back.n) == (17.75, 4)
    assert cache.prefetch(ORIGIN.lat0_deg, ORIGIN.lon0_deg).georef.n == 4
    with pytest.raises(KeyError, match="no cached model"):
        cache.save_georef("elsewhere", ev)
    with sqlite3.connect(cache.db_path) as db:
        db.execute("UPDATE georef SET evidence_json=replace(evidence_json, '17.75', '1.75')")
    with pytest.raises(CacheCorrupt, match="zurich.*georeference.*SHA-256"):
        cache.load_georef(site)
    bad = json.dumps({"info": [[1, 0], [0, 1]], "info_d": [0, 0, 0], "dWd": 0.0, "n": 1}, sort_keys=True)
    with sqlite3.connect(cache.db_path) as db:  # a consistent hash over invalid content
        db.execute("UPDATE georef SET evidence_json=?, sha256=?", (bad, hashlib.sha256(bad.encode()).hexdigest()))
    with pytest.raises(CacheCorrupt, match="zurich.*invalid"):
        cache.load_georef(site)


def test_local_provider_radius(tmp_path, model):
    mesh = trimesh.creation.box(extents=[20, 20, 10])
    path = tmp_path / "b.ply"
    mesh.export(path)
    path.with_name("b.ply.georef.json").write_text(json.dumps({"crs": "EPSG:32632", "offset_m": [465000, 5250000, 400], "vertical": "ellipsoid"}))
    from pyproj import Transformer
    lon, lat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True).transform(465000 + 500, 5250000)
    prov = LocalProvider((tmp_path,))
    assert len(prov.fetch(lat, lon, 1000.0)) == 1
    assert prov.fetch(lat, lon, 100.0) == []
    with pytest.raises(FetchError, match="no GIS model"):
        fetch_model([prov], lat, lon, 100.0)


@pytest.fixture()
def tile_server(tmp_path):
    root = tmp_path / "srv"
    (root / "t").mkdir(parents=True)
    tiles = []
    for i, (lat, lon) in enumerate([(47.3769, 8.5417), (47.4769, 8.5417)]):  # second one ~11 km north
        rtc = geodetic_to_ecef(lat, lon, 450.0)
        box = trimesh.creation.box(extents=[30, 12, 20])
        (root / "t" / f"{i}.b3dm").write_bytes(_b3dm(trimesh.Scene(box).export(file_type="glb"), np.zeros(3)))
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_ecef_enu(lat, lon), rtc
        tiles.append({"boundingVolume": {"sphere": [0, 0, 0, 30]}, "geometricError": 0,
                      "transform": T.T.reshape(-1).tolist(), "content": {"uri": f"t/{i}.b3dm"}})
    (root / "tileset.json").write_text(json.dumps({"asset": {"version": "1.0"}, "geometricError": 100, "root": {
        "boundingVolume": {"sphere": [0, 0, 0, 7e6]}, "geometricError": 50, "children": tiles}}))
    requests_seen = []

    class Handler(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *a):
            requests_seen.append(self.path)

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=str(root)))
    th = threading.Thread(target=srv.serve_forever, daemon=True)
    th.start()
    yield f"http://127.0.0.1:{srv.server_address[1]}", requests_seen
    srv.shutdown()


def test_http_tiles_provider_radius_cache_and_errors(tmp_path, tile_server):
    url, seen = tile_server
    prov = HttpTilesProvider(f"{url}/tileset.json?key=abc", tmp_path / "dl", timeout_s=5.0)
    m = fetch_model([prov], 47.3769, 8.5417, 10_000.0)
    lat, lon, h = m.origin.enu_to_geodetic(m.points_enu)
    assert abs(lat.mean() - 47.3769) < 1e-3  # only the near tile
    assert any("0.b3dm?key=abc" in s for s in seen) and not any("1.b3dm" in s for s in seen)
    n = len(seen)
    fetch_model([prov], 47.3769, 8.5417, 10_000.0)  # second fetch: served from the download cache
    assert seen[n:] == ["/tileset.json?key=abc"]  # but for the top tileset (a server's session may have expired)
    with pytest.raises(FetchError, match="404"):
        HttpTilesProvider(f"{url}/missing.json", tmp_path / "dl2", timeout_s=5.0).fetch(47.3, 8.5, 100.0)
    with pytest.raises(FetchError, match="leaves the download folder"):  # an encoded ../ never writes outside it
        HttpTilesProvider(f"{url}/%2e%2e/%2e%2e/%2e%2e/escape.json", tmp_path / "dl4", timeout_s=5.0).fetch(47.3, 8.5, 100.0)
    assert not (tmp_path / "escape.json").exists()
    with pytest.raises(FetchError, match="127.0.0.1:9"):
        HttpTilesProvider("http://127.0.0.1:9/tileset.json", tmp_path / "dl3", timeout_s=2.0).fetch(47.3, 8.5, 100.0)


def _draco_box_glb(extents, offset_yup=(0.0, 0.0, 0.0)) -> bytes:
    """A box as a Draco-compressed binary glTF (trimesh + DracoPy, KHR_draco_mesh_compression), in
    glTF's Y-up axes like Google's tiles."""
    box = trimesh.creation.box(extents=extents)
    box.apply_translation(offset_yup)
    return trimesh.Scene(box).export(file_type="glb", extension_draco=True)


@pytest.fixture()
def google_like_server(tmp_path):
    """A server shaped like Google Photorealistic 3D Tiles: every request needs ``key``; the root
    names an external tileset by an absolute path with a ``session``, which every request below it
    needs too although the URIs there do not repeat it; Draco glb content; an HLOD tree
    (REPLACE) whose coarse, middle and finest levels have geometric errors 20, 0.5 and 0 m, plus a
    far branch 11 km away. ``rotate()`` starts a new session and ends the old one."""
    lat, lon, h = 47.3769, 8.5417, 450.0
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_ecef_enu(lat, lon), geodetic_to_ecef(lat, lon, h)  # tile frame: ENU at the site
    far = np.eye(4)
    far[:3, :3], far[:3, 3] = R_ecef_enu(lat + 0.1, lon), geodetic_to_ecef(lat + 0.1, lon, h)
    files = {"coarse.glb": _draco_box_glb([60, 4, 60]),
             "mid_0.glb": _draco_box_glb([30, 12, 20], (-20, 0, 0)), "mid_1.glb": _draco_box_glb([30, 12, 20], (20, 0, 0)),
             "fine_0.glb": _draco_box_glb([30, 12, 20]), "fine_1.glb": _draco_box_glb([30, 12, 20]),
             "far.glb": _draco_box_glb([30, 12, 20])}
    base = "/v1/3dtiles/datasets/CgA/files/"

    def mid(i):  # absolute-path URIs without the session, one relative
        return {"boundingVolume": {"sphere": [0, 0, 0, 40]}, "geometricError": 0.5,
                "content": {"uri": f"{base}mid_{i}.glb" if i == 0 else f"mid_{i}.glb"},
                "children": [{"boundingVolume": {"sphere": [0, 0, 0, 40]}, "geometricError": 0,
                              "content": {"uri": f"{base}fine_{i}.glb"}}]}
    sub = {"asset": {"version": "1.0"}, "geometricError": 100, "root": {
        "boundingVolume": {"sphere": [0, 0, 0, 7e6]}, "geometricError": 50, "refine": "REPLACE", "children": [
            {"boundingVolume": {"sphere": [0, 0, 0, 60]}, "geometricError": 20, "transform": T.T.reshape(-1).tolist(),
             "content": {"uri": "coarse.glb"}, "children": [mid(0), mid(1)]},
            {"boundingVolume": {"sphere": [0, 0, 0, 60]}, "geometricError": 0, "transform": far.T.reshape(-1).tolist(),
             "content": {"uri": f"{base}far.glb"}}]}}
    session = ["s1"]
    seen: list[tuple[str, dict]] = []
    flaked: list[str] = []

    class Handler(http.server.BaseHTTPRequestHandler):
        def log_message(self, *a):
            pass

        def do_GET(self):
            from urllib.parse import parse_qs, urlsplit
            u = urlsplit(self.path)
            q = {k: v[0] for k, v in parse_qs(u.query).items()}
            seen.append((u.path, q))
            if q.get("key") != "SECRET":
                return self.send_error(403, "API key missing")
            if u.path == "/v1/3dtiles/root.json":
                body = json.dumps({"asset": {"version": "1.0"}, "geometricError": 1e7, "root": {
                    "boundingVolume": {"sphere": [0, 0, 0, 7e6]}, "geometricError": 1e7, "refine": "REPLACE",
                    "children": [{"boundingVolume": {"sphere": [0, 0, 0, 7e6]}, "geometricError": 1e6,
                                  "content": {"uri": f"{base}sub.json?session={session[0]}"}}]}}).encode()
            elif u.path.startswith(base) and q.get("session") != session[0]:
                return self.send_error(400, "session expired or missing")
            elif u.path == base + "sub.json":
                body = json.dumps(sub).encode()
            elif u.path.startswith(base) and u.path[len(base):] in files:
                if u.path.endswith("mid_1.glb") and not flaked:  # one transient failure: asked again, then served
                    flaked.append(u.path)
                    return self.send_error(503, "busy")
                body = files[u.path[len(base):]]
            else:
                return self.send_error(404)
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=srv.serve_forever, daemon=True).start()

    def rotate():
        session[0] = session[0] + "x"
    yield f"http://127.0.0.1:{srv.server_address[1]}/v1/3dtiles/root.json?key=SECRET", seen, rotate
    srv.shutdown()


def test_http_tiles_provider_google_style_session_lod_and_draco(tmp_path, google_like_server):
    """Fetched as Google serves them: key and session on every request, the coarsest level fine
    enough for the sampling spacing (1 m: the middle level, 0.5 m; neither the 20 m coarse tile nor
    the finest), Draco content decoded into the two boxes where they stand; a later fetch after the
    session expired asks the top tileset again and reaches the far tile with the new session."""
    url, seen, rotate = google_like_server
    lines: list[str] = []
    prov = HttpTilesProvider(url, tmp_path / "dl", timeout_s=5.0, sample_spacing_m=1.0, progress=lines.append)
    m = fetch_model([prov], 47.3769, 8.5417, 2_000.0)
    assert any("2 / 2 tiles (2 downloaded, 0 from the mirror)" in line for line in lines), lines
    assert not any("SECRET" in line for line in lines)
    got = {p.rsplit("/", 1)[-1] for p, q in seen}
    assert got == {"root.json", "sub.json", "mid_0.glb", "mid_1.glb"}, got
    assert sum(p.endswith("mid_1.glb") for p, _ in seen) == 2  # the 503 was retried
    assert all(q.get("key") == "SECRET" for _, q in seen) and all(q.get("session") == "s1" for p, q in seen if "datasets" in p)
    enu = ORIGIN.ecef_to_enu(m.origin.enu_to_ecef(m.points_enu))
    assert np.ptp(enu[:, 2]) == pytest.approx(12.0, abs=0.1)  # Draco decoded, glTF Y is up
    assert np.ptp(enu[:, 0]) == pytest.approx(70.0, abs=0.2) and np.ptp(enu[:, 1]) == pytest.approx(20.0, abs=0.2)
    assert abs(enu[:, 0].mean()) < 1.0 and abs(enu[:, 1].mean()) < 1.0  # the two boxes side by side about the site

    rotate()
    n = len(seen)
    m2 = fetch_model([prov], 47.3769, 8.5417, 20_000.0)  # now the far branch too
    assert [p.rsplit("/", 1)[-1] for p, _ in seen[n:]] == ["root.json", "far.glb"]  # the rest from the mirror
    assert seen[-1][1] == {"session": "s1x", "key": "SECRET"}
    assert len(m2) > len(m)
    with pytest.raises(FetchError, match="403") as e:  # a wrong key: the error names the URL, not the key
        HttpTilesProvider(url.replace("SECRET", "WRONGKEY"), tmp_path / "dl_bad", timeout_s=5.0).fetch(47.3769, 8.5417, 100.0)
    assert "WRONGKEY" not in str(e.value) and "root.json?key=…" in str(e.value)


def test_service_maps_an_unchanged_model_from_the_cache_and_imports_a_changed_one(tmp_path, monkeypatch, caplog):
    """`terraslam run` loads gis.model through the cache: the first start parses the file and maps
    the saved copy back; a restart with the file unchanged maps it without parsing; a changed file
    or a cached copy that fails its hash is imported again. gis.site maps a cached site."""
    import os

    from companion.config import AppConfig
    from companion.service import load_gis_model
    from gis import loaders
    from gis.config import GisConfig
    from gis.synthetic import box_city_mesh

    path = tmp_path / "city.ply"
    mesh, _ = box_city_mesh(120.0, seed=3)
    mesh.export(path)
    path.with_name("city.ply.georef.json").write_text(json.dumps({"crs": "EPSG:32632", "offset_m": [465000, 5250000, 400],
                                                                   "vertical": "ellipsoid"}))
    cfg = AppConfig(gis=GisConfig(model=path, cache_dir=tmp_path / "cache", sample_spacing_m=2.0))
    cache = GisCache(cfg.gis.cache_dir)
    first, site, file = load_gis_model(cfg, cache)
    assert isinstance(first.points_enu.base, np.memmap)
    parsed = loaders.load_model(path, 2.0)
    np.testing.assert_array_equal(first.points_enu, parsed.points_enu)  # the file's model, cell-sorted both ways

    def no_parsing(*a, **k):
        raise AssertionError("an unchanged, imported file was parsed again")
    monkeypatch.setattr(loaders, "load_model", no_parsing)
    again, site2, _ = load_gis_model(cfg, cache)
    assert site2 == site and isinstance(again.points_enu.base, np.memmap)
    np.testing.assert_array_equal(again.points_enu, first.points_enu)
    monkeypatch.undo()

    mesh2, _ = box_city_mesh(120.0, seed=4)  # the file changes: imported again
    mesh2.export(path)
    os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 10**9))
    changed, site3, _ = load_gis_model(cfg, cache)
    assert site3 != site and len(changed) != len(first)
    f = cache.root / "models" / cache._row(site3)["file"]  # its cached copy corrupted: imported again, with a warning
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0xFF
    f.write_bytes(bytes(data))
    with caplog.at_level("WARNING"):
        fixed, _, _ = load_gis_model(cfg, cache)
    assert "SHA-256" in caplog.text and "importing" in caplog.text
    np.testing.assert_array_equal(fixed.points_enu, changed.points_enu)
    assert file == path  # what a replay of the flight loads

    # gis.site instead: the site as `gis import`/`gis fetch` stored it; the cache's file reads as a model too
    from gis.model import GisFormatError
    by_site = AppConfig(gis=GisConfig(site=site3, cache_dir=tmp_path / "cache"))
    m, s_id, f = load_gis_model(by_site, cache)
    assert s_id == site3 and f == cache.model_file(site3) and isinstance(m.points_enu.base, np.memmap)
    np.testing.assert_array_equal(m.points_enu, changed.points_enu)
    np.testing.assert_array_equal(loaders.load_model(f).points_enu, changed.points_enu)
    with pytest.raises(GisFormatError, match="no site 'atlantis'"):
        load_gis_model(AppConfig(gis=GisConfig(site="atlantis", cache_dir=tmp_path / "cache")), cache)
    with pytest.raises(ValueError, match="not both"):
        GisConfig(site=site3, model=path)


def test_size_sweep_maps_each_model_from_a_cache_in_a_fresh_process():
    """gis.bench.size_sweep as `terraslam bench --sweep` runs it: each box city saved to a GIS cache
    and fine-tuned on, mapped, in a child process that reports its anonymous memory."""
    from gis.bench import size_sweep

    rows = size_sweep((500.0, 700.0), spacing_m=4.0)
    assert rows[0]["ratio"] == 1.0 and rows[1]["n_model_points"] > rows[0]["n_model_points"] > 1000
    assert all(np.isfinite(r["median_ms"]) and 10.0 < r["anon_mb"] < 4000.0 for r in rows)


def test_local_provider_finds_every_supported_format_in_a_folder(tmp_path):
    """A folder with a GeoTIFF surface model and a CityJSONSeq city (formats the folder scan used to
    pass over) yields both, merged by fetch_model into one model holding both."""
    from test_gis_loaders import OFFSET, _cityjson_cube, _write_dsm

    _write_dsm(tmp_path / "dsm.tif")
    cube = _cityjson_cube()
    header = {k: v for k, v in cube.items() if k not in ("CityObjects", "vertices")} | {"CityObjects": {}, "vertices": []}
    feature = {"type": "CityJSONFeature", "id": "b1", "CityObjects": cube["CityObjects"], "vertices": cube["vertices"]}
    (tmp_path / "city.city.jsonl").write_text(json.dumps(header) + "\n" + json.dumps(feature) + "\n")
    (tmp_path / "city.city.jsonl.georef.json").write_text(json.dumps({"vertical": "ellipsoid"}))  # (UTM is 2D)
    (tmp_path / "notes.txt").write_text("not a model")
    from pyproj import Transformer
    lon, lat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True).transform(OFFSET[0] + 50, OFFSET[1] + 50)
    models = LocalProvider((tmp_path,)).fetch(lat, lon, 500.0)
    assert sorted(m.source_path.name for m in models) == ["city.city.jsonl", "dsm.tif"]
    merged = fetch_model([LocalProvider((tmp_path,))], lat, lon, 500.0)
    assert len(merged) == sum(len(m) for m in models)


def test_a_site_whose_origin_came_from_a_transform_is_stored_as_numbers(tmp_path):
    """A LocalFrame made from what a geodetic transform returns (0-d arrays) is plain floats, so the
    cache's SQLite index holds numbers, and Pre-fetch works over it and every other site (a blob
    there made every lookup fail)."""
    cache = GisCache(tmp_path / "cache")
    lat, lon, h = ORIGIN.enu_to_geodetic(np.array([3000.0, 0.0, 0.0]))
    there = LocalFrame(lat, lon, h)
    assert all(type(v) is float for v in (there.lat0_deg, there.lon0_deg, there.h0_ellipsoid_m))
    cache.save_model(box_city_model(100.0, there, seed=1, spacing_m=4.0), "there")
    cache.save_model(box_city_model(100.0, ORIGIN, seed=2, spacing_m=4.0), "here")
    assert cache.prefetch(ORIGIN.lat0_deg, ORIGIN.lon0_deg).site_id == "here"
    assert cache.prefetch(float(lat), float(lon)).site_id == "there"
    import sqlite3
    with sqlite3.connect(cache.db_path) as db:  # an index row that is not numbers: refused by name, not a crash
        db.execute("UPDATE models SET h0_ellipsoid_m=? WHERE site_id='there'", (np.zeros(1).tobytes(),))
    with pytest.raises(CacheCorrupt, match="site 'there': its index row"):
        cache.prefetch(ORIGIN.lat0_deg, ORIGIN.lon0_deg)
