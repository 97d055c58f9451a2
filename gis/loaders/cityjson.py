"""CityJSON and CityJSONSeq: every surface of the highest LoD geometry of each city object, labelled by its type."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable

import numpy as np
from pyproj import CRS
from pyproj.exceptions import CRSError

from gis.loaders.common import _read_json, sample_polygon
from gis.loaders.georef import _georeferenced
from gis.loaders.heights import georef_of, read_sidecar
from gis.model import BUILDING, GROUND, HIGH_VEGETATION, ROAD, UNCLASSIFIED, GisFormatError, GisModel

_CITYJSON_LABELS = {
    "Building": BUILDING, "BuildingPart": BUILDING, "BuildingInstallation": BUILDING,
    "Road": ROAD, "Railway": ROAD, "TransportSquare": ROAD,
    "TINRelief": GROUND, "LandUse": GROUND,
    "PlantCover": HIGH_VEGETATION, "SolitaryVegetationObject": HIGH_VEGETATION,
}


def load_cityjson(path: Path, sample_spacing_m: float = 1.0, doc: dict | None = None,
                  features: Iterable[dict] = ()) -> GisModel:
    """A CityJSON file, or a CityJSONSeq one (``load_cityjson_seq``): ``doc`` the CityJSON object
    (CRS, ``transform``, templates), ``features`` the CityJSONFeature objects after it, each with
    its own CityObjects and vertices."""
    doc = doc if doc is not None else _read_json(path)
    try:
        ref = doc.get("metadata", {}).get("referenceSystem")
        if not ref:
            raise GisFormatError(path, "CityJSON has no metadata.referenceSystem; cannot georeference")
        crs = _cityjson_crs(path, ref)
        pts, nrms, labs = [], [], []
        for part in [doc, *features]:
            v = np.asarray(part["vertices"], float).reshape(-1, 3)
            if "transform" in doc:
                v = v * np.asarray(doc["transform"]["scale"], float) + np.asarray(doc["transform"]["translate"], float)
            for obj in part["CityObjects"].values():
                geoms = [_cityjson_geometry(doc, v, g) for g in obj.get("geometry", [])]
                geoms = [g for g in geoms if g is not None]
                if not geoms:
                    continue
                _, gv, boundaries = max(geoms, key=lambda g: g[0])
                label = _CITYJSON_LABELS.get(obj.get("type", ""), UNCLASSIFIED)
                for surface in _surfaces(boundaries):
                    rings = [gv[np.asarray(r, int)] for r in surface]
                    p, n = sample_polygon(rings[0], rings[1:], sample_spacing_m)
                    pts.append(p)
                    nrms.append(np.broadcast_to(n, p.shape))
                    labs.append(np.full(len(p), label, np.uint8))
    except (KeyError, TypeError, IndexError, ValueError) as e:
        if isinstance(e, GisFormatError):
            raise
        raise GisFormatError(path, f"malformed CityJSON: {type(e).__name__}: {e}") from None
    if not pts:
        raise GisFormatError(path, "CityJSON holds no surfaces")
    p, n = np.concatenate(pts), np.concatenate(nrms)
    # (after the geometry: a malformed file is refused as such before its heights' datum is asked for)
    georef = georef_of(path, "CityJSON", crs, read_sidecar(path, "CityJSON"))
    return _georeferenced(path, p, n, np.concatenate(labs), georef, sample_spacing_m)


_CITYJSON_SURFACE_TYPES = ("MultiSurface", "CompositeSurface", "Solid", "MultiSolid", "CompositeSolid")


def _cityjson_geometry(doc: dict, v: np.ndarray, g: dict) -> tuple[float, np.ndarray, list] | None:
    """(LoD, vertices, boundaries) of a CityJSON geometry that has surfaces, None for points and
    lines. A GeometryInstance (CityJSON 2.0 §"Geometry templates": trees, street furniture) is its
    template's geometry moved by ``transformationMatrix`` (4×4, row-major) onto its reference
    vertex; template vertices are real coordinates, not scaled by ``transform``."""
    if g.get("type") == "GeometryInstance":
        templates = doc["geometry-templates"]
        t = templates["templates"][int(g["template"])]
        M = np.asarray(g["transformationMatrix"], float).reshape(4, 4)
        tv = np.asarray(templates["vertices-templates"], float) @ M[:3, :3].T + M[:3, 3] + v[int(g["boundaries"][0])]
        return (float(t.get("lod", 0)), tv, t["boundaries"]) if t.get("type") in _CITYJSON_SURFACE_TYPES else None
    return (float(g.get("lod", 0)), v, g["boundaries"]) if g.get("type") in _CITYJSON_SURFACE_TYPES else None


def load_cityjson_seq(path: Path, sample_spacing_m: float = 1.0) -> GisModel:
    """CityJSON Text Sequences (CityJSONSeq, ``.city.jsonl``, as cjio and the 3D BAG write them):
    a CityJSON object on the first line, then one CityJSONFeature per line."""
    try:
        lines = [ln for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip()]
        docs = [json.loads(ln) for ln in lines]
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise GisFormatError(path, f"invalid CityJSONSeq line: {e}") from None
    if not docs or not isinstance(docs[0], dict) or docs[0].get("type") != "CityJSON":
        raise GisFormatError(path, "CityJSONSeq must start with a CityJSON object")
    bad = [i + 1 for i, d in enumerate(docs[1:], 1) if not isinstance(d, dict) or d.get("type") != "CityJSONFeature"]
    if bad:
        raise GisFormatError(path, f"line {bad[0]} is not a CityJSONFeature")
    return load_cityjson(path, sample_spacing_m, docs[0], docs[1:])


def _cityjson_crs(path: Path, ref: str) -> CRS:
    # "https://www.opengis.net/def/crs/EPSG/0/7415" or "urn:ogc:def:crs:EPSG::7415" or "EPSG:7415"
    code = ref.rstrip("/").replace("::", "/").replace(":", "/").split("/")[-1]
    try:
        return CRS.from_epsg(int(code)) if code.isdigit() else CRS.from_user_input(ref)
    except CRSError as e:
        raise GisFormatError(path, f"unknown referenceSystem {ref!r}: {e}") from None


def _surfaces(b):
    """Yield surfaces (lists of rings of vertex indices) from any CityJSON boundary nesting."""
    if b and isinstance(b[0], list) and b[0] and isinstance(b[0][0], int):
        yield b
    else:
        for x in b:
            yield from _surfaces(x)
