"""3D Tiles 1.0/1.1 tilesets (b3dm, i3dm, glb, pnts, cmpt content; implicit tiling): the tiles a sampling spacing
needs, in ECEF."""
from __future__ import annotations

import io
import json
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator
from urllib.parse import unquote, urlsplit

import numpy as np
import trimesh

from gis.geodesy import R_ecef_enu, ecef_to_geodetic
from gis.implicit_tiles import IMPLICIT, ImplicitTilingError, implicit_children, implicit_root
from gis.loaders.common import R_ZUP_YUP, _median_spacing, _read_json, estimate_normals, first_per_voxel, sample_mesh
from gis.loaders.mesh import _glb_json, check_gltf_extensions
from gis.model import (
    UNCLASSIFIED,
    GisFormatError,
    GisModel,
    check_on_earth,
    frame_at_centroid,
    merge_models,
    model_from_ecef,
)


def load_3dtiles(tileset_path: Path, sample_spacing_m: float = 1.0,
                 resolve: Callable[[Path, str], Path | None] | None = None) -> GisModel:
    """The tiles of a 3D Tiles tileset (b3dm or glb content) that ``tileset_contents`` selects for
    this sampling spacing → one model.

    resolve(tileset file, content URI) → its local file, or None to leave it out: by default
    relative to the tileset file, query and fragment dropped; a download mirror (gis.providers)
    passes its own (absolute-path URIs, only what this fetch downloaded)."""
    models: list[GisModel] = []
    _walk_tileset(tileset_path, np.eye(4), "REPLACE", sample_spacing_m, models, 0, resolve or _relative_uri)
    if not models:
        raise GisFormatError(tileset_path, "tileset has no b3dm/pnts/glb content in the tiles selected")
    return merge_models(models, tileset_path)


@dataclass(frozen=True)
class TileContent:
    """One content URI that a tileset selection keeps: its tile's transform (tile → tileset's
    parent frame, ECEF at the top) and refinement, which an external tileset's root inherits."""
    uri: str
    T: np.ndarray
    refine: str

    @property
    def is_tileset(self) -> bool:
        return urlsplit(self.uri).path.lower().endswith(".json")


def tileset_contents(tile: dict, T_parent: np.ndarray, refine: str, max_geometric_error_m: float,
                     keep: Callable[[dict, np.ndarray], bool] = lambda tile, T: True,
                     read_subtree: Callable[[str], bytes | None] | None = None) -> Iterator[TileContent]:
    """The contents a viewer needs to show the tileset with at most max_geometric_error_m of error
    (3D Tiles 1.1 §"Geometric error", §"Refinement"): descend while a tile's ``geometricError`` is
    above the target and it has children; a REPLACE tile's content is kept only where the descent
    stops there, an ADD tile's on the way down too (its children add to it). External tilesets
    (.json content) are yielded for the caller to open and continue with the same rules; their
    root inherits T and refine. ``keep(tile, T)`` prunes whole subtrees (e.g. a fetch radius).
    Implicit tiling (gis.implicit_tiles) is expanded as the descent reaches it, reading subtree
    files by their tileset-relative URI with ``read_subtree``."""
    T = T_parent @ (np.asarray(tile["transform"], float).reshape(4, 4).T if "transform" in tile else np.eye(4))
    if not keep(tile, T):
        return
    if "implicitTiling" in tile:  # (after keep: a pruned tree's subtrees are not read)
        tile = implicit_root(tile, read_subtree)
    refine = str(tile.get("refine", refine)).upper()
    fine_enough = float(tile.get("geometricError", 0.0)) <= max_geometric_error_m
    if fine_enough:
        children = []
    elif IMPLICIT in tile:  # (children outside keep are left out before their availability is read)
        children = implicit_children(tile, lambda ch: keep(ch, T))
    else:
        children = tile.get("children") or []
    stop = fine_enough or not children
    for c in ([tile["content"]] if "content" in tile else []) + list(tile.get("contents") or []):
        content = TileContent(c.get("uri") or c.get("url") or "", T, refine)
        if content.uri and (stop or refine == "ADD" or content.is_tileset):
            yield content
    if not stop:
        for ch in children:
            yield from tileset_contents(ch, T, refine, max_geometric_error_m, keep, read_subtree)


