"""The survey SLAM map: our SLAM over a survey dataset's frames, saved with its T_rough so that the
service can start in it without GNSS (TerraSLAM §4.3: the online SLAM shares the survey's frame, so
T_rough applies online).

``terraslam align-offline`` maps the survey (``map_survey``), computes T_rough on a COLMAP
reconstruction of the same frames (gis/align/survey.py, gis/align/rough.py), carries it into the
map's frame through the camera centres of the keyframes (``gis.align.survey.register_centres``)
and writes the map with it (``save_survey_map``) into the GIS cache. The service loads it through
``companion.persistence.load_survey``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from companion.app import ATTITUDE_MAX_AGE_S
from companion.persistence import SURVEY_ALIGNMENT, alignment_json
from companion.pipeline import attitude_prior
from gis.sim3 import Sim3
from gis.types import Alignment, AlignmentSource
from slam.config import SlamConfig
from slam.persist import SavedMap
from slam.types import CameraModel


class SurveyMappingFailed(RuntimeError):
    """Our SLAM could not map the survey; the message says why."""


@dataclass
class SurveyMap:
    slam: object                       # slam.system.SlamSystem, still open (saved once T_rough is known)
    keyframe_centres: dict[str, np.ndarray]  # frame file name → camera centre in the map's frame
    tracking_ratio: float              # frames tracked / frames

    def close(self) -> None:
        self.slam.close()


def map_survey(camera: CameraModel, steps: Iterable, frame_names: list[str], config: SlamConfig,
               progress: Callable[[int, int], None] | None = None, min_keyframes: int = 6) -> SurveyMap:
    """Run our SLAM over the survey's frames (``steps``: SimStep of a dataset or the simulator, with
    the recorded attitude as the replay gives it) and return the map with its keyframes' camera
    centres by frame name (``frame_names[frame.seq]``). A map reset during the survey keeps only the
    last map: SurveyMappingFailed if it holds fewer than ``min_keyframes``. Every keyframe is kept
    whole (``slam.max_keyframes`` raised to the frame count): the memory cap would forget all but
    every 10th of a survey longer than ~4 minutes, and the service keeps a survey map whole too."""
    from slam.system import SlamSystem
    from slam.types import TrackingState

    slam = SlamSystem(camera, config.model_copy(update={"max_keyframes": max(config.max_keyframes, len(frame_names))}))
    n, tracked, last_att = len(frame_names), 0, None
    try:
        for k, step in enumerate(steps):
            last_att = step.attitude[-1] if step.attitude else last_att
            fresh = last_att is not None and step.frame.t_s - last_att.t_s <= ATTITUDE_MAX_AGE_S
            pose = slam.track(step.frame, attitude_prior(last_att) if fresh else None)
            tracked += pose.state in (TrackingState.OK, TrackingState.RELOCALIZED)
            if progress is not None:
                progress(k + 1, n)
        slam.wait_mapping()
        m = slam.mapper.map
        with m.lock:
            centres = {frame_names[kf.seq]: np.asarray(kf.center, float) for kf in m.keyframes.values() if 0 <= kf.seq < n}
    except BaseException:
        slam.close()
        raise
    if len(centres) < min_keyframes:
        slam.close()
        raise SurveyMappingFailed(f"SLAM kept {len(centres)} keyframes of {n} survey frames (need ≥ {min_keyframes}); "
                                  f"tracked {tracked} frames")
    return SurveyMap(slam, centres, tracked / max(n, 1))


def survey_alignment(sm: SurveyMap, T_ecef_slam: Sim3, sigma_m: float) -> Alignment:
    """T_rough of the survey map as an Alignment about the centre of its keyframes: isotropic
    position 1-σ ``sigma_m`` (metres) there, and rotation and scale 1-σ of sigma_m over the
    keyframes' RMS distance from it (a fit that is ``sigma_m`` off is that much off across the
    survey, not only at its centre). SLAM drift counts only beyond the keyframes' farthest
    distance from the centre (``drift_free_radius_m``): the service holds the survey map's
    keyframes and points, so within it the flight is tracked against the map T_rough registers."""
    map_id, reset_counter = sm.slam.current_map_key()
    c = np.array(list(sm.keyframe_centres.values()))
    centre = np.median(c, axis=0)
    d_m = T_ecef_slam.scale * np.linalg.norm(c - centre, axis=1)  # keyframes from the centre, metres
    radius_m = max(float(np.sqrt(np.mean(d_m**2))), sigma_m)
    rel = sigma_m / radius_m
    info = np.diag([1 / rel**2] * 3 + [1 / sigma_m**2] * 3)
    # the service holds the survey map (slam/mapping.py): no SLAM drift across it, only beyond it
    return Alignment(T_ecef_slam, AlignmentSource.ROUGH, time.monotonic(), reset_counter, info, float(sigma_m),
                     map_id=map_id, center_slam=centre, scale_sigma=rel, drift_free_radius_m=float(d_m.max()))


def save_survey_map(sm: SurveyMap, path: Path, alignment: Alignment, site_id: str) -> SavedMap:
    """Write the survey map with its T_rough (header attachment ``SURVEY_ALIGNMENT``) for ``site_id``."""
    saved = sm.slam.save_map(path, {SURVEY_ALIGNMENT: alignment_json(alignment, site_id)})
    if saved is None:
        raise SurveyMappingFailed("the survey map holds no keyframes")
    return saved
