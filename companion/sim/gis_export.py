"""Export a world (usually its stale GIS variant) as real GIS files with a CRS.

- ``model.ply`` triangle mesh (binary PLY, per-face ``classification`` = ASPRS code) with its
  ``model.ply.georef.json`` sidecar (CONTRIBUTING.md): UTM coordinates minus ``offset_m``,
  ellipsoidal heights.
- ``model.laz`` point cloud (LAS 1.4, point format 6) with ASPRS classification and a WKT CRS VLR
  (UTM, 2D: there is no EPSG vertical CRS for ellipsoidal heights), its heights stated in the
  ``model.laz.georef.json`` sidecar: ellipsoidal, metres.
- ``buildings.geojson`` footprints (RFC 7946 lon/lat; third coordinate = ellipsoidal height of the
  footprint base) with ``height`` (m above base), ``min_height`` and MSL heights as properties.
Every vertex goes ENU → geodetic → UTM through PROJ (no flat-earth shortcut).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np
import trimesh
from pyproj import CRS, Transformer

from companion.sim.world import World
from gis.geodesy import LocalFrame, ellipsoid_to_msl


@dataclass(frozen=True)
class GisFiles:
    mesh_ply: Path
    points_laz: Path
    buildings_geojson: Path
    crs: str


def utm_crs(lat_deg: float, lon_deg: float) -> str:
    zone = int((lon_deg + 180) // 6) + 1
    return f"EPSG:{(32600 if lat_deg >= 0 else 32700) + zone}"


def enu_to_crs(origin: LocalFrame, p_enu: np.ndarray, crs: str) -> np.ndarray:
    """ENU (N, 3) → (easting, northing, h_ellipsoid) in a projected CRS."""
    lat, lon, h = origin.enu_to_geodetic(p_enu)
    tr = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    e, n = tr.transform(lon, lat)
    return np.stack([e, n, h], axis=-1)


def write_mesh_ply(world: World, path: Path, crs: str) -> Path:
    m = world.mesh
    p = enu_to_crs(world.origin, m.vertices, crs)
    offset = np.round(p.mean(axis=0), 0)
    mesh = trimesh.Trimesh(vertices=p - offset, faces=m.triangles, process=False)
    mesh.face_attributes["classification"] = m.labels.astype(np.uint8)
    path.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="binary", include_attributes=True))
    side = path.with_name(path.name + ".georef.json")
    side.write_text(json.dumps({"crs": crs, "offset_m": offset.tolist(), "vertical": "ellipsoid"}, indent=2) + "\n")
    return path


def write_points_las(world: World, path: Path, crs: str, spacing_m: float = 1.0, margin_m: float = 150.0,
                     seed: int = 0) -> Path:
    """Area-uniform samples of the model surface (within the site + margin) as LAS/LAZ."""
    pts, labels = world.gis_points_enu(spacing_m, seed=seed)
    lim = world.site_half_m + margin_m
    keep = (np.abs(pts[:, 0]) <= lim) & (np.abs(pts[:, 1]) <= lim)
    pts, labels = pts[keep], labels[keep]
    p = enu_to_crs(world.origin, pts, crs)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets = np.floor(p.min(axis=0))
    header.scales = np.array([0.001, 0.001, 0.001])
    header.add_crs(CRS.from_user_input(crs))
    las = laspy.LasData(header)
    las.x, las.y, las.z = p[:, 0], p[:, 1], p[:, 2]
    las.classification = labels
    las.write(str(path))
    path.with_name(path.name + ".georef.json").write_text(json.dumps({"vertical": "ellipsoid", "vertical_unit": "m"}, indent=2) + "\n")
    return path


def write_buildings_geojson(world: World, path: Path) -> Path:
    feats = []
    o = world.origin
    for b in world.buildings:
        ring = np.vstack([b.outline_enu, b.outline_enu[:1]])
        enu = np.c_[ring, np.full(len(ring), b.ground_z_m)] @ world.T_model_world[:3, :3].T + world.T_model_world[:3, 3]
        lat, lon, h = o.enu_to_geodetic(enu)
        base_h = float(np.mean(h))
        base_msl = float(np.mean(ellipsoid_to_msl(lat, lon, h)))
        feats.append({
            "type": "Feature",
            "properties": {"id": int(b.id), "building": "yes", "kind": b.kind, "height": round(b.height_m, 3),
                           "min_height": round(base_h, 3), "base_h_ellipsoid_m": round(base_h, 3),
                           "base_h_msl_m": round(base_msl, 3), "roof_h_msl_m": round(base_msl + b.height_m, 3)},
            "geometry": {"type": "Polygon",
                         "coordinates": [[[round(float(x), 9), round(float(y), 9), round(float(z), 3)]
                                          for x, y, z in zip(lon, lat, h)]]},
        })
    path.write_text(json.dumps({"type": "FeatureCollection", "features": feats}) + "\n")
    return path


def export_gis(world: World, out_dir: Path, las_spacing_m: float = 1.0, seed: int = 0) -> GisFiles:
    """Write the three model files of ``world`` into out_dir (created)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    crs = utm_crs(world.origin.lat0_deg, world.origin.lon0_deg)
    return GisFiles(
        mesh_ply=write_mesh_ply(world, out_dir / "model.ply", crs),
        points_laz=write_points_las(world, out_dir / "model.laz", crs, las_spacing_m, seed=seed),
        buildings_geojson=write_buildings_geojson(world, out_dir / "buildings.geojson"),
        crs=crs,
    )
