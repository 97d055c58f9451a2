"""LAS/LAZ point clouds (laspy), read in chunks and thinned as they are read."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from gis.loaders.common import _median_spacing, first_per_voxel
from gis.loaders.georef import _georeferenced
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
