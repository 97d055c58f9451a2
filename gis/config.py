"""Config sections ``gis`` and ``alignment`` (validated; unknown keys are errors)."""
from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, model_validator

AUTO_SITE = "auto"  # gis.site: the cached site covering the rough position (TerraSLAM §6 Pre-fetch, then Fetch)


class GisConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    cache_dir: Path = Field(Path("~/.cache/terraslam/gis"), description="GIS cache (SQLite index + model files)")
    model: Path | None = Field(None, description="GIS model file to use directly (any supported format)")
    site: str | None = Field(None, description="instead of model: a site of the GIS cache (what `terraslam gis import` or `gis fetch` stored; `gis ls` lists them), or `auto`: the cached site covering the rough position (TerraSLAM §6 Pre-fetch), else one fetched from fetch_sources around it")
    rough_position_deg: tuple[float, float] | None = Field(None, description="site auto: [lat, lon] WGS-84 degrees of the flight area, where the site is looked up; without it, the saved SLAM map's site (a restart in flight) or the autopilot's first trusted GNSS position")
    position_wait_s: float = Field(300.0, gt=0, le=86_400, description="site auto without rough_position_deg or a fresh saved map: wait this long for a trusted GNSS position from the autopilot, then exit (1: systemd starts it again)")
    fetch_sources: list[str] = Field(default_factory=list, description="site auto: model files, directories or http(s):// 3D Tiles tileset URLs to fetch from (within fetch_radius_m) when no cached site covers the position; the result is cached as a new site")
    use_survey_map: bool = Field(True, description="start in the site's survey SLAM map with its T_rough (`terraslam align-offline`) when no saved map with a usable alignment exists: fixes without GNSS from the first relocalised frame")
    survey_reloc_timeout_s: float = Field(900.0, gt=0, le=86_400, description="started in the survey map: relocalise in it within this long (frame time: on the ground before take-off too), else a fresh map (GNSS bootstrap as usual)")
    survey_reach_m: float = Field(300.0, gt=0, le=100_000, description="started in the survey map and not relocalised yet: trusted GNSS farther than this from every survey keyframe gives the survey map up at once (fresh map, GNSS bootstrap), instead of waiting survey_reloc_timeout_s without a map")
    fetch_radius_m: float = Field(10_000.0, gt=0, le=100_000, description="fetch models within this radius of the rough position (TerraSLAM §6)")
    fetch_timeout_s: float = Field(30.0, gt=0, le=600)
    sample_spacing_m: float = Field(1.0, gt=0.05, le=20, description="surface sampling of meshes/polygons when loading a model (one point per spacing²); 3D Tiles are loaded at the coarsest level whose geometric error is at most this")
    footprint_ground_h_msl_m: float | None = Field(None, ge=-500, le=9000, description="the site's ground height above MSL for building footprints that carry no heights (OSM, GeoJSON without z); such files are refused without it or footprint_ground_dem")
    footprint_ground_dem: Path | None = Field(None, description="a terrain model (GeoTIFF DTM, heights' datum as for any GeoTIFF model) under building footprints that carry no heights: each stands on it at its outline's lowest vertex (hilly sites: one ground height is metres off); instead of footprint_ground_h_msl_m")

    @model_validator(mode="after")
    def _one_of_each(self) -> "GisConfig":
        if self.footprint_ground_h_msl_m is not None and self.footprint_ground_dem is not None:
            raise ValueError("set footprint_ground_h_msl_m or footprint_ground_dem, not both")
        if self.model is not None and self.site is not None:
            raise ValueError("set gis.model or gis.site, not both")
        if self.site != AUTO_SITE:
            unused = [k for k in ("rough_position_deg", "fetch_sources") if getattr(self, k)]
            if unused:
                raise ValueError(f"gis.{unused[0]} is only used with gis.site: {AUTO_SITE}")
        if self.rough_position_deg is not None:
            lat, lon = self.rough_position_deg
            if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
                raise ValueError(f"gis.rough_position_deg {[lat, lon]} is not [lat, lon] in degrees "
                                 "(latitude -90..90, longitude -180..180)")
        return self

    @property
    def footprint_ground(self) -> float | Path | None:
        """What footprints without heights stand on (gis.loaders.Ground)."""
        return self.footprint_ground_dem.expanduser() if self.footprint_ground_dem is not None else self.footprint_ground_h_msl_m


class AlignmentConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    finetune_every_frames: int = Field(200, ge=1, le=100_000, description="online ICP fine-tuning period (TerraSLAM §4.4)")
    finetune_every_frames_denied: int = Field(50, ge=1, le=100_000, description="fine-tuning period while GNSS is not trusted (we are the position source: keep the drifting map registered)")
    crop_size_m: float = Field(150.0, gt=10, le=5000, description="side of the GIS crop used for registration (digital-twin §III-E)")
    min_fitness: float = Field(0.2, ge=0, le=1, description="registration rejected below this inlier fraction (real monocular SLAM at the right place: 0.25-0.35; wrong basins 6-10 m off: 0.02-0.27, so the prior/basin gates of gis.align.fine do the rest)")
    max_rmse_m: float = Field(1.0, gt=0, description="registration rejected above this inlier RMSE")
    max_jump_m: float = Field(5.0, gt=0, description="registration rejected if it moves the map more than this")
    bootstrap_from_gnss: bool = Field(True, description="without T_rough, bootstrap the alignment from good GNSS (digital-twin §III-D)")
    source_voxel_m: float = Field(0.5, gt=0, le=20, description="voxel size for the SLAM points before fine-tuning")
    target_voxel_m: float = Field(1.0, gt=0, le=20, description="voxel size for the cropped GIS model before fine-tuning")
    max_correspondence_m: float = Field(3.0, gt=0, le=50, description="first (widest) ICP correspondence distance; halved twice (coarse-to-fine)")
    robust_kernel_m: float = Field(0.5, gt=0, le=10, description="narrowest Tukey kernel width on point-to-plane residuals (outliers, stale model); coarser ICP levels use half their correspondence distance when wider")
    inlier_distance_m: float = Field(0.5, gt=0, le=10, description="a SLAM point is an inlier (fitness, RMSE) within this point-to-plane distance")
    min_points: int = Field(50, ge=10, le=1_000_000, description="registration rejected with fewer SLAM points in the crop")
    finetune_min_parallax_deg: float = Field(8.0, ge=0, le=60, description="SLAM points whose first and last observing keyframes see them under a smaller angle are left out of fine-tuning (depth error grows as 1/parallax); 0 keeps all. 8: after-loss 3D error lower in 3 of 4 bench runs (nominal/stale, seeds 0/1), 5 and 12 worse on stale (docs/BENCHMARKS.md)")
    finetune_recent_keyframes: int = Field(0, ge=0, le=100_000, description="only SLAM points observed by one of the newest N keyframes go into fine-tuning; 0 keeps all. A revisited area holds an older layer of points placed under an older, drifted SLAM frame, which anchors the registration at the old alignment (docs/BENCHMARKS.md, \"Long denials\")")
    max_sigma_m: float = Field(0.5, gt=0, description="registration rejected when the data alone (σ²H⁻¹, Eq. 8–9) leave a position 1-σ above this along their weakest direction (degeneracy, e.g. one facade); not the reported σ")
    max_sigma_rot_deg: float = Field(2.0, gt=0, le=180, description="registration rejected when its weakest rotation 1-σ exceeds this")
    max_sigma_scale: float = Field(0.05, gt=0, le=1, description="registration rejected when the relative scale 1-σ exceeds this")
    sigma_floor_m: float = Field(0.05, gt=0, le=10, description="lower bound of the per-point residual σ used for the alignment information")
    finetune_threads: int = Field(1, ge=0, le=256, description="OpenMP threads of fine-tuning's nearest-neighbour searches (pykdtree), in the background worker only; 1 leaves the other cores to tracking and mapping, 0 uses every core. On 2 cores: replayed alone 86 → 73 ms wall per registration with 2, but 103 → 245 ms in the demo flight, where OpenMP's threads spin against tracking (docs/BENCHMARKS.md)")
    fpfh_fallback: bool = Field(False, description="when ICP from the guess fails, retry from an FPFH+RANSAC global registration (off: seconds per try, and on sparse SLAM clouds vs dense models it rarely finds the right pose)")
    model_sigma_m: float = Field(0.25, ge=0, le=100, description="1-σ absolute accuracy of the GIS model's georeference, added to every fix (a fix cannot beat its map); while GNSS is good it is tested, and a model found metres off is corrected (gis/align/georef.py)")
    slam_scale_drift_per_100m: float = Field(0.02, ge=0, le=1, description="relative 1-σ drift of the monocular SLAM map's scale per 100 m flown: a registration's prior scale σ grows by this × distance / 100 m from the prior's centre (measured: registrations 40-50 m apart saw the scale change 1.5-2.5 % while the prior held 0.4 %; with 0.02 and Kalman updates the demo flight's horizontal error after the loss over seeds 0-5 went from 1.56 to 1.19 m mean, docs/BENCHMARKS.md)")
    denial_sigma_per_m: float = Field(0.0, ge=0, le=1, description="while GNSS is not trusted, every fix's horizontal 1-σ is at least this × the distance flown since it was (0: off). Registrations in a long denial can lock onto a wrong optimum and claim ~1 m (docs/BENCHMARKS.md, \"Registrations replayed offline\"); 0.03 kept four long `loop` denials within 3σ before the SLAM-jump term was held in a denial, which alone keeps eight of them within 3σ (docs/BENCHMARKS.md, \"Long denials: honest by default\"); at 0.03 h_acc passes 5 m after ~170 m of denial")
    velocity_sigma_floor_mps: float = Field(0.3, ge=0, le=10, description="1-σ added (in quadrature) to the velocity fit's own σ in every fix's speed accuracy: SLAM positions carry errors that change over about a second, which the fit's residuals do not show (gis/fix_velocity.py). Measured in two `terraslam sitl --autopilot ardupilot` flights: the fit's σ alone left the velocity error at 1.3× it (RMS, per axis) and 5-7 % of fixes beyond 3σ; with 0.3 m/s, 0.9-1.05× and 0.6-2.9 %")
    slam_drift_fraction: float = Field(0.02, ge=0, le=1, description="SLAM drift per metre travelled away from the last alignment's centre, added to a fix's σ (measured: 1-3 % locally after GNSS loss at 10 fps, turns included, although the whole-run ATE is 0.3-0.4 %; 0.01 let 1.3 % of fixes exceed 3σ in one run, 0.03 made ArduPilot drop our fixes as too vague)")