def _relative_uri(ts_path: Path, uri: str) -> Path:
    parts = urlsplit(uri)
    if parts.scheme or parts.path.startswith("/"):
        raise GisFormatError(ts_path, f"content URI {uri!r} is not relative to the tileset; fetch the tileset "
                                      "from its server (an http(s):// source) so its URIs are mirrored")
    return ts_path.parent / unquote(parts.path)


def _walk_tileset(path: Path, T_parent: np.ndarray, refine: str, spacing: float, out: list[GisModel], depth: int,
                  resolve: Callable[[Path, str], Path | None]) -> None:
    if depth > 16:
        raise GisFormatError(path, "external tilesets nested deeper than 16")
    doc = _read_json(path)
    if not isinstance(doc, dict) or "root" not in doc:
        raise GisFormatError(path, "tileset.json without 'root'")

    def read_subtree(uri: str) -> bytes | None:
        sub = resolve(path, uri)
        if sub is None:  # (a download mirror: outside what this fetch needed, left out like a tile)
            return None
        if not sub.is_file():
            raise GisFormatError(path, f"subtree {uri} of its implicit tiling is missing")
        return sub.read_bytes()

    try:
        contents = list(tileset_contents(doc["root"], T_parent, refine, spacing, read_subtree=read_subtree))
    except GisFormatError:
        raise
    except ImplicitTilingError as e:
        raise GisFormatError(path, str(e)) from None
    except (AttributeError, KeyError, TypeError, ValueError) as e:  # a tile that is not a tile
        raise GisFormatError(path, f"malformed tile: {type(e).__name__}: {e}") from None
    for c in contents:
        cpath = resolve(path, c.uri)
        if cpath is None:
            continue
        if c.is_tileset:
            _walk_tileset(cpath, c.T, c.refine, spacing, out, depth + 1, resolve)
        else:
            out.append(_load_tile_content(cpath, c.T, spacing))


def _load_tile_content(path: Path, T_ecef_tile: np.ndarray, spacing: float) -> GisModel:
    if not path.is_file():
        raise GisFormatError(path, "tile content referenced by the tileset is missing")
    return _tile_model(path, path.read_bytes(), T_ecef_tile, spacing)


def _cmpt_tiles(path: Path, data: bytes, depth: int = 0) -> list[bytes]:
    """The inner tiles of a composite tile (3D Tiles 1.0 cmpt: magic, version, byteLength,
    tilesLength, then the tiles back to back, each with its byteLength at offset 8), nested
    composites flattened."""
    if depth > 8:
        raise GisFormatError(path, "composite tiles nested deeper than 8")
    if len(data) < 16:
        raise GisFormatError(path, "truncated cmpt header")
    _, _, total, n_tiles = struct.unpack("<4sIII", data[:16])
    tiles, at = [], 16
    for k in range(n_tiles):
        if at + 12 > min(total, len(data)):
            raise GisFormatError(path, f"composite tile truncated at its inner tile {k} of {n_tiles}")
        length = struct.unpack("<I", data[at + 8:at + 12])[0]
        if length < 12 or at + length > len(data):
            raise GisFormatError(path, f"composite tile: inner tile {k} of {n_tiles} ({length} bytes) runs past the file's end")
        inner = data[at:at + length]
        tiles += _cmpt_tiles(path, inner, depth + 1) if inner[:4] == b"cmpt" else [inner]
        at += length
    return tiles


