"""Progressive local mapping and recursive loop closing control flow (TerraSLAM §5.2-§5.3).

Pure functions over keyframe camera centres; the BA itself is passed in, so the control flow is
testable on constructed trajectories.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np


@dataclass(frozen=True)
class ReliableRegion:
    center: np.ndarray  # (3,) c_{k+w}
    radius: float  # r_{k+w}

    def contains(self, p: np.ndarray) -> bool:
        return bool(np.linalg.norm(np.asarray(p) - self.center) <= self.radius)


def reliable_region(prev_centers: np.ndarray, prev_t_s: np.ndarray | None = None,
                    t_next_s: float | None = None) -> ReliableRegion:
    """TerraSLAM Eq. 4 from the w previous positions p_{I_k} .. p_{I_{k+w-1}} (oldest first).

    c_{k+w} = p_{k+w-1} + (p_{k+w-1} - p_k) / w,   r_{k+w} = ||p_{k+w-1} - p_k|| / (3w).

    Eq. 4 assumes evenly spaced frames. Keyframes are not, so with times given the step d/w and the
    radius are scaled by (t_next - t_last) / mean spacing, which is Eq. 4 exactly when the spacing
    is even (our extension, needed because keyframes come every 3 to 20 frames).
    """
    prev = np.asarray(prev_centers, float)
    if len(prev) < 2:
        raise ValueError(f"reliable_region needs at least 2 previous positions, got {len(prev)}")
    w = len(prev)
    d = prev[-1] - prev[0]
    k = 1.0
    if prev_t_s is not None and t_next_s is not None:
        mean_dt = (prev_t_s[-1] - prev_t_s[0]) / (w - 1)
        if mean_dt > 0:
            k = (t_next_s - prev_t_s[-1]) / mean_dt
    return ReliableRegion(prev[-1] + k * d / w, k * float(np.linalg.norm(d)) / (3 * w))


def plm_window(prev_centers: np.ndarray, vo_center: np.ndarray, w: int, prev_t_s: np.ndarray | None = None,
               t_s: float | None = None) -> int:
    """Local-BA window for the new keyframe (§5.2): w/2 when the VO estimate is inside R, else w."""
    if len(prev_centers) < 2:
        return w
    region = reliable_region(prev_centers[-w:], None if prev_t_s is None else prev_t_s[-w:], t_s)
    return max(2, w // 2) if region.contains(vo_center) else w


def in_reliable_region(centers: Sequence[np.ndarray], i: int, w: int, times_s: Sequence[float] | None = None) -> bool:
    """Is keyframe i inside the reliable region built from the (up to) w keyframes before it?"""
    lo = max(0, i - w)
    if i - lo < 2:
        return True  # too little history to call the motion unstable
    if times_s is None:
        return reliable_region(np.asarray(centers[lo:i])).contains(centers[i])
    return reliable_region(np.asarray(centers[lo:i]), np.asarray(times_s[lo:i]), times_s[i]).contains(centers[i])


def recursive_loop_closing(start: int, current: int, w: int, ba: Callable[[list[int]], None],
                           centers: Callable[[], Sequence[np.ndarray]],
                           times_s: Sequence[float] | None = None) -> list[list[int]]:
    """Algorithm 1 (Recursive Loop Closing) over keyframe indices; returns the BA windows run.

    ``ba(indices)`` optimizes those keyframes (and their points) in place; ``centers()`` returns the
    current camera centres of all keyframes (read again after every BA); ``times_s`` the keyframe
    times for uneven spacing (see reliable_region).
    """
    windows: list[list[int]] = []

    def run(idx: list[int]) -> None:
        windows.append(idx)
        ba(idx)

    # Line 1: initial BA on [start, start+w] ∪ [current-w, current]
    run(sorted(set(range(start, min(start + w, current) + 1)) | set(range(max(current - w, start), current + 1))))
    probe = current - w
    # Lines 2-4
    if probe <= start or in_reliable_region(centers(), probe, w, times_s):
        return windows
    temp = probe  # Line 6
    while temp > start:  # Line 7
        run(list(range(max(temp - w, start), min(temp + w, current) + 1)))  # Line 8
        if temp - w <= start or in_reliable_region(centers(), temp - w, w, times_s):  # Line 9
            return windows  # Lines 10-11
        temp -= w  # Line 13
    return windows
