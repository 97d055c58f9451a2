"""LAS/LAZ point clouds (laspy), read in chunks and thinned as they are read."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from pyproj import CRS
from pyproj.exceptions import CRSError

from gis.loaders.common import _median_spacing, first_per_voxel
from gis.loaders.georef import _georeferenced
from gis.loaders.heights import georef_of, read_sidecar
from gis.model import GisFormatError, GisModel

#: ASPRS classes that are not surfaces: 7 low point (noise), 18 high noise (birds, multipath)
LAS_NOISE_CLASSES = (7, 18)
#: points read from a LAS/LAZ file at a time (bounded memory on a companion board: ~100 MB per chunk)
LAS_CHUNK_POINTS = 2_000_000


def load_las(path: Path, sample_spacing_m: float = 1.0) -> GisModel:
    """A LAS/LAZ point cloud, thinned to its first point in each sample_spacing_m voxel (file
    coordinates) as it is read chunk by chunk: airborne surveys hold 10–50 points per m², which no
    registration here uses (the fine-tuner voxelises its crop at ``target_voxel_m``), and a 1 km²
    tile read whole would need several GB. A cloud sparser than the spacing keeps all its points.
    Noise (classes 7, 18) and withheld points are dropped: they are no surface to register to.
    Heights: a compound CRS's, the vertical GeoKeys', else the sidecar's (gis.loaders.heights)."""
    import laspy

    pts, labs = [], []
    try:
        with laspy.open(path) as f:
            crs = f.header.parse_crs()
            if crs is None:
                raise GisFormatError(path, "LAS/LAZ has no CRS VLR (WKT or GeoTIFF keys); cannot georeference")
            georef = georef_of(path, "LAS/LAZ", crs, read_sidecar(path, "LAS/LAZ"), *_vertical_geokeys(path, f.header))
            for chunk in f.chunk_iterator(LAS_CHUNK_POINTS):
                cls = np.asarray(chunk.classification).astype(np.uint8)
                good = ~np.isin(cls, LAS_NOISE_CLASSES) & ~np.asarray(chunk.withheld, bool)
                xyz = np.column_stack([chunk.x, chunk.y, chunk.z]).astype(float)[good]  # scaled + offset
                keep = first_per_voxel(xyz, sample_spacing_m)
                pts.append(xyz[keep])
                labs.append(cls[good][keep])
    except GisFormatError:
        raise
    except Exception as e:  # laspy raises LaspyException, ValueError, struct errors...
        raise GisFormatError(path, f"cannot parse LAS/LAZ: {type(e).__name__}: {e}") from None
    p = np.concatenate(pts) if pts else np.zeros((0, 3))
    if len(p) == 0:
        raise GisFormatError(path, "LAS/LAZ holds no points (after dropping noise and withheld ones)")
    keep = first_per_voxel(p, sample_spacing_m)  # voxels that straddle two chunks
    p, labels = p[keep], np.concatenate(labs)[keep]
    return _georeferenced(path, p, None, labels, georef, max(_median_spacing(p), sample_spacing_m))


#: GeoTIFF keys (OGC 19-008r4) a LAS file's GeoKeyDirectory VLR may state its heights by, which laspy's
#: parse_crs does not read: VerticalCRSGeoKey (an EPSG vertical CRS) and VerticalUnitsGeoKey (EPSG
#: unit codes: 9001 metre, 9002 foot, 9003 US survey foot)
VERTICAL_CRS_GEOKEY, VERTICAL_UNITS_GEOKEY = 4096, 4099
_GEOKEY_UNITS_M = {9001: 1.0, 9002: 0.3048, 9003: 1200.0 / 3937.0}


def _vertical_geokeys(path: Path, header) -> tuple[CRS | None, float | None]:
    """(the vertical CRS, metres per height unit) a GeoKeyDirectory VLR states (None for what it
    does not); a WKT VLR, which laspy prefers, states its heights in its own CRS."""
    from laspy.vlrs.known import GeoKeyDirectoryVlr, WktCoordinateSystemVlr

    vlrs = list(header.vlrs) + list(header.evlrs or [])
    if any(isinstance(v, WktCoordinateSystemVlr) for v in vlrs):
        return None, None
    keys = {k.id: k.value_offset for v in vlrs if isinstance(v, GeoKeyDirectoryVlr) for k in v.geo_keys}
    vertical, unit = keys.get(VERTICAL_CRS_GEOKEY), keys.get(VERTICAL_UNITS_GEOKEY)
    if unit is not None and unit not in _GEOKEY_UNITS_M:
        raise GisFormatError(path, f"VerticalUnitsGeoKey {unit} is not metre (9001), foot (9002) or US survey foot (9003)")
    if vertical is None or vertical == 32767:  # (user-defined: only its unit is stated)
        return None, None if unit is None else _GEOKEY_UNITS_M[unit]
    try:
        v = CRS.from_epsg(vertical)
    except CRSError as e:
        raise GisFormatError(path, f"VerticalCRSGeoKey {vertical} is no EPSG vertical CRS: {e}") from None
    if not v.is_vertical:
        raise GisFormatError(path, f"VerticalCRSGeoKey {vertical} names a {v.type_name}, not a vertical CRS")
    return v, None
