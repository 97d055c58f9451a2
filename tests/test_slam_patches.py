"""slam/patches.py: reference patches cut at sub-pixel positions and aligned in a shifted image.

The second image is the first warped by a known sub-pixel translation (OpenCV warpAffine), with a
change of exposure (gain and offset) and sensor noise, so the true position of every patch there
is known exactly."""
import cv2
import numpy as np
import pytest

from slam.patches import MAX_SHIFT_PX, PatchAligner, image_levels
from slam.types import CameraModel

W_PX, H_PX = 640, 480
K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random((H_PX, W_PX)).astype(np.float32) * 255, (0, 0), 2.0)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def _shifted(img: np.ndarray, shift_px: tuple[float, float], gain: float, offset: float, seed: int) -> np.ndarray:
    A = np.array([[1, 0, shift_px[0]], [0, 1, shift_px[1]]], np.float64)
    moved = cv2.warpAffine(img.astype(np.float32), A, (W_PX, H_PX), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    noisy = gain * moved + offset + np.random.default_rng(seed).normal(0, 2.0, moved.shape)
    return np.clip(noisy, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("octave", [0, 2])
def test_patches_align_to_the_true_subpixel_position_despite_exposure_and_noise(octave):
    rng = np.random.default_rng(1)
    al = PatchAligner(CameraModel(W_PX, H_PX, K))
    a = _texture(0)
    shift = (3.37, -1.81)
    b = _shifted(a, shift, gain=0.7, offset=25.0, seed=2)
    uv_a = rng.uniform(60, [W_PX - 60, H_PX - 60], (200, 2))
    oct_ = np.full(len(uv_a), octave)
    patches, cut_ok = al.cut(image_levels(a, oct_), uv_a, oct_)
    assert cut_ok.mean() > 0.95
    truth = uv_a + shift
    start = truth + rng.uniform(-1.0, 1.0, truth.shape) * 1.2 ** octave  # a re-detected corner, ~1 level pixel off
    uv_b, ok = al.align(image_levels(b, oct_), patches, np.where(cut_ok, oct_, -1), start)
    err = np.linalg.norm(uv_b - truth, axis=1)
    assert ok.mean() > 0.9
    # cv2.remap interpolates at 1/32 px steps: a noise-free shift comes out ~0.05 px off (a re-detected
    # ORB corner: 0.65 px at level 0 in the simulator)
    assert np.median(err[ok]) < 0.08 * 1.2 ** octave
    assert np.percentile(err[ok], 95) < 0.2 * 1.2 ** octave
    assert np.array_equal(uv_b[~ok], start[~ok])  # not aligned: the detection is kept


def test_a_patch_that_is_not_there_is_refused_and_the_detection_kept():
    al = PatchAligner(CameraModel(W_PX, H_PX, K))
    a, other = _texture(0), _texture(5)
    uv = np.random.default_rng(3).uniform(60, [W_PX - 60, H_PX - 60], (100, 2))
    oct_ = np.zeros(len(uv), int)
    patches, cut_ok = al.cut(image_levels(a, oct_), uv, oct_)
    uv_b, ok = al.align(image_levels(other, oct_), patches, oct_, uv)  # another scene: nothing matches
    assert ok.mean() < 0.05
    assert np.array_equal(uv_b[~ok], uv[~ok])
    far = uv + np.array([2.0 * MAX_SHIFT_PX + 2, 0.0])  # the right scene, but the start beyond reach
    uv_c, ok_c = al.align(image_levels(a, oct_), patches, oct_, far)
    assert not np.any(ok_c & (np.linalg.norm(uv_c - uv, axis=1) < 0.5))


def test_flat_and_edge_patches_are_not_cut_for_alignment():
    al = PatchAligner(CameraModel(W_PX, H_PX, K))
    img = np.full((H_PX, W_PX), 100, np.uint8)
    img[:, 320:] = 180  # a vertical edge: position along it is undetermined (aperture problem)
    uv = np.array([[100.0, 200.0], [320.0, 200.0]])
    oct_ = np.zeros(2, int)
    _, ok = al.cut(image_levels(img, oct_), uv, oct_)
    assert not ok.any()
    near_border = np.array([[2.0, 2.0]])
    _, ok = al.cut(image_levels(_texture(0), oct_[:1]), near_border, oct_[:1])
    assert not ok.any()


def test_distorted_camera_positions_stay_undistorted_pixels():
    """Patches are cut and aligned in the distorted image; what goes in and out are undistorted
    pixels (slam.features.Features), so a pure image shift becomes the undistortion of it."""
    dist = np.array([-0.12, 0.03, 0.0005, -0.0003, 0.0])
    cam = CameraModel(W_PX, H_PX, K, dist)
    al = PatchAligner(cam)
    a = _texture(0)
    shift = (1.6, 0.7)
    b = _shifted(a, shift, gain=1.0, offset=0.0, seed=4)
    rng = np.random.default_rng(5)
    d_a = rng.uniform(80, [W_PX - 80, H_PX - 80], (150, 2))  # distorted pixels in a
    def undist(d):
        return cv2.undistortPoints(d.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2)
    oct_ = np.zeros(len(d_a), int)
    patches, cut_ok = al.cut(image_levels(a, oct_), undist(d_a), oct_)
    truth = undist(d_a + shift)
    uv, ok = al.align(image_levels(b, oct_), patches, np.where(cut_ok, 0, -1), undist(d_a + shift + rng.uniform(-0.8, 0.8, d_a.shape)))
    assert ok.mean() > 0.9
    assert np.median(np.linalg.norm(uv[ok] - truth[ok], axis=1)) < 0.08
