"""The validated application config: one model per section, YAML file + TERRASLAM_* overrides.

Sections: camera, slam, gis, alignment, mavlink, switching, supervisor, persistence, recording, logging. Each
package owns its section's model (slam/config.py, gis/config.py, mavlink_bridge/config.py); this module owns
camera/supervisor/persistence/recording/logging and the root.

Environment overrides: ``TERRASLAM_<SECTION>__<KEY>=value`` (double underscore between levels),
e.g. ``TERRASLAM_MAVLINK__CONNECT=/dev/ttyTHS1``. Values are parsed as YAML scalars.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal, Mapping

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from gis.config import AlignmentConfig, GisConfig
from mavlink_bridge.config import MavlinkConfig, SwitchingConfig
from slam.config import SlamConfig

DEFAULT_CONFIG_PATH = Path(__file__).resolve().parent.parent / "config" / "default.yaml"
ENV_PREFIX = "TERRASLAM_"


class CameraConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    source: str = Field("sim", description="'sim', V4L2 index or /dev/videoN, video file, image folder, rtsp:// URL or GStreamer pipeline")
    calibration: Path | None = Field(None, description="OpenCV-style YAML with K, distortion, size")
    width_px: int = Field(640, ge=16, le=8192)
    height_px: int = Field(480, ge=16, le=8192)
    fps: float = Field(30.0, gt=0, le=1000)
    fourcc: str | None = Field(None, min_length=4, max_length=4, description="V4L2 pixel format, e.g. MJPG")
    T_body_cam: list[list[float]] | None = Field(None, description="4x4 camera-to-body (FRD) mount; default nadir-free forward-oblique from the sim")
    stall_timeout_s: float = Field(2.0, gt=0, description="no frame for this long → reopen the source")
    sim_start_s: float = Field(0.0, ge=0, description="source 'sim' only: start the simulated flight at this flight time (s), e.g. to test a restart mid-flight")


class SupervisorConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    watchdog: bool = Field(True, description="send WATCHDOG=1 to systemd only while the pipeline makes progress")
    stage_restart_limit: int = Field(5, ge=0, description="restarts of a failed stage before giving up")
    state_dir: Path = Field(Path("~/.local/state/terraslam"), description="recordings and the saved SLAM map + alignment (slam_map.npz)")


class PersistenceConfig(BaseModel):
    """SLAM map persistence across restarts (docs/SERVICE.md "Restart during a GNSS outage")."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="save the SLAM map and its alignment to supervisor.state_dir/slam_map.npz; resume from it after a restart")
    save_every_s: float = Field(10.0, ge=1.0, le=3600.0, description="periodic map save in a background thread (also on each accepted alignment and at clean shutdown)")
    reloc_timeout_s: float = Field(15.0, gt=0, le=600.0, description="after a restart, relocalise in the saved map within this long (frame time), else start a fresh map and drop the restored alignment")
    restore_sigma_m: float = Field(0.5, ge=0, le=50.0, description="1-σ (m) added to a restored alignment for the restart (relocalisation, map refined after the alignment)")
    restore_sigma_growth_mps: float = Field(0.01, ge=0, le=10.0, description="1-σ (m) added per second of the alignment's age at the restart (wall clock)")
    max_restore_age_s: float = Field(1800.0, gt=0, description="an alignment older than this (wall clock) is not restored; the map still is")


