"""3D Tiles 1.1 implicit tiling (gis/implicit_tiles.py): a quadtree tileset written to disk as the
spec lays it out (binary and JSON subtree files, bitstream and constant availability, a child
subtree), loaded at three levels of detail, fetched over HTTP from 127.0.0.1, and broken files
refused by name."""
from __future__ import annotations

import functools
import http.server
import json
import struct
import threading
from pathlib import Path

import numpy as np
import pytest
import trimesh

from gis.geodesy import LocalFrame, R_ecef_enu
from gis.implicit_tiles import morton
from gis.loaders import load_model
from gis.model import GisFormatError
from gis.providers import FetchError, HttpTilesProvider, fetch_model

SITE = LocalFrame(47.37, 8.54, 420.0)
HALF_M = 100.0  # the root tile: a 200 x 200 m square about the site
ROOT_ERROR_M = 40.0  # geometric error: 20 m at level 1, 10 m at level 2


def _bits(indices: list[int], n_bits: int) -> bytes:
    """An availability bitstream: bit i in byte i // 8, bit i % 8."""
    b = bytearray((n_bits + 7) // 8)
    for i in indices:
        b[i >> 3] |= 1 << (i & 7)
    return bytes(b)


def _subtree_bin(doc: dict, body: bytes) -> bytes:
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 8)
    body += b"\x00" * (-len(body) % 8)
    return struct.pack("<4sIQQ", b"subt", 1, len(js), len(body)) + js + body


def _tile_box(level: int, x: int, y: int) -> bytes:
    """Tile (level, x, y)'s content: a box half the tile's side, 2 (level + 1) m tall, at the tile's
    centre (glTF is Y-up: ENU (e, n, u) is (e, u, -n) there)."""
    side = 2 * HALF_M / 2 ** level
    ce, cn, h = -HALF_M + (x + 0.5) * side, -HALF_M + (y + 0.5) * side, 2.0 * (level + 1)
    box = trimesh.creation.box(extents=[side / 2, h, side / 2])
    box.apply_translation([ce, h / 2, -cn])
    return trimesh.Scene(box).export(file_type="glb")


def _footprint_has_roof(enu: np.ndarray, normals: np.ndarray, level: int, x: int, y: int) -> bool:
    side = 2 * HALF_M / 2 ** level
    ce, cn, h = -HALF_M + (x + 0.5) * side, -HALF_M + (y + 0.5) * side, 2.0 * (level + 1)
    inside = (np.abs(enu[:, 0] - ce) < side / 4 - 0.5) & (np.abs(enu[:, 1] - cn) < side / 4 - 0.5)
    return bool(np.any(inside & (np.abs(enu[:, 2] - h) < 0.05) & (normals[:, 2] > 0.9)))


