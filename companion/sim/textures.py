"""Surface textures with natural image statistics, built from images shipped in scikit-image.

Every texture is a seamless grayscale tile (mirror-tiled 1024×1024 from a 512×512 photograph) so the
renderer can wrap texture coordinates without seams. Colour comes from a per-surface tint, so one
gather per pixel gives a BGR image. Facade textures overlay a procedural window grid on a
photograph: repetitive like real facades, with photographic detail inside every cell.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

import cv2
import numpy as np
import skimage.data

TILE_PX = 1024  # texels per tile side (power of two: wrap with a bit mask)


class Tex(enum.IntEnum):
    """Texture slots of the atlas (index into ``Textures.atlas``)."""

    GRASS = 0
    GRAVEL = 1
    SOIL = 2
    PAVING = 3
    ROAD = 4
    ROOF_A = 5
    ROOF_B = 6
    ROOF_C = 7
    FACADE_A = 8
    FACADE_B = 9
    FACADE_C = 10
    FOLIAGE = 11
    CLUTTER = 12


@dataclass(frozen=True)
class Textures:
    """atlas: (n, TILE_PX, TILE_PX) uint8; macro: (M, M) float32 low-frequency albedo multiplier
    (mean 1) draped over the whole site at ``macro_m_per_px`` to break the repetition of tiles."""

    atlas: np.ndarray
    macro: np.ndarray
    macro_m_per_px: float


def _gray(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    return img.astype(np.uint8)


def _square(img: np.ndarray, size: int = TILE_PX // 2) -> np.ndarray:
    h, w = img.shape[:2]
    s = min(h, w)
    y0, x0 = (h - s) // 2, (w - s) // 2
    return cv2.resize(img[y0:y0 + s, x0:x0 + s], (size, size), interpolation=cv2.INTER_AREA)


def _normalise(img: np.ndarray, mean: float, std: float) -> np.ndarray:
    """Local contrast equalisation (CLAHE) then a target mean/std: every surface carries texture."""
    img = cv2.createCLAHE(clipLimit=2.5, tileGridSize=(8, 8)).apply(img)
    f = img.astype(np.float32)
    f = (f - f.mean()) / max(float(f.std()), 1.0) * std + mean
    return np.clip(f, 0, 255).astype(np.uint8)


def _mirror_tile(img: np.ndarray) -> np.ndarray:
    top = np.hstack([img, img[:, ::-1]])
    return np.vstack([top, top[::-1]])


def _facade(base: np.ndarray, cell_px: tuple[int, int], win_frac: tuple[float, float], glass: np.ndarray,
            rng: np.random.Generator) -> np.ndarray:
    """Window grid on a wall photograph; the glass shows another photograph (reflections)."""
    out = base.astype(np.float32)
    cw, ch = cell_px
    g = glass.astype(np.float32) * 0.45 + 20
    yy, xx = np.mgrid[0:out.shape[0], 0:out.shape[1]]
    in_win = ((xx % cw) < win_frac[0] * cw) & ((yy % ch) < win_frac[1] * ch)
    out[in_win] = g[in_win]
    # frames: a bright sill under each window
    sill = ((yy % ch) >= win_frac[1] * ch) & ((yy % ch) < win_frac[1] * ch + 3) & ((xx % cw) < win_frac[0] * cw)
    out[sill] = np.minimum(out[sill] + 70, 255)
    out += rng.normal(0, 4, out.shape)
    return np.clip(out, 0, 255).astype(np.uint8)


def _road(base: np.ndarray) -> np.ndarray:
    """Asphalt photograph with a dashed centre line along u (texture x) at v = TILE/2."""
    out = (base.astype(np.float32) * 0.55 + 25)
    half = out.shape[0] // 2
    yy, xx = np.mgrid[0:out.shape[0], 0:out.shape[1]]
    dash = (np.abs(yy - half) < 3) & ((xx % 60) < 30)
    edge = (np.abs(yy - 12) < 2) | (np.abs(yy - (out.shape[0] - 12)) < 2)
    out[dash | edge] = 215
    return np.clip(out, 0, 255).astype(np.uint8)


def make_textures(seed: int = 0) -> Textures:
    rng = np.random.default_rng(seed)
    grass = _normalise(_square(_gray(skimage.data.grass())), 120, 38)
    gravel = _normalise(_square(_gray(skimage.data.gravel())), 130, 35)
    soil = _normalise(_square(_gray(skimage.data.moon())), 125, 35)
    paving = _normalise(_square(_gray(skimage.data.brick())), 140, 30)
    brick = _normalise(_square(_gray(skimage.data.brick())), 135, 35)
    cells = _normalise(_square(_gray(skimage.data.immunohistochemistry())), 140, 35)
    hubble = _normalise(_square(_gray(skimage.data.hubble_deep_field())), 150, 30)
    coffee = _normalise(_square(_gray(skimage.data.coffee())), 120, 45)
    cam = _normalise(_square(_gray(skimage.data.camera())), 120, 45)
    rocket = _normalise(_square(_gray(skimage.data.rocket())), 120, 45)
    chelsea = _normalise(_square(_gray(skimage.data.chelsea())), 130, 40)
    astronaut = _normalise(_square(_gray(skimage.data.astronaut())), 120, 45)
    half = [
        grass, gravel, soil, paving,
        _road(gravel),
        _normalise(cv2.addWeighted(gravel, 0.6, cells, 0.4, 0), 150, 35),
        _normalise(cv2.addWeighted(hubble, 0.5, soil, 0.5, 0), 135, 35),
        _normalise(cv2.addWeighted(paving, 0.5, coffee, 0.5, 0), 145, 35),
        _facade(brick, (48, 64), (0.55, 0.55), cam, rng),
        _facade(cells, (64, 56), (0.7, 0.5), rocket, rng),
        _facade(paving, (40, 72), (0.5, 0.6), chelsea, rng),
        _normalise(cv2.addWeighted(grass, 0.6, soil, 0.4, 0), 95, 40),
        astronaut,
    ]
    atlas = np.stack([_mirror_tile(t) for t in half])
    macro = cv2.GaussianBlur(_square(_gray(skimage.data.camera()), 256).astype(np.float32), (0, 0), 3)
    macro = 0.8 + 0.4 * (macro - macro.min()) / max(float(np.ptp(macro)), 1.0)
    return Textures(atlas=np.ascontiguousarray(atlas), macro=(macro / macro.mean()).astype(np.float32),
                    macro_m_per_px=4.0)
