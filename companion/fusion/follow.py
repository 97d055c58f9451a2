"""Alignments follow their points (beyond the papers): an alignment says where the SLAM points it
was registered on lie on the globe, but bundle adjustment keeps moving those points in SLAM
coordinates. On `nominal` seed 2 one periodic 25-keyframe BA moved the newest keyframes 1.2–1.4 m
along the track (a flat direction of its cost: 1085 against 1089 for the map before it, which was
0.1 m from the truth); the tracked pose followed the moved points and every fix jumped 1.3 m, 0.6 s
after GNSS was lost, and stayed off until the next registrations (2.1–2.5 m mean after the loss in
the 3 of 5 runs with that BA, 1.2 m in the 2 without). So each registration keeps the points it
was computed on (Cloud), and when local mapping moves them, its alignment moves with them by their
least-squares similarity (follow_points; companion.pipeline.Localizer._follow_map decides when):
what a registration of the moved points would find, to first order. A local BA that moves only the
newest of them hardly moves it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from companion.fusion.sigma import inflate_alignment
from gis.sim3 import umeyama
from gis.types import Alignment

FOLLOW_MIN_M = 0.05  # a move of the alignment's points is followed once it shifts the fix this much
FOLLOW_EVENT_M = 0.3  # ... and goes into the alignment timeline from this much on
CARRY_SIGMA_FRACTION = 0.5  # a registration carried by a move it cannot test: + this × the move (1-σ; a wrong carry is 2σ off)


@dataclass
class Cloud:
    """The SLAM points a registration was computed on (Localizer._follow_map): point_ids sorted,
    p_slam (N, 3) where they were when last followed; alignment: the alignment they carry (for the
    submitted cloud, the prior it was registered from); version: the local map last compared with;
    t_s: the registration's time (submitted cloud)."""

    alignment: Alignment
    point_ids: np.ndarray
    p_slam: np.ndarray
    version: int = -1
    t_s: float = math.nan


def follow_points(cloud: Cloud, alignment: Alignment, lm, c_slam: np.ndarray,
                  widen: bool) -> tuple[Alignment, np.ndarray, np.ndarray, float] | None:
    """``alignment`` carried by the move of ``cloud``'s points to where local map ``lm`` holds them
    (points it does not hold count as unmoved): (the followed alignment, the points' new positions,
    which of them ``lm`` holds, how far that moves the fix at SLAM camera centre ``c_slam`` in
    metres); None while that is below FOLLOW_MIN_M or the points' similarity is degenerate.
    ``widen``: the move could not be tested against the track, + CARRY_SIGMA_FRACTION of it in σ."""
    k = np.minimum(np.searchsorted(lm.point_ids, cloud.point_ids), len(lm.point_ids) - 1)
    held = lm.point_ids[k] == cloud.point_ids
    p_now = cloud.p_slam.copy()
    p_now[held] = lm.p_slam[k[held]]
    # a similarity of points none of which moved FOLLOW_MIN_M cannot move a fix among them by more
    if alignment.T_ecef_slam.scale * float(np.abs(p_now - cloud.p_slam).max(initial=0.0)) < FOLLOW_MIN_M / 2:
        return None
    try:
        S_inv = umeyama(cloud.p_slam, p_now).inverse()  # new SLAM coordinates → old
    except ValueError:  # degenerate cloud (collinear): leave the alignment where it is
        return None
    moved_m = float(np.linalg.norm(alignment.T_ecef_slam.apply(S_inv.apply(c_slam)) - alignment.T_ecef_slam.apply(c_slam)))
    if moved_m < FOLLOW_MIN_M:
        return None
    followed = replace(alignment, T_ecef_slam=alignment.T_ecef_slam @ S_inv,
                       center_slam=S_inv.inverse().apply(np.asarray(alignment.center_slam, float)))
    if widen:
        followed = inflate_alignment(followed, CARRY_SIGMA_FRACTION * moved_m)
    return followed, p_now, held, moved_m
