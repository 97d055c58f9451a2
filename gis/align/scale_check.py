"""The barometer against the SLAM map under the camera (beyond the papers), for the fine-tuner
(gis.align.fine).

- Barometer check (beyond the papers; with ``camera_h_ell_m``): before the ICP, the barometric
  height of the camera over the level GIS surface under each SLAM point near nadir, divided by
  its SLAM height under the alignment (nadir_scale_ratio); if even the lower quartile of these
  ratios is above 1 + MAX_SCALE_MISMATCH, or even the upper quartile below 1 − MAX_SCALE_MISMATCH
  (3σ order-statistic bounds), the registration is refused with SCALE_MISMATCH_REASON and the
  pipeline withholds fixes (the map under the camera no longer has the alignment's scale).
  ``check_scale`` runs the same test alone on the points the camera is tracking now (within
  TRACKED_RADIUS_M); the pipeline calls it every second between registrations. A registration's
  crop mixes older points, which may still fit after the map's scale broke under the camera: at
  the first registration after demo seed 4's break the points near nadir gave a median ratio of
  0.65 with a robust SD of 0.24, too mixed to flag.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from gis.align.crop import _Crop, _in_square

# Scale check against the barometer (beyond the papers; docs/BENCHMARKS.md "Fine-tuning update"):
SCALE_MISMATCH_REASON = "SLAM scale under the camera disagrees with the barometer"
NADIR_RADIUS_M = 30.0          # SLAM points within this horizontal distance of the camera are tested
NADIR_MIN_POINTS = 20          # fewer: no test
TRACKED_MAX_SCALE_MISMATCH = 0.12  # check_scale's tolerance: a frame over trees the model lacks read a lower
                               # quartile up to 1.077 (demo seeds 1, 2, 4); offline, maps shrunk 20 % were flagged
                               # by 99–100 % of the checks, 15 % by 48–94 %, 10 % by 13–18 % (docs/BENCHMARKS.md)
                               # quartile up to 1.077 (demo seeds 1, 2, 4); offline, maps shrunk 20 % were flagged
                               # by 99–100 % of the checks, 15 % by 48–94 %, 10 % by 13–18 % (docs/BENCHMARKS.md)
TRACKED_RADIUS_M = 150.0       # check_scale: the tracked points this close (horizontally); a forward-looking
                               # camera's are 40–200 m away (a 0.5° tilt error then moves k by ≤ 2 %)
                               # camera's are 40–200 m away (a 0.5° tilt error then moves k by ≤ 2 %)
SURFACE_RADIUS_M = 1.5         # the model surface under a point: level model points this close (horizontally)
WALL_RADIUS_M = 3.0            # ... and no wall of the model this close: a point on a facade, a metre or two off
                               # it, found only ground (or roof) within SURFACE_RADIUS_M and read k ≈ 1.5 (`loop` seed 1)
                               # it, found only ground (or roof) within SURFACE_RADIUS_M and read k ≈ 1.5 (`loop` seed 1)
SURFACE_STEP_M = 1.0           # level model surfaces under a point further apart in height: an edge, no test
LEVEL_NORMAL_Z = 0.8           # a model point on a level surface (ground, roof): |normal up-component| above this
# |k − 1| tolerated beyond the quartiles' 3σ bounds (demo seeds 0/4/5: good registrations' medians
# 0.946–1.022, the scale break 1.080–1.084)
MAX_SCALE_MISMATCH = 0.06
#: SLAM scale errors measured lie within a few tens of percent (breaks in turns: 6–20 %); a median ratio
#: outside these bounds (or not positive: the model's surface above the camera) is no scale error SLAM
#: makes: the GIS model's heights are off (a wrong vertical datum or unit, an ignored offset)
PLAUSIBLE_SCALE_RATIO = (0.5, 2.0)


@dataclass(frozen=True)
class ScaleCheck:
    """The barometer against the SLAM map under the camera (nadir_scale_ratio): per point, k_i =
    barometric ÷ SLAM height of the camera over the model surface under the point."""

    ratio: float     # median k_i (nan: too few points to test)
    low: float       # lower 3σ confidence bound of the 25 % quantile of k_i
    high: float      # upper 3σ confidence bound of the 75 % quantile of k_i
    n_points: int
    tolerance: float = MAX_SCALE_MISMATCH

    @property
    def mismatch(self) -> bool:
        """The map under the camera is not at the alignment's scale: even its lower quarter of
        points is more than ``tolerance`` too close to the camera (the map shrank), or even its
        upper quarter too far (it grew)."""
        return math.isfinite(self.ratio) and (self.low > 1.0 + self.tolerance or self.high < 1.0 - self.tolerance)

    @property
    def model_heights_suspect(self) -> bool:
        """The ratio is far beyond any SLAM scale error (PLAUSIBLE_SCALE_RATIO): the model's heights are
        more likely wrong than the map's scale."""
        lo, hi = PLAUSIBLE_SCALE_RATIO
        return math.isfinite(self.ratio) and not lo <= self.ratio <= hi

    def describe(self) -> str:
        text = (f"ratio {self.ratio:.3f} over {self.n_points} points, quartiles beyond {self.low:.3f} … "
                f"{self.high:.3f} (3σ; tolerance 1 ± {self.tolerance:g})")
        if self.model_heights_suspect:
            lo, hi = PLAUSIBLE_SCALE_RATIO
            text += (f"; a ratio outside {lo:g} … {hi:g} is no SLAM scale error: the GIS model's heights or vertical "
                     "datum are suspect (check the model file's vertical CRS and unit, or its .georef.json 'vertical', "
                     "'vertical_unit' and 'offset_m')")
        return text


