"""The real-time localisation pipeline: frames in, global fixes out (README.md, data flow).

Hot path, one thread, top to bottom per frame::

    frame ─▶ slam.track ─SlamPose─▶ globalizer.fix ─GlobalFix─▶ sink (MAVLink bridge, recorder)

Background: SLAM's own local-mapping/loop-closing threads, and one fine-tuning worker that every
``alignment.finetune_every_frames`` frames (``finetune_every_frames_denied`` while GNSS is not
trusted) registers the current SLAM map to the GIS model
(TerraSLAM §4.4) and hands the accepted T_fine to the Globalizer. Until an alignment exists, good
GNSS bootstraps one (digital-twin paper §III-D): pairs of (SLAM camera centre, GNSS position) are
collected while GNSS is trusted and fitted with a similarity.

Alignments follow their points (beyond the papers): an alignment says where the SLAM points it
was registered on lie on the globe, but bundle adjustment keeps moving those points in SLAM
coordinates. On `nominal` seed 2 one periodic 25-keyframe BA moved the newest keyframes 1.2–1.4 m
along the track (a flat direction of its cost: 1085 against 1089 for the map before it, which was
0.1 m from the truth); the tracked pose followed the moved points and every fix jumped 1.3 m, 0.6 s
after GNSS was lost, and stayed off until the next registrations (2.1–2.5 m mean after the loss in
the 3 of 5 runs with that BA, 1.2 m in the 2 without). So each registration keeps the points it
was computed on, and when local mapping moves them, its alignment moves with them by their
least-squares similarity (_follow_map): what a registration of the moved points would find, to
first order. A local BA that moves only the newest of them hardly moves it.

The pipeline knows no camera device, MAVLink or simulator: callers pass an iterator of
``PipelineInput`` and a sink; ``companion.app`` wires cameras, the bridge and the simulator.
"""
from __future__ import annotations

import collections
import logging
import math
import threading
import time
from concurrent.futures import CancelledError, Future
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace
from typing import Callable, Iterable, Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from gis.align.bootstrap import gnss_bootstrap
from gis.align.georef import GeorefCheck, GeorefCorrection, GeorefEvidence, IcpMeasurement
from gis.align.fine import NADIR_MIN_POINTS, SCALE_MISMATCH_REASON, FineTuner, ScaleCheck
from gis.align.journal import Journal, RegistrationJob
from gis.geodesy import R_NED_ENU, LocalFrame, R_ecef_enu, ecef_to_geodetic, geodetic_to_ecef
from gis.globalizer import Globalizer, with_horizontal_floor
from gis.sim3 import Sim3, umeyama
from gis.types import Alignment, AlignmentSource, GlobalFix
from mavlink_bridge.monitor import h_acc_of, h_ellipsoid_of
from mavlink_bridge.types import GnssSample, GpsFixType
from slam.geometry import gravity_cam_from_roll_pitch
from slam.types import AttitudePrior, Frame, SlamPose
from slam.worker import ForkedWorker

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PipelineInput:
    """One camera frame plus what the vehicle knew at its capture time.

    gnss: the latest receiver sample and whether the GNSS monitor trusts it (None when unknown).
    prior: optional autopilot attitude/baro prior for SLAM.
    """

    frame: Frame
    gnss: GnssSample | None = None
    gnss_trusted: bool = False
    prior: AttitudePrior | None = None


def attitude_prior(att) -> AttitudePrior | None:
    """The autopilot's attitude (bridge VehicleAttitude or a dataset AttitudeSample) as a pipeline prior."""
    if att is None:
        return None
    return AttitudePrior(att.t_s, att.roll_rad, att.pitch_rad, att.yaw_rad, getattr(att, "baro_alt_m", None))


def with_gravity(prior: AttitudePrior | None, R_cam_body: np.ndarray) -> AttitudePrior | None:
    """The prior with its gravity direction in the camera frame (g_cam = R_cam_body·R_ned_bodyᵀ·(0,0,1)),
    which is what SLAM uses (slam.use_attitude_prior); the camera mount stays on this side."""
    if prior is None or prior.gravity_cam is not None:
        return prior
    return replace(prior, gravity_cam=gravity_cam_from_roll_pitch(prior.roll_rad, prior.pitch_rad, R_cam_body))


@dataclass(frozen=True)
class FrameRecord:
    """What the pipeline did with one frame (the evaluation and the recorder read these)."""

    seq: int
    t_s: float
    pose: SlamPose
    fix: GlobalFix | None
    alignment_source: AlignmentSource | None
    wall_done_s: float  # time.monotonic() when the fix left the pipeline


@dataclass(frozen=True)
class GnssPair:
    """One receiver solution carried to a frame's time (and, with an attitude, from its antenna to
    the camera centre), with that frame's SLAM camera centre.

    R_ecef_enu: the local level frame at the GNSS position (for horizontal innovations);
    R_ecef_slam: the SLAM frame's orientation from the autopilot's attitude, or None."""

    t_s: float
    p_slam: np.ndarray
    p_ecef: np.ndarray
    R_ecef_enu: np.ndarray
    R_ecef_slam: np.ndarray | None
    h_acc_m: float
    v_acc_m: float


WALK_WINDOW_S = 10.0     # GNSS fits this far apart bound an undetected walk-off (Localizer._walk_floor)


def walk_from_m(fits: Iterable[Alignment], newest: Alignment, c_slam: np.ndarray,
                window_s: float = WALK_WINDOW_S) -> tuple[float, Alignment] | None:
    """How far (horizontally, metres) the newest GNSS fit puts the camera at ``c_slam`` (SLAM frame)
    from where the newest of ``fits`` at least ``window_s`` older than it puts it (same SLAM map),
    and that older fit; None without one. Two fits ``window_s`` apart, compared through the SLAM
    track, differ by what the receiver walked meanwhile, plus the older fit's own error carried
    that far (its extrapolated rotation and scale: ~3 m 20 s into the demo's clean flight) and the
    receiver's wander (Localizer._walk_floor). Beyond the papers."""
    old = None
    for a in fits:
        if (a.map_id, a.reset_counter) == (newest.map_id, newest.reset_counter) and a.t_s <= newest.t_s - window_s:
            if old is None or a.t_s > old.t_s:
                old = a
    if old is None:
        return None
    c = np.asarray(c_slam, float).reshape(1, 3)
    p_new = newest.T_ecef_slam.apply(c)[0]
    lat, lon, _ = ecef_to_geodetic(p_new)
    d = R_ecef_enu(float(lat), float(lon)).T @ (p_new - old.T_ecef_slam.apply(c)[0])
    return float(np.hypot(d[0], d[1])), old


@dataclass
class GnssConsistency:
    """Does GNSS move like visual odometry says we move? (beyond the papers; spoofing, issue 6)

    Innovation ν = horizontal GNSS position − the current alignment's prediction from the SLAM
    pose. Its slowly varying part (receiver bias, alignment error) is tracked by an exponential
    mean with time constant ``ema_s``; a sample more than ``gate_m`` from that mean is kept out of
    the alignment fits, and ``persist_s`` of such samples flags GNSS as inconsistent (a drifting or
    jumping spoofer) until it agrees again for as long. The mean is not updated while samples
    disagree, so a slow walk-off cannot drag it along. Defaults from a Monte Carlo with the
    simulator's standalone-receiver model (Gauss–Markov 2.7 m, τ 20 s + 0.7 m white): no false
    flag in 1 h of clean GNSS; a 10 m jump is flagged after persist_s, a 1 m/s walk-off after ~11 s
    (median). After a GNSS gap longer than ``reset_gap_s`` the mean restarts (vision drifted
    meanwhile; only the bridge's absolute test applies to the first samples).
    """

    gate_m: float = 5.0
    ema_s: float = 5.0
    persist_s: float = 2.0
    reset_gap_s: float = 2.0
    inconsistent: bool = False
    last_dev_m: float = 0.0
    _mean: np.ndarray | None = None
    _since: float | None = None
    _last_t: float | None = None

    def update(self, t_s: float, nu_en_m: np.ndarray) -> bool:
        """Feed one innovation (east, north metres); True when the sample may be used for fits."""
        nu = np.asarray(nu_en_m, float)[:2]
        if self._mean is None or self._last_t is None or t_s - self._last_t > self.reset_gap_s:
            self._mean, self._since, self.inconsistent = nu.copy(), None, False
        dt = t_s - self._last_t if self._last_t is not None else 0.0
        self._last_t = t_s
        self.last_dev_m = float(np.linalg.norm(nu - self._mean))
        agrees = self.last_dev_m <= self.gate_m
        if agrees != (not self.inconsistent):  # evidence against the current verdict
            self._since = t_s if self._since is None else self._since
            if t_s - self._since >= self.persist_s:
                self.inconsistent, self._since = not agrees, None
        else:
            self._since = None
        if agrees and not self.inconsistent:
            self._mean += min(1.0, max(dt, 0.0) / self.ema_s) * (nu - self._mean)
        return agrees and not self.inconsistent

    def offset_m(self, now_s: float, max_age_s: float) -> float | None:
        """|mean innovation| (horizontal metres) while innovations keep coming (the newest at most
        ``max_age_s`` before ``now_s``), else None."""
        if self._mean is None or self._last_t is None or now_s - self._last_t > max_age_s:
            return None
        return float(np.hypot(self._mean[0], self._mean[1]))

    def shift(self, d_en_m: np.ndarray) -> None:
        """The alignment changed: predictions moved by −d, so innovations move by +d."""
        if self._mean is not None:
            self._mean += np.asarray(d_en_m, float)[:2]

    def reset(self) -> None:
        self._mean, self._since, self._last_t, self.inconsistent = None, None, None, False


