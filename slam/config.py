"""Config section ``slam`` (validated; unknown keys are errors)."""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class SlamConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    feature_backend: Literal["cpu", "torch"] = Field("cpu", description="ORB path: OpenCV on CPU or torch patch-parallel (TerraSLAM §5.1)")
    torch_device: str = Field("cpu", description="torch device for the torch backend, e.g. 'cpu', 'cuda:0'")
    n_features: int = Field(1500, ge=100, le=20000, description="features per frame (1500: 20 repeatable bench runs 0.665 -> 0.579 m after the GNSS loss against 1000, free-running 0.61 -> 0.42 m; tracking +3-4 ms and fine-tuning +40 ms on 2 cores; docs/BENCHMARKS.md, \"Features per frame\")")
    torch_low_contrast_std_dn: float = Field(20.0, ge=0, le=255, description="torch backend: a frame whose intensity std is below this (DN) is denoised and stretched first (slam.features.normalise_contrast), as the OpenCV path does for frames short of FAST corners; simulator `dark` frames 9-10 DN, `nominal` 33-38; 0: never")
    n_patches: int = Field(256, ge=1, le=4096, description="image patches for GPU-parallel extraction (§5.1)")
    local_window: int = Field(10, ge=2, le=100, description="local BA window w in keyframes (§5.2)")
    progressive_local_mapping: bool = Field(True, description="PLM: BA over w/2 inside the reliable region (§5.2, Eq. 4)")
    loop_closing: Literal["off", "full", "recursive"] = Field("full", description="loop correction: one BA over the whole loop (full) or TerraSLAM's recursive windows (§5.3, Alg. 1), both after the loop_shares correction. `loop` flight, 75-s GNSS denials, seeds 0-7: full 0.43-1.47 m 3D after the loss, a fix on 5363 of 5992 denied frames; recursive 0.66-2.30 m, 4302 (Alg. 1 stops at its reliable region; a flown loop drifts all the way round). Cost: ~1.6 s for a 144-keyframe loop on 2 cores against ~0.5 s (docs/BENCHMARKS.md, \"Full or recursive loop closing\")")
    use_attitude_prior: bool = Field(False, description="use the autopilot's gravity direction (AttitudePrior.gravity_cam): gravity-aligned initial map, gravity factors in every BA. Experimental: levels the map, but measured worse ATE on nominal (scale drift), docs/BENCHMARKS.md")
    attitude_prior_sigma_deg: float = Field(1.0, gt=0, le=30, description="1-sigma of the autopilot's roll/pitch for the gravity factors when the prior carries none (AHRS: ~0.5-1 deg)")
    # tracking
    patch_alignment: bool = Field(True, description="a keyframe observes each map point where the image patch the point was first seen with aligns (Lucas-Kanade, slam/patches.py), not at the re-detected ORB corner: 0.17-0.27 px from the true position instead of 0.84-0.99 px in the simulator; triangulation, fusing and bundle adjustment use these (docs/BENCHMARKS.md)")
    min_inliers: int = Field(25, ge=6, le=500, description="PnP inliers needed to call a frame tracked")
    search_radius_px: float = Field(12.0, gt=0, le=200, description="projection search radius around the motion-model prediction (px); retried at 3x")
    refine_radius_px: float = Field(4.0, gt=0, le=50, description="search radius of the second matching pass after the first pose (px)")
    pnp_reproj_px: float = Field(3.0, gt=0, le=20, description="PnP inlier reprojection gate (px)")
    keyframe_inlier_ratio: float = Field(0.75, gt=0, le=1, description="new keyframe when inliers drop below this share of the reference keyframe's")
    min_frames_between_keyframes: int = Field(3, ge=1, le=100, description="earliest keyframe after the last one (frames)")
    triangulation_min_baseline_ratio: float = Field(0.05, ge=0, le=0.5, description="new points only from keyframe pairs at least this share of the scene depth apart (the 2 newest of the last 8; else the previous keyframe); 0: the 2 previous keyframes")
    keyframe_max_rotation_deg: float = Field(10.0, gt=0, le=180, description="new keyframe once the camera has turned this much since the last one (turns)")
    max_frames_between_keyframes: int = Field(20, ge=1, le=1000, description="latest keyframe after the last one (frames)")
    init_min_matches: int = Field(150, ge=30, le=5000, description="feature matches needed to attempt/keep two-view initialization")
    init_min_flow_px: float = Field(20.0, gt=0, le=300, description="median feature motion before trying two-view initialization (px)")
    reloc_keyframes: int = Field(60, ge=2, le=10000, description="most recent keyframes whose points relocalization searches")
    reloc_place_candidates: int = Field(3, ge=0, le=20, description="keyframes anywhere in the map that place recognition finds most like a lost frame; relocalization searches their points (and 2 neighbours' each) too")
    reloc_min_inliers: int = Field(40, ge=10, le=1000, description="PnP inliers needed to accept a relocalization")
    reset_after_lost_frames: int = Field(90, ge=1, le=100000, description="frames lost before the map is abandoned and re-initialized (reset_counter+1)")
    # mapping
    fuse_keyframes: int = Field(10, ge=0, le=200, description="after triangulating, a new keyframe's points are fused with those of this many most covisible keyframes: missed observations joined, duplicate points merged (ORB-SLAM SearchInNeighbors; slam.map_points.fuse_points); 0: off")
    local_map_keyframes: int = Field(20, ge=2, le=500, description="keyframes whose points form the tracker's local map")
    ba_iterations: int = Field(5, ge=1, le=100, description="Levenberg-Marquardt iterations per local BA")
    ba_nice: int = Field(0, ge=0, le=19, description="run the BA worker process this much below the tracking's priority (Unix niceness; 0: the same). On 2 shared cores 10 lowered the tracking latency P99 in 15 of 18 free-running bench flights (means 37.4 -> 35.1, 45.3 -> 40.3, 41.9 -> 40.5 ms) but the error after the GNSS loss was higher in 11 of 18 (0.52 -> 0.57 m mean): opt-in (docs/BENCHMARKS.md, \"Bundle adjustment at a lower priority\")")
    ba_fixed_keyframes: int = Field(10, ge=0, le=100, description="most fixed border keyframes (that see the window's points) in a local BA; 0: local_window/2, at least 2. More anchors hold the scale through turns")
    periodic_ba_every_keyframes: int = Field(5, ge=0, le=1000, description="every N keyframes the background BA covers periodic_ba_window keyframes instead of the local window (0: off)")
    periodic_ba_window: int = Field(30, ge=2, le=1000, description="keyframes optimised by the periodic larger BA (halved by PLM while the motion is inside the Eq. 4 reliable region)")
    max_reproj_px: float = Field(3.0, gt=0, le=20, description="observations above this reprojection error after BA are dropped (px)")
    max_keyframes: int = Field(400, ge=20, le=100000, description="keyframes kept whole (features, points, place-index entry); older ones are forgotten or kept as loop anchors (slam/mapping.py _forget_old)")
    loop_anchor_every: int = Field(10, ge=1, le=10000, description="every N-th keyframe leaving the max_keyframes window stays as a loop anchor (features + points + place-index entry, ~100-150 KB each)")
    max_loop_anchors: int = Field(200, ge=0, le=100000, description="loop-anchor cap: beyond it every second anchor is forgotten (older places thinner)")
    max_trajectory_keyframes: int = Field(20000, ge=0, le=10000000, description="poses of forgotten keyframes kept for the trajectory (~0.5 KB each); the oldest go beyond it")
    max_queued_map_updates: int = Field(32, ge=1, le=10000, description="MapUpdates held for poll_map_updates; the oldest are dropped beyond it (a full snapshot replaces all queued)")
    # loop closing
    loop_min_gap_keyframes: int = Field(30, ge=5, le=10000, description="a loop candidate must be this many keyframes older than the query")
    loop_min_score: float = Field(0.06, gt=0, le=1, description="place-recognition score a loop candidate needs: DBoW2 L1 score of the tf-idf word vectors (slam/place.py), 0 nothing in common .. 1 identical. With the shipped vocabulary, revisits in the simulator score ~0.11 (median), the best unrelated place ~0.05 (median, at most ~0.06): `python -m companion.slam_bench.place_eval recall`")
    loop_min_inliers: int = Field(30, ge=6, le=1000, description="Sim(3) RANSAC inliers needed to accept a loop")
