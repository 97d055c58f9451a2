"""Geodesy: WGS-84 geodetic ↔ ECEF ↔ local ENU/NED, ellipsoidal ↔ MSL (EGM96) heights.

Conventions (CONTRIBUTING.md, Naming):
- geodetic: WGS-84, EPSG:4979, (lat_deg, lon_deg, h_ellipsoid_m).
- ecef: EPSG:4978, metres.
- enu / ned: local level frames at a geodetic origin (lat0_deg, lon0_deg, h0_ellipsoid_m);
  ENU = (east, north, up), NED = (north, east, down).
- MSL heights are orthometric heights above the EGM96 geoid: h_msl_m = h_ellipsoid_m − N.

All conversions go through PROJ (pyproj); all functions are vectorised over arrays of any
leading shape. TerraSLAM's Eq. 3 (iterative ECEF→geodetic) is not reimplemented: PROJ's
``cart`` inverse is the reference implementation of the same conversion.
"""
from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pyproj import Transformer

#: EGM96 15' geoid grid. Debian's ``proj-data`` package ships it (installed by the Makefile);
#: TERRASLAM_EGM96_GRID points at another copy (.gtx or .tif).
_EGM96_CANDIDATES = (
    os.environ.get("TERRASLAM_EGM96_GRID", ""),
    "/usr/share/proj/egm96_15.gtx",
    "/usr/share/proj/us_nga_egm96_15.tif",
    "/usr/local/share/proj/egm96_15.gtx",
)


class GeoidUnavailable(RuntimeError):
    """The EGM96 grid file is missing: MSL heights cannot be computed (never guessed)."""


@functools.lru_cache(maxsize=None)
def _geodetic_to_ecef() -> Transformer:
    return Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)


@functools.lru_cache(maxsize=None)
def _geoid_transformer() -> Transformer:
    for path in _EGM96_CANDIDATES:
        if path and Path(path).is_file():
            # vgridshift with multiplier +1 adds the grid value: h_out = h_in + N.
            return Transformer.from_pipeline(f"+proj=vgridshift +grids={path} +multiplier=1")
    raise GeoidUnavailable(
        "EGM96 geoid grid not found (looked for "
        + ", ".join(p for p in _EGM96_CANDIDATES if p)
        + "); install Debian's proj-data (`make setup` does) or set TERRASLAM_EGM96_GRID"
    )


def geodetic_to_ecef(lat_deg, lon_deg, h_ellipsoid_m) -> np.ndarray:
    """WGS-84 geodetic → ECEF metres, shape (..., 3)."""
    lat, lon, h = np.broadcast_arrays(
        np.asarray(lat_deg, float), np.asarray(lon_deg, float), np.asarray(h_ellipsoid_m, float)
    )
    x, y, z = _geodetic_to_ecef().transform(lon, lat, h)
    return np.stack([x, y, z], axis=-1)