def _tile_model(path: Path, data: bytes, T_ecef_tile: np.ndarray, spacing: float) -> GisModel:
    """A tile's content (b3dm, i3dm, glb, pnts, or a cmpt of them) as a model in ECEF via the tile's transform."""
    if data[:4] == b"cmpt":
        models = [_tile_model(path, inner, T_ecef_tile, spacing) for inner in _cmpt_tiles(path, data)]
        if not models:
            raise GisFormatError(path, "composite tile holds no tiles")
        return models[0] if len(models) == 1 else merge_models(models, path)
    rtc = np.zeros(3)
    if data[:4] == b"pnts":
        return _load_pnts(path, data, T_ecef_tile, spacing)
    if data[:4] == b"i3dm":
        return _load_i3dm(path, data, T_ecef_tile, spacing)
    if data[:4] == b"b3dm":
        ft, _, end = _tile_feature_table(path, data, "b3dm")
        rtc = np.asarray(ft.get("RTC_CENTER", [0, 0, 0]), float)
        data = data[end:]
    if data[:4] != b"glTF":
        raise GisFormatError(path, f"tile content is neither b3dm, i3dm, pnts, cmpt nor glb ({data[:4]!r})")
    p, n, cesium_rtc = _glb_surface(path, data, spacing)
    p = p + (rtc if cesium_rtc is None else cesium_rtc)
    R = T_ecef_tile[:3, :3]
    p_ecef = p @ R.T + T_ecef_tile[:3, 3]
    return model_from_ecef(p_ecef, n @ R.T, np.full(len(p), UNCLASSIFIED, np.uint8), "EPSG:4978", path)