def write_quadtree(root: Path) -> Path:
    """availableLevels 3, subtreeLevels 2. Subtree (0,0,0), binary with bitstreams: every tile of
    levels 0-1 but (1,1,1); content on all of them; child subtrees at level 2 for (0,0) and (1,1)
    only. Subtree (2,0,0), JSON: its tile and content available (constants). Subtree (2,1,1),
    binary: its tile available, no content. So at 1 m sampling (REPLACE) the tiles drawn are
    (1,1,0), (1,0,1) and (2,0,0); (1,0,0) is replaced by its children."""
    (root / "content").mkdir(parents=True)
    (root / "subtrees").mkdir()
    tiles = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (1, 0, 1), (2, 0, 0)]
    for level, x, y in tiles:
        (root / "content" / f"{level}_{x}_{y}.glb").write_bytes(_tile_box(level, x, y))
    avail = [0] + [1 + morton(x, y, 0, False) for x, y in [(0, 0), (1, 0), (0, 1)]]
    tile_bits, child_bits = _bits(avail, 5), _bits([morton(0, 0, 0, False), morton(1, 1, 0, False)], 16)
    body = tile_bits + b"\x00" * 7 + child_bits
    (root / "subtrees" / "0.0.0.subtree").write_bytes(_subtree_bin({
        "buffers": [{"byteLength": len(body)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 1}, {"buffer": 0, "byteOffset": 8, "byteLength": 2}],
        "tileAvailability": {"bitstream": 0}, "contentAvailability": [{"bitstream": 0}],
        "childSubtreeAvailability": {"bitstream": 1}}, body))
    (root / "subtrees" / "2.0.0.subtree").write_text(json.dumps({
        "tileAvailability": {"constant": 1}, "contentAvailability": [{"constant": 1}],
        "childSubtreeAvailability": {"constant": 0}}))
    (root / "subtrees" / "2.1.1.subtree").write_bytes(_subtree_bin({
        "buffers": [{"byteLength": 1}], "bufferViews": [{"buffer": 0, "byteLength": 1}],
        "tileAvailability": {"bitstream": 0}, "contentAvailability": [{"constant": 0}],
        "childSubtreeAvailability": {"constant": 0}}, _bits([0], 5)))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_ecef_enu(SITE.lat0_deg, SITE.lon0_deg), SITE.origin_ecef_m
    ts = root / "tileset.json"
    ts.write_text(json.dumps({"asset": {"version": "1.1"}, "geometricError": 80.0, "root": {
        "boundingVolume": {"box": [0, 0, 5, HALF_M, 0, 0, 0, HALF_M, 0, 0, 0, 5]}, "geometricError": ROOT_ERROR_M,
        "refine": "REPLACE", "transform": T.T.reshape(-1).tolist(), "content": {"uri": "content/{level}_{x}_{y}.glb"},
        "implicitTiling": {"subdivisionScheme": "QUADTREE", "subtreeLevels": 2, "availableLevels": 3,
                           "subtrees": {"uri": "subtrees/{level}.{x}.{y}.subtree"}}}}))
    return ts


def _drawn(m) -> set[tuple[int, int, int]]:
    enu = SITE.ecef_to_enu(m.origin.enu_to_ecef(m.points_enu))
    n = m.normals_enu  # (the model's ENU is a few metres from SITE's: the same axes to well under a degree)
    return {(lv, x, y) for lv in range(3) for x in range(2 ** lv) for y in range(2 ** lv)
            if _footprint_has_roof(enu, n, lv, x, y)}


@pytest.mark.parametrize("spacing_m,expect", [
    (50.0, {(0, 0, 0)}),                         # the root's 40 m of error is fine enough
    (30.0, {(1, 0, 0), (1, 1, 0), (1, 0, 1)}),   # level 1 (20 m); (1, 1, 1) is not available
    (1.0, {(1, 1, 0), (1, 0, 1), (2, 0, 0)}),    # down to the leaves: (1, 0, 0) replaced by its children
])
def test_implicit_quadtree_is_loaded_at_the_level_the_sampling_needs(tmp_path: Path, spacing_m: float, expect: set) -> None:
    assert _drawn(load_model(write_quadtree(tmp_path), sample_spacing_m=spacing_m)) == expect


def test_morton_order_interleaves_x_lowest() -> None:
    assert [morton(x, y, 0, False) for y in range(2) for x in range(2)] == [0, 1, 2, 3]
    assert morton(2, 0, 0, False) == 4 and morton(3, 3, 0, False) == 15
    assert morton(1, 0, 1, True) == 5 and morton(0, 1, 1, True) == 6


def test_broken_subtrees_are_refused_by_name(tmp_path: Path) -> None:
    ts = write_quadtree(tmp_path)
    sub = tmp_path / "subtrees" / "0.0.0.subtree"
    good = sub.read_bytes()
    sub.write_bytes(good[:40])
    with pytest.raises(GisFormatError, match=r"subtree subtrees/0\.0\.0\.subtree: truncated"):
        load_model(ts)
    sub.write_bytes(good)
    (tmp_path / "subtrees" / "2.0.0.subtree").unlink()
    with pytest.raises(GisFormatError, match=r"subtree subtrees/2\.0\.0\.subtree of its implicit tiling is missing"):
        load_model(ts, sample_spacing_m=1.0)
    assert _drawn(load_model(ts, sample_spacing_m=30.0))  # above level 2: that subtree is never read
    doc = json.loads(ts.read_text())
    # constant availability to level 20 under a huge geometric error: 4^20 tiles from 100 bytes; refused, not walked
    (tmp_path / "subtrees" / "0.0.0.subtree").write_text(json.dumps({
        "tileAvailability": {"constant": 1}, "contentAvailability": [{"constant": 0}], "childSubtreeAvailability": {"constant": 1}}))
    deep = json.loads(json.dumps(doc))
    deep["root"]["geometricError"] = 1e9
    deep["root"]["implicitTiling"].update(availableLevels=21, subtreeLevels=21)
    ts.write_text(json.dumps(deep))
    with pytest.raises(GisFormatError, match="more than 200000 tiles of its implicit tiling"):
        load_model(ts)
    doc["root"]["implicitTiling"]["subdivisionScheme"] = "S2"
    ts.write_text(json.dumps(doc))
    with pytest.raises(GisFormatError, match="neither QUADTREE nor OCTREE"):
        load_model(ts)


