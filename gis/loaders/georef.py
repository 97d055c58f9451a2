"""Georeferencing of the GIS loaders: a mesh's ``.georef.json`` sidecar (gis.loaders.heights), a CRS's points to ECEF with PROJ (the
system's geoid grids included; no "ballpark" fallback), and file points + normals to a GisModel."""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
from pyproj import CRS, Transformer
from pyproj import datadir as pyproj_datadir
from pyproj.exceptions import ProjError
from pyproj.transformer import TransformerGroup

from gis.geodesy import geodetic_to_ecef, msl_to_ellipsoid
from gis.loaders.common import estimate_normals
from gis.loaders.heights import Georef, georef_of, read_sidecar, sidecar_path
from gis.model import GisFormatError, GisModel, check_on_earth, frame_at_centroid, model_from_ecef


def read_georef(path: Path, fmt: str = "mesh") -> Georef:
    """A mesh's georeference: its ``.georef.json`` sidecar (gis.loaders.heights), which it needs."""
    if not sidecar_path(path).is_file():
        raise GisFormatError(path, f"no georeference: {sidecar_path(path).name} sidecar missing (see CONTRIBUTING.md)")
    return georef_of(path, fmt, None, read_sidecar(path, fmt))


def crs_to_ecef(p: np.ndarray, crs: CRS, vertical: str = "ellipsoid", height_unit_m: float = 1.0) -> np.ndarray:
    """Points (N,3) in ``crs`` → ECEF. A 2D CRS takes z × height_unit_m as a height in metres on
    ``vertical``; a 3D/compound CRS carries its own vertical datum and unit (PROJ handles them)."""
    p = np.asarray(p, float)
    if crs.is_geocentric:
        return p.copy()
    to_geo = _transformer(crs.to_wkt())
    lon, lat, h = to_geo.transform(p[:, 0], p[:, 1], p[:, 2])
    lat, lon, h = np.asarray(lat), np.asarray(lon), np.asarray(h)
    if len(crs.axis_info) < 3 and height_unit_m != 1.0:  # (PROJ passes a 2D CRS's z through unchanged)
        h = h * height_unit_m
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
        raise ValueError(missing_grid_message(group)) from None


def missing_grid_message(group: TransformerGroup) -> str:
    """What PROJ lacks for an exact transformation: the grid(s) of its best unavailable operation
    (PROJ lists them best first; the others only name grids that one does not need), and how to
    install them."""
    msg = "PROJ has no exact transformation to WGS 84 heights on this machine"
    ops = [op for op in group.unavailable_operations if any(not g.available for g in op.grids)]
    if not ops:
        return msg + (" (none is known for this vertical datum: convert the file to ellipsoidal or EGM96 heights first)")
    missing = [g for g in ops[0].grids if not g.available]
    names = ", ".join(g.short_name for g in missing)
    where = ", ".join(pyproj_datadir.get_data_dir().split(os.pathsep)[:1] + [pyproj_datadir.get_user_data_dir()])
    package = "".join(f" (package {g.package_name})" for g in missing if g.package_name)
    return (f"{msg}: its best one ({ops[0].name}) needs the grid {names}{package}, not installed. Install it: "
            f"`pyproj sync --file {missing[0].short_name}` (the venv's pyproj; PROJ's own `projsync --file "
            f"{missing[0].short_name}` does the same), or download {missing[0].url or 'it from https://cdn.proj.org/'} "
            f"into one of PROJ's data directories ({where})")


def _normals_to_ecef(p: np.ndarray, n: np.ndarray, g: Georef) -> np.ndarray:
    """Carry normals through the (non-linear) CRS → ECEF map by a 1 m finite difference."""
    return crs_to_ecef(p + n, g.crs, g.vertical, g.height_unit_m) - crs_to_ecef(p, g.crs, g.vertical, g.height_unit_m)


def _georeferenced(path: Path, p_file: np.ndarray, n_file: np.ndarray | None, labels: np.ndarray,
                   g: Georef, sample_spacing_m: float) -> GisModel:
    crs = g.crs
    p = p_file + g.offset
    try:
        ecef = crs_to_ecef(p, crs, g.vertical, g.height_unit_m)
        n_ecef = None if n_file is None else _normals_to_ecef(p, n_file, g)
    except ValueError as e:
        raise GisFormatError(path, f"cannot transform from {crs.name}: {e}") from None
    check_on_earth(ecef, path)  # (e.g. a projected CRS given for geographic coordinates)
    if n_ecef is None:
        origin = frame_at_centroid(ecef)
        p_enu = origin.ecef_to_enu(ecef)
        return GisModel(p_enu, estimate_normals(p_enu, 3.0 * sample_spacing_m), labels, origin, crs.to_string(), path)
    return model_from_ecef(ecef, n_ecef, labels, crs.to_string(), path)
