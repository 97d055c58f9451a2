"""Georeferencing of the GIS loaders: the ``.georef.json`` sidecar, a CRS's points to ECEF with PROJ (the
system's geoid grids included; no "ballpark" fallback), and file points + normals to a GisModel."""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
from pyproj import CRS, Transformer
from pyproj import datadir as pyproj_datadir
from pyproj.exceptions import CRSError, ProjError
from pyproj.transformer import TransformerGroup

from gis.geodesy import geodetic_to_ecef, msl_to_ellipsoid
from gis.loaders.common import _read_json, estimate_normals
from gis.model import GisFormatError, GisModel, check_on_earth, frame_at_centroid, model_from_ecef


def read_georef(path: Path) -> tuple[CRS, np.ndarray, str]:
    """The ``<file>.georef.json`` sidecar: (crs, offset_m (3,), vertical 'ellipsoid'|'egm96')."""
    side = path.with_name(path.name + ".georef.json")
    if not side.is_file():
        raise GisFormatError(path, f"no georeference: {side.name} sidecar missing (see CONTRIBUTING.md)")
    doc = _read_json(side)
    try:
        crs = CRS.from_user_input(doc["crs"])
        offset = np.asarray(doc.get("offset_m", [0.0, 0.0, 0.0]), float).reshape(3)
        vertical = doc.get("vertical", "ellipsoid")
    except KeyError as e:
        raise GisFormatError(side, f"missing key {e}") from None
    except (CRSError, ValueError, TypeError) as e:
        raise GisFormatError(side, f"bad georeference: {e}") from None
    if vertical not in ("ellipsoid", "egm96"):
        raise GisFormatError(side, f"key 'vertical' must be 'ellipsoid' or 'egm96', got {vertical!r}")
    return crs, offset, vertical


def crs_to_ecef(p: np.ndarray, crs: CRS, vertical: str = "ellipsoid") -> np.ndarray:
    """Points (N,3) in ``crs`` → ECEF. A 2D CRS takes z as height on ``vertical``; a 3D/compound CRS
    carries its own vertical datum (PROJ handles it)."""
    p = np.asarray(p, float)
    if crs.is_geocentric:
        return p.copy()
    to_geo = _transformer(crs.to_wkt())
    lon, lat, h = to_geo.transform(p[:, 0], p[:, 1], p[:, 2])
    lat, lon, h = np.asarray(lat), np.asarray(lon), np.asarray(h)
    if len(crs.axis_info) < 3 and vertical == "egm96":
        h = msl_to_ellipsoid(lat, lon, h)
    ecef = geodetic_to_ecef(lat, lon, h)
    if not np.all(np.isfinite(ecef)):
        raise ValueError(f"{int((~np.isfinite(ecef)).any(axis=1).sum())} points fall outside the CRS's area")
    return ecef


#: the system's PROJ grids (Debian's proj-data, which the Makefile installs: the EGM96 geoid and
#: others) beside the few in pyproj's wheel, so that a CRS with EGM96 heights (e.g. EPSG:32632+5773,
#: as photogrammetry tools export) transforms exactly instead of being refused
SYSTEM_PROJ_DIRS = ("/usr/share/proj", "/usr/local/share/proj")
for _d in SYSTEM_PROJ_DIRS:
    if Path(_d).is_dir() and _d not in pyproj_datadir.get_data_dir().split(os.pathsep):
        pyproj_datadir.append_data_dir(_d)


def _transformer(wkt: str) -> Transformer:
    """CRS → WGS 84 (lon, lat, ellipsoidal h), refusing PROJ's "ballpark" fallback: without the
    grid a vertical datum needs, PROJ would carry NAP or DHHN heights over unchanged as ellipsoidal
    ones (measured: EPSG:7415 NAP 0 m → h 0 m, where the geoid lies ~43 m above the ellipsoid),
    a model tens of metres too low, silently."""
    crs = CRS.from_wkt(wkt)
    try:
        return Transformer.from_crs(crs, "EPSG:4979", always_xy=True, allow_ballpark=False)
    except ProjError:
        with warnings.catch_warnings():  # pyproj warns of the missing grid; the error below names it
            warnings.simplefilter("ignore", UserWarning)
            group = TransformerGroup(crs, "EPSG:4979", always_xy=True, allow_ballpark=False)
        grids = sorted({g.short_name for op in group.unavailable_operations for g in op.grids if not g.available})
        raise ValueError("PROJ has no exact transformation to WGS 84 heights on this machine" + (
            f"; it needs the grid(s) {', '.join(grids)}: `pyproj sync --file NAME` (the venv's pyproj) downloads one from "
            f"https://cdn.proj.org/ into {pyproj_datadir.get_user_data_dir()}" if grids else " (none is known for this vertical datum: convert the file to "
            "ellipsoidal or EGM96 heights first)")) from None


def _normals_to_ecef(p: np.ndarray, n: np.ndarray, crs: CRS, vertical: str) -> np.ndarray:
    """Carry normals through the (non-linear) CRS → ECEF map by a 1 m finite difference."""
    return crs_to_ecef(p + n, crs, vertical) - crs_to_ecef(p, crs, vertical)


def _georeferenced(path: Path, p_file: np.ndarray, n_file: np.ndarray | None, labels: np.ndarray,
                   crs: CRS, offset: np.ndarray, vertical: str, sample_spacing_m: float) -> GisModel:
    p = p_file + offset
    try:
        ecef = crs_to_ecef(p, crs, vertical)
        n_ecef = None if n_file is None else _normals_to_ecef(p, n_file, crs, vertical)
    except ValueError as e:
        raise GisFormatError(path, f"cannot transform from {crs.name}: {e}") from None
    check_on_earth(ecef, path)  # (e.g. a projected CRS given for geographic coordinates)
    if n_ecef is None:
        origin = frame_at_centroid(ecef)
        p_enu = origin.ecef_to_enu(ecef)
        return GisModel(p_enu, estimate_normals(p_enu, 3.0 * sample_spacing_m), labels, origin, crs.to_string(), path)
    return model_from_ecef(ecef, n_ecef, labels, crs.to_string(), path)
