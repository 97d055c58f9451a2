"""TerraSLAM companion: process, CLI, supervision and camera sources (no SLAM/GIS/MAVLink logic)."""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("terraslam")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+source"