@pytest.fixture()
def served(tmp_path: Path):
    write_quadtree(tmp_path / "srv")
    seen: list[str] = []

    class Handler(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *a):
            seen.append(self.path)

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=str(tmp_path / "srv")))
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{srv.server_address[1]}", seen
    srv.shutdown()


def test_implicit_tileset_fetched_over_http(tmp_path: Path, served) -> None:
    """gis fetch's provider mirrors the subtrees the walk reaches and the contents it selects, no
    more, and loads the same model as the files on disk."""
    url, seen = served
    prov = HttpTilesProvider(f"{url}/tileset.json?key=k", tmp_path / "mirror", timeout_s=10.0, sample_spacing_m=1.0)
    (m,) = prov.fetch(SITE.lat0_deg, SITE.lon0_deg, 500.0)
    assert _drawn(m) == {(1, 1, 0), (1, 0, 1), (2, 0, 0)}
    got = {p.split("?")[0] for p in seen if p.startswith("/")}
    assert got == {"/tileset.json", "/subtrees/0.0.0.subtree", "/subtrees/2.0.0.subtree", "/subtrees/2.1.1.subtree",
                   "/content/1_1_0.glb", "/content/1_0_1.glb", "/content/2_0_0.glb"}, got
    assert all("key=k" in p for p in seen if p.startswith("/"))  # the API key rides along
    # 11 km north: nothing of the tileset within 500 m, and nothing but the tileset asked for
    n = len(seen)
    far = HttpTilesProvider(f"{url}/tileset.json", tmp_path / "mirror2", timeout_s=10.0, sample_spacing_m=1.0)
    with pytest.raises(FetchError, match="no GIS model within 500 m"):
        fetch_model([far], SITE.lat0_deg + 0.1, SITE.lon0_deg, 500.0)
    assert [p.split("?")[0] for p in seen[n:]] == ["/tileset.json"]


def test_sub_volumes_split_regions_and_boxes_as_the_spec_does() -> None:
    from gis.implicit_tiles import _sub_volume

    region = {"region": [-1.0, 0.2, -0.6, 0.6, 10.0, 90.0]}  # radians, metres
    r = _sub_volume(region, 2, 3, 1, 0, False)["region"]  # quadtree: longitude and latitude in 4, heights kept
    assert np.allclose(r, [-0.7, 0.3, -0.6, 0.4, 10.0, 90.0])
    r = _sub_volume(region, 1, 0, 1, 1, True)["region"]  # octree: heights halved too
    assert np.allclose(r, [-1.0, 0.4, -0.8, 0.6, 50.0, 90.0])
    box = {"box": [10.0, 20.0, 30.0, 8.0, 0, 0, 0, 4.0, 0, 0, 0, 2.0]}
    b = np.asarray(_sub_volume(box, 2, 0, 3, 0, False)["box"])  # x: 1st of 4, y: 4th of 4, z whole
    assert np.allclose(b[:3], [10.0 - 6.0, 20.0 + 3.0, 30.0]) and np.allclose(b[3:], [2, 0, 0, 0, 1, 0, 0, 0, 2])
    b = np.asarray(_sub_volume(box, 1, 1, 0, 1, True)["box"])
    assert np.allclose(b[:3], [14.0, 18.0, 31.0]) and np.allclose(b[3:], [4, 0, 0, 0, 2, 0, 0, 0, 1])
