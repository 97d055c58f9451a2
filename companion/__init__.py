"""TerraSLAM companion: process, CLI, supervision and camera sources (no SLAM/GIS/MAVLink logic)."""
import os
from importlib.metadata import PackageNotFoundError, version

# OpenBLAS (numpy's and scipy's) must run single-threaded here, set before numpy is first imported:
# the service forks worker processes (bundle adjustment, GIS fine-tuning) while other threads may be
# inside a BLAS call, and OpenBLAS's fork handler stops its thread pool under them — that thread then
# spins forever (seen: the camera thread stuck in exec_blas in 1 of ~7 service starts). Our BLAS
# calls are small (3x3 to 4x4 matrices, per-ray products); threads bought nothing.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

try:
    __version__ = version("terraslam")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+source"
