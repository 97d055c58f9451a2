"""Building footprints (GeoJSON, OpenStreetMap) extruded into walls and roofs, standing on their own heights or
on the ground they are given."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from pyproj import CRS
from pyproj.exceptions import CRSError

from gis.geodesy import LocalFrame, msl_to_ellipsoid
from gis.loaders.common import _read_json, sample_polygon
from gis.loaders.georef import _transformer
from gis.loaders.raster import dem_heights_ellipsoid_m
from gis.model import BUILDING, GisFormatError, GisModel

log = logging.getLogger(__name__)


LEVEL_HEIGHT_M = 3.0            # height of one OSM building:level
DEFAULT_BUILDING_HEIGHT_M = 10.0  # footprint with neither height nor building:levels
#: what building footprints without heights stand on: the site's ground height above MSL (m), a
#: terrain model (GeoTIFF DTM), or nothing (such footprints are refused)
Ground = float | Path | None


def load_geojson(path: Path, sample_spacing_m: float = 1.0, ground: Ground = None,
                 doc: dict | None = None) -> GisModel:
    doc = doc if doc is not None else _read_json(path)
    feats = doc["features"] if doc.get("type") == "FeatureCollection" else [doc]
    to_lonlat = _geojson_legacy_crs(path, doc.get("crs"))
    footprints = []  # Footprint
    for i, f in enumerate(feats):
        try:
            g = f["geometry"]
            props = f.get("properties") or {}
            polys = [g["coordinates"]] if g["type"] == "Polygon" else g["coordinates"] if g["type"] == "MultiPolygon" else []
            height = _building_height(props)
            for poly in polys:
                rings = [to_lonlat(np.asarray(r, float)) for r in poly]
                if rings[0].ndim != 2 or len(rings[0]) < 4:
                    raise ValueError("polygon ring needs at least 4 positions")
                if np.any(np.abs(rings[0][:, 0]) > 180) or np.any(np.abs(rings[0][:, 1]) > 90):
                    raise ValueError("coordinates are not WGS 84 lon/lat (RFC 7946); projected ones need a 'crs' member")
                base = float(np.mean(rings[0][:, 2])) if rings[0].shape[1] > 2 else None
                footprints.append(Footprint(rings, base, float(props.get("min_height", 0.0)), height))
        except (KeyError, TypeError, ValueError) as e:
            raise GisFormatError(path, f"feature {i}: {type(e).__name__}: {e}") from None
    if not footprints:
        raise GisFormatError(path, "GeoJSON holds no Polygon/MultiPolygon footprints")
    return _extruded_buildings(path, footprints, sample_spacing_m, ground)


def _geojson_legacy_crs(path: Path, member) -> Callable[[np.ndarray], np.ndarray]:
    """RFC 7946 GeoJSON is WGS 84 lon/lat; the 2008 specification's ``crs`` member (still written by
    QGIS and GDAL for projected data: {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::28992"}})
    names another CRS. Returns the map from a ring's positions to lon/lat (third coordinate kept)."""
    if member is None:
        return lambda r: r
    try:
        crs = CRS.from_user_input(member["properties"]["name"])
    except (KeyError, TypeError, CRSError) as e:
        raise GisFormatError(path, f"unreadable 'crs' member {member!r}: {e}") from None
    if crs.equals(CRS.from_epsg(4326), ignore_axis_order=True):
        return lambda r: r
    try:
        to_geo = _transformer(crs.to_wkt())
    except ValueError as e:
        raise GisFormatError(path, f"cannot transform from {crs.name}: {e}") from None

    def to_lonlat(r: np.ndarray) -> np.ndarray:
        if r.ndim != 2 or r.shape[1] < 2:
            return r
        lon, lat, _ = to_geo.transform(r[:, 0], r[:, 1], np.zeros(len(r)))
        return np.column_stack([lon, lat, r[:, 2:]])
    return to_lonlat


def load_osm(path: Path, sample_spacing_m: float = 1.0, ground: Ground = None) -> GisModel:
    """OSM building footprints (PBF / XML) through pyosmium's area assembler (multipolygons, holes)."""
    import osmium

    footprints = []  # Footprint
    bad: list[str] = []  # unreadable height tags (crowd-sourced data: warn and use the fallback, not fail)

    class _Buildings(osmium.SimpleHandler):
        def area(self, a) -> None:
            tags = {t.k: t.v for t in a.tags}
            if "building" not in tags and "building:part" not in tags:
                return
            height, min_h = _osm_height(tags, bad), _osm_min_height(tags, bad)
            try:
                for outer in a.outer_rings():
                    rings = [np.array([(n.lon, n.lat) for n in r], float) for r in [outer, *a.inner_rings(outer)]]
                    footprints.append(Footprint(rings, None, min_h, height))
            except osmium.InvalidLocationError as e:
                kind = "way" if a.from_way() else "relation"
                raise GisFormatError(path, f"{kind} {a.orig_id()}: {type(e).__name__}: {e}") from None

    try:
        _Buildings().apply_file(str(path), locations=True)
    except RuntimeError as e:  # libosmium's parse errors (truncated / corrupt PBF, bad XML)
        raise GisFormatError(path, f"not a readable OSM file: {e}") from None
    if not footprints:
        raise GisFormatError(path, "OSM file holds no building areas (closed ways / multipolygons tagged building)")
    if bad:
        log.warning("%s: %d unreadable OSM height tags (e.g. %s) replaced by building:levels or %.0f m",
                    path, len(bad), ", ".join(bad[:3]), DEFAULT_BUILDING_HEIGHT_M)
    return _extruded_buildings(path, footprints, sample_spacing_m, ground)


def _osm_height(tags: dict, bad: list[str]) -> float:
    try:
        return _building_height(tags)
    except ValueError:
        bad.append(f"height={tags.get('height')!r} building:levels={tags.get('building:levels')!r}")
        try:
            return _building_height({"building:levels": tags.get("building:levels")})
        except (ValueError, TypeError):
            return DEFAULT_BUILDING_HEIGHT_M


def _osm_min_height(tags: dict, bad: list[str]) -> float:
    try:
        h = float(str(tags.get("min_height", "0")).rstrip(" m"))
        if np.isfinite(h) and h >= 0:
            return h
    except ValueError:
        pass
    bad.append(f"min_height={tags.get('min_height')!r}")
    return 0.0


@dataclass(frozen=True)
class Footprint:
    rings_lonlat: list[np.ndarray]  # outer ring first, then holes; (N, 2|3) lon_deg, lat_deg[, h]
    base_h_ellipsoid_m: float | None  # from the polygon's heights; None: ground + min_height
    min_height_m: float  # base above ground (OSM/GeoJSON ``min_height``)
    height_m: float  # top above ground


def _extruded_buildings(path: Path, footprints: list[Footprint], sample_spacing_m: float, ground: Ground) -> GisModel:
    """Footprints → walls + roofs in one model (local ENU frame at the footprints' centroid). A
    footprint without heights stands on ``ground``: the site's height above MSL, or a terrain model
    (GeoTIFF DTM) read at its outline's lowest vertex (on a slope its walls reach the ground);
    footprints outside the DTM or over its nodata are left out, with a warning."""
    all_ll = np.concatenate([f.rings_lonlat[0][:, :2] for f in footprints])
    lat_c, lon_c = float(all_ll[:, 1].mean()), float(all_ll[:, 0].mean())
    need = [i for i, f in enumerate(footprints) if f.base_h_ellipsoid_m is None]
    if need and ground is None:
        raise GisFormatError(path, "building footprints carry no heights: give the site's ground height "
                                   "(gis.footprint_ground_h_msl_m / --ground-h-msl-m) or a terrain model (gis.footprint_ground_dem)")
    bases: list[float | None] = [f.base_h_ellipsoid_m for f in footprints]
    if need and isinstance(ground, Path):
        rings = [footprints[i].rings_lonlat[0] for i in need]
        ll = np.concatenate(rings)
        h = dem_heights_ellipsoid_m(ground, ll[:, 0], ll[:, 1])
        for i, part in zip(need, np.split(h, np.cumsum([len(r) for r in rings])[:-1])):
            bases[i] = float(np.nanmin(part)) + footprints[i].min_height_m if np.isfinite(part).any() else None
    elif need:
        for i in need:
            f = footprints[i]
            lon, lat = f.rings_lonlat[0][:, 0].mean(), f.rings_lonlat[0][:, 1].mean()
            bases[i] = float(msl_to_ellipsoid(lat, lon, float(ground))) + f.min_height_m
    outside = sum(b is None for b in bases)
    if outside:
        log.warning("%s: %d footprints outside the terrain model %s (or over its nodata) left out", path, outside, ground)
    known = [b for b in bases if b is not None]
    if not known:
        raise GisFormatError(path, f"no footprint lies on the terrain model {ground}")
    origin = LocalFrame(lat_c, lon_c, float(np.mean(known)))
    pts, nrms, skipped = [], [], 0
    for f, base in zip(footprints, bases):
        if base is None:
            continue
        # a polygon with heights is extruded from them by height_m; else from min_height up to height_m (OSM)
        extent_m = f.height_m if f.base_h_ellipsoid_m is not None else f.height_m - f.min_height_m
        if extent_m <= 0:
            skipped += 1
            continue
        enu = [origin.geodetic_to_enu(r[:, 1], r[:, 0], np.full(len(r), base)) for r in f.rings_lonlat]
        p, n = extrude_footprint(enu, extent_m, sample_spacing_m)
        pts.append(p)
        nrms.append(n)
    if skipped:
        log.warning("%s: %d footprints skipped: min_height not below height", path, skipped)
    if not pts:
        raise GisFormatError(path, "no footprint with a positive height (min_height ≥ height everywhere)")
    p = np.concatenate(pts)
    return GisModel(p, np.concatenate(nrms), np.full(len(p), BUILDING, np.uint8), origin, "EPSG:4979", path)


def _building_height(props: dict) -> float:
    if props.get("height") is not None:
        h = float(str(props["height"]).rstrip(" m"))
    elif props.get("building:levels") is not None:
        h = float(props["building:levels"]) * LEVEL_HEIGHT_M
    else:
        h = DEFAULT_BUILDING_HEIGHT_M
    if not np.isfinite(h) or h <= 0:
        raise ValueError(f"building height must be > 0, got {h}")
    return h


def extrude_footprint(rings_enu: list[np.ndarray], height_m: float, spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Walls (outward normals) and a flat roof of a footprint (outer + hole rings in ENU at base height)."""
    pts, nrms = [], []
    outer = rings_enu[0]
    ccw = np.sum(outer[:-1, 0] * outer[1:, 1] - outer[1:, 0] * outer[:-1, 1]) > 0
    for k, ring in enumerate(rings_enu):
        sign = (1.0 if ccw else -1.0) * (1.0 if k == 0 else -1.0)
        a, b = ring[:-1], ring[1:]
        for a_i, b_i in zip(a, b):
            edge = b_i[:2] - a_i[:2]
            length = float(np.linalg.norm(edge))
            if length < 1e-6:
                continue
            s = (np.arange(max(1, int(length / spacing_m))) + 0.5) / max(1, int(length / spacing_m))
            z = np.arange(spacing_m / 2, height_m, spacing_m)
            ss, zz = np.meshgrid(s, z)
            wall = a_i + ss.reshape(-1, 1) * (b_i - a_i)
            wall[:, 2] = a_i[2] + zz.reshape(-1)
            out = sign * np.array([edge[1], -edge[0], 0.0]) / length
            pts.append(wall)
            nrms.append(np.broadcast_to(out, wall.shape))
    roof = [r + np.array([0.0, 0.0, height_m]) for r in rings_enu]
    p, _ = sample_polygon(roof[0], roof[1:], spacing_m)
    pts.append(p)
    nrms.append(np.broadcast_to(np.array([0.0, 0.0, 1.0]), p.shape))
    return np.concatenate(pts), np.concatenate(nrms)
