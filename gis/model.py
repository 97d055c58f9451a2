"""The one in-memory GIS model every loader produces, and the fixed-size crop used by alignment.

Points and normals are in a local ENU frame (``origin``: geodetic WGS-84, ellipsoidal height).
Labels are ASPRS LAS classification codes (1 unclassified, 2 ground, 5 high vegetation,
6 building, 11 road surface).

Cropping uses a grid index over the horizontal plane (cell offsets over the points sorted by
cell, one slice per cell row), so the cost of a crop depends on the crop size only, not on the
size of the model (digital-twin paper §III-E: registration on a fixed-size crop); a model stored
cell by cell (the GIS cache's) needs no per-point index and can stay memory-mapped.
"""
from __future__ import annotations

import functools
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gis.geodesy import LocalFrame, ecef_to_geodetic

UNCLASSIFIED, GROUND, HIGH_VEGETATION, BUILDING, ROAD = 1, 2, 5, 6, 11

#: Grid cell size (m) of the crop index; a 150 m crop touches about 16 cells.
INDEX_CELL_M = 50.0
_CHUNK = 1 << 20  # rows per step of whole-model passes (validation, indexing)


class GisFormatError(ValueError):
    """A GIS file is corrupt, unsupported or lacks its georeference; the message names file + problem."""

    def __init__(self, path: Path | str, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = Path(path)
        self.problem = problem


@dataclass(frozen=True, eq=False)
class GisModel:
    """points_enu (N,3) m, normals_enu (N,3) unit, labels (N,) uint8 ASPRS, origin of the ENU frame,
    source_crs (the CRS the file was in, as text), source_path (file or directory it came from)."""

    points_enu: np.ndarray
    normals_enu: np.ndarray
    labels: np.ndarray
    origin: LocalFrame
    source_crs: str
    source_path: Path

    def __post_init__(self) -> None:
        p = np.ascontiguousarray(self.points_enu, dtype=np.float64)
        n = np.ascontiguousarray(self.normals_enu, dtype=np.float64)
        lab = np.ascontiguousarray(self.labels, dtype=np.uint8)
        if p.ndim != 2 or p.shape[1] != 3 or n.shape != p.shape or lab.shape != (len(p),):
            raise ValueError(f"GisModel arrays disagree: points {p.shape}, normals {n.shape}, labels {lab.shape}")
        if len(p) == 0:
            raise GisFormatError(self.source_path, "model holds no points")
        if not (_all_finite(p) and _all_finite(n)):
            raise GisFormatError(self.source_path, "model has non-finite coordinates or normals")
        object.__setattr__(self, "points_enu", p)
        object.__setattr__(self, "normals_enu", n)
        object.__setattr__(self, "labels", lab)
        object.__setattr__(self, "source_path", Path(self.source_path))

    def __len__(self) -> int:
        return len(self.points_enu)

    @property
    def bounds_enu(self) -> tuple[np.ndarray, np.ndarray]:
        return self.points_enu.min(axis=0), self.points_enu.max(axis=0)

    @functools.cached_property
    def _grid(self) -> tuple[np.ndarray | None, np.ndarray, np.ndarray, int]:
        """(order, cell offsets, cell-min, number of columns) of the horizontal grid index: the
        points of cell k are ``order[offsets[k]:offsets[k + 1]]`` (CSR), order None where the points
        are stored cell by cell already (``sorted_by_cell``, as the GIS cache keeps them): then the
        index holds nothing per point, and a memory-mapped model is read only where it is cropped.
        Built in chunks, so indexing a model never needs a copy of it."""
        lo = np.full(2, np.iinfo(np.int64).max)
        hi = np.full(2, np.iinfo(np.int64).min)
        for a in range(0, len(self), _CHUNK):
            ij = self._cells(a)
            lo, hi = np.minimum(lo, ij.min(axis=0)), np.maximum(hi, ij.max(axis=0))
        ncol, nrow = int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1
        counts = np.zeros(ncol * nrow, np.int64)
        in_order, last = True, -1
        for a in range(0, len(self), _CHUNK):
            ij = self._cells(a) - lo
            keys = ij[:, 1] * ncol + ij[:, 0]
            counts += np.bincount(keys, minlength=len(counts))
            in_order = in_order and keys[0] >= last and bool(np.all(np.diff(keys) >= 0))
            last = keys[-1]
        order = None
        if not in_order:
            ij = np.floor(self.points_enu[:, :2] / INDEX_CELL_M).astype(np.int64) - lo
            order = np.argsort(ij[:, 1] * ncol + ij[:, 0], kind="stable")
        return order, np.concatenate([[0], np.cumsum(counts)]), lo, ncol

    def _cells(self, start: int) -> np.ndarray:
        return np.floor(self.points_enu[start:start + _CHUNK, :2] / INDEX_CELL_M).astype(np.int64)

    @property
    def sorted_by_cell(self) -> "GisModel":
        """The same model with its points stored cell by cell (row-major over the grid index),
        which makes its index free of per-point arrays; self if they are already."""
        order, offsets, lo, ncol = self._grid
        if order is None:
            return self
        m = GisModel(self.points_enu[order], self.normals_enu[order], self.labels[order], self.origin,
                     self.source_crs, self.source_path)
        m.__dict__["_grid"] = (None, offsets, lo, ncol)  # the same cells, now in order (cached_property's slot)
        return m

    def crop(self, center_enu: np.ndarray, size_m: float) -> np.ndarray:
        """Indices of points inside the horizontal square of side size_m centred at center_enu (any height)."""
        c = np.asarray(center_enu, float)[:2]
        return self.crop_box(c - size_m / 2.0, c + size_m / 2.0)

    def crop_box(self, lo_en: np.ndarray, hi_en: np.ndarray) -> np.ndarray:
        """Indices of points whose east/north lie in [lo_en, hi_en] (m, inclusive; any height)."""
        order, offsets, lo, ncol = self._grid
        nrow = (len(offsets) - 1) // ncol
        lo_en, hi_en = np.asarray(lo_en, float)[:2], np.asarray(hi_en, float)[:2]
        i0, j0 = (np.floor(lo_en / INDEX_CELL_M).astype(np.int64) - lo)
        i1, j1 = (np.floor(hi_en / INDEX_CELL_M).astype(np.int64) - lo)
        i0, i1 = max(i0, 0), min(i1, ncol - 1)
        rows = np.arange(max(j0, 0), min(j1, nrow - 1) + 1)
        if i1 < i0 or len(rows) == 0:
            return np.zeros(0, dtype=np.int64)
        pos = np.concatenate([np.arange(offsets[r * ncol + i0], offsets[r * ncol + i1 + 1]) for r in rows])
        idx = pos if order is None else order[pos]
        p = self.points_enu[idx, :2]
        inside = np.all((p >= lo_en) & (p <= hi_en), axis=1)
        return idx[inside]


def frame_at_centroid(p_ecef_m: np.ndarray) -> LocalFrame:
    """A local ENU frame whose origin is the geodetic position of the points' centroid."""
    lat, lon, h = ecef_to_geodetic(np.asarray(p_ecef_m, float).mean(axis=0))
    return LocalFrame(float(lat), float(lon), float(h))


EARTH_SHELL_M = (6_300_000.0, 6_450_000.0)  # |ECEF| of anything on Earth: radius 6357-6378 km, heights -50..+70 km


def check_on_earth(p_ecef_m: np.ndarray, source_path: Path | str) -> None:
    """GisFormatError unless every point is finite and within EARTH_SHELL_M of the Earth's centre:
    else a wrong CRS, a missing transform or a corrupt file (one wild point would also stretch
    the crop index over a continent)."""
    r = np.linalg.norm(np.asarray(p_ecef_m, float), axis=1)
    bad = ~((r >= EARTH_SHELL_M[0]) & (r <= EARTH_SHELL_M[1]))  # (NaN counts as bad)
    if bad.any():
        off = np.abs(r[bad] - 6_371_000.0)
        worst = f"up to {np.nanmax(off) / 1e3:.0f} km off" if np.isfinite(off).any() else "not finite"
        raise GisFormatError(source_path, f"{int(bad.sum())} of {len(r)} points are not near the Earth's surface "
                                          f"({worst}): wrong CRS, a missing transform or a corrupt file")


def model_from_ecef(
    p_ecef_m: np.ndarray,
    normals_ecef: np.ndarray,
    labels: np.ndarray,
    source_crs: str,
    source_path: Path | str,
    origin: LocalFrame | None = None,
) -> GisModel:
    """Build a GisModel from ECEF points and ECEF-frame normals (origin: centroid unless given);
    the points must be on Earth (check_on_earth)."""
    if len(p_ecef_m) == 0:
        raise GisFormatError(source_path, "no geometry found")
    check_on_earth(p_ecef_m, source_path)
    origin = origin or frame_at_centroid(p_ecef_m)
    R = origin.R_ecef_enu
    n = np.asarray(normals_ecef, float) @ R
    return GisModel(origin.ecef_to_enu(p_ecef_m), _unit(n, source_path), labels, origin, source_crs, Path(source_path))


def merge_models(models: list[GisModel], source_path: Path | str) -> GisModel:
    """One model from several (e.g. the tiles of a tileset), in the first model's ENU frame."""
    if not models:
        raise GisFormatError(source_path, "no models to merge")
    origin = models[0].origin
    pts, nrm = [], []
    for m in models:
        p_ecef = m.origin.enu_to_ecef(m.points_enu)
        pts.append(origin.ecef_to_enu(p_ecef))
        nrm.append(m.normals_enu @ m.origin.R_ecef_enu.T @ origin.R_ecef_enu)
    crs = sorted({m.source_crs for m in models})
    return GisModel(
        np.concatenate(pts), np.concatenate(nrm), np.concatenate([m.labels for m in models]),
        origin, ";".join(crs), Path(source_path),
    )


def npz_mapped(path: Path) -> dict[str, np.ndarray]:
    """The arrays of an .npz written by ``np.savez`` (ZIP members stored, not deflated), each
    memory-mapped read-only where it lies in the file, so that a model larger than the board's RAM
    is paged in only where it is cropped. By hand because NumPy maps .npy files but not the
    members of an .npz (its ``mmap_mode`` is ignored there); a deflated member is read instead.
    A member's data starts after its 30-byte ZIP local header, name and extra field (APPNOTE
    §4.3.7), then the .npy header (NumPy format 1.0 or 2.0)."""
    out: dict[str, np.ndarray] = {}
    with zipfile.ZipFile(path) as zf, open(path, "rb") as f:
        for info in zf.infolist():
            name = info.filename.removesuffix(".npy")
            if info.compress_type != zipfile.ZIP_STORED:
                out[name] = np.load(zf.open(info))
                continue
            f.seek(info.header_offset)
            local = f.read(30)
            if local[:4] != b"PK\x03\x04":
                raise GisFormatError(path, f"member {info.filename} has no ZIP local header")
            name_len, extra_len = struct.unpack("<HH", local[26:30])
            f.seek(info.header_offset + 30 + name_len + extra_len)
            version = np.lib.format.read_magic(f)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, fortran, dtype = read_header(f)
            if dtype.hasobject or fortran:
                raise GisFormatError(path, f"member {info.filename} is not a plain C-ordered array")
            out[name] = np.memmap(path, dtype=dtype, mode="r", offset=f.tell(), shape=shape) if np.prod(shape) else np.zeros(shape, dtype)
    return out


def model_from_npz(path: Path | str, source_crs: str = "", source_path: Path | str | None = None) -> GisModel:
    """A GisModel stored as the GIS cache stores it (``points_enu``, ``normals_enu``, ``labels``,
    ``origin`` = lat, lon, h of the ENU frame; uncompressed .npz), memory-mapped (``npz_mapped``)."""
    path = Path(path)
    try:
        z = npz_mapped(path)
        arrays = z["points_enu"], z["normals_enu"], z["labels"]
        origin = LocalFrame(*map(float, z["origin"]))
    except (OSError, KeyError, ValueError, TypeError, zipfile.BadZipFile) as e:
        if isinstance(e, GisFormatError):
            raise
        raise GisFormatError(path, f"not a GIS model .npz ({type(e).__name__}: {e})") from None
    return GisModel(*arrays, origin, source_crs or "GisModel .npz", source_path or path)


def _all_finite(a: np.ndarray) -> bool:
    """np.all(np.isfinite(a)) a chunk of rows at a time (no N-sized temporary for a large model)."""
    return all(bool(np.isfinite(a[i:i + _CHUNK]).all()) for i in range(0, len(a), _CHUNK))


def _unit(v: np.ndarray, path: Path | str) -> np.ndarray:
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    if np.any(norm < 1e-12):
        raise GisFormatError(path, f"{int(np.sum(norm < 1e-12))} zero-length normals")
    return v / norm
