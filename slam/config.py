"""Config section ``slam`` (validated; unknown keys are errors)."""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class SlamConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    feature_backend: Literal["cpu", "torch"] = Field("cpu", description="ORB path: OpenCV on CPU or torch patch-parallel (TerraSLAM §5.1)")
    torch_device: str = Field("cpu", description="torch device for the torch backend, e.g. 'cpu', 'cuda:0'")
    n_features: int = Field(1000, ge=100, le=20000, description="features per frame")
    n_patches: int = Field(256, ge=1, le=4096, description="image patches for GPU-parallel extraction (§5.1)")
    local_window: int = Field(10, ge=2, le=100, description="local BA window w in keyframes (§5.2)")
    progressive_local_mapping: bool = Field(True, description="PLM: BA over w/2 inside the reliable region (§5.2, Eq. 4)")
    loop_closing: Literal["off", "full", "recursive"] = Field("recursive", description="loop correction: full-loop optimisation or recursive (§5.3, Alg. 1)")
    use_attitude_prior: bool = Field(False, description="use autopilot gravity/baro priors (off until it measurably helps)")
