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
- Heights (every format with a CRS of its own): their vertical datum and unit are read where the
  file states them (a compound or 3D CRS, a LAS file's vertical GeoKeys), else from the sidecar's
  ``vertical`` / ``vertical_unit``; a file stating neither is refused (gis.loaders.heights).
- glTF files that require an extension changing geometry that we do not decode
  (EXT_meshopt_compression, KHR_mesh_quantization, …) are refused by name: trimesh would load
  placeholder zeros for them.

One module per format family: ``mesh`` (PLY/OBJ/glTF), ``las``, ``raster`` (GeoTIFF), ``cityjson``,
``footprints`` (GeoJSON, OSM), ``tiles`` (3D Tiles); ``georef`` (sidecar, CRS → ECEF, vertical datums)
and ``common`` (sampling, thinning) are what they share. This module dispatches a file to its loader.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

from gis.loaders.cityjson import load_cityjson, load_cityjson_seq
from gis.loaders.common import _read_json
from gis.loaders.common import sample_mesh as sample_mesh
from gis.loaders.footprints import DEFAULT_BUILDING_HEIGHT_M as DEFAULT_BUILDING_HEIGHT_M
from gis.loaders.footprints import LEVEL_HEIGHT_M as LEVEL_HEIGHT_M
from gis.loaders.footprints import Ground, load_geojson, load_osm
from gis.loaders.heights import no_sidecar
from gis.loaders.las import load_las
from gis.loaders.mesh import load_mesh, load_ply
from gis.loaders.raster import dem_heights_ellipsoid_m as dem_heights_ellipsoid_m
from gis.loaders.raster import load_geotiff
from gis.loaders.tiles import load_3dtiles
from gis.loaders.tiles import tileset_contents as tileset_contents
from gis.model import GisFormatError, GisModel, model_from_npz

#: bump when a loader's output for the same file changes, so that imports cached by an older one
#: are not reused (``source_key``); 2: LAS thinning, 3D Tiles level of detail, cell-sorted points;
#: 3: heights' datum and unit read or refused (gis.loaders.heights), a GeoTIFF's sidecar offset_m added
LOADER_VERSION = 3


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
        no_sidecar(path, "OSM")
        return load_osm(path, sample_spacing_m, ground)
    if name.endswith(".jsonl"):
        return load_cityjson_seq(path, sample_spacing_m)
    if name.endswith(".npz"):  # a GisModel as the GIS cache stores it (a site's model file)
        no_sidecar(path, "GisModel .npz")
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
            no_sidecar(path, "GeoJSON")
            return load_geojson(path, sample_spacing_m, ground, doc)
        if isinstance(doc, dict) and "asset" in doc and "root" in doc:
            no_sidecar(path, "3D Tiles")
            return load_3dtiles(path, sample_spacing_m)
        raise GisFormatError(path, f"JSON is neither CityJSON, GeoJSON nor a 3D Tiles tileset (type={kind!r})")
    if name.endswith((".las", ".laz")):
        raise GisFormatError(path, "not a LAS/LAZ file (missing 'LASF' signature)")
    raise GisFormatError(path, "unsupported or unrecognised GIS format (PLY, OBJ, GLB/glTF, LAS/LAZ, GeoTIFF, CityJSON, GeoJSON, OSM, 3D Tiles)")
