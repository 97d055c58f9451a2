"""ORB features spread over the image (OpenCV CPU path) and the backend switch.

Keypoints are returned undistorted (pixels of the ideal pinhole camera K), so everything
downstream uses K only.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from slam.config import SlamConfig
from slam.types import CameraModel


@dataclass(frozen=True)
class Features:
    uv_px: np.ndarray  # (N,2) float64, undistorted pixels
    desc: np.ndarray  # (N,32) uint8, 256-bit binary descriptors
    octave: np.ndarray  # (N,) int pyramid level (0 = full resolution)

    def __len__(self) -> int:
        return len(self.uv_px)


def to_gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return image


def keep_spread(uv: np.ndarray, response: np.ndarray, shape: tuple[int, int], n_keep: int,
                grid: tuple[int, int] = (16, 16)) -> np.ndarray:
    """Indices of at most n_keep keypoints, best first within each grid cell, round-robin over cells.

    OpenCV ORB keeps the globally strongest corners, which bunch up on high-contrast texture;
    ORB-SLAM's per-cell distribution is what keeps the pose well conditioned.
    """
    h, w = shape
    cell = (np.clip((uv[:, 1] * grid[0] / h).astype(int), 0, grid[0] - 1) * grid[1]
            + np.clip((uv[:, 0] * grid[1] / w).astype(int), 0, grid[1] - 1))
    order = np.lexsort((-response, cell))  # by cell, strongest first
    sorted_cells = cell[order]
    first = np.searchsorted(sorted_cells, sorted_cells, side="left")
    rank = np.arange(len(order)) - first  # rank of each keypoint within its cell
    pick = order[np.lexsort((-response[order], rank))]
    return pick[:n_keep]


def undistort_px(camera: CameraModel, uv: np.ndarray) -> np.ndarray:
    if not camera.is_distorted or len(uv) == 0:
        return uv.astype(np.float64)
    return cv2.undistortPoints(uv.reshape(-1, 1, 2).astype(np.float64), camera.K, camera.dist,
                               P=camera.K).reshape(-1, 2)


FAST_THRESHOLD = 20             # ORB-SLAM's iniThFAST (intensity levels)
LOW_CONTRAST_BLUR_PX = 1.0      # low-contrast frames: Gaussian denoising σ before the stretch
LOW_CONTRAST_STD_DN = 30.0      # ... and the intensity std they are stretched to (nominal frames: 28–35 DN)
LOW_CONTRAST_MAX_GAIN = 4.0     # ... by at most this factor (a featureless frame's noise is not made into corners)


def normalise_contrast(gray: np.ndarray) -> np.ndarray:
    """A low-contrast (dark) frame denoised and stretched: Gaussian σ LOW_CONTRAST_BLUR_PX, then an
    affine intensity map to std LOW_CONTRAST_STD_DN about mid-grey (gain ≤ LOW_CONTRAST_MAX_GAIN).
    FAST's fixed threshold then stands in the same ratio to the scene's contrast as on a normal
    frame, and the denoising keeps sensor noise from making corners. (BRIEF compares intensities,
    so the stretch leaves descriptors comparable with a well-lit frame's; the blur changes them a
    little: ORB blurs before describing anyway.)"""
    blurred = cv2.GaussianBlur(gray, (0, 0), LOW_CONTRAST_BLUR_PX)
    mean, std = (float(v[0, 0]) for v in cv2.meanStdDev(blurred))
    gain = min(LOW_CONTRAST_STD_DN / max(std, 1e-6), LOW_CONTRAST_MAX_GAIN)
    return cv2.convertScaleAbs(blurred, alpha=gain, beta=128.0 - gain * mean)


def make_orb_cpu(camera: CameraModel, n_features: int) -> Callable[[np.ndarray], Features]:
    """OpenCV ORB (8 levels, x1.2) over-detecting 1.5x, then spread over a 16x16 grid.

    A frame that gives fewer than n_features corners at FAST_THRESHOLD (dark, low contrast) is
    detected and described again on normalise_contrast(frame). The simulator's `dark` frames
    (gain 0.3, ~4 DN of noise, std 8–13 DN) give 85–900 corners at 20, and before this SLAM never
    initialised in half the dark flights; its other scenarios give ≥ 1310 and are never touched.
    Lowering the FAST threshold instead (ORB-SLAM's minThFAST fallback) found corners but matched
    them poorly (dark seed 0, consecutive frames: 148 matches at 12 against 276 here), and at 7 a
    dark track failed the GNSS bootstrap (docs/BENCHMARKS.md, "Dark frames").

    Harris ranking kept: FAST score saved ~1.5 ms/frame but doubled-to-tenfold the trajectory
    error on the nominal sequence in our runs.
    """
    orb = cv2.ORB_create(nfeatures=int(1.5 * n_features), scaleFactor=1.2, nlevels=8, fastThreshold=FAST_THRESHOLD,
                         scoreType=cv2.ORB_HARRIS_SCORE)

    def extract(image: np.ndarray) -> Features:
        gray = to_gray(image)
        kps = orb.detect(gray, None)
        if len(kps) < n_features:  # low contrast: detect and describe on the normalised frame
            gray = normalise_contrast(gray)
            kps = orb.detect(gray, None)
        if not kps:
            return Features(np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros(0, int))
        # cv2.KeyPoint_convert: the (float32) positions in one C call, not a Python loop (0.7-1 ms a frame)
        uv = cv2.KeyPoint_convert(kps).astype(np.float64)
        resp = np.array([k.response for k in kps])
        keep = keep_spread(uv, resp, gray.shape, n_features)
        kps, desc = orb.compute(gray, [kps[i] for i in keep])
        if desc is None or not kps:
            return Features(np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros(0, int))
        uv = cv2.KeyPoint_convert(kps).astype(np.float64)
        octave = np.array([k.octave for k in kps])
        return Features(undistort_px(camera, uv), desc, octave)

    return extract


def make_extractor(camera: CameraModel, config: SlamConfig) -> Callable[[np.ndarray], Features]:
    """Feature extractor chosen by ``config.feature_backend``."""
    if config.feature_backend == "torch":
        from slam.torch_orb import make_orb_torch  # torch is imported only when selected

        return make_orb_torch(camera, config.n_features, config.n_patches, config.torch_device,
                              config.torch_low_contrast_std_dn)
    return make_orb_cpu(camera, config.n_features)
