"""Load any supported GIS file into one :class:`gis.model.GisModel` (issue 5 §1).

Formats (dispatched on content, then extension):
- Triangle meshes PLY / OBJ / GLB / glTF, with a ``<file>.georef.json`` sidecar (CONTRIBUTING.md).
  GLB/glTF follow glTF's Y-up convention: file (x, y, z) is CRS (x, −z, y), as 3D Tiles do.
  Meshes are sampled on their surface (``sample_spacing_m``), normals are face normals, labels
  come from a ``classification``/``label`` vertex or face property when present.
- Point clouds PLY (sidecar) and LAS/LAZ (CRS from the WKT/GeoTIFF VLR, read by laspy + pyproj,
  in chunks, thinned to one point per sampling voxel), labels from the LAS classification; normals
  from the file or estimated (open3d, k-NN PCA).
- Digital surface / terrain models (GeoTIFF heights, read by rasterio): triangulated at the
  sampling spacing and sampled as a mesh (walls at height jumps); CRS from the GeoKeys, the
  heights' datum from a compound CRS or the sidecar's ``vertical``.
- CityJSON (``metadata.referenceSystem``) and CityJSONSeq (``.jsonl``): every surface of the
  highest LoD geometry of each city object (geometry templates instanced), labelled by object type.
- GeoJSON building footprints (WGS-84 lon/lat, RFC 7946), extruded by ``height`` (m) or by
  ``building:levels`` × 3 m, else ``DEFAULT_BUILDING_HEIGHT_M``; the base is the polygon's third
  coordinate (ellipsoidal height) if given, else ``ground`` + ``min_height``: the site's ground
  height above MSL (turned ellipsoidal with EGM96 at the footprint) or a terrain model (GeoTIFF
  DTM, read at the outline's lowest vertex). Footprints without heights and no ``ground`` are
  refused: a model at the wrong altitude would only be rejected later.
- OpenStreetMap files (.osm.pbf, .osm XML, .osm.bz2/.osm.gz), read by pyosmium: every area tagged
  ``building`` or ``building:part`` (closed ways and multipolygon relations, holes kept), extruded
  with the same height rules as GeoJSON (OSM carries no ground heights: ``ground`` is needed).
- A GisModel .npz as the GIS cache stores it (``terraslam gis import|fetch``; a site's model file).
- 3D Tiles 1.0/1.1 (``tileset.json`` with b3dm or glb content, as Cesium and Google Photorealistic
  3D Tiles serve them): the tiles of the coarsest level whose geometric error is at most the
  sampling spacing (finer detail would only be sampled away; ``refine`` REPLACE / ADD as the spec
  says), with tile transforms, RTC_CENTER / CESIUM_RTC, the glTF Y-up → Z-up rotation of the spec,
  and Draco-compressed meshes (KHR_draco_mesh_compression, decoded by trimesh with DracoPy);
  point cloud tiles (pnts) too, thinned to the sampling spacing.
  Content URIs may carry a query (``?session=…``); see gis.providers for HTTP.
- glTF files that require an extension changing geometry that we do not decode
  (EXT_meshopt_compression, KHR_mesh_quantization, …) are refused by name: trimesh would load
  placeholder zeros for them.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import os
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator
from urllib.parse import unquote, urlsplit

import numpy as np
import open3d as o3d
import trimesh
from matplotlib.path import Path as PolyPath
from pyproj import CRS, Transformer
from pyproj import datadir as pyproj_datadir
from pyproj.exceptions import CRSError, ProjError
from pyproj.transformer import TransformerGroup

from gis.geodesy import LocalFrame, R_ecef_enu, ecef_to_geodetic, geodetic_to_ecef, msl_to_ellipsoid
from gis.implicit_tiles import IMPLICIT, ImplicitTilingError, implicit_children, implicit_root
from gis.model import (
    BUILDING, GROUND, HIGH_VEGETATION, ROAD, UNCLASSIFIED,
    GisFormatError, GisModel, check_on_earth, frame_at_centroid, merge_models, model_from_ecef, model_from_npz,
)

log = logging.getLogger(__name__)
LEVEL_HEIGHT_M = 3.0            # height of one OSM building:level
DEFAULT_BUILDING_HEIGHT_M = 10.0  # footprint with neither height nor building:levels
#: glTF is Y-up; 3D Tiles and our georeferenced files are Z-up: (x, y, z)_gltf → (x, −z, y).
R_ZUP_YUP = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
_LABEL_KEYS = ("classification", "label", "class")
_CITYJSON_LABELS = {
    "Building": BUILDING, "BuildingPart": BUILDING, "BuildingInstallation": BUILDING,
    "Road": ROAD, "Railway": ROAD, "TransportSquare": ROAD,
    "TINRelief": GROUND, "LandUse": GROUND,
    "PlantCover": HIGH_VEGETATION, "SolitaryVegetationObject": HIGH_VEGETATION,
}


#: bump when a loader's output for the same file changes, so that imports cached by an older one
#: are not reused (``source_key``); 2: LAS thinning, 3D Tiles level of detail, cell-sorted points
LOADER_VERSION = 2


#: what building footprints without heights stand on: the site's ground height above MSL (m), a
#: terrain model (GeoTIFF DTM), or nothing (such footprints are refused)
Ground = float | Path | None


def load_model(path: Path | str, sample_spacing_m: float = 1.0, ground: Ground = None) -> GisModel:
    """Load a GIS model file (or a 3D Tiles directory) into a GisModel; GisFormatError on bad input.
    ``ground``: what building footprints that carry no heights stand on (``Ground``).
    The points come stored cell by cell of the crop index (``GisModel.sorted_by_cell``), as the
    GIS cache keeps and maps them: a model read from its file and one mapped from the cache are
    the same arrays, so a flight's registrations replay bit for bit from either."""
    return _load_model(Path(path).expanduser(), sample_spacing_m, ground).sorted_by_cell