class RecordingConfig(BaseModel):
    """Flight recorder (companion/recorder.py): what `terraslam run` feeds the pipeline, as a dataset
    (docs/DATASET.md) that `terraslam replay` reads back."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(False, description="record every run of the service to dir/flight-<UTC time>/")
    dir: Path | None = Field(None, description="where recordings go, one flight-<UTC time>/ folder per run (null: supervisor.state_dir/recordings)")
    image_format: Literal["jpg", "png"] = Field("jpg", description="jpg (q95: 170 kB, 1.4 ms a noisy 640x480 simulator frame here); png: lossless, replays to the bit, 3x larger, 13x slower")
    jpeg_quality: int = Field(95, ge=50, le=100)
    min_free_mb: float = Field(1000.0, ge=0, description="stop recording (the service goes on) when the disk has less free space")
    queue_frames: int = Field(64, ge=1, le=4096, description="frames waiting for the writer; when full, frames are left out of the recording, never delayed")


class LoggingConfig(BaseModel):
    level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    json_logs: bool = Field(False, alias="json", description="one JSON object per log line")
    rerun: Literal["off", "save", "serve", "spawn"] = Field("off", description="rerun-sdk visualisation")
    record_dir: Path | None = Field(None, description="where .rrd recordings and plots go")

    model_config = ConfigDict(extra="forbid", populate_by_name=True)


class AppConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    camera: CameraConfig = CameraConfig()
    slam: SlamConfig = SlamConfig()
    gis: GisConfig = GisConfig()
    alignment: AlignmentConfig = AlignmentConfig()
    mavlink: MavlinkConfig = MavlinkConfig()
    switching: SwitchingConfig = SwitchingConfig()
    supervisor: SupervisorConfig = SupervisorConfig()
    persistence: PersistenceConfig = PersistenceConfig()
    recording: RecordingConfig = RecordingConfig()
    logging: LoggingConfig = LoggingConfig()

    @model_validator(mode="after")
    def _frame_period_fits_fix_age(self) -> "AppConfig":
        # One fix per frame: a frame period longer than max_fix_age_s makes every fix stale before
        # the next one arrives, so the output would flap between a fix and NO_FIX.
        if 1.0 / self.camera.fps >= self.mavlink.max_fix_age_s:
            raise ValueError(
                f"camera.fps {self.camera.fps:g} gives a frame every {1.0 / self.camera.fps:.2f} s, not shorter than "
                f"mavlink.max_fix_age_s {self.mavlink.max_fix_age_s:g}: raise the frame rate or max_fix_age_s"
            )
        return self


class ConfigError(ValueError):
    """A config file or override is invalid; the message names key, value and expectation."""


def _format_validation_error(err: ValidationError, source: str) -> str:
    lines = [f"invalid configuration ({source}):"]
    for e in err.errors():
        key = ".".join(str(p) for p in e["loc"])
        if not key and e["type"] == "value_error":  # a cross-section check: its message names the keys
            lines.append("  " + str(e["msg"]).removeprefix("Value error, "))
        elif e["type"] == "extra_forbidden":
            lines.append(f"  {key}: unknown key (value {e.get('input')!r}); check spelling against `terraslam config dump`")
        else:
            lines.append(f"  {key}: got {e.get('input')!r}; expected {e['msg'].lower()}")
    return "\n".join(lines)


def _env_overrides(environ: Mapping[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, raw in environ.items():
        if not name.startswith(ENV_PREFIX) or "__" not in name:
            continue
        path = name[len(ENV_PREFIX):].lower().split("__")
        node = out
        for part in path[:-1]:
            node = node.setdefault(part, {})
        node[path[-1]] = yaml.safe_load(raw) if raw != "" else None
    return out


def _merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(merged.get(k), Mapping):
            merged[k] = _merge(merged[k], v)
        else:
            merged[k] = v
    return merged


def load_config(path: Path | str | None = None, environ: Mapping[str, str] | None = None) -> AppConfig:
    """Load ``path`` (default: config/default.yaml) and apply TERRASLAM_* overrides.

    Raises ConfigError naming the offending key, its value and what was expected.
    """
    path = Path(path) if path is not None else DEFAULT_CONFIG_PATH
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {path}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"config file {path} is not valid YAML: {e}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path}: top level must be a mapping of sections, got {type(data).__name__}")
    env = _env_overrides(os.environ if environ is None else environ)
    try:
        return AppConfig.model_validate(_merge(data, env))
    except ValidationError as e:
        src = str(path) + (" + TERRASLAM_* environment" if env else "")
        raise ConfigError(_format_validation_error(e, src)) from None


def dump_config(cfg: AppConfig) -> str:
    """The effective config as YAML (paths as strings, aliases as written in files)."""
    return yaml.safe_dump(cfg.model_dump(mode="json", by_alias=True), sort_keys=False)