@dataclass(frozen=True)
class SurveyArea:
    """Where a site's survey map lies: its keyframes' camera centres in ECEF (metres) under its
    T_rough, and ``reach_m``, how far from the nearest of them a camera can still see what the
    survey saw (``gis.survey_reach_m``). Farther than that, relocalising in the survey map is not
    to be expected; waiting for it (``gis.survey_reloc_timeout_s``) would leave the vehicle with
    no SLAM map, so no GNSS bootstrap, until the wait ends."""

    keyframes_ecef_m: np.ndarray
    reach_m: float

    def distance_m(self, lat_deg: float, lon_deg: float, h_ellipsoid_m: float) -> float:
        """Horizontal distance (metres, in the local level frame at the position) from the
        position to the nearest survey keyframe."""
        d_enu = (self.keyframes_ecef_m - geodetic_to_ecef(lat_deg, lon_deg, h_ellipsoid_m)) @ R_ecef_enu(lat_deg, lon_deg)
        return float(np.min(np.hypot(d_enu[:, 0], d_enu[:, 1])))


@dataclass
class SlamSpeedCheck:
    """Is the SLAM map's scale still the one the alignment assumed? (integrity; beyond the papers)

    Monocular SLAM can lose its scale in a turn (the map shrinks 2–4× within seconds). Positions
    then drift at metres per second while the alignment's covariance still claims a metre — the
    worst failure a position source can have. While GNSS is available, its Doppler ground speed
    is an independent yardstick: the horizontal speed of the globalised SLAM track over
    ``window_s`` must match it within ``max_ratio_error`` whenever the vehicle moves faster than
    ``min_speed_mps``. A spoofer walking the position off at ≤ 1–2 m/s barely changes the ratio;
    a scale collapse changes it by tens of percent. Any mismatch withholds fixes at once
    (``suspect``); ``persist_s`` of it → ``broken`` (the alignment is dropped).

    The window keeps SLAM-frame positions and takes the displacement under the alignment of the
    latest sample: while GNSS is good a new alignment is adopted every few seconds, and the
    globalised positions of one window under two alignments differ by the change between them,
    which is not motion. The speed is the length of the component-wise median of the frame-to-frame
    horizontal velocities, not the window's end-to-end displacement: local mapping moves the map,
    and the tracked camera with it, by metres in one frame (bundle adjustment, loop closures; 3–9 m
    in a `loop` flight's second lap), which read as scale breaks (ratios 0.08–1.35) and dropped the
    alignment just before GNSS was lost, so no fix came for the rest of the flight
    (docs/BENCHMARKS.md, "Long `loop` denials on this machine"). A jump is one step of ~10; a scale
    break shrinks or stretches every step.
    """

    window_s: float = 1.0
    min_speed_mps: float = 3.0
    max_ratio_error: float = 0.3
    persist_s: float = 0.5
    broken: bool = False
    last_ratio: float = 1.0
    _hist: list[tuple[float, np.ndarray, float]] = field(default_factory=list)  # (t, camera centre in the SLAM frame, GNSS speed)
    _since: float | None = None

    def update(self, t_s: float, c_slam: np.ndarray, T_ecef_slam: Sim3, R_ecef_enu_: np.ndarray,
               gnss_speed_mps: float | None) -> bool:
        """Feed the SLAM camera centre, the current alignment and the GNSS ground speed; returns
        ``broken``."""
        if gnss_speed_mps is None or not math.isfinite(gnss_speed_mps):
            self._hist.clear()  # compare only over spans with GNSS speed throughout
            return self.broken
        if self._hist and t_s - self._hist[-1][0] > self.window_s:
            self._hist.clear()  # GNSS speed came back after a gap: a new span
        self._hist.append((t_s, np.asarray(c_slam, float), float(gnss_speed_mps)))
        while len(self._hist) > 2 and self._hist[1][0] <= t_s - self.window_s:
            self._hist.pop(0)
        t0 = self._hist[0][0]
        if t_s - t0 < 0.5 * self.window_s:
            return self.broken
        t = np.array([h[0] for h in self._hist])
        p_enu = T_ecef_slam.apply(np.array([h[1] for h in self._hist])) @ R_ecef_enu_  # rows: ENU axes, ECEF origin
        dt = np.diff(t)
        steps = dt > 0
        v_step = np.diff(p_enu[:, :2], axis=0)[steps] / dt[steps, None]
        v_vis = float(np.linalg.norm(np.median(v_step, axis=0)))
        v_gnss = float(np.mean([v for _, _, v in self._hist[1:]]))  # the same span's mean ground speed
        if max(v_vis, v_gnss) < self.min_speed_mps:
            self._since = None
            return self.broken
        self.last_ratio = v_vis / max(v_gnss, 1e-3)
        if abs(self.last_ratio - 1.0) > self.max_ratio_error:
            self._since = t_s if self._since is None else self._since
            if t_s - self._since >= self.persist_s:
                self.broken = True
        else:
            self._since = None
        return self.broken

    @property
    def suspect(self) -> bool:
        """Mismatch seen (not yet persistent) or broken: fixes are withheld meanwhile."""
        return self.broken or self._since is not None

    def reset(self) -> None:
        self._hist.clear()
        self._since, self.broken, self.last_ratio = None, False, 1.0

    def open_since(self, t_s: float) -> float | None:
        """When a mismatch that GNSS ground speed stopped coming for (a loss mid-check, ``window_s``
        or more before ``t_s``) was first seen; else None. Nothing here can settle it any more:
        fixes stay withheld (``suspect``) until ``settle`` with another test of the scale."""
        if self._since is None or self.broken or (self._hist and t_s - self._hist[-1][0] < self.window_s):
            return None
        return self._since

    def settle(self) -> None:
        """Another test of the scale passed after the open mismatch began (``open_since``)."""
        self._hist.clear()
        self._since, self.last_ratio = None, 1.0