def ecef_to_geodetic(p_ecef_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF (..., 3) → (lat_deg, lon_deg, h_ellipsoid_m)."""
    p = np.asarray(p_ecef_m, float)
    lon, lat, h = _geodetic_to_ecef().transform(p[..., 0], p[..., 1], p[..., 2], direction="INVERSE")
    return np.asarray(lat), np.asarray(lon), np.asarray(h)


def geoid_undulation_m(lat_deg, lon_deg) -> np.ndarray:
    """EGM96 geoid height N above the WGS-84 ellipsoid (metres), bilinear on the 15' grid."""
    lat, lon = np.broadcast_arrays(np.asarray(lat_deg, float), np.asarray(lon_deg, float))
    _, _, n = _geoid_transformer().transform(lon, lat, np.zeros_like(lat))
    n = np.asarray(n)
    if not np.all(np.isfinite(n)):
        raise GeoidUnavailable("EGM96 grid returned no value for some positions")
    return n


def ellipsoid_to_msl(lat_deg, lon_deg, h_ellipsoid_m) -> np.ndarray:
    """Ellipsoidal height → MSL (EGM96 orthometric) height: H = h − N."""
    return np.asarray(h_ellipsoid_m, float) - geoid_undulation_m(lat_deg, lon_deg)


def msl_to_ellipsoid(lat_deg, lon_deg, h_msl_m) -> np.ndarray:
    """MSL (EGM96) height → ellipsoidal height: h = H + N."""
    return np.asarray(h_msl_m, float) + geoid_undulation_m(lat_deg, lon_deg)


# ICAO standard atmosphere, troposphere (ICAO Doc 7488): p = P0·(1 − h/H)^(1/N), h pressure altitude
ISA_P0_HPA = 1013.25
ISA_H_M = 44330.77
ISA_N = 0.190263


def pressure_altitude_m(press_abs_hpa: float) -> float:
    """Pressure altitude (m) of a static pressure (hPa) in the standard atmosphere. Its offset from
    the true height varies with the weather; the pipeline learns it from GNSS."""
    return ISA_H_M * (1.0 - (press_abs_hpa / ISA_P0_HPA) ** ISA_N)


def pressure_hpa_at(h_m: float) -> float:
    """Static pressure (hPa) at pressure altitude h_m: the inverse of pressure_altitude_m."""
    return ISA_P0_HPA * (1.0 - h_m / ISA_H_M) ** (1.0 / ISA_N)


def R_ecef_enu(lat0_deg: float, lon0_deg: float) -> np.ndarray:
    """Rotation whose columns are the east, north, up unit vectors in ECEF at (lat0, lon0).

    Standard local-level rotation (e.g. Hofmann-Wellenhof, GNSS, Eq. 10.13): p_ecef − p0 = R · p_enu.
    """
    lat, lon = np.radians(lat0_deg), np.radians(lon0_deg)
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    return np.array(
        [
            [-so, -sl * co, cl * co],
            [co, -sl * so, cl * so],
            [0.0, cl, sl],
        ]
    )


#: ENU ↔ NED axis swap (its own inverse): (e, n, u) → (n, e, −u).
R_NED_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


@dataclass(frozen=True)
class LocalFrame:
    """A local level frame at a geodetic origin (lat0_deg, lon0_deg, h0_ellipsoid_m)."""

    lat0_deg: float
    lon0_deg: float
    h0_ellipsoid_m: float = 0.0

    def __post_init__(self) -> None:
        # plain floats whatever they came as (numpy scalars or 0-d arrays from a transform): the GIS
        # cache stores them in SQLite, which would keep an array's bytes as a blob
        for name in ("lat0_deg", "lon0_deg", "h0_ellipsoid_m"):
            object.__setattr__(self, name, float(getattr(self, name)))

    @functools.cached_property
    def origin_ecef_m(self) -> np.ndarray:
        return geodetic_to_ecef(self.lat0_deg, self.lon0_deg, self.h0_ellipsoid_m)

    @functools.cached_property
    def R_ecef_enu(self) -> np.ndarray:
        return R_ecef_enu(self.lat0_deg, self.lon0_deg)

    # ECEF <-> ENU
    def ecef_to_enu(self, p_ecef_m) -> np.ndarray:
        return (np.asarray(p_ecef_m, float) - self.origin_ecef_m) @ self.R_ecef_enu

    def enu_to_ecef(self, p_enu_m) -> np.ndarray:
        return np.asarray(p_enu_m, float) @ self.R_ecef_enu.T + self.origin_ecef_m

    # ECEF <-> NED
    def ecef_to_ned(self, p_ecef_m) -> np.ndarray:
        return self.ecef_to_enu(p_ecef_m) @ R_NED_ENU.T

    def ned_to_ecef(self, p_ned_m) -> np.ndarray:
        return self.enu_to_ecef(np.asarray(p_ned_m, float) @ R_NED_ENU.T)

    # geodetic <-> ENU / NED
    def geodetic_to_enu(self, lat_deg, lon_deg, h_ellipsoid_m) -> np.ndarray:
        return self.ecef_to_enu(geodetic_to_ecef(lat_deg, lon_deg, h_ellipsoid_m))

    def enu_to_geodetic(self, p_enu_m):
        return ecef_to_geodetic(self.enu_to_ecef(p_enu_m))

    def geodetic_to_ned(self, lat_deg, lon_deg, h_ellipsoid_m) -> np.ndarray:
        return self.ecef_to_ned(geodetic_to_ecef(lat_deg, lon_deg, h_ellipsoid_m))

    def ned_to_geodetic(self, p_ned_m):
        return ecef_to_geodetic(self.ned_to_ecef(p_ned_m))