def source_key(path: Path | str, sample_spacing_m: float, ground: Ground) -> str:
    """A SHA-256 naming what ``load_model`` would make of path with these settings: the file's (or,
    for a 3D Tiles directory, every file's) size and modification time, a mesh's georeference
    sidecar, the settings (a terrain model for footprints: its files too) and LOADER_VERSION.
    Equal keys: the cached import can stand in for
    loading the file again (gis.cache ``imported``)."""
    path = Path(path).expanduser().resolve()
    files = sorted(f for f in path.rglob("*") if f.is_file()) if path.is_dir() else \
        [f for f in (path, path.with_name(path.name + ".georef.json")) if f.is_file()]
    if not files:
        raise GisFormatError(path, "no such file")
    stats = [[str(f.relative_to(path.parent)), f.stat().st_size, f.stat().st_mtime_ns] for f in files]
    ground_doc = source_key(ground, 0.0, None) if isinstance(ground, Path) else ground
    doc = {"path": str(path), "files": stats, "sample_spacing_m": sample_spacing_m, "ground": ground_doc,
           "loader_version": LOADER_VERSION}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def _load_model(path: Path, sample_spacing_m: float, ground: Ground) -> GisModel:
    if path.is_dir():
        if (path / "tileset.json").is_file():
            return load_3dtiles(path / "tileset.json", sample_spacing_m)
        raise GisFormatError(path, "directory without a tileset.json (only 3D Tiles come as directories)")
    if not path.is_file():
        raise GisFormatError(path, "no such file")
    name = path.name.lower()
    if name.endswith((".pbf", ".osm", ".osm.bz2", ".osm.gz")):
        return load_osm(path, sample_spacing_m, ground)
    if name.endswith(".jsonl"):
        return load_cityjson_seq(path, sample_spacing_m)
    if name.endswith(".npz"):  # a GisModel as the GIS cache stores it (a site's model file)
        return model_from_npz(path)
    with open(path, "rb") as f:
        head = f.read(16)
    if head.startswith(b"ply"):
        return load_ply(path, sample_spacing_m)
    if head.startswith(b"LASF"):
        return load_las(path, sample_spacing_m)
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):  # TIFF / BigTIFF
        return load_geotiff(path, sample_spacing_m)
    if head.startswith(b"glTF"):
        return load_mesh(path, sample_spacing_m)
    if head.startswith(b"b3dm"):
        raise GisFormatError(path, "a lone b3dm tile has no georeference; load the tileset.json that references it")
    if name.endswith(".obj") or name.endswith(".gltf"):
        return load_mesh(path, sample_spacing_m)
    if head.lstrip()[:1] in (b"{", b"["):
        doc = _read_json(path)
        kind = doc.get("type") if isinstance(doc, dict) else None
        if kind == "CityJSON":
            return load_cityjson(path, sample_spacing_m, doc)
        if kind in ("FeatureCollection", "Feature"):
            return load_geojson(path, sample_spacing_m, ground, doc)
        if isinstance(doc, dict) and "asset" in doc and "root" in doc:
            return load_3dtiles(path, sample_spacing_m)
        raise GisFormatError(path, f"JSON is neither CityJSON, GeoJSON nor a 3D Tiles tileset (type={kind!r})")
    if name.endswith((".las", ".laz")):
        raise GisFormatError(path, "not a LAS/LAZ file (missing 'LASF' signature)")
    raise GisFormatError(path, "unsupported or unrecognised GIS format (PLY, OBJ, GLB/glTF, LAS/LAZ, GeoTIFF, CityJSON, GeoJSON, OSM, 3D Tiles)")