def _glb_surface(path: Path, glb: bytes, spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Points and normals sampled on a binary glTF's meshes, turned Z-up as 3D Tiles turns glTF's
    Y-up, and its CESIUM_RTC centre (None without)."""
    gltf_json = _glb_json(path, glb)
    check_gltf_extensions(path, gltf_json)
    cesium_rtc = gltf_json.get("extensions", {}).get("CESIUM_RTC", {}).get("center")
    try:
        scene = trimesh.load(io.BytesIO(glb), file_type="glb", force="scene")
        mesh = scene.to_mesh()
        p, n, _ = sample_mesh(mesh, spacing)
    except Exception as e:  # corrupt glb: trimesh/json/struct errors of many kinds
        raise GisFormatError(path, f"cannot parse glb payload: {type(e).__name__}: {e}") from None
    return p @ R_ZUP_YUP.T, n @ R_ZUP_YUP.T, None if cesium_rtc is None else np.asarray(cesium_rtc, float)


def _oct_decode_16(v: np.ndarray) -> np.ndarray:
    """Unit vectors from 16-bit oct encoding (i3dm NORMAL_*_OCT32P; Cigolle et al., "A Survey of
    Efficient Representations for Independent Unit Vectors", JCGT 2014, §3.4)."""
    xy = v.astype(float) / 65535.0 * 2.0 - 1.0
    x, y = xy[:, 0], xy[:, 1]
    z = 1.0 - np.abs(x) - np.abs(y)
    sx, sy = np.where(x >= 0, 1.0, -1.0), np.where(y >= 0, 1.0, -1.0)
    x, y = np.where(z < 0, (1.0 - np.abs(xy[:, 1])) * sx, x), np.where(z < 0, (1.0 - np.abs(xy[:, 0])) * sy, y)
    out = np.column_stack([x, y, z])
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _load_i3dm(path: Path, data: bytes, T_ecef_tile: np.ndarray, spacing: float, chunk: int = 2000) -> GisModel:
    """Instanced 3D Model (3D Tiles 1.0 i3dm): one glTF (embedded, or by URI beside the tile) placed
    at every instance of the feature table: POSITION (float32) or POSITION_QUANTIZED (uint16 over
    QUANTIZED_VOLUME_OFFSET / _SCALE), plus RTC_CENTER; orientation from NORMAL_UP / NORMAL_RIGHT
    (or their _OCT32P encodings), else the east-north-up frame at the instance with EAST_NORTH_UP,
    else none; SCALE or SCALE_NON_UNIFORM. Composed as CesiumJS does: the glTF turned Z-up, scaled,
    rotated by the columns [right, up, right × up], moved to its position, then the tile transform.
    Sampled at the spacing over the largest instance, thinned to one point per spacing voxel."""
    ft, body, end = _tile_feature_table(path, data, "i3dm")
    gltf_format = struct.unpack("<I", data[28:32])[0]
    if gltf_format == 1:
        glb = data[end:]
    elif gltf_format == 0:
        uri = data[end:].decode("utf-8", "replace").strip(" \x00")
        glb_path = _relative_uri(path, uri)
        if not glb_path.is_file():
            raise GisFormatError(path, f"its glTF {uri} is missing")
        glb = glb_path.read_bytes()
    else:
        raise GisFormatError(path, f"i3dm gltfFormat {gltf_format} is neither 0 (URI) nor 1 (embedded)")

    def vec(name: str, dtype: str, n: int, width: int) -> np.ndarray:
        return np.frombuffer(body, dtype, width * n, int(ft[name]["byteOffset"])).reshape(n, width)

    try:
        n = int(ft["INSTANCES_LENGTH"])
        if "POSITION" in ft:
            pos = vec("POSITION", "<f4", n, 3).astype(float)
        else:
            pos = (np.asarray(ft["QUANTIZED_VOLUME_OFFSET"], float)
                   + vec("POSITION_QUANTIZED", "<u2", n, 3) / 65535.0 * np.asarray(ft["QUANTIZED_VOLUME_SCALE"], float))
        pos = pos + np.asarray(ft.get("RTC_CENTER", [0.0, 0.0, 0.0]), float)
        if "NORMAL_UP" in ft and "NORMAL_RIGHT" in ft:
            up, right = vec("NORMAL_UP", "<f4", n, 3).astype(float), vec("NORMAL_RIGHT", "<f4", n, 3).astype(float)
        elif "NORMAL_UP_OCT32P" in ft and "NORMAL_RIGHT_OCT32P" in ft:
            up, right = _oct_decode_16(vec("NORMAL_UP_OCT32P", "<u2", n, 2)), _oct_decode_16(vec("NORMAL_RIGHT_OCT32P", "<u2", n, 2))
        else:
            up = right = None
        if "SCALE_NON_UNIFORM" in ft:
            scale = vec("SCALE_NON_UNIFORM", "<f4", n, 3).astype(float)
        elif "SCALE" in ft:
            scale = np.repeat(vec("SCALE", "<f4", n, 1).astype(float), 3, axis=1)
        else:
            scale = np.ones((n, 3))
    except (KeyError, TypeError, ValueError) as e:  # frombuffer beyond the body, shapes
        raise GisFormatError(path, f"cannot parse i3dm feature table: {type(e).__name__}: {e}") from None
    if n == 0:
        raise GisFormatError(path, "i3dm without instances")
    if not (np.isfinite(pos).all() and np.isfinite(scale).all() and (scale > 0).all()):
        raise GisFormatError(path, "i3dm positions or scales are not finite and positive")
    R_T = T_ecef_tile[:3, :3]
    if up is not None:
        right = right / np.linalg.norm(right, axis=1, keepdims=True)
        up = up / np.linalg.norm(up, axis=1, keepdims=True)
        rot = np.stack([right, up, np.cross(right, up)], axis=2)  # columns
    elif ft.get("EAST_NORTH_UP"):
        lat, lon, _ = ecef_to_geodetic(pos @ R_T.T + T_ecef_tile[:3, 3])
        rot = np.einsum("ji,njk->nik", R_T, np.stack([R_ecef_enu(a, b) for a, b in zip(lat, lon)]))  # ENU in the tile frame
    else:
        rot = np.broadcast_to(np.eye(3), (n, 3, 3))
    if not np.isfinite(rot).all():
        raise GisFormatError(path, "i3dm NORMAL_UP / NORMAL_RIGHT are not all non-zero vectors")
    p_m, n_m, _ = _glb_surface(path, glb, spacing / float(scale.max()))
    pts, nrm = [], []
    for a in range(0, n, chunk):  # (bounded memory: a tile may hold thousands of trees)
        b = slice(a, a + chunk)
        p = pos[b, None, :] + np.einsum("nij,nkj->nki", rot[b], p_m[None] * scale[b, None, :])
        q = np.einsum("nij,nkj->nki", rot[b], n_m[None] / scale[b, None, :])
        p_ecef = p.reshape(-1, 3) @ R_T.T + T_ecef_tile[:3, 3]
        keep = first_per_voxel(p_ecef, spacing)
        pts.append(p_ecef[keep])
        nrm.append((q.reshape(-1, 3) @ R_T.T)[keep])
    p_ecef, n_ecef = np.concatenate(pts), np.concatenate(nrm)
    keep = first_per_voxel(p_ecef, spacing)  # voxels two chunks share
    n_ecef = n_ecef[keep] / np.linalg.norm(n_ecef[keep], axis=1, keepdims=True)
    return model_from_ecef(p_ecef[keep], n_ecef, np.full(len(keep), UNCLASSIFIED, np.uint8), "EPSG:4978", path)


def _tile_feature_table(path: Path, data: bytes, kind: str) -> tuple[dict, bytes, int]:
    """(feature table JSON, its binary body, where the tile's payload starts) of a 3D Tiles 1.0 tile
    (b3dm, pnts: a 28-byte header magic, version, byteLength, then the feature and batch tables'
    JSON and binary lengths; i3dm: 32 bytes, gltfFormat last)."""
    head = 32 if kind == "i3dm" else 28
    if len(data) < head:
        raise GisFormatError(path, f"truncated {kind} header")
    _, _, total, ft_json, ft_bin, bt_json, bt_bin = struct.unpack("<4sIIIIII", data[:28])
    end = head + ft_json + ft_bin + bt_json + bt_bin
    if total != len(data) or end > len(data):
        raise GisFormatError(path, f"{kind} byteLength {total} != file size {len(data)} (truncated?)")
    try:
        ft = json.loads(data[head:head + ft_json].decode("utf-8").strip(" \x00") or "{}")
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise GisFormatError(path, f"cannot parse {kind} feature table: {e}") from None
    if not isinstance(ft, dict):
        raise GisFormatError(path, f"{kind} feature table is not a JSON object")
    return ft, data[head + ft_json:head + ft_json + ft_bin], end


def _load_pnts(path: Path, data: bytes, T_ecef_tile: np.ndarray, spacing: float) -> GisModel:
    """A point cloud tile (3D Tiles 1.0 pnts: feature table POSITION float32 or POSITION_QUANTIZED
    uint16 with QUANTIZED_VOLUME_OFFSET / _SCALE, RTC_CENTER; tile coordinates are Z-up, no glTF
    rotation), thinned to one point per spacing voxel; normals estimated (a feature-table NORMAL is
    not trusted to face up). Draco-compressed pnts are refused by name."""
    ft, body, _ = _tile_feature_table(path, data, "pnts")
    try:
        n = int(ft["POINTS_LENGTH"])
        if "3DTILES_draco_point_compression" in (ft.get("extensions") or {}):
            raise GisFormatError(path, "Draco-compressed point cloud tile (3DTILES_draco_point_compression) is not read")
        if "POSITION" in ft:
            p = np.frombuffer(body, "<f4", 3 * n, int(ft["POSITION"]["byteOffset"])).reshape(n, 3).astype(float)
        else:
            q = np.frombuffer(body, "<u2", 3 * n, int(ft["POSITION_QUANTIZED"]["byteOffset"])).reshape(n, 3)
            p = np.asarray(ft["QUANTIZED_VOLUME_OFFSET"], float) + q / 65535.0 * np.asarray(ft["QUANTIZED_VOLUME_SCALE"], float)
        p = p + np.asarray(ft.get("RTC_CENTER", [0.0, 0.0, 0.0]), float)
    except GisFormatError:
        raise
    except (KeyError, TypeError, ValueError) as e:  # frombuffer beyond the body, shapes
        raise GisFormatError(path, f"cannot parse pnts feature table: {type(e).__name__}: {e}") from None
    p_ecef = p @ T_ecef_tile[:3, :3].T + T_ecef_tile[:3, 3]
    check_on_earth(p_ecef, path)
    p_ecef = p_ecef[first_per_voxel(p_ecef, spacing)]
    origin = frame_at_centroid(p_ecef)
    p_enu = origin.ecef_to_enu(p_ecef)
    return GisModel(p_enu, estimate_normals(p_enu, 3.0 * max(_median_spacing(p_enu), spacing)),
                    np.full(len(p_enu), UNCLASSIFIED, np.uint8), origin, "EPSG:4978", path)