@dataclass
class BootstrapCollector:
    """Pairs (SLAM camera centre, GNSS ECEF position) while GNSS is trusted (digital-twin §III-D).

    A fit needs a baseline: ``min_pairs`` pairs spanning ``min_baseline_m`` metres of GNSS track,
    so that yaw and scale are observable. Pairs are dropped when the SLAM map resets; only the
    last ``max_pairs`` are kept (monocular scale drifts: the fit should describe the recent map).
    Each GNSS position is carried to the frame's capture time with its reported velocity (a 0.1 s
    lag at 10 m/s would otherwise be a 1 m along-track bias). With ``T_body_cam`` and an attitude
    prior per frame, each pair also records the SLAM frame's orientation in ECEF
    (R_ecef_enu·R_enu_ned·R_ned_body·R_body_cam·R_slam_camᵀ) and the fit uses it for the rotation,
    and the receiver's position is carried from its antenna (``p_body_gnss_m``, FRD metres from the
    body origin: the autopilot's GPS_POS*/EKF2_GPS_POS_*) to the camera centre (T_body_cam's
    translation) along the attitude: R_ecef_body·(t_body_cam − p_body_gnss). Without an attitude
    that lever arm cannot be turned into the map, and its length is added to the pair's accuracy.
    """

    min_pairs: int = 30
    min_baseline_m: float = 40.0
    max_pairs: int = 150
    T_body_cam: np.ndarray | None = None
    p_body_gnss_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    max_prior_age_s: float = 0.1
    p_slam: list[np.ndarray] = field(default_factory=list)
    p_ecef: list[np.ndarray] = field(default_factory=list)
    R_ecef_slam: list[np.ndarray | None] = field(default_factory=list)
    t_s: list[float] = field(default_factory=list)
    h_acc_m: list[float] = field(default_factory=list)
    v_acc_m: list[float] = field(default_factory=list)
    map_key: tuple[int, int] | None = None
    last_refusal: str | None = None
    _last_gnss_t: float | None = None

    def _lists(self) -> tuple[list, ...]:
        return self.p_slam, self.p_ecef, self.R_ecef_slam, self.t_s, self.h_acc_m, self.v_acc_m

    def clear(self) -> None:
        for lst in self._lists():
            lst.clear()

    def add(self, pose: SlamPose, sample: GnssSample | None, trusted: bool, prior: AttitudePrior | None = None) -> None:
        """make_pair + append for a trusted sample (the Localizer gates pairs in between)."""
        pair = self.make_pair(pose, sample, prior)
        if pair is not None and trusted:
            self.append(pair)

    def make_pair(self, pose: SlamPose, sample: GnssSample | None, prior: AttitudePrior | None = None) -> GnssPair | None:
        """The pair for a new receiver solution at this frame, or None (no pose, repeated or
        incomplete sample). A new SLAM map (map_id / reset_counter) drops the old map's pairs."""
        key = (pose.map_id, pose.reset_counter)
        if key != self.map_key:
            for lst in self._lists():
                lst.clear()
            self.map_key = key
        if sample is None or not pose.state.has_pose or sample.fix_type < GpsFixType.FIX_3D:
            return None
        if sample.t_s == self._last_gnss_t:  # one pair per receiver solution
            return None
        self._last_gnss_t = sample.t_s
        h_ell = h_ellipsoid_of(sample)
        h_acc = h_acc_of(sample)
        v_acc = sample.v_acc_m if math.isfinite(sample.v_acc_m) and sample.v_acc_m > 0 else 1.6 * h_acc
        if not all(math.isfinite(x) for x in (sample.lat_deg, sample.lon_deg, h_ell, h_acc, v_acc)):
            return None  # an incomplete solution is no reference
        p_ecef = geodetic_to_ecef(sample.lat_deg, sample.lon_deg, h_ell)
        frame = LocalFrame(sample.lat_deg, sample.lon_deg, h_ell)
        dt = pose.t_s - sample.t_s
        if sample.vel_ned_mps is not None and abs(dt) <= 1.0:
            v_ned = np.nan_to_num(np.asarray(sample.vel_ned_mps, float))  # GPS_RAW_INT has no vertical speed
            p_ecef = frame.ned_to_ecef(v_ned * dt)
        R = None
        lever_body_m = (np.zeros(3) if self.T_body_cam is None else self.T_body_cam[:3, 3]) - np.asarray(self.p_body_gnss_m, float)
        if prior is not None and self.T_body_cam is not None and abs(prior.t_s - pose.t_s) <= self.max_prior_age_s:
            R_ned_body = Rotation.from_euler("ZYX", [prior.yaw_rad, prior.pitch_rad, prior.roll_rad]).as_matrix()
            R_ecef_body = frame.R_ecef_enu @ R_NED_ENU.T @ R_ned_body
            p_ecef = p_ecef + R_ecef_body @ lever_body_m  # antenna → camera centre
            R = R_ecef_body @ self.T_body_cam[:3, :3] @ np.asarray(pose.T_slam_cam, float)[:3, :3].T
        else:
            lever_m = float(np.linalg.norm(lever_body_m))
            h_acc, v_acc = math.hypot(h_acc, lever_m), math.hypot(v_acc, lever_m)
        return GnssPair(pose.t_s, pose.T_slam_cam[:3, 3].copy(), p_ecef, frame.R_ecef_enu, R, max(h_acc, 0.1), max(v_acc, 0.1))

    def append(self, pair: GnssPair) -> None:
        self.p_slam.append(pair.p_slam)
        self.p_ecef.append(pair.p_ecef)
        self.R_ecef_slam.append(pair.R_ecef_slam)
        self.t_s.append(pair.t_s)
        self.h_acc_m.append(pair.h_acc_m)
        self.v_acc_m.append(pair.v_acc_m)
        if len(self.p_slam) > self.max_pairs:
            for lst in self._lists():
                del lst[0]

    def ready(self) -> bool:
        if len(self.p_ecef) < self.min_pairs:
            return False
        pts = np.asarray(self.p_ecef)
        return float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0))) >= self.min_baseline_m

    def solve(self) -> Alignment | None:
        reset_counter = self.map_key[1] if self.map_key else 0
        map_id = self.map_key[0] if self.map_key else 0
        with_att = [i for i, R in enumerate(self.R_ecef_slam) if R is not None]
        use = with_att if len(with_att) >= self.min_pairs else list(range(len(self.p_slam)))
        h_acc = float(np.median([self.h_acc_m[i] for i in use]))
        try:
            return gnss_bootstrap(
                np.asarray([self.p_slam[i] for i in use]), np.asarray([self.p_ecef[i] for i in use]),
                t_s=self.t_s[-1], reset_counter=reset_counter, map_id=map_id,
                sigma_gnss_m=0.5,  # white per-axis noise floor of a code receiver; the fit's residuals raise it
                bias_sigma_h_m=h_acc, bias_sigma_v_m=float(np.median([self.v_acc_m[i] for i in use])),
                R_ecef_slam=np.asarray([self.R_ecef_slam[i] for i in use]) if use is with_att else None,
                t_pairs_s=np.asarray([self.t_s[i] for i in use]),
            )
        except ValueError as e:
            log.debug("GNSS bootstrap refused: %s", e)
            self.last_refusal = str(e)
            return None


_TUNER: FineTuner | None = None  # the fine-tuning process's own FineTuner (inherited through fork)


def _adopt_tuner(tuner: FineTuner) -> None:
    global _TUNER
    _TUNER = tuner