# --- georeference ---------------------------------------------------------------------------

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


def estimate_normals(p_enu: np.ndarray, radius_m: float) -> np.ndarray:
    """Per-point normals by local PCA (open3d), oriented upward where the sign is free."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p_enu))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=12))  # 12: half the time of 30, planes are as good
    pcd.orient_normals_to_align_with_direction(np.array([0.0, 0.0, 1.0]))
    return np.asarray(pcd.normals)


# --- meshes and PLY point clouds -----------------------------------------------------------

def load_ply(path: Path, sample_spacing_m: float = 1.0) -> GisModel:
    return load_mesh(path, sample_spacing_m)


def load_mesh(path: Path, sample_spacing_m: float = 1.0) -> GisModel:
    """PLY/OBJ/GLB/glTF mesh or PLY point cloud + georef sidecar."""
    crs, offset, vertical = read_georef(path)
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
        return _georeferenced(path, p[keep], None if n is None else n[keep], labels[keep], crs, offset, vertical, sample_spacing_m)
    if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
        raise GisFormatError(path, f"no triangles or points found ({type(geom).__name__})")
    p, n, face_idx = sample_mesh(geom, sample_spacing_m)
    labels = _mesh_labels(geom, face_idx)
    if is_gltf:
        p, n = p @ R_ZUP_YUP.T, n @ R_ZUP_YUP.T
    return _georeferenced(path, p, n, labels, crs, offset, vertical, sample_spacing_m)


def sample_mesh(mesh: trimesh.Trimesh, spacing_m: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Uniform surface samples (about one per spacing_m²), their face normals and face indices."""
    area = float(mesh.area)
    if not np.isfinite(area) or area <= 0:
        raise ValueError("mesh has zero or non-finite surface area")
    count = max(int(np.ceil(area / spacing_m**2)), len(mesh.faces))
    p, face_idx = trimesh.sample.sample_surface(mesh, count, seed=seed)
    normals = np.asarray(mesh.face_normals)[face_idx]
    return np.asarray(p, float), normals, np.asarray(face_idx)


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


# --- LAS / LAZ ------------------------------------------------------------------------------

#: ASPRS classes that are not surfaces: 7 low point (noise), 18 high noise (birds, multipath)
LAS_NOISE_CLASSES = (7, 18)
#: points read from a LAS/LAZ file at a time (bounded memory on a companion board: ~100 MB per chunk)
LAS_CHUNK_POINTS = 2_000_000


def load_las(path: Path, sample_spacing_m: float = 1.0) -> GisModel:
    """A LAS/LAZ point cloud, thinned to its first point in each sample_spacing_m voxel (file
    coordinates) as it is read chunk by chunk: airborne surveys hold 10–50 points per m², which no
    registration here uses (the fine-tuner voxelises its crop at ``target_voxel_m``), and a 1 km²
    tile read whole would need several GB. A cloud sparser than the spacing keeps all its points.
    Noise (classes 7, 18) and withheld points are dropped: they are no surface to register to."""
    import laspy

    pts, labs = [], []
    try:
        with laspy.open(path) as f:
            crs = f.header.parse_crs()
            if crs is None:
                raise GisFormatError(path, "LAS/LAZ has no CRS VLR (WKT or GeoTIFF keys); cannot georeference")
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
    return _georeferenced(path, p, None, labels, crs, np.zeros(3), "ellipsoid", max(_median_spacing(p), sample_spacing_m))


