"""Camera calibration files → ``CameraModel`` + undistortion.

Reads both common on-disk forms with ``cv2.FileStorage`` (it parses YAML and JSON):

* OpenCV's calibration sample / tutorial output (``%YAML`` header, ``!!opencv-matrix`` nodes)::

    image_width: 640
    image_height: 480
    camera_matrix: !!opencv-matrix {rows: 3, cols: 3, dt: d, data: [fx, 0, cx, 0, fy, cy, 0, 0, 1]}
    distortion_coefficients: !!opencv-matrix {rows: 5, cols: 1, dt: d, data: [k1, k2, p1, p2, k3]}

* ROS ``camera_info`` YAML (``camera_calibration`` package output): the same keys, matrices as
  plain ``{rows, cols, data}`` maps, plus ``distortion_model`` (only ``plumb_bob`` /
  ``rational_polynomial`` — OpenCV's pinhole model — are accepted; fisheye is refused by name).

Undistortion (``cv2.initUndistortRectifyMap`` + ``cv2.remap``) maps every image to an ideal pinhole
camera of the same size whose K comes from ``cv2.getOptimalNewCameraMatrix`` with alpha=0, i.e. only
valid pixels (no black borders that would create spurious corners for the feature detector).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from slam.types import CameraModel

PINHOLE_DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")


class CalibrationError(ValueError):
    """A calibration file is missing, malformed or describes an unsupported camera model."""


@dataclass(frozen=True)
class Calibration:
    """raw: the camera as calibrated; model: the camera after ``undistort`` (dist = 0).

    map_x / map_y: ``cv2.remap`` tables (float32, HxW); None when the lens has no distortion.
    """

    raw: CameraModel
    model: CameraModel
    map_x: np.ndarray | None
    map_y: np.ndarray | None

    def undistort(self, image: np.ndarray) -> np.ndarray:
        """Remap one image (calibrated size) to the undistorted pinhole ``model``."""
        h, w = image.shape[:2]
        if (w, h) != (self.raw.width_px, self.raw.height_px):
            raise CalibrationError(
                f"image is {w}x{h} px but the calibration is for {self.raw.width_px}x{self.raw.height_px} px"
            )
        if self.map_x is None:
            return image
        return cv2.remap(image, self.map_x, self.map_y, interpolation=cv2.INTER_LINEAR)


def _matrix(fs: cv2.FileStorage, key: str, path: Path) -> np.ndarray:
    node = fs.getNode(key)
    if node.empty():
        raise CalibrationError(f"{path}: missing key '{key}'")
    if not node.getNode("dt").empty():  # OpenCV !!opencv-matrix
        mat = node.mat()
    else:
        # ROS camera_info style: {rows, cols, data: [...]} without an OpenCV type tag
        data = node.getNode("data")
        if not data.isSeq():
            raise CalibrationError(f"{path}: '{key}' must be an OpenCV matrix or a {{rows, cols, data}} map")
        values = [data.at(i).real() for i in range(data.size())]
        rows, cols = int(node.getNode("rows").real()), int(node.getNode("cols").real())
        if rows * cols != len(values):
            raise CalibrationError(f"{path}: '{key}' has rows={rows} cols={cols} but {len(values)} data values")
        mat = np.array(values, dtype=float).reshape(rows, cols)
    mat = np.asarray(mat, dtype=float)
    if not np.all(np.isfinite(mat)):
        raise CalibrationError(f"{path}: '{key}' contains non-finite values")
    return mat


def _size(fs: cv2.FileStorage, key: str, path: Path) -> int:
    node = fs.getNode(key)
    if node.empty() or not (node.isInt() or node.isReal()):
        raise CalibrationError(f"{path}: missing or non-numeric key '{key}'")
    value = int(node.real())
    if value <= 0:
        raise CalibrationError(f"{path}: '{key}' must be positive, got {value}")
    return value


def read_camera_model(path: Path | str) -> CameraModel:
    """The calibrated (distorted) camera in ``path``; CalibrationError names the file and key."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"calibration file not found: {path}")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:  # OpenCV's parser error surfaces as SystemError in Python
        cause = e.__cause__ if isinstance(e, SystemError) and e.__cause__ is not None else e
        detail = getattr(cause, "err", str(cause))
        raise CalibrationError(f"{path}: not a readable OpenCV/ROS calibration YAML ({detail})") from None
    try:
        if not fs.isOpened():
            raise CalibrationError(f"{path}: could not be opened as YAML/JSON")
        model_node = fs.getNode("distortion_model")
        if not model_node.empty():
            name = model_node.string()
            if name not in PINHOLE_DISTORTION_MODELS:
                raise CalibrationError(
                    f"{path}: distortion_model '{name}' is not supported (use one of {', '.join(PINHOLE_DISTORTION_MODELS)})"
                )
        width, height = _size(fs, "image_width", path), _size(fs, "image_height", path)
        K = _matrix(fs, "camera_matrix", path)
        dist = _matrix(fs, "distortion_coefficients", path).ravel()
    finally:
        fs.release()
    if K.shape != (3, 3):
        raise CalibrationError(f"{path}: camera_matrix must be 3x3, got {K.shape[0]}x{K.shape[1]}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1.0) > 1e-9 or np.any(K[1:, 0]) or K[2, 1] != 0:
        raise CalibrationError(f"{path}: camera_matrix is not an intrinsics matrix [[fx,s,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0")
    if dist.size not in (4, 5, 8, 12, 14):
        raise CalibrationError(f"{path}: distortion_coefficients must have 4, 5, 8, 12 or 14 values, got {dist.size}")
    return CameraModel(width_px=width, height_px=height, K=K, dist=dist)


def make_calibration(raw: CameraModel) -> Calibration:
    """Undistortion maps for ``raw`` and the resulting distortion-free camera (same image size)."""
    size = (raw.width_px, raw.height_px)
    if not raw.is_distorted:
        return Calibration(raw=raw, model=raw, map_x=None, map_y=None)
    K_new, _roi = cv2.getOptimalNewCameraMatrix(raw.K, raw.dist, size, 0.0, size)
    map_x, map_y = cv2.initUndistortRectifyMap(raw.K, raw.dist, None, K_new, size, cv2.CV_32FC1)
    model = CameraModel(width_px=raw.width_px, height_px=raw.height_px, K=K_new, dist=np.zeros(5))
    return Calibration(raw=raw, model=model, map_x=map_x, map_y=map_y)


def load_calibration(path: Path | str) -> Calibration:
    """Read an OpenCV or ROS calibration YAML and prepare its undistortion."""
    return make_calibration(read_camera_model(path))


def write_calibration(path: Path | str, camera: CameraModel) -> None:
    """Write ``camera`` in OpenCV's calibration-sample format (what ``load_calibration`` reads)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", int(camera.width_px))
        fs.write("image_height", int(camera.height_px))
        fs.write("camera_matrix", np.asarray(camera.K, dtype=float))
        fs.write("distortion_coefficients", np.asarray(camera.dist, dtype=float).reshape(-1, 1))
    finally:
        fs.release()
