"""Sub-pixel feature positions: each map point keeps the image patch it was first seen with, and
its later observations are placed where that patch aligns best (Lucas-Kanade, translation only).

Why: ORB keypoints are FAST corners at integer pixels of their pyramid level, detected anew in
every frame. Measured on the simulator (`nominal`, true depth under each keypoint projected into a
later frame with the true pose), the matched keypoint lies 0.84 px (median; 0.65 px at level 0,
1.16 px at level 4) from where the first keypoint's scene point is; aligning the first keypoint's
11x11 patch instead puts it 0.17 px off after 3 frames and 0.27 px after 30 (docs/BENCHMARKS.md,
"Sub-pixel observations"). Every observation of a point is then of the same scene point, which is
what triangulation, bundle adjustment and the pose need (SVO's feature alignment does the same).

Written here rather than with cv2.calcOpticalFlowPyrLK: OpenCV's tracker needs the reference
image at the target's size, and a map point keeps only a 13x13 patch of it (169 bytes) for as
long as the point lives. The solver is the inverse-compositional one of Baker & Matthews, "Lucas-
Kanade 20 years on" (IJCV 2004), §3.2, for a pure translation warp, with the patch's mean and
contrast normalised (zero-mean, gain to the template's), vectorised over all patches of a frame.

Where (``slam.patch_alignment``): a map point's patch is cut from the keyframe it is triangulated
in (slam.mapping); the other keyframe of its triangulation, every later keyframe that tracks it
and every keyframe fusing joins it to observe it where the patch aligns, all in local mapping (a
keyframe carries its image levels there; the tracking thread only builds them, ~0.5 ms on a
keyframe's frame). Frames between keyframes are tracked on the detected corners: their poses are
output, not mapped, and aligning there cost 5-8 ms a frame without a measurable gain
(docs/BENCHMARKS.md).

Positions in and out are undistorted pixels (as ``slam.features.Features``); patches are cut from
and aligned in the camera's own (distorted) image.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slam.features import to_gray
from slam.types import CameraModel

PATCH_PX = 11  # aligned window (pixels of the keypoint's pyramid level)
STORED_PX = PATCH_PX + 2  # stored with a 1 px border for the template's central-difference gradient
SCALE_FACTOR = 1.2  # pyramid scale step (ORB's)
N_LEVELS = 8
ITERATIONS = 10
MAX_SHIFT_PX = 2.0  # an alignment may move the detected keypoint this far (level pixels), no further
MIN_ZNCC = 0.8  # aligned patch vs template: zero-mean normalised cross-correlation
CONVERGED_PX = 0.05  # last step below this (level pixels)
MIN_EIG = 50.0  # smallest eigenvalue of the template's gradient matrix (an edge or flat patch cannot fix 2 DoF)


@dataclass(frozen=True)
class ImageLevels:
    """A frame's grey image at up to N_LEVELS scales (level o = 1 / SCALE_FACTOR**o, pixel centres
    aligned, as cv2.resize), side by side in one atlas so that one cv2.remap samples patches of all
    levels; and the pyramid level of each of the frame's features."""

    atlas: np.ndarray  # (H, sum of level widths) uint8
    x0: np.ndarray  # (L,) atlas column where each level starts
    size: np.ndarray  # (L, 2) width, height of each level
    octave: np.ndarray  # (N,) of the frame's features

    @property
    def n_levels(self) -> int:
        return len(self.x0)


def image_levels(image: np.ndarray, octave: np.ndarray) -> ImageLevels:
    """A frame's image (grey or BGR) at the levels up to the highest octave any of its features
    was detected at."""
    gray = to_gray(image)
    top = min(int(octave.max()) if len(octave) else 0, N_LEVELS - 1)
    h, w = gray.shape
    lv = [gray] + [cv2.resize(gray, (max(1, round(w / SCALE_FACTOR ** o)), max(1, round(h / SCALE_FACTOR ** o))),
                              interpolation=cv2.INTER_LINEAR) for o in range(1, top + 1)]
    size = np.array([(a.shape[1], a.shape[0]) for a in lv])
    x0 = np.r_[0, np.cumsum(size[:, 0])[:-1]]
    atlas = np.zeros((h, int(size[:, 0].sum())), np.uint8)
    for a, x in zip(lv, x0.tolist()):
        atlas[:a.shape[0], x:x + a.shape[1]] = a
    return ImageLevels(atlas, x0, size, np.asarray(octave, np.int8))