def nadir_scale_ratio(src: np.ndarray, crop: _Crop, c: np.ndarray, up_baro_m: float,
                      radius_m: float = NADIR_RADIUS_M, tolerance: float = MAX_SCALE_MISMATCH) -> ScaleCheck:
    """The ratios, over the SLAM points p_i within radius_m (horizontally) of the camera, of

        k_i = (up_baro_m − (z_model(p_i) − c_z)) / (−p_i,z)

    with src the points in ENU centred on the camera (the camera at 0), up_baro_m the barometric
    camera height in the same coordinates, and z_model the height of the level model surface
    (ground, roof: normal within ~37° of vertical) within SURFACE_RADIUS_M of p_i horizontally that
    is nearest to p_i in height. Points over walls only, and points near an edge (level model
    surfaces more than SURFACE_STEP_M apart in height within that radius: roof and ground) are
    skipped: a map a few percent off in scale moves its points metres sideways there, onto the
    other surface (in a box city 25 % of the points read k_i < 0.8 or > 1.15 before). So are points
    with a wall of the model within WALL_RADIUS_M: a point on a facade that its triangulation put a
    metre or two off the wall finds only the ground within SURFACE_RADIUS_M, and reads the height
    of the facade above it as scale (`loop` seed 1: 55–65 % of the tested points, lower quartile's
    bound 1.17–1.18 and fixes withheld at 78 s and for the rest of the denial from 212 s, while the
    track kept its scale within 3 %; without them 1.01, median 1.06).
    k_i is the true height of the
    camera over what it sees divided by the height the SLAM map and the alignment give it: 1 when
    the map under the camera has the alignment's scale, 1.06 at every point when it has shrunk 6 %
    (a scale break in a turn). A vertical shift of the alignment moves camera and points together
    and leaves k alone.

    Quartiles, not the median: points on what the model lacks (trees, cars, new buildings) sit
    above its surface and read k_i > 1 (a 10 m tree under a camera 76 m up: 1.15), and points on
    walls read anything. Measured on demo seed 1 at 67–70 s, over trees: median 1.23–1.32 while the
    camera moved at the alignment's scale (0.94–1.07 per second against truth); the lower
    quartile's bound stayed ≤ 1.06. A
    shrunk map moves even its lowest (ground) points, so the lower quartile; a grown one the upper.
    Their bounds are order statistics at ranks n·q ∓ 3·√(n·q·(1 − q)) (binomial: no distribution
    assumed, and narrow where the ground points crowd). Written by hand: sorting and two ranks.
    Not tested (nan) with fewer than NADIR_MIN_POINTS usable points."""
    near = src[(np.hypot(src[:, 0], src[:, 1]) < radius_m) & (src[:, 2] < -1.0)]
    untested = ScaleCheck(float("nan"), float("nan"), float("nan"), len(near), tolerance)
    if len(near) < NADIR_MIN_POINTS:
        return untested
    q = near[:, :2] + c[:2]
    i0, j0, i1, j1 = crop.box  # either tree finds the same neighbours, in the same order
    if (2 * (radius_m + WALL_RADIUS_M)) ** 2 < 0.5 * (i1 - i0 + 1) * (j1 - j0 + 1) * crop.tile_m ** 2:
        # a registration's check, in the crop's middle: a tree over the points it can reach
        local = np.flatnonzero(_in_square(crop.points, c, radius_m + WALL_RADIUS_M))
        hits = cKDTree(crop.points[local, :2], balanced_tree=False).query_ball_point(q, WALL_RADIUS_M)
    else:  # check_scale's wide radius: the crop's own tree, built once for the crop
        local, hits = None, crop.tree_en.query_ball_point(q, WALL_RADIUS_M)
    # The neighbourhoods flattened to (point, model point) pairs, in the search's order: one
    # numpy pass instead of a Python loop per point (check_scale tests ~1000 points).
    counts = np.fromiter(map(len, hits), np.intp, count=len(hits))
    owner = np.repeat(np.arange(len(near)), counts)
    j = np.fromiter(itertools.chain.from_iterable(hits), np.intp, count=int(counts.sum()))
    if local is not None:
        j = local[j]
    walled = np.zeros(len(near), bool)  # one level surface (ground, roof) only, and no wall near
    walled[owner[np.abs(crop.normals[j, 2]) <= LEVEL_NORMAL_Z]] = True
    keep = ~walled[owner] & (np.hypot(*(crop.points[j, :2] - q[owner]).T) <= SURFACE_RADIUS_M)
    owner, z = owner[keep], crop.points[j[keep], 2]
    z_model = np.full(len(near), np.nan)
    if len(owner):
        # by point, then by height from the point (stable: the search's order among ties)
        order = np.lexsort((np.abs(z - (near[owner, 2] + c[2])), owner))
        owner, z = owner[order], z[order]
        first = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
        level = np.maximum.reduceat(z, first) - np.minimum.reduceat(z, first) <= SURFACE_STEP_M
        z_model[owner[first[level]]] = z[first[level]]
    ok = np.isfinite(z_model)
    n = int(ok.sum())
    if n < NADIR_MIN_POINTS:
        return replace(untested, n_points=n)
    k = np.sort((up_baro_m - (z_model[ok] - c[2])) / (-near[ok, 2]))
    half = 3.0 * math.sqrt(n * 0.25 * 0.75)
    low = k[max(int(math.floor(0.25 * n - half)), 0)]
    high = k[min(int(math.ceil(0.75 * n + half)), n - 1)]
    return ScaleCheck(float(np.median(k)), float(low), float(high), n, tolerance)