def _register_in_worker(points: np.ndarray, initial: Alignment, center: np.ndarray, t_s: float,
                        camera_h_ell_m: float | None, camera_h_sigma_m: float | None,
                        correction: GeorefCorrection | None) -> tuple[Alignment | None, str, float, float, IcpMeasurement | None]:
    """(alignment or None, reason, wall ms, CPU ms of the worker process, the ICP's own result) of
    one registration against the model under ``correction``."""
    t0, c0 = time.perf_counter(), time.process_time()
    _TUNER.set_correction(correction)
    reg = _TUNER.register(points, initial, t_s=t_s, reset_counter=initial.reset_counter, center_slam=center,
                          map_id=initial.map_id, camera_h_ell_m=camera_h_ell_m, camera_h_sigma_m=camera_h_sigma_m)
    return reg.alignment, reg.reason, (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3, reg.icp


def _prefetch_in_worker() -> bool:
    return _TUNER.prefetch_crop()


def _check_scale_in_worker(points: np.ndarray, alignment: Alignment, center: np.ndarray, camera_h_ell_m: float,
                           correction: GeorefCorrection | None) -> ScaleCheck:
    _TUNER.set_correction(correction)
    return _TUNER.check_scale(points, alignment, center, camera_h_ell_m)


class FineTuneWorker:
    """Runs FineTuner.register in its own process (``slam.worker.ForkedWorker``); at most one
    registration in flight (a new one is refused while busy).

    A process, not a thread: the registration is numpy/scipy with many small steps, so in a thread
    it competed with tracking and mapping for the GIL (measured: 85 ms alone, ~420 ms wall inside
    the pipeline on 2 cores) and lengthened tracking's frames. The worker is forked once with the
    tuner (GIS model and its crop cache stay in the child, nothing is re-sent per job); a job sends
    the SLAM points, the prior alignment and the model's georeference ``correction`` (set by the
    caller; gis.align.georef), and gets back the alignment or the rejection reason.
    ``wall_ms`` is each registration's wall time inside the worker, ``cpu_ms`` the CPU time it used
    (on a loaded 2-core board the two differ by the time the worker waited for a core). If the worker dies, the job in
    flight reports why, and the next submit starts a new worker (never an exception on the hot path).

    ``lag_s`` (offline runs on a simulated or recorded clock): a job's result is not handed over
    when it finishes but by ``release(t_s)`` once the flight clock has passed the job's time + lag_s,
    on the caller's thread, waiting for the job if it has not finished. Which frame adopts a result
    then depends on flight time alone, not on how fast this machine ran the loop, so a run repeats
    (live, lag_s is None: results are adopted as soon as they exist).
    """

    def __init__(self, tuner: FineTuner, on_result: Callable[[Alignment | None, str, float, IcpMeasurement | None], None],
                 on_scale_check: Callable[[Alignment, ScaleCheck], None] | None = None, lag_s: float | None = None):
        self._on_result = on_result
        self._on_scale_check = on_scale_check
        self.lag_s = lag_s
        self._held: collections.deque[tuple[float, Callable[[], None]]] = collections.deque()  # (due t_s, hand over)
        self.busy = threading.Event()
        self.checking = threading.Event()  # a scale check in flight
        self.wall_ms: list[float] = []
        self.cpu_ms: list[float] = []
        self.n_prefetched = 0  # GIS crops built ahead of a registration (_prefetch)
        self.correction: GeorefCorrection | None = None  # sent with every job
        self.journal: Journal | None = None  # writes each registration's inputs and outcome (gis.align.journal)
        self._lock = threading.Lock()
        self._proc = ForkedWorker("fine-tuning", initializer=_adopt_tuner, initargs=(tuner,))

    def submit(self, points_slam: np.ndarray, initial: Alignment, center_slam: np.ndarray, t_s: float,
               camera_h_ell_m: float | None = None, camera_h_sigma_m: float | None = None) -> bool:
        with self._lock:
            if self.busy.is_set():
                return False
            job = RegistrationJob(t_s, points_slam, initial, center_slam, camera_h_ell_m, camera_h_sigma_m, self.correction)
            fut = self._proc.submit(_register_in_worker, points_slam, initial, center_slam, t_s, camera_h_ell_m,
                                    camera_h_sigma_m, self.correction)
            self.busy.set()
        self._hand_over(t_s, fut, lambda f: self._done(f, job))
        return True

    def check_scale(self, points_slam: np.ndarray, alignment: Alignment, center_slam: np.ndarray,
                    camera_h_ell_m: float, t_s: float) -> bool:
        """Run FineTuner.check_scale in the worker (queued behind a registration in flight); the
        result goes to on_scale_check with the alignment it tested. At most one in flight: False
        (nothing submitted) while one is. ``t_s``: the frame's time (for ``lag_s``)."""
        with self._lock:
            if self.checking.is_set() or self._on_scale_check is None:
                return False
            fut = self._proc.submit(_check_scale_in_worker, points_slam, alignment, center_slam, camera_h_ell_m,
                                    self.correction)
            self.checking.set()
        self._hand_over(t_s, fut, lambda f: self._checked(f, alignment))
        return True

    def _hand_over(self, t_s: float, fut: Future, deliver: Callable[[Future], None]) -> None:
        if self.lag_s is None:
            fut.add_done_callback(deliver)
        else:
            self._held.append((t_s + self.lag_s, lambda: deliver(fut)))

    def release(self, t_s: float) -> None:
        """Hand over, in submission order, every held result due by flight time ``t_s`` (waiting
        for its job if it has not finished); ``math.inf`` hands over all. Nothing to do when
        lag_s is None."""
        while self._held and self._held[0][0] <= t_s:
            self._held.popleft()[1]()

    def _checked(self, fut: Future, alignment: Alignment) -> None:
        try:
            chk = fut.result()
        except Exception as e:  # CancelledError at close, a dead worker (restarted by the next submit)
            log.debug("scale check did not run: %s: %s", type(e).__name__, e)
            self.checking.clear()
            return
        self.checking.clear()
        self._on_scale_check(alignment, chk)

    def _done(self, fut: Future, job: RegistrationJob) -> None:
        try:
            alignment, reason, ms, cpu_ms, icp = fut.result()
        except CancelledError:
            self.busy.clear()
            return
        except BrokenProcessPool as e:  # the worker died (e.g. out of memory): restarted at the next submit
            log.error("fine-tuning worker died: %s", e)
            alignment, reason, ms, cpu_ms, icp = None, f"fine-tuning worker died: {e}", float("nan"), float("nan"), None
        except Exception as e:  # a failed registration must not kill the pipeline
            log.error("fine-tuning failed: %s: %s", type(e).__name__, e)
            alignment, reason, ms, cpu_ms, icp = None, f"exception: {type(e).__name__}: {e}", float("nan"), float("nan"), None
        if math.isfinite(ms):
            self.wall_ms.append(ms)
            self.cpu_ms.append(cpu_ms)
        if self.journal is not None:
            try:
                self.journal.record(job, alignment, reason)
            except OSError as e:  # a full disk must not stop the registrations
                log.warning("registration journal not written: %s", e)
        try:  # busy until the result is adopted: whoever sees the worker free sees its alignment
            self._on_result(alignment, reason, ms, icp)
            self._prefetch()  # queued before the next registration can be
        finally:
            self.busy.clear()

    def _prefetch(self) -> None:
        """The worker builds the next registration's GIS crop in its idle time after this one
        (FineTuner.prefetch_crop), so that registration, and the fix that waits for it, need not.
        Best effort: a closed or dead worker just builds the crop when it is asked for."""
        try:
            fut = self._proc.submit(_prefetch_in_worker)
        except (RuntimeError, BrokenProcessPool) as e:
            log.debug("GIS crop not prefetched: %s: %s", type(e).__name__, e)
            return
        fut.add_done_callback(self._prefetched)

    def _prefetched(self, fut: Future) -> None:
        if fut.cancelled():
            return
        if fut.exception() is not None:
            log.warning("GIS crop prefetch failed: %s: %s", type(fut.exception()).__name__, fut.exception())
        elif fut.result():
            self.n_prefetched += 1

    def close(self) -> None:
        self._proc.close()


def _baro_m(prior: AttitudePrior | None) -> float | None:
    """The prior's barometric altitude when it has a finite one, else None."""
    if prior is None or prior.baro_alt_m is None or not math.isfinite(prior.baro_alt_m):
        return None
    return prior.baro_alt_m


BARO_OFFSET_GAIN = 0.02  # per trusted GNSS pair (5 Hz): ~10 s time constant
BARO_NOISE_M = 0.3       # barometric height 1-σ beside the offset's (noise 0.15 m, drift 0.02 m/√s over a minute)
GEOREF_MAX_FIT_AGE_S = 5.0  # a GNSS fit at most this old is what a registration is compared with (gis.align.georef) and refines instead of a straying chain
SCALE_CHECK_EVERY_S = 1.0  # the barometer checks the map under the camera this often between registrations
RETRY_FRAMES = 10  # frames before fine-tuning tries again when the map had too few points
FOLLOW_MIN_M = 0.05  # a move of the alignment's points is followed once it shifts the fix this much
FOLLOW_EVENT_M = 0.3  # ... and goes into the alignment timeline from this much on
CARRY_SIGMA_FRACTION = 0.5  # a registration carried by a move it cannot test: + this × the move (1-σ; a wrong carry is 2σ off)
MAX_EVENTS = 10_000  # alignment timeline entries kept (~200 per 10 min of flight: days of service)


def _baro_ema(prev: float | None, value: float) -> float:
    """The barometer offset's running mean (and its σ's): BARO_OFFSET_GAIN per trusted pair."""
    return value if prev is None else prev + BARO_OFFSET_GAIN * (value - prev)


@dataclass
class _Cloud:
    """The SLAM points a registration was computed on (Localizer._follow_map): point_ids sorted,
    p_slam (N, 3) where they were when last followed; alignment: the alignment they carry (for the
    submitted cloud, the prior it was registered from); version: the local map last compared with;
    t_s: the registration's time (submitted cloud)."""

    alignment: Alignment
    point_ids: np.ndarray
    p_slam: np.ndarray
    version: int = -1
    t_s: float = math.nan


class Localizer:
    """SLAM + alignment + globalisation for one camera; ``process`` is the per-frame hot path."""

    def __init__(self, slam, tuner: FineTuner | None, globalizer: Globalizer, finetune_every_frames: int = 200,
                 finetune_every_frames_denied: int = 50,
                 initial_alignment: Alignment | None = None, bootstrap: BootstrapCollector | None = None,
                 min_points_for_finetune: int = 200, finetune_min_parallax_deg: float = 0.0,
                 finetune_recent_keyframes: int = 0, repeatable_lag_s: float | None = None,
                 denial_sigma_per_m: float = 0.0):
        """``repeatable_lag_s``: offline, repeatable runs only (``settle``); None live.
        ``denial_sigma_per_m``: alignment.denial_sigma_per_m (``_denial_floor``)."""
        self.slam = slam
        self.globalizer = globalizer
        self.repeatable = repeatable_lag_s is not None
        self.every = finetune_every_frames
        self.every_denied = finetune_every_frames_denied
        self.min_points = min_points_for_finetune
        self.min_parallax_deg = finetune_min_parallax_deg
        self.recent_keyframes = finetune_recent_keyframes
        self.denial_sigma_per_m = denial_sigma_per_m
        self._denied_m: float | None = None  # metres flown since GNSS was last trusted (None: it is)
        self._denied_cam: tuple[tuple[int, int], np.ndarray] | None = None  # (map key, SLAM camera) of the last frame
        self.bootstrap = bootstrap if bootstrap is not None else BootstrapCollector()
        self.gnss_check = GnssConsistency()
        self.speed_check = SlamSpeedCheck()
        self._unanchored = False  # the Globalizer's ``unanchored`` after the previous frame (_after_jump: its onset)
        self.alignment: Alignment | None = None
        # (t_s, text): alignment timeline, the newest MAX_EVENTS (a service runs for hours)
        self.events: collections.deque[tuple[float, str]] = collections.deque(maxlen=MAX_EVENTS)
        self._lock = threading.Lock()
        self._frames_since_tune = 0
        self._frames_since_boot = 0
        self._baro_offset_m: float | None = None  # ellipsoidal height − barometric altitude (learned from GNSS)
        self._baro_offset_sigma_m: float | None = None  # ... and the GNSS vertical 1-σ it was learned from
        self.rebootstrap_every = 30  # frames between GNSS re-fits while GNSS is trusted
        self._last_pose: SlamPose | None = None
        self._cloud: _Cloud | None = None      # the current alignment's points (_follow_map)
        self._lm_prev = None                   # the local map the previous frame's pose was solved against
        self._submitted: _Cloud | None = None  # the last registration's points, as submitted
        self._tuner = tuner
        # the GIS model's georeference against GNSS (gis.align.georef): the newest GNSS fit, and
        # (t_s, camera centre, GNSS fit) of the registration in flight when GNSS was trusted at its submission
        self.georef = GeorefCheck(tuner.config.model_sigma_m) if tuner is not None else None
        self._gnss_fit: Alignment | None = None
        self._gnss_fits: collections.deque[Alignment] = collections.deque(maxlen=16)  # recent fits (_walk_floor)
        self._georef_job: tuple[float, np.ndarray, Alignment] | None = None
        self._scale_check_t_s = -math.inf
        self._scale_confirmed: tuple[float, str] | None = None  # (t_s, by what) of the latest passed test of the scale
        # (t_s, check) of the recent barometer checks between registrations (diagnostics)
        self.scale_checks: collections.deque[tuple[float, ScaleCheck]] = collections.deque(maxlen=MAX_EVENTS)
        self.worker = (FineTuneWorker(tuner, self._on_finetune, self._on_scale_check, lag_s=repeatable_lag_s)
                       if tuner is not None else None)
        self._survey_area: SurveyArea | None = None  # while SLAM waits to relocalise in a survey map
        self.on_event: Callable[[float, str], None] | None = None  # (t_s, text) of each event, as it happens (the service logs them)
        if initial_alignment is not None:
            self._accept(initial_alignment, "initial")

    def _follow_map(self, pose: SlamPose, alignment: Alignment, lm, lm_prev) -> Alignment:
        """Carry a registration along when local mapping moves its points (module doc, "Alignments
        follow their points"). A registration keeps the SLAM points it was computed on (_Cloud:
        the submitted map points in its crop). When the local map the pose was solved against
        (``lm``) holds some of them elsewhere, the similarity S from their old to their new
        positions (Umeyama 1991; points it does not hold count as unmoved) makes the alignment
        T_ecef_slam ∘ S⁻¹ and its centre S·center_slam; followed once that shifts this frame's fix
        by FOLLOW_MIN_M. GNSS fits (refitted every few seconds), offline and restored alignments
        have no points of ours and are not followed.

        Only a move between the previous frame's local map (``lm_prev``) and this one is handed to
        the Globalizer as the same alignment carried along: its fixes continuous, and the move
        tested by the Globalizer's SLAM-jump term (if the tracked pose did not move with the
        points, the fix jumps). A registration that arrives now is first carried to ``lm_prev`` as
        the new alignment it is, since the previous pose was solved against that map. What the map
        moved while the registration was computed cannot be tested against the track any more,
        so that carry widens it by CARRY_SIGMA_FRACTION of the move at the camera (`loop` seed 5
        with full loop closing: a registration carried 2.8 m in the frame it arrived, the track
        steady, fixes 2.7 m off claiming 0.72 m, the move never tested)."""
        if not pose.state.has_pose:
            return alignment
        cloud = self._cloud
        if cloud is None or cloud.alignment is not alignment:
            sub = self._submitted
            if sub is None or alignment.source is not AlignmentSource.FINE or alignment.t_s != sub.t_s:
                self._cloud = None  # not a registration of ours: its points are not known
                return alignment
            self._cloud = _Cloud(alignment, sub.point_ids, sub.p_slam)
            first = lm_prev if lm_prev is not None else lm
            alignment = self._carry(pose, alignment, first, follows=False, widen=True)
            if first is lm:
                return alignment
        return self._carry(pose, alignment, lm, follows=True)

    def _carry(self, pose: SlamPose, alignment: Alignment, lm, follows: bool, widen: bool = False) -> Alignment:
        """_follow_map's step: the current registration (self._cloud) carried to local map ``lm``;
        handed to the Globalizer as the alignment it follows (``follows``) or as a new one,
        widened by CARRY_SIGMA_FRACTION of its move at the camera (``widen``)."""
        cloud = self._cloud
        if cloud is None or lm is None or lm.version == cloud.version or len(lm.point_ids) == 0:
            return alignment
        cloud.version = lm.version
        k = np.minimum(np.searchsorted(lm.point_ids, cloud.point_ids), len(lm.point_ids) - 1)
        held = lm.point_ids[k] == cloud.point_ids
        p_now = cloud.p_slam.copy()
        p_now[held] = lm.p_slam[k[held]]
        # a similarity of points none of which moved FOLLOW_MIN_M cannot move a fix among them by more
        if alignment.T_ecef_slam.scale * float(np.abs(p_now - cloud.p_slam).max(initial=0.0)) < FOLLOW_MIN_M / 2:
            return alignment
        try:
            S_inv = umeyama(cloud.p_slam, p_now).inverse()  # new SLAM coordinates → old
        except ValueError:  # degenerate cloud (collinear): leave the alignment where it is
            return alignment
        c = pose.T_slam_cam[:3, 3]
        moved_m = float(np.linalg.norm(alignment.T_ecef_slam.apply(S_inv.apply(c)) - alignment.T_ecef_slam.apply(c)))
        if moved_m < FOLLOW_MIN_M:
            return alignment
        followed = replace(alignment, T_ecef_slam=alignment.T_ecef_slam @ S_inv,
                           center_slam=S_inv.inverse().apply(np.asarray(alignment.center_slam, float)))
        if widen:
            followed = inflate_alignment(followed, CARRY_SIGMA_FRACTION * moved_m)
        with self._lock:
            if self.alignment is not alignment:  # the worker adopted a new one meanwhile
                return self.alignment
            self.alignment = followed
            self.globalizer.update_alignment(followed, follows=alignment if follows else None)
        self._cloud = _Cloud(followed, cloud.point_ids, p_now, lm.version)
        if moved_m >= FOLLOW_EVENT_M:
            self._note((pose.t_s, f"alignment follows its points: {int(held.sum())} of {len(held)} moved "
                                   f"by local mapping, the fix by {moved_m:.2f} m"
                                   + (f" (while it was computed: σ + {CARRY_SIGMA_FRACTION * moved_m:.2f} m)" if widen else "")))
        return followed

    def _accept(self, alignment: Alignment, why: str) -> None:
        with self._lock:
            old, pose = self.alignment, self._last_pose
            if old is not None and pose is not None and (old.map_id, old.reset_counter) == (alignment.map_id, alignment.reset_counter):
                c = pose.T_slam_cam[:3, 3][None]
                p_new = alignment.T_ecef_slam.apply(c)[0]
                lat, lon, _ = ecef_to_geodetic(p_new)
                self.gnss_check.shift((R_ecef_enu(float(lat), float(lon)).T @ (old.T_ecef_slam.apply(c)[0] - p_new))[:2])
            self.alignment = alignment
            self.globalizer.update_alignment(alignment)
        self._note((alignment.t_s, f"alignment {alignment.source.value} accepted ({why}; σ={alignment.sigma_m:.2f} m)"))

    def restore_alignment(self, saved: Alignment, age_s: float, sigma_restart_m: float, sigma_growth_mps: float,
                          source: str = "after a restart") -> Alignment:
        """Adopt an alignment saved with the SLAM map this process resumed in (after a restart, or
        a site's survey map: ``source`` says which in the event).

        Its covariance is inflated, never shrunk: an isotropic position term
        σ_add = hypot(sigma_restart_m, sigma_growth_mps · age_s) is added to the translation block
        (about its centre), so σ_restored = hypot(σ_saved, σ_add). sigma_restart_m covers the
        relocalisation and the map having been refined after the alignment was computed; the growth
        term grows with the wall time since the alignment was accepted (age_s). The alignment still
        applies only to poses of its own map (map_id, reset_counter): if relocalisation fails and
        SLAM starts a fresh map, ``process`` drops it like any other."""
        add_m = math.hypot(sigma_restart_m, sigma_growth_mps * max(age_s, 0.0))
        a = inflate_alignment(saved, add_m)
        self._accept(a, f"restored {source}, {age_s:.0f} s old, σ {saved.sigma_m:.2f} → {a.sigma_m:.2f} m")
        return a

    def _note(self, event: tuple[float, str]) -> None:
        """An alignment event (t_s, text): kept in ``events`` and handed to ``on_event``."""
        self.events.append(event)
        if self.on_event is not None:
            self.on_event(*event)

    def watch_survey_area(self, area: SurveyArea) -> None:
        """SLAM started in a site's survey map (lying in ``area``) and waits to relocalise in it.
        While it waits, a trusted GNSS fix farther than ``area.reach_m`` from every survey
        keyframe gives the survey map up (``_leave_survey_if_far``)."""
        self._survey_area = area

    def _leave_survey_if_far(self, t_s: float, gnss: GnssSample | None, trusted: bool) -> None:
        """Started in a survey map but taking off elsewhere: the wait to relocalise there would
        leave SLAM without a map (so no GNSS bootstrap either) for up to
        ``gis.survey_reloc_timeout_s``, and a GNSS loss meanwhile without any fix. With trusted
        GNSS placing the vehicle beyond the survey's reach, SLAM starts a fresh map now and
        bootstraps from GNSS as on any flight. Untrusted GNSS never gives the survey map up."""
        if self._survey_area is None:
            return
        if not self.slam.resuming:  # relocalised in it, or the wait ended
            self._survey_area = None
            return
        if not trusted or gnss is None or gnss.fix_type < GpsFixType.FIX_3D:
            return
        d_m = self._survey_area.distance_m(gnss.lat_deg, gnss.lon_deg, h_ellipsoid_of(gnss))
        if d_m > self._survey_area.reach_m:
            self.slam.abandon_loaded_map()
            self._note((t_s, f"survey map given up: GNSS (trusted) puts the vehicle {d_m:.0f} m from its nearest "
                              f"keyframe (reach {self._survey_area.reach_m:.0f} m); fresh map, GNSS bootstrap"))
            self._survey_area = None

    def _drop_alignment(self, t_s: float, why: str) -> None:
        self._note((t_s, why))
        with self._lock:
            self.alignment = None
            self.gnss_check.reset()

    def _withhold(self, t_s: float, why: str) -> None:
        """Our map, not the world, broke: drop the alignment and send no fix until a new one."""
        self._drop_alignment(t_s, "alignment dropped, fixes withheld: " + why)
        self.globalizer.clear_alignment()

    def _on_finetune(self, alignment: Alignment | None, reason: str, wall_ms: float, icp: IcpMeasurement | None = None) -> None:
        t = self._last_pose.t_s if self._last_pose else 0.0
        job, self._georef_job = self._georef_job, None
        if alignment is not None and icp is not None and job is not None:
            self._check_georef(*job, icp)
        if alignment is None:
            self._note((t, f"fine-tuning rejected: {reason} ({wall_ms:.0f} ms)"))
            if reason.startswith(SCALE_MISMATCH_REASON):
                # The map under the camera is not at the alignment's scale: fixes would drift
                # off at speed × mismatch while claiming the alignment's σ. Send nothing.
                self._withhold(t, reason)
            return
        with self._lock:
            current = self.alignment
        if current is not None and (alignment.map_id, alignment.reset_counter) != (current.map_id, current.reset_counter):
            return  # the map changed while we registered: stale
        self._accept(alignment, f"{reason}, {wall_ms:.0f} ms")
        # its scale is the model's (and it passed the barometer's check when there is one)
        self._scale_confirmed = (alignment.t_s, "a GIS registration")

    def _check_georef(self, t_s: float, c_slam: np.ndarray, fit: Alignment, icp: IcpMeasurement) -> None:
        """One registration made while GNSS was trusted: where its ICP alone put the camera against
        where the GNSS fit of that time puts it (gis.align.georef); the model's correction follows
        the verdict (tuner, worker jobs, the Globalizer's model term)."""
        p_gnss = fit.T_ecef_slam.apply(np.asarray(c_slam, float)[None])[0]
        lat, lon, _ = ecef_to_geodetic(p_gnss)
        d = R_ecef_enu(float(lat), float(lon)).T @ (icp.p_ecef_m - p_gnss)
        with self._lock:
            taken = self.georef.add(t_s, d, icp.cov_enu_m2 + self._sigma_here_m(fit, c_slam) ** 2 * np.eye(3))
        if taken:
            self._apply_georef(t_s)

    def georef_evidence(self) -> GeorefEvidence | None:
        """All evidence on the model's georeference so far, for the GIS cache (None without a model)."""
        with self._lock:
            return None if self.georef is None else self.georef.evidence

    def restore_georef(self, evidence: GeorefEvidence, t_s: float = 0.0) -> GeorefCorrection | None:
        """Start from earlier flights' evidence on the model's georeference (gis.cache, same site):
        a model they found off is corrected from now on. Returns the correction in force."""
        if self.georef is None:
            return None
        with self._lock:
            self.georef.add_evidence(evidence)
        self._note((t_s, f"GIS model georeference: {evidence.n} registrations vs GNSS from earlier flights"))
        self._apply_georef(t_s)
        return self._tuner.correction

    def _apply_georef(self, t_s: float) -> None:
        """The correction the georeference evidence calls for goes to the tuner, the worker's jobs
        and the Globalizer's model term."""
        new, old = self.georef.correction(), self._tuner.correction
        if new is None and old is None:
            return
        self._tuner.set_correction(new)
        self.worker.correction = new
        self.globalizer.model_sigma_m = self._tuner.model_sigma_m
        g = self.georef
        test = f"F {g.stat:.1f} {'>' if new is not None else '<='} {g.critical:.1f}, variance factor {g.alpha:.2f}"
        if new is not None:
            self._note((t_s, f"{new.describe()}: corrected ({test})"))
            if old is None:
                log.warning("%s: corrected (%s)", new.describe(), test)
        else:
            self._note((t_s, f"GIS model georeference as configured again ({test}): correction dropped"))

    def _settle_speed_check(self, t_s: float) -> None:
        """A SLAM-speed mismatch left open by the end of GNSS ground speed (GNSS lost in the middle
        of the check) withholds fixes until another test of the scale made after it began passes:
        a GIS registration or the barometer's check. Before, it withheld them for the rest of the
        denial (docs/BENCHMARKS.md, "Long `loop` denials on this machine")."""
        since = self.speed_check.open_since(t_s)
        ok = self._scale_confirmed
        if since is not None and ok is not None and ok[0] >= since:
            self._note((t_s, f"SLAM speed mismatch seen at {since:.1f} s (ratio {self.speed_check.last_ratio:.2f}) "
                              f"as GNSS speed ended: scale confirmed by {ok[1]}, fixes resume"))
            self.speed_check.settle()

    def _on_scale_check(self, checked: Alignment, chk: ScaleCheck) -> None:
        t = self._last_pose.t_s if self._last_pose else 0.0
        self.scale_checks.append((t, chk))
        with self._lock:
            current = self.alignment
        if chk.mismatch and current is checked:  # (a newer alignment was not tested)
            self._withhold(t, f"{SCALE_MISMATCH_REASON}: {chk.describe()} (check between registrations)")
        elif math.isfinite(chk.ratio) and not chk.mismatch and current is checked:
            self._scale_confirmed = (self._scale_check_t_s, "the barometer")  # (submitted then; one in flight)

    def _check_scale(self, pose: SlamPose, alignment: Alignment, prior: AttitudePrior | None) -> None:
        """Every SCALE_CHECK_EVERY_S: the barometer against the map points this frame was tracked
        with (FineTuner.check_scale, in the worker process; the answer comes back asynchronously)."""
        if self.worker is None or pose.t_s - self._scale_check_t_s < SCALE_CHECK_EVERY_S:
            return
        h = self._camera_h_ell_m(prior)
        pts = self.slam.tracked_points_slam()
        if h is not None and len(pts) >= NADIR_MIN_POINTS and self.worker.check_scale(
                pts, alignment, pose.T_slam_cam[:3, 3].copy(), h, pose.t_s):
            self._scale_check_t_s = pose.t_s

    def settle(self, t_s: float) -> None:
        """Repeatable offline runs (``repeatable_lag_s``): before the frame at flight time ``t_s``,
        wait until local mapping has mapped every keyframe and applied its bundle adjustment (the
        SLAM system, ``stepped``, hands a frame's keyframe to local mapping only here, so nothing
        the frame reads from the map after tracking depends on the mapping thread's speed), and
        adopt the fine-tuning results due by ``t_s`` (submitted repeatable_lag_s or more before;
        waiting for them). What each frame sees then depends on flight time alone, not on this
        machine's speed, so the run repeats to the bit. It is optimistic about local mapping
        (live, a keyframe's map arrives some frames later). Offline loops call it before each
        frame, outside the frame's timing, and with ``math.inf`` at the end. Nothing to do live."""
        if not self.repeatable:
            return
        if not self.slam.wait_mapping():
            log.warning("repeatable run: local mapping still busy after 60 s; going on")
        if self.worker is not None:
            self.worker.release(t_s)

    def process(self, item: PipelineInput) -> FrameRecord:
        self._leave_survey_if_far(item.frame.t_s, item.gnss, item.gnss_trusted)
        pose = self.slam.track(item.frame, with_gravity(item.prior, self.globalizer.T_cam_body[:3, :3]))
        self._last_pose = pose
        with self._lock:
            alignment = self.alignment
        if alignment is not None and (alignment.map_id, alignment.reset_counter) != (pose.map_id, pose.reset_counter):
            # SLAM map reset or loop-corrected: the alignment no longer applies (the Globalizer
            # refuses fixes for another map by itself).
            self._drop_alignment(pose.t_s, "SLAM map changed: alignment dropped")
            alignment = None
        lm = self.slam.tracked_local_map() if pose.state.has_pose else None
        if alignment is not None:
            alignment = self._follow_map(pose, alignment, lm, self._lm_prev)
        self._lm_prev = lm
        if pose.state.has_pose and alignment is not None and item.gnss is not None and item.gnss.fix_type >= GpsFixType.FIX_3D:
            v = item.gnss.vel_ned_mps
            speed = float(np.hypot(v[0], v[1])) if v is not None else None
            # the receiver's own position gives the local level frame (metres away: same axes)
            if self.speed_check.update(pose.t_s, pose.T_slam_cam[:3, 3], alignment.T_ecef_slam,
                                       R_ecef_enu(item.gnss.lat_deg, item.gnss.lon_deg), speed):
                # Our map, not GNSS, is what broke: withhold fixes, refit from fresh GNSS pairs only.
                self._withhold(pose.t_s, f"SLAM scale inconsistent with GNSS ground speed (ratio "
                                         f"{self.speed_check.last_ratio:.2f})")
                alignment = None
                self.bootstrap.clear()
                self.speed_check.reset()
        if pose.state.has_pose:
            pair = self.bootstrap.make_pair(pose, item.gnss, item.prior)
            if pair is not None:
                usable = True
                if alignment is not None:
                    nu_ecef = pair.p_ecef - alignment.T_ecef_slam.apply(pair.p_slam[None])[0]
                    with self._lock:
                        if self.globalizer.unanchored and not self.gnss_check.inconsistent:
                            # our track jumped (_after_jump): no reference to judge GNSS by until
                            # a new alignment; the check starts again from the first pair after it
                            self.gnss_check.reset()
                        else:
                            usable = self.gnss_check.update(pair.t_s, (pair.R_ecef_enu.T @ nu_ecef)[:2])
                if usable and item.gnss_trusted:
                    self.bootstrap.append(pair)
                    self._learn_baro_offset(pair, item.prior)
            self._frames_since_boot += 1
            if (item.gnss_trusted and self.bootstrap.ready()
                    and (alignment is None or self._frames_since_boot >= self.rebootstrap_every)):
                self._frames_since_boot = 0
                boot = self.bootstrap.solve()
                if boot is not None:
                    self._gnss_fit = boot
                    self._gnss_fits.append(boot)
                c = pose.T_slam_cam[:3, 3]
                # A fresh GNSS fit replaces a GIS one only where it is the better of the two here
                # (the older alignment has drifted away from the current pose meanwhile), or where
                # the SLAM track jumped by more than 3× that one's σ since it was adopted (its σ no
                # longer holds: Globalizer.unanchored).
                if boot is not None and (alignment is None or alignment.source is AlignmentSource.GNSS
                                         or self.globalizer.unanchored
                                         or self._sigma_here_m(boot, c) <= self._sigma_here_m(alignment, c)):
                    self._accept(boot, f"{len(self.bootstrap.p_slam)} GNSS pairs")
                    alignment = boot
            self._frames_since_tune += 1
            every = self.every if item.gnss_trusted else self.every_denied
            if (alignment is not None and self.worker is not None and not self.worker.busy.is_set()
                    and self._frames_since_tune >= every):
                snapshot = self.slam.map_points()
                points, ids = snapshot.points_slam, snapshot.point_ids
                keep = np.ones(len(ids), bool)
                if self.min_parallax_deg > 0 and snapshot.parallax_deg is not None:
                    keep &= snapshot.parallax_deg >= self.min_parallax_deg
                if self.recent_keyframes > 0 and snapshot.last_seen_kf_age is not None:
                    keep &= snapshot.last_seen_kf_age < self.recent_keyframes
                points, ids = points[keep], ids[keep]
                fit = self._fresh_gnss_fit(pose) if item.gnss_trusted else None
                prior = self._registration_prior(alignment, pose, fit)
                h_cam = self._camera_h_ell_m(item.prior)
                # its 1-σ: the GNSS vertical accuracy the offset was learned from, and the barometer's own
                h_sigma = None if h_cam is None else math.hypot(self._baro_offset_sigma_m, BARO_NOISE_M)
                if len(points) >= self.min_points and self.worker.submit(
                        points, prior, pose.T_slam_cam[:3, 3].copy(), pose.t_s, h_cam, h_sigma):
                    self._frames_since_tune = 0
                    self._georef_job = (pose.t_s, pose.T_slam_cam[:3, 3].copy(), fit) if fit is not None else None
                    crop = self._tuner.in_crop(points, prior.T_ecef_slam, pose.T_slam_cam[:3, 3])
                    order = np.argsort(ids[crop], kind="stable")
                    self._submitted = _Cloud(prior, ids[crop][order], points[crop][order], t_s=pose.t_s)
                else:  # too few well-triangulated points: retry soon, not every frame (a
                    # snapshot of a big map costs tens of ms on this, the tracking, thread)
                    self._frames_since_tune = every - RETRY_FRAMES
            if alignment is not None:
                self._check_scale(pose, alignment, item.prior)
        self._settle_speed_check(pose.t_s)
        self.globalizer.hold_jumps(pose.t_s, not item.gnss_trusted)
        fix = None if self.speed_check.suspect else self.globalizer.fix(pose)
        self._after_jump(pose.t_s)
        fix = self._denial_floor(item.gnss_trusted, pose, alignment, fix)
        fix = self._walk_floor(item.gnss_trusted, pose, fix)
        return FrameRecord(pose.seq, pose.t_s, pose, fix, alignment.source if alignment else None, time.monotonic())

    def _after_jump(self, t_s: float) -> None:
        """The SLAM track has just jumped by more than 3× the alignment's σ (Globalizer.unanchored;
        a relocalisation into a part of the map that disagrees with the rest): until a new
        alignment, (1) the next GNSS fit replaces the current one whatever its σ (``process``);
        (2) the GNSS pairs from before the jump are dropped, so that fit is made of pairs after it
        (a fit mixing both, 1 s after a 9 m jump in `loop` seed 6, left the fixes 8.8 m off);
        (3) GnssConsistency does not judge GNSS by our track (``process``): the jump moved every
        innovation by its size, and past the gate (5 m) the check took GNSS for spoofed 2 s
        later (same flight, 184.3 s). A spoofer would have to start within the seconds between a
        SLAM jump and the next fit; the bridge's own GNSS/vision test still runs, with the jump
        in the fix's σ."""
        unanchored = self.globalizer.unanchored
        if unanchored and not self._unanchored:
            self.bootstrap.clear()
            self._note((t_s, f"SLAM track jumped {self.globalizer.unanchoring_jump_m:.2f} m, beyond 3× the alignment's σ: "
                             f"GNSS pairs from before it dropped, GNSS not judged by vision until a new alignment"))
        self._unanchored = unanchored

    def _fresh_gnss_fit(self, pose: SlamPose) -> Alignment | None:
        """The newest GNSS fit if it is of this pose's map and at most GEOREF_MAX_FIT_AGE_S old."""
        fit = self._gnss_fit
        if (fit is not None and (fit.map_id, fit.reset_counter) == (pose.map_id, pose.reset_counter)
                and pose.t_s - fit.t_s <= GEOREF_MAX_FIT_AGE_S):
            return fit
        return None

    def _registration_prior(self, alignment: Alignment, pose: SlamPose, fit: Alignment | None) -> Alignment:
        """The alignment a registration refines: the current one, except where GNSS is trusted and
        ``fit`` is its fresh fit (_fresh_gnss_fit; None otherwise), the current one is itself a
        registration (FINE) and it puts the camera further from where the fit puts it than the
        fit's own 1-σ there: then the fit. A chain of
        registrations, each refining the last, is anchored by nothing outside the GIS model: over
        a model that is out of date it walked 5 m off while GNSS was trusted and 0.5 m off, each
        link claiming ~1 m, below the fits' σ, so no fit replaced it (`stale` seed 3, a
        registration every 5 s: 90 of 90 fixes after the loss beyond 3σ). Refining the fit
        instead every time cost accuracy where the chain was right (`nominal` at 30 fps: 0.29 →
        0.37 m); dropping the chain only where it strays from GNSS kept both (docs/BENCHMARKS.md,
        "Registrations while GNSS is trusted"). In a denial the chain is all there is."""
        if fit is None or alignment.source is not AlignmentSource.FINE:
            return alignment
        c = pose.T_slam_cam[:3, 3]
        apart_m = float(np.linalg.norm(alignment.T_ecef_slam.apply(c[None])[0] - fit.T_ecef_slam.apply(c[None])[0]))
        return alignment if apart_m <= self._sigma_here_m(fit, c) else fit

    def _walk_floor(self, gnss_trusted: bool, pose: SlamPose, fix: GlobalFix | None) -> GlobalFix | None:
        """While GNSS is trusted, every alignment is anchored to it, and GnssConsistency follows a
        walk-off slower than ~1 m/s (its gate is distance from its own running mean): the fixes
        follow a slow spoofer while claiming the fit's σ (a 0.5 m/s walk: 3.7 m off 9 s into it,
        claiming 1.2 m; docs/BENCHMARKS.md, "A slow GNSS walk-off"). So no horizontal direction of
        the fix's σ is below how far the fresh GNSS fit puts this camera from where the fit
        WALK_WINDOW_S before it does (walk_from_m), less that older fit's own σ here
        (_sigma_here_m): the part of the difference the older fit's error does not explain, a
        lower bound on what the receiver walked. It bounds a steady walk for about 3 × the window
        (the error keeps growing, the difference does not); detecting one is not solved."""
        fit = self._fresh_gnss_fit(pose) if gnss_trusted and fix is not None else None
        if fit is None:
            return fix
        c = pose.T_slam_cam[:3, 3]
        walk = walk_from_m(self._gnss_fits, fit, c)
        if walk is None:
            return fix
        floor_m = walk[0] - self._sigma_here_m(walk[1], c)
        return fix if floor_m <= 0.0 else with_horizontal_floor(fix, floor_m)

    def _denial_floor(self, gnss_trusted: bool, pose: SlamPose, alignment: Alignment | None,
                      fix: GlobalFix | None) -> GlobalFix | None:
        """With ``denial_sigma_per_m`` > 0: while GNSS is not trusted, the fix's horizontal 1-σ is at
        least that × the distance flown since it was (the tracked camera's SLAM steps in metres at
        the alignment's scale; a step across a map reset is not counted). Beyond the papers: a
        registration in a long denial can lock onto a wrong optimum next to a drifted prior and
        claim ~1 m (docs/BENCHMARKS.md, "Registrations replayed offline"), which no registration
        gate detected; this bounds the claim by distance, as dead reckoning would."""
        if self.denial_sigma_per_m <= 0.0:
            return fix
        if gnss_trusted:
            self._denied_m, self._denied_cam = None, None
            return fix
        if self._denied_m is None:
            self._denied_m = 0.0
        if pose.state.has_pose:
            key, cam = (pose.map_id, pose.reset_counter), np.asarray(pose.T_slam_cam, float)[:3, 3]
            if self._denied_cam is not None and self._denied_cam[0] == key and alignment is not None:
                self._denied_m += alignment.T_ecef_slam.scale * float(np.linalg.norm(cam - self._denied_cam[1]))
            self._denied_cam = (key, cam)
        return None if fix is None else with_horizontal_floor(fix, self.denial_sigma_per_m * self._denied_m)

    def _learn_baro_offset(self, pair: GnssPair, prior: AttitudePrior | None) -> None:
        """Ellipsoidal height − barometric altitude, averaged over trusted GNSS pairs (exponential,
        BARO_OFFSET_GAIN per pair: ~10 s at 5 Hz). The barometer drifts ~0.02 m/√s, so the offset
        stays good to decimetres for minutes after GNSS is lost."""
        baro = _baro_m(prior)
        if baro is None or abs(prior.t_s - pair.t_s) > 0.2:
            return
        off = float(ecef_to_geodetic(pair.p_ecef)[2]) - baro
        self._baro_offset_m = _baro_ema(self._baro_offset_m, off)
        self._baro_offset_sigma_m = _baro_ema(self._baro_offset_sigma_m, pair.v_acc_m)

    def _camera_h_ell_m(self, prior: AttitudePrior | None) -> float | None:
        """The camera's ellipsoidal height from the barometer (the offset is learned from pairs,
        which hold the camera centre when the attitude is known), or None without a barometer or an
        offset learned from GNSS."""
        baro = _baro_m(prior)
        return None if baro is None or self._baro_offset_m is None else baro + self._baro_offset_m

    def _sigma_here_m(self, a: Alignment, c_slam: np.ndarray) -> float:
        """Rough 1-σ of a fix at SLAM position c under alignment a: its own σ plus SLAM drift over
        the distance from its centre (the Globalizer's propagation without the rotation terms)."""
        if a.center_slam is None:
            return a.sigma_m
        d_m = a.T_ecef_slam.scale * float(np.linalg.norm(np.asarray(c_slam) - a.center_slam))
        return float(np.hypot(a.sigma_m, self.globalizer.slam_drift_fraction * a.drift_distance_m(d_m) + a.scale_sigma * d_m))

    def gnss_offset_m(self, now_s: float, max_age_s: float = 1.0) -> float | None:
        """How far GNSS sits from our position, horizontally: the running mean (``ema_s``) of the
        innovations GnssConsistency tracks, while they keep coming (the newest at most
        ``max_age_s`` before ``now_s``, on the frames' clock); else None. A readiness figure for a
        field trial: while GNSS is good, alignments are fitted to it, so this is agreement (the
        GIS registrations' and the receiver's), not accuracy."""
        with self._lock:
            return self.gnss_check.offset_m(now_s, max_age_s)

    def gnss_inconsistency(self) -> str | None:
        """Why GNSS is not to be trusted according to visual odometry, or None."""
        c = self.gnss_check
        if not c.inconsistent:
            return None
        return f"GNSS moves {c.last_dev_m:.1f} m away from visual odometry (gate {c.gate_m:g} m): spoofing suspected"

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()
        self.slam.close()


def inflate_alignment(a: Alignment, add_sigma_m: float) -> Alignment:
    """``a`` with an isotropic 1-σ ``add_sigma_m`` (metres) added to its position uncertainty."""
    cov6 = a.covariance_6x6()
    cov6[3:, 3:] += add_sigma_m**2 * np.eye(3)
    return replace(a, information_6x6=np.linalg.inv(cov6), sigma_m=float(math.hypot(a.sigma_m, add_sigma_m)))


def run(inputs: Iterable[PipelineInput], localizer: Localizer, sink: Callable[[GlobalFix | None], None] | None = None,
        on_record: Callable[[FrameRecord], None] | None = None) -> Iterator[FrameRecord]:
    """Drive the localizer over ``inputs``; every fix (or None) goes to ``sink`` at once."""
    for item in inputs:
        localizer.settle(item.frame.t_s)
        rec = localizer.process(item)
        if sink is not None:
            sink(rec.fix)
        if on_record is not None:
            on_record(rec)
        yield rec
