"""Config sections ``gis`` and ``alignment`` (validated; unknown keys are errors)."""
from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field


class GisConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    cache_dir: Path = Field(Path("~/.cache/terraslam/gis"), description="GIS cache (SQLite index + model files)")
    model: Path | None = Field(None, description="GIS model file to use directly (any supported format)")
    fetch_radius_m: float = Field(10_000.0, gt=0, le=100_000, description="fetch models within this radius of the rough position (TerraSLAM §6)")
    fetch_timeout_s: float = Field(30.0, gt=0, le=600)


class AlignmentConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    finetune_every_frames: int = Field(200, ge=1, le=100_000, description="online ICP fine-tuning period (TerraSLAM §4.4)")
    crop_size_m: float = Field(150.0, gt=10, le=5000, description="side of the GIS crop used for registration (digital-twin §III-E)")
    min_fitness: float = Field(0.3, ge=0, le=1, description="registration rejected below this inlier fraction")
    max_rmse_m: float = Field(1.0, gt=0, description="registration rejected above this inlier RMSE")
    max_jump_m: float = Field(5.0, gt=0, description="registration rejected if it moves the map more than this")
    bootstrap_from_gnss: bool = Field(True, description="without T_rough, bootstrap the alignment from good GNSS (digital-twin §III-D)")