def _to_level(uv_px: np.ndarray, octave: np.ndarray) -> np.ndarray:
    s = SCALE_FACTOR ** octave.astype(np.float64)
    return (uv_px + 0.5) / s[:, None] - 0.5


def _from_level(xy: np.ndarray, octave: np.ndarray) -> np.ndarray:
    s = SCALE_FACTOR ** octave.astype(np.float64)
    return (xy + 0.5) * s[:, None] - 0.5


_GRID = {n: np.arange(n, dtype=np.float32) - (n - 1) / 2 for n in (PATCH_PX, STORED_PX)}


def _sample(src: ImageLevels, xy: np.ndarray, octave: np.ndarray, size: int) -> np.ndarray:
    """(N, size, size) float32 bilinear samples on size x size grids centred at xy (level pixels
    of each point's level)."""
    g = _GRID[size]
    ax = (xy[:, 0] + src.x0[octave]).astype(np.float32)
    mx = np.broadcast_to(ax[:, None, None] + g[None, None, :], (len(xy), size, size))
    my = np.broadcast_to(xy[:, 1, None, None].astype(np.float32) + g[None, :, None], (len(xy), size, size))
    out = cv2.remap(src.atlas, np.ascontiguousarray(mx).reshape(-1, size), np.ascontiguousarray(my).reshape(-1, size),
                    cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(len(xy), size, size).astype(np.float32)


def _inside(src: ImageLevels, xy: np.ndarray, octave: np.ndarray, half: float) -> np.ndarray:
    w, h = src.size[octave].T
    return (xy[:, 0] >= half) & (xy[:, 0] <= w - 1 - half) & (xy[:, 1] >= half) & (xy[:, 1] <= h - 1 - half)


class PatchAligner:
    """Cuts reference patches and aligns them, for one camera (distortion handled here)."""

    def __init__(self, camera: CameraModel) -> None:
        self.camera = camera

    def _distort(self, uv_px: np.ndarray) -> np.ndarray:
        cam = self.camera
        if not cam.is_distorted or len(uv_px) == 0:
            return np.asarray(uv_px, np.float64)
        xn = np.c_[(uv_px[:, 0] - cam.cx) / cam.fx, (uv_px[:, 1] - cam.cy) / cam.fy, np.ones(len(uv_px))]
        out, _ = cv2.projectPoints(xn, np.zeros(3), np.zeros(3), cam.K, cam.dist)
        return out.reshape(-1, 2)

    def _undistort(self, uv_px: np.ndarray) -> np.ndarray:
        cam = self.camera
        if not cam.is_distorted or len(uv_px) == 0:
            return uv_px
        return cv2.undistortPoints(uv_px.reshape(-1, 1, 2), cam.K, cam.dist, P=cam.K).reshape(-1, 2)

    def cut(self, src: ImageLevels, uv_px: np.ndarray, octave: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Reference patches (N, STORED_PX, STORED_PX) uint8 at each feature's own level, centred on
        its (sub-pixel) position, and whether each could be cut (inside the image, textured in
        both directions)."""
        n = len(uv_px)
        out = np.zeros((n, STORED_PX, STORED_PX), np.uint8)
        ok = np.zeros(n, bool)
        if n == 0:
            return out, ok
        octave = np.minimum(np.asarray(octave, int), src.n_levels - 1)
        xy = _to_level(self._distort(np.asarray(uv_px, np.float64)), octave)
        k = np.flatnonzero(_inside(src, xy, octave, STORED_PX / 2 + 1))
        if len(k):
            p = _sample(src, xy[k], octave[k], STORED_PX)
            out[k] = np.clip(np.rint(p), 0, 255).astype(np.uint8)
            ok[k] = _min_eig(*_hessian(*_gradients(out[k].astype(np.float32)))) >= MIN_EIG
        return out, ok

    def align(self, dst: ImageLevels, patches: np.ndarray, octave: np.ndarray,
              uv_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where each reference patch (from ``cut``, at its point's level ``octave``; -1: none)
        lies in the frame ``dst``, starting from the matched keypoint ``uv_px`` (N, 2). Returns
        (N, 2) undistorted pixels and a mask of the alignments that converged within MAX_SHIFT_PX
        with ZNCC >= MIN_ZNCC; where the mask is False the input position is returned unchanged."""
        uv_px = np.asarray(uv_px, np.float64)
        out = uv_px.copy()
        ok = np.zeros(len(uv_px), bool)
        octave = np.asarray(octave, int)
        k = np.flatnonzero((octave >= 0) & (octave < dst.n_levels))
        if len(k) == 0:
            return out, ok
        xy0 = _to_level(self._distort(uv_px[k]), octave[k])
        xy, ok[k] = _align(dst, patches[k].astype(np.float32), octave[k], xy0)
        if ok.any():
            good = ok[k]
            out[k[good]] = self._undistort(_from_level(xy[good], octave[k[good]]))
        return out, ok


def _gradients(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference gradients of each stored patch over its aligned window."""
    return (p[:, 1:-1, 2:] - p[:, 1:-1, :-2]) / 2, (p[:, 2:, 1:-1] - p[:, :-2, 1:-1]) / 2


def _hessian(gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each patch's 2x2 gradient matrix H = [[a, b], [b, c]] (the Gauss-Newton Hessian of a
    translation) from its gradients."""
    return (gx * gx).sum((1, 2)), (gx * gy).sum((1, 2)), (gy * gy).sum((1, 2))


def _min_eig(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Smallest eigenvalue of each [[a, b], [b, c]]."""
    return (a + c) / 2 - np.sqrt(((a - c) / 2) ** 2 + b * b)


def _align(dst: ImageLevels, stored: np.ndarray, octave: np.ndarray, xy0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-compositional LK (Baker & Matthews 2004, §3.2, for the warp W(x; p) = x + p) of the
    stored patches, each in its level of ``dst``, from xy0 (level pixels): the Hessian H from the
    template's gradients once, then per iteration dp = H^-1 sum(grad T^T (I(x + p) - T(x))) and
    p <- p - dp (composing with the inverse of a translation)."""
    T = stored[:, 1:-1, 1:-1]
    gx, gy = _gradients(stored)
    Tz = T - T.mean((1, 2), keepdims=True)
    t_norm = np.sqrt((Tz * Tz).sum((1, 2)))
    a, b, c = _hessian(gx, gy)
    live = _min_eig(a, b, c) >= MIN_EIG
    det = np.where(live, a * c - b * b, 1.0)
    xy = xy0.astype(np.float64).copy()
    step = np.full(len(xy), np.inf)
    half = PATCH_PX / 2 + 1
    for _ in range(ITERATIONS):
        live &= _inside(dst, xy, octave, half) & (step >= CONVERGED_PX)
        j = np.flatnonzero(live)
        if len(j) == 0:
            break
        Iz = _sample(dst, xy[j], octave[j], PATCH_PX)
        Iz -= Iz.mean((1, 2), keepdims=True)
        i_norm = np.sqrt((Iz * Iz).sum((1, 2)))
        r = Iz * (t_norm[j] / np.maximum(i_norm, 1e-6))[:, None, None] - Tz[j]  # gain-normalised residual
        bx, by = (gx[j] * r).sum((1, 2)), (gy[j] * r).sum((1, 2))
        dx, dy = (c[j] * bx - b[j] * by) / det[j], (a[j] * by - b[j] * bx) / det[j]  # H^-1 [bx, by]
        xy[j] -= np.c_[dx, dy]  # inverse composition of a translation
        step[j] = np.hypot(dx, dy)
    ok = (step < CONVERGED_PX) & _inside(dst, xy, octave, half) & (np.hypot(*(xy - xy0).T) <= MAX_SHIFT_PX)
    j = np.flatnonzero(ok)
    if len(j):
        Iz = _sample(dst, xy[j], octave[j], PATCH_PX)
        Iz -= Iz.mean((1, 2), keepdims=True)
        zncc = (Iz * Tz[j]).sum((1, 2)) / np.maximum(np.sqrt((Iz * Iz).sum((1, 2))) * t_norm[j], 1e-6)
        ok[j] = zncc >= MIN_ZNCC
    return np.where(ok[:, None], xy, xy0), ok