def first_per_voxel(p: np.ndarray, voxel_m: float) -> np.ndarray:
    """Sorted indices of the first point in each voxel_m cube of a grid fixed in the coordinates
    (so that chunks thinned apart agree), keeping the points themselves, not voxel centroids:
    they stay on the surveyed surface and keep their labels."""
    keys = np.floor(p / voxel_m).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first)


def _median_spacing(p: np.ndarray) -> float:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p[:: max(1, len(p) // 2000)] - p.mean(axis=0)))
    d = np.asarray(pcd.compute_nearest_neighbor_distance())
    return float(np.median(d)) if len(d) and np.median(d) > 0 else 1.0


# --- rasters: digital surface / terrain models -----------------------------------------------

#: output pixels per side of the blocks a raster is read and triangulated in (bounded memory)
RASTER_BLOCK_PX = 256


def load_geotiff(path: Path, sample_spacing_m: float = 1.0) -> GisModel:
    """A digital surface or terrain model (GeoTIFF, heights in band 1) as the surface it describes:
    every k-th pixel (k: the pixels per sampling spacing; picked, not averaged, so no height between
    a roof and the ground is invented), triangulated cell by cell in ECEF and sampled as a mesh is,
    so that the jump at a building's edge becomes a wall. Nodata pixels leave holes. Read in blocks.
    CRS from the file's GeoKeys (else the ``.georef.json`` sidecar's ``crs``); the heights' datum
    from a compound CRS, else the sidecar's ``vertical`` ("egm96" for most DEMs, or "ellipsoid"):
    a DEM without it is refused, as its heights are usually above the geoid, not the ellipsoid."""
    import rasterio
    from rasterio.windows import Window

    with _raster(path) as (ds, crs, vertical):
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
                mesh = _heightfield_ecef(path, ds.transform, r, c, z, crs, vertical)
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
    """(the open rasterio dataset, its CRS, the heights' datum: ``_raster_georef``)."""
    import rasterio

    try:
        ds = rasterio.open(path)
    except rasterio.errors.RasterioIOError as e:
        raise GisFormatError(path, f"cannot read GeoTIFF: {e}") from None
    with ds:
        yield ds, *_raster_georef(path, ds)


def _pixel_size_m(ds, crs: CRS) -> float:
    """The raster's smaller pixel side in metres: degrees of a geographic CRS (SRTM, Copernicus DEM)
    by the length of a degree at the raster's centre, other units (US feet) by their factor."""
    rx, ry = abs(ds.res[0]), abs(ds.res[1])
    if crs.is_geographic:
        lat = np.radians((ds.bounds.bottom + ds.bounds.top) / 2)
        return float(min(rx * 111_320.0 * np.cos(lat), ry * 110_574.0))
    return float(min(rx, ry) * crs.axis_info[0].unit_conversion_factor)


def _raster_georef(path: Path, ds) -> tuple[CRS, str]:
    side = path.with_name(path.name + ".georef.json")
    doc = _read_json(side) if side.is_file() else {}
    try:
        crs = CRS.from_user_input(doc["crs"]) if "crs" in doc else CRS.from_wkt(ds.crs.to_wkt()) if ds.crs else None
    except CRSError as e:
        raise GisFormatError(side if "crs" in doc else path, f"bad CRS: {e}") from None
    if crs is None:
        raise GisFormatError(path, f"GeoTIFF has no CRS (GeoKeys); give it in {side.name}: {{\"crs\": ..., \"vertical\": ...}}")
    if len(crs.axis_info) >= 3:
        return crs, "ellipsoid"  # the CRS carries its vertical datum (crs_to_ecef lets PROJ apply it)
    vertical = doc.get("vertical")
    if vertical not in ("egm96", "ellipsoid"):
        raise GisFormatError(path, f"the heights' datum is unknown ({crs.name} is 2D): say it in {side.name}, "
                                   "{\"vertical\": \"egm96\"} (most DEMs: above the geoid) or \"ellipsoid\"")
    return crs, vertical


def _heightfield_ecef(path: Path, T_px, rows: np.ndarray, cols: np.ndarray, z: np.ma.MaskedArray, crs: CRS,
                      vertical: str) -> trimesh.Trimesh | None:
    """The grid of picked pixel centres (rows × cols of the raster, heights z) as a triangle mesh in
    ECEF: two triangles per cell whose four corners hold heights."""
    valid = ~np.ma.getmaskarray(z) & np.isfinite(np.ma.getdata(z))
    cell = valid[:-1, :-1] & valid[1:, :-1] & valid[:-1, 1:] & valid[1:, 1:]
    if not cell.any():
        return None
    cc, rr = np.meshgrid(cols + 0.5, rows + 0.5)
    x, y = T_px @ (cc.ravel(), rr.ravel())  # affine: pixel centre → CRS
    try:
        v = crs_to_ecef(np.column_stack([x, y, np.ma.getdata(z).ravel().astype(float)]), crs, vertical)
    except ValueError as e:
        raise GisFormatError(path, f"cannot transform from {crs.name}: {e}") from None
    w = len(cols)
    i, j = np.nonzero(cell)
    a, b, c, d = i * w + j, i * w + j + 1, (i + 1) * w + j, (i + 1) * w + j + 1
    faces = np.concatenate([np.column_stack([a, c, b]), np.column_stack([b, c, d])])
    return trimesh.Trimesh(v, faces, process=False)


# --- polygons (CityJSON surfaces, GeoJSON footprints) ---------------------------------------

def sample_polygon(outer: np.ndarray, holes: list[np.ndarray], spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Grid samples (spacing_m) inside a planar 3D polygon with holes, and its Newell normal.

    The polygon is projected on its own plane and tested with matplotlib's point-in-polygon, so
    concave footprints and holes need no triangulation library.
    """
    outer = np.asarray(outer, float)
    nrm = np.cross(outer, np.roll(outer, -1, axis=0)).sum(axis=0)  # Newell's method
    if np.linalg.norm(nrm) < 1e-12:
        return np.zeros((0, 3)), np.zeros(3)
    nrm /= np.linalg.norm(nrm)
    u = np.cross(nrm, [0.0, 0.0, 1.0] if abs(nrm[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(nrm, u)
    o = outer.mean(axis=0)
    to2 = lambda r: np.stack([(r - o) @ u, (r - o) @ v], axis=1)  # noqa: E731
    o2 = to2(outer)
    lo, hi = o2.min(axis=0), o2.max(axis=0)
    gu = np.arange(lo[0] + spacing_m / 2, hi[0], spacing_m)
    gv = np.arange(lo[1] + spacing_m / 2, hi[1], spacing_m)
    g = np.stack(np.meshgrid(gu, gv), axis=-1).reshape(-1, 2)
    inside = PolyPath(o2).contains_points(g) if len(g) else np.zeros(0, bool)
    for h in holes:
        if len(g):
            inside &= ~PolyPath(to2(np.asarray(h, float))).contains_points(g)
    g = g[inside]
    if len(g) == 0:  # smaller than one grid cell: keep its centroid
        g = o2.mean(axis=0, keepdims=True)
    return o + g[:, :1] * u + g[:, 1:] * v, nrm


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
    return _georeferenced(path, p, n, np.concatenate(labs), crs, np.zeros(3), "ellipsoid", sample_spacing_m)


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


def dem_heights_ellipsoid_m(dem: Path, lon_deg: np.ndarray, lat_deg: np.ndarray) -> np.ndarray:
    """Ellipsoidal heights (m) of a GeoTIFF terrain model at WGS-84 positions (its pixel there, no
    interpolation); NaN outside it or over nodata. CRS and the heights' datum as ``load_geotiff``."""
    with _raster(dem) as (ds, crs, vertical):
        horizontal = crs.sub_crs_list[0] if crs.is_compound else crs
        x, y = Transformer.from_crs("EPSG:4326", horizontal, always_xy=True).transform(lon_deg, lat_deg)
        samples = list(ds.sample(zip(x, y), masked=True))
        nodata = np.array([bool(np.ma.getmaskarray(v)[0]) for v in samples], bool)
        z = np.array([float(np.ma.getdata(v)[0]) for v in samples]) * ds.scales[0] + ds.offsets[0]
    ok = ~nodata & np.isfinite(z)
    h = np.full(len(x), np.nan)
    if ok.any():
        try:
            ecef = crs_to_ecef(np.column_stack([np.asarray(x)[ok], np.asarray(y)[ok], z[ok]]), crs, vertical)
        except ValueError as e:
            raise GisFormatError(dem, f"cannot transform from {crs.name}: {e}") from None
        h[ok] = ecef_to_geodetic(ecef)[2]
    return h


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


# --- 3D Tiles --------------------------------------------------------------------------------

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


def _read_json(path: Path):
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise GisFormatError(path, f"invalid JSON: {e}") from None


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
