"""The fine-tuner's GIS crops (digital-twin §III-E): the model cut into 25 m tiles voxelised once on a global
grid and cached; a crop's KD-tree is reused while the next request needs no tile outside it, and any crop
holding a registration's tiles gives it the same correspondences (_CropCache)."""
from __future__ import annotations

import threading
from collections import OrderedDict, deque
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from pykdtree.kdtree import KDTree
from scipy.spatial import cKDTree

from gis.model import GisModel

TILE_M = 25.0                  # GIS crop tiles (voxelised once, cached); rounded to a multiple of target_voxel_m
MAX_CACHED_TILES = 4096        # ≈ 2.5 km² of voxelised tiles kept (least recently used dropped)
PREFETCH_MAX_STEP_M = 150.0    # a prefetched crop reaches at most this far beyond the last registration's (_CropCache.prefetch)
PREFETCH_MARGIN_M = TILE_M     # ... and this far around the guessed one (turns; journals: 4 of 5 registrations after the second found it built, 3 of 5 without)


@dataclass(frozen=True)
class _Crop:
    """The GIS model over a box of whole tiles, voxelised on the global voxel grid, with its KD-tree
    (ENU coordinates). Tiles are concatenated in index order, so any crop holding a tile holds the
    same points for it in the same order: a registration gets the same correspondences from any
    crop that covers the tiles it needs."""

    box: tuple[int, int, int, int]   # tile indices (i0, j0, i1, j1), inclusive
    tile_m: float
    points: np.ndarray
    normals: np.ndarray
    tree: KDTree | None              # pykdtree (ICP correspondences); None for an empty crop (pykdtree
                                     # refuses one; registrations stop at the GIS-crop gate first)

    @cached_property
    def tree_en(self) -> cKDTree:
        """The points' horizontal coordinates, for radius searches over most of the crop
        (nadir_scale_ratio); built when first asked for: 6 ms for a crop of the demo flight, three
        times its 3-D KD-tree, and a registration's own check needs only the crop's middle."""
        return cKDTree(self.points[:, :2], balanced_tree=False)

    def covers(self, box: tuple[int, int, int, int]) -> bool:
        i0, j0, i1, j1 = self.box
        return i0 <= box[0] and j0 <= box[1] and box[2] <= i1 and box[3] <= j1

    def spacing_m(self, c_enu: np.ndarray, half_m: float) -> float:
        """Median nearest-neighbour distance of the crop's points within half_m of c_enu (≤ 300,
        taken in the crop's order: the same whichever covering crop is asked)."""
        inner = np.flatnonzero(_in_square(self.points, c_enu, half_m))
        if len(inner) < 2:
            return 0.0
        sample = self.points[inner[:: max(1, len(inner) // 300)]]
        return float(np.median(self.tree.query(sample, k=2)[0][:, 1]))


class _CropCache:
    """Fixed-size GIS crops (digital-twin §III-E) without rebuilding them every registration:
    the model is voxelised per tile once (LRU-cached), and the last crop of each user (``slot``:
    the registrations, the barometer checks) and its KD-tree are reused while that user's next
    request needs no tile outside it. Thread-safe."""

    def __init__(self, model: GisModel, voxel_m: float) -> None:
        self._model = model
        self._voxel_m = voxel_m
        self.tile_m = voxel_m * max(1, round(TILE_M / voxel_m))  # tile edges on voxel edges: no voxel straddles two tiles
        self._tiles: OrderedDict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._last: dict[str, _Crop] = {}
        self._asked: dict[str, deque] = {}  # per slot, the last two requests: (centre EN m, half_m)
        self._lock = threading.Lock()
        self.n_built = 0  # crops (KD-trees) built so far

    def last(self, slot: str = "registration") -> _Crop | None:
        return self._last.get(slot)

    def _box(self, c_enu: np.ndarray, half_m: float) -> tuple[int, int, int, int]:
        lo = np.floor((np.asarray(c_enu[:2], float) - half_m) / self.tile_m).astype(int)
        hi = np.floor((np.asarray(c_enu[:2], float) + half_m) / self.tile_m).astype(int)
        return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])

    def get(self, c_enu: np.ndarray, half_m: float, slot: str = "registration", margin_m: float = 0.0) -> _Crop:
        """A crop holding every model point within half_m (horizontally, square) of c_enu; a new
        one reaches margin_m further, so that a moving user rebuilds it less often."""
        box = self._box(c_enu, half_m)
        with self._lock:
            self._asked.setdefault(slot, deque(maxlen=2)).append((np.array(c_enu[:2], float), half_m))
            last = self._last.get(slot)
            if last is not None and last.covers(box):
                return last
            return self._build(self._box(c_enu, half_m + margin_m), slot)

    def prefetch(self, slot: str = "registration") -> bool:
        """Build, ahead of time, the crop the slot's next request will probably need, so that
        request finds it built (the next registration then skips voxelising its new tiles and the
        KD-tree: about a quarter of a registration's CPU on the journals of a moving camera, which
        needed a new crop every time). The guess: the next request lies as far on from the last
        one as that one from the one before (at most PREFETCH_MAX_STEP_M); the crop covers both
        the last request's box and the guessed one's, PREFETCH_MARGIN_M wider for a turn, so any
        request along the way is covered too (a registration every 20 s while GNSS is trusted,
        then every 5 s in a denial, at the same speed, lands between them). True when a crop was
        built; False when fewer than two requests were made or the slot's crop already covers
        the guess. Any crop covering a request gives it the same points in the same order
        (_Crop), so a prefetched crop changes no result, only when the work is done."""
        with self._lock:
            asked = self._asked.get(slot)
            if asked is None or len(asked) < 2:
                return False
            (c0, _), (c1, half_m) = asked
            step = c1 - c0
            n = float(np.hypot(*step))
            if n > PREFETCH_MAX_STEP_M:
                step *= PREFETCH_MAX_STEP_M / n
            a, b = self._box(c1, half_m), self._box(c1 + step, half_m + PREFETCH_MARGIN_M)
            box = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
            last = self._last.get(slot)
            if last is not None and last.covers(box):
                return False
            self._build(box, slot)
            return True

    def _build(self, box: tuple[int, int, int, int], slot: str) -> _Crop:
        """The crop over ``box`` (tile indices), the slot's crop from now on (lock held)."""
        keys = [(i, j) for j in range(box[1], box[3] + 1) for i in range(box[0], box[2] + 1)]
        self._voxelise_missing([k for k in keys if k not in self._tiles])
        parts = [self._tiles[k] for k in keys]
        for k in keys:
            self._tiles.move_to_end(k)
        while len(self._tiles) > max(MAX_CACHED_TILES, len(keys)):
            self._tiles.popitem(last=False)
        pts = np.concatenate([p for p, _ in parts]) if parts else np.zeros((0, 3))
        nrm = np.concatenate([n for _, n in parts]) if parts else np.zeros((0, 3))
        crop = _Crop(box, self.tile_m, pts, nrm, KDTree(pts) if len(pts) else None)
        self._last[slot] = crop
        self.n_built += 1
        return crop

    def _voxelise_missing(self, keys: list[tuple[int, int]]) -> None:
        """Voxelise the model over the given tiles in one pass: one model crop over their bounding
        box, each point assigned to the tile that floor(east/north / tile_m) names (a point on a
        tile edge goes to one tile), the points of tiles not asked for dropped. One crop, not one
        per tile: the model's 50 m index cells made each 25 m tile crop sort through up to 16× its
        points (≈0.6 ms a tile; 16 → 10 ms per registration of the demo flight)."""
        if not keys:
            return
        k = np.asarray(keys, np.int64)
        idx = self._model.crop_box(k.min(axis=0) * self.tile_m, (k.max(axis=0) + 1) * self.tile_m)
        p = self._model.points_enu[idx]
        tile = np.floor(p[:, :2] / self.tile_m).astype(np.int64)
        want = np.isin(tile[:, 1] * (1 << 32) + tile[:, 0], k[:, 1] * (1 << 32) + k[:, 0])
        p, n = _voxel_global(p[want], self._model.normals_enu[idx[want]], self._voxel_m)
        tile = np.floor(p[:, :2] / self.tile_m).astype(int)
        order = np.lexsort((tile[:, 0], tile[:, 1]))  # stable: voxel order kept within a tile
        p, n, tile = p[order], n[order], tile[order]
        for key in keys:
            lo, hi = np.searchsorted(tile[:, 1], key[1], "left"), np.searchsorted(tile[:, 1], key[1], "right")
            row = tile[lo:hi, 0]
            a, b = lo + np.searchsorted(row, key[0], "left"), lo + np.searchsorted(row, key[0], "right")
            self._tiles[key] = (p[a:b], n[a:b])


def _in_square(p_enu: np.ndarray, c_enu: np.ndarray, half_m: float) -> np.ndarray:
    """(N,) bool: points within ``half_m`` of ``c_enu`` in east and in north (a crop square)."""
    return np.all(np.abs(p_enu[:, :2] - c_enu[:2]) <= half_m, axis=1)


def _voxel_global(p: np.ndarray, n: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean point and unit mean normal per voxel of the global grid (edges at multiples of voxel_m,
    so a crop made of whole tiles voxelises every tile the same way); voxels whose normals cancel
    (|mean| ≤ 0.5: both faces of a thin wall) are dropped. Sorted by voxel (deterministic order)."""
    if len(p) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    v = np.floor(p / voxel_m).astype(np.int64)
    v -= v.min(axis=0)
    span = v.max(axis=0) + 1
    key = (v[:, 0] * span[1] + v[:, 1]) * span[2] + v[:, 2]
    _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    mean = lambda a: np.stack([np.bincount(inv, a[:, k], len(counts)) for k in range(3)], 1) / counts[:, None]  # noqa: E731
    pts, nrm = mean(p), mean(n)
    norm = np.linalg.norm(nrm, axis=1)
    keep = norm > 0.5
    return pts[keep], nrm[keep] / norm[keep, None]
