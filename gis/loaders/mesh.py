"""Triangle meshes (PLY, OBJ, GLB/glTF) and PLY point clouds, georeferenced by their ``.georef.json`` sidecar;
glTF's required extensions checked."""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import trimesh

from gis.loaders.common import R_ZUP_YUP, _read_json, first_per_voxel, sample_mesh
from gis.loaders.georef import _georeferenced, read_georef
from gis.model import UNCLASSIFIED, GisFormatError, GisModel

_LABEL_KEYS = ("classification", "label", "class")


def load_ply(path: Path, sample_spacing_m: float = 1.0) -> GisModel:
    return load_mesh(path, sample_spacing_m)


def load_mesh(path: Path, sample_spacing_m: float = 1.0) -> GisModel:
    """PLY/OBJ/GLB/glTF mesh or PLY point cloud + georef sidecar."""
    georef = read_georef(path)
    if path.suffix.lower() in (".glb", ".gltf"):
        data = path.read_bytes()
        check_gltf_extensions(path, _glb_json(path, data) if data[:4] == b"glTF" else _read_json(path))
    try:
        geom = trimesh.load(path, process=False)
    except Exception as e:  # trimesh raises many types on corrupt input
        raise GisFormatError(path, f"cannot parse: {type(e).__name__}: {e}") from None
    is_gltf = path.suffix.lower() in (".glb", ".gltf")
    if isinstance(geom, trimesh.Scene):
        if not geom.geometry:
            raise GisFormatError(path, "scene holds no geometry")
        geom = geom.to_mesh() if all(isinstance(g, trimesh.Trimesh) for g in geom.geometry.values()) else geom.to_geometry()
    if isinstance(geom, trimesh.PointCloud):
        p = np.asarray(geom.vertices, float)
        raw = geom.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
        labels = _labels_from(raw, len(p))
        n = None
        if raw is not None and all(k in raw.dtype.names for k in ("nx", "ny", "nz")):
            n = np.stack([raw["nx"], raw["ny"], raw["nz"]], axis=1).astype(float)
        keep = first_per_voxel(p, sample_spacing_m) if len(p) else slice(None)
        return _georeferenced(path, p[keep], None if n is None else n[keep], labels[keep], georef, sample_spacing_m)
    if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
        raise GisFormatError(path, f"no triangles or points found ({type(geom).__name__})")
    p, n, face_idx = sample_mesh(geom, sample_spacing_m)
    labels = _mesh_labels(geom, face_idx)
    if is_gltf:
        p, n = p @ R_ZUP_YUP.T, n @ R_ZUP_YUP.T
    return _georeferenced(path, p, n, labels, georef, sample_spacing_m)


def _labels_from(raw: np.ndarray | None, n: int) -> np.ndarray:
    if raw is not None and raw.dtype.names:
        for k in _LABEL_KEYS:
            if k in raw.dtype.names:
                return np.asarray(raw[k]).astype(np.uint8)
    return np.full(n, UNCLASSIFIED, np.uint8)


def _mesh_labels(mesh: trimesh.Trimesh, face_idx: np.ndarray) -> np.ndarray:
    raw = mesh.metadata.get("_ply_raw", {})
    face = raw.get("face", {}).get("data")
    if face is not None and face.dtype.names and any(k in face.dtype.names for k in _LABEL_KEYS):
        return _labels_from(face, len(mesh.faces))[face_idx]
    vert = raw.get("vertex", {}).get("data")
    per_vertex = _labels_from(vert, len(mesh.vertices))
    return per_vertex[np.asarray(mesh.faces)[face_idx, 0]]


def _glb_json(path: Path, data: bytes) -> dict:
    """The JSON chunk of a binary glTF (glTF 2.0 §"GLB File Format Specification")."""
    try:
        magic, _, _, jlen, jtype = struct.unpack("<4sIIII", data[:20])
        if magic != b"glTF" or jtype != 0x4E4F534A:  # "JSON"
            raise ValueError("no JSON chunk first")
        doc = json.loads(data[20 : 20 + jlen])
    except (struct.error, ValueError, UnicodeDecodeError) as e:
        raise GisFormatError(path, f"cannot parse glb header: {type(e).__name__}: {e}") from None
    if not isinstance(doc, dict):
        raise GisFormatError(path, "glb JSON chunk is not an object")
    return doc


#: glTF extensions a file may require that leave our geometry right: materials and textures are not
#: read, CESIUM_RTC is applied by the 3D Tiles loader, Draco is decoded by trimesh (with DracoPy).
_GLTF_HARMLESS_PREFIXES = ("KHR_materials_", "KHR_texture_", "EXT_texture_")
_GLTF_DECODED = ("CESIUM_RTC", "KHR_draco_mesh_compression")


def check_gltf_extensions(path: Path, gltf: dict) -> None:
    """Refuse a glTF whose ``extensionsRequired`` (glTF 2.0 §3.12: a loader that does not support
    one must not load the asset) names one we cannot honour. trimesh does not check them: a
    meshopt-compressed or quantized mesh would load as zeros or at the wrong scale."""
    required = [str(e) for e in gltf.get("extensionsRequired") or []]
    bad = [e for e in required if not (e in _GLTF_DECODED or e.startswith(_GLTF_HARMLESS_PREFIXES))]
    if bad:
        raise GisFormatError(path, f"glTF requires unsupported extension(s) {', '.join(bad)}")
