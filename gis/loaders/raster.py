"""Digital surface / terrain models (GeoTIFF, rasterio): the surface they describe, and a terrain model's
heights at given positions (what building footprints stand on)."""
from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import trimesh
from pyproj import CRS, Transformer

from gis.geodesy import ecef_to_geodetic
from gis.loaders.georef import crs_to_ecef
from gis.loaders.heights import Georef, georef_of, read_sidecar
from gis.model import UNCLASSIFIED, GisFormatError, GisModel, model_from_ecef

#: output pixels per side of the blocks a raster is read and triangulated in (bounded memory)
RASTER_BLOCK_PX = 256


def load_geotiff(path: Path, sample_spacing_m: float = 1.0) -> GisModel:
    """A digital surface or terrain model (GeoTIFF, heights in band 1) as the surface it describes:
    every k-th pixel (k: the pixels per sampling spacing; picked, not averaged, so no height between
    a roof and the ground is invented), triangulated cell by cell in ECEF and sampled as a mesh is,
    so that the jump at a building's edge becomes a wall. Nodata pixels leave holes. Read in blocks.
    CRS from the file's GeoKeys (else the ``.georef.json`` sidecar's ``crs``); the heights' datum
    from a compound CRS, else the sidecar's ``vertical`` ("egm96" for most DEMs, "ellipsoid", or a
    vertical CRS) and ``vertical_unit``; the sidecar's ``offset_m`` is added (gis.loaders.heights):
    a DEM without it is refused, as its heights are usually above the geoid, not the ellipsoid."""
    import rasterio
    from rasterio.windows import Window

    with _raster(path) as (ds, g):
        crs = g.crs
        k = max(1, int(round(sample_spacing_m / _pixel_size_m(ds, crs))))
        scale, offset = ds.scales[0], ds.offsets[0]  # stored value → height (GDAL band scale/offset: packed int16 DEMs)
        rows, cols = np.arange(k // 2, ds.height, k), np.arange(k // 2, ds.width, k)  # picked pixels
        pts, nrms, up_sign = [], [], 0.0
        for bi in range(0, len(rows) - 1, RASTER_BLOCK_PX):
            for bj in range(0, len(cols) - 1, RASTER_BLOCK_PX):
                r, c = rows[bi:bi + RASTER_BLOCK_PX + 1], cols[bj:bj + RASTER_BLOCK_PX + 1]  # one pixel of overlap
                win = Window(int(c[0]), int(r[0]), int(c[-1] - c[0] + 1), int(r[-1] - r[0] + 1))
                try:
                    z = ds.read(1, window=win, masked=True)[(r - r[0])[:, None], (c - c[0])[None, :]] * scale + offset
                except rasterio.errors.RasterioIOError as e:
                    raise GisFormatError(path, f"cannot read GeoTIFF block at row {r[0]}, column {c[0]}: {e}") from None
                mesh = _heightfield_ecef(path, ds.transform, r, c, z, g)
                if mesh is None:
                    continue
                # one sample per spacing² (sample_mesh's floor of one per face would double it: two triangles a cell)
                p, f = trimesh.sample.sample_surface(mesh, int(np.ceil(mesh.area / sample_spacing_m**2)), seed=0)
                p, n = np.asarray(p, float), np.asarray(mesh.face_normals)[f]
                up = p / np.linalg.norm(p, axis=1, keepdims=True)  # ellipsoid normal ≈ geocentric up (a 0.2° difference at most)
                up_sign = up_sign or float(np.sign(np.median(np.einsum("ij,ij->i", n, up))))
                pts.append(p)
                nrms.append(n)
    if not pts:
        raise GisFormatError(path, "GeoTIFF holds no valid heights (all nodata?)")
    n = np.concatenate(nrms) * (up_sign or 1.0)  # one winding for the whole raster: roofs and ground face up
    return model_from_ecef(np.concatenate(pts), n, np.full(sum(map(len, pts)), UNCLASSIFIED, np.uint8), crs.to_string(), path)


@contextlib.contextmanager
def _raster(path: Path):
    """(the open rasterio dataset, its Georef: ``_raster_georef``)."""
    import rasterio

    try:
        ds = rasterio.open(path)
    except rasterio.errors.RasterioIOError as e:
        raise GisFormatError(path, f"cannot read GeoTIFF: {e}") from None
    with ds:
        yield ds, _raster_georef(path, ds)


def _pixel_size_m(ds, crs: CRS) -> float:
    """The raster's smaller pixel side in metres: degrees of a geographic CRS (SRTM, Copernicus DEM)
    by the length of a degree at the raster's centre, other units (US feet) by their factor."""
    rx, ry = abs(ds.res[0]), abs(ds.res[1])
    if crs.is_geographic:
        lat = np.radians((ds.bounds.bottom + ds.bounds.top) / 2)
        return float(min(rx * 111_320.0 * np.cos(lat), ry * 110_574.0))
    return float(min(rx, ry) * crs.axis_info[0].unit_conversion_factor)


def _raster_georef(path: Path, ds) -> Georef:
    """The GeoTIFF's CRS (its GeoKeys, or the sidecar's ``crs``) and its heights' datum and unit."""
    file_crs = CRS.from_wkt(ds.crs.to_wkt()) if ds.crs else None
    return georef_of(path, "GeoTIFF", file_crs, read_sidecar(path, "GeoTIFF"))


def _heightfield_ecef(path: Path, T_px, rows: np.ndarray, cols: np.ndarray, z: np.ma.MaskedArray,
                      g: Georef) -> trimesh.Trimesh | None:
    """The grid of picked pixel centres (rows × cols of the raster, heights z) as a triangle mesh in
    ECEF: two triangles per cell whose four corners hold heights."""
    valid = ~np.ma.getmaskarray(z) & np.isfinite(np.ma.getdata(z))
    cell = valid[:-1, :-1] & valid[1:, :-1] & valid[:-1, 1:] & valid[1:, 1:]
    if not cell.any():
        return None
    cc, rr = np.meshgrid(cols + 0.5, rows + 0.5)
    x, y = T_px @ (cc.ravel(), rr.ravel())  # affine: pixel centre → file coordinates
    try:
        v = crs_to_ecef(np.column_stack([x, y, np.ma.getdata(z).ravel().astype(float)]) + g.offset, g.crs, g.vertical,
                        g.height_unit_m)
    except ValueError as e:
        raise GisFormatError(path, f"cannot transform from {g.crs.name}: {e}") from None
    w = len(cols)
    i, j = np.nonzero(cell)
    a, b, c, d = i * w + j, i * w + j + 1, (i + 1) * w + j, (i + 1) * w + j + 1
    faces = np.concatenate([np.column_stack([a, c, b]), np.column_stack([b, c, d])])
    return trimesh.Trimesh(v, faces, process=False)


def dem_heights_ellipsoid_m(dem: Path, lon_deg: np.ndarray, lat_deg: np.ndarray) -> np.ndarray:
    """Ellipsoidal heights (m) of a GeoTIFF terrain model at WGS-84 positions (its pixel there, no
    interpolation); NaN outside it or over nodata. CRS and the heights' datum as ``load_geotiff``."""
    with _raster(dem) as (ds, g):
        crs = g.crs
        horizontal = crs.sub_crs_list[0] if crs.is_compound else crs
        x, y = Transformer.from_crs("EPSG:4326", horizontal, always_xy=True).transform(lon_deg, lat_deg)
        samples = list(ds.sample(zip(np.asarray(x) - g.offset[0], np.asarray(y) - g.offset[1]), masked=True))
        nodata = np.array([bool(np.ma.getmaskarray(v)[0]) for v in samples], bool)
        z = np.array([float(np.ma.getdata(v)[0]) for v in samples]) * ds.scales[0] + ds.offsets[0]
    ok = ~nodata & np.isfinite(z)
    h = np.full(len(x), np.nan)
    if ok.any():
        try:
            ecef = crs_to_ecef(np.column_stack([np.asarray(x)[ok], np.asarray(y)[ok], z[ok] + g.offset[2]]), crs, g.vertical,
                               g.height_unit_m)
        except ValueError as e:
            raise GisFormatError(dem, f"cannot transform from {crs.name}: {e}") from None
        h[ok] = ecef_to_geodetic(ecef)[2]
    return h
