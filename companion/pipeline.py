"""The real-time localisation pipeline: frames in, global fixes out (README.md, data flow).

Hot path, one thread, top to bottom per frame::

    frame ─▶ slam.track ─SlamPose─▶ globalizer.fix ─GlobalFix─▶ sink (MAVLink bridge, recorder)

Background: SLAM's own local-mapping/loop-closing threads, and one fine-tuning worker that every
``alignment.finetune_every_frames`` frames (``finetune_every_frames_denied`` while GNSS is not
trusted) registers the current SLAM map to the GIS model
(TerraSLAM §4.4) and hands the accepted T_fine to the Globalizer. Until an alignment exists, good
GNSS bootstraps one (digital-twin paper §III-D): pairs of (SLAM camera centre, GNSS position) are
collected while GNSS is trusted and fitted with a similarity. Alignments follow their points when
local mapping moves them (beyond the papers; companion.fusion.follow). The fusion's parts live in
companion/fusion/: GNSS fits (gnss_fit), registrations (registration), the barometer (barometer),
integrity checks (integrity), map following (follow) and where σ comes from (sigma).

The pipeline knows no camera device, MAVLink or simulator: callers pass an iterator of
``PipelineInput`` and a sink; ``companion.app`` wires cameras, the bridge and the simulator.
"""
from __future__ import annotations

import collections
import logging
import math
import threading
import time
from dataclasses import dataclass, replace
from typing import Callable, Iterable, Iterator

import numpy as np

from companion.fusion.barometer import BaroOffset
from companion.fusion.follow import CARRY_SIGMA_FRACTION, FOLLOW_EVENT_M, Cloud, follow_points
from companion.fusion.gnss_fit import BootstrapCollector
from companion.fusion.integrity import GnssConsistency, SlamSpeedCheck
from companion.fusion.registration import FineTuneWorker
from companion.fusion.sigma import DenialFloor, inflate_alignment, sigma_here_m, walk_floor
from gis.align.fine import NADIR_MIN_POINTS, SCALE_MISMATCH_REASON, FineTuner, ScaleCheck
from gis.align.georef import GeorefCheck, GeorefCorrection, GeorefEvidence, IcpMeasurement
from gis.geodesy import R_ecef_enu, ecef_to_geodetic, geodetic_to_ecef
from gis.globalizer import Globalizer
from gis.types import Alignment, AlignmentSource, GlobalFix
from mavlink_bridge.monitor import h_ellipsoid_of
from mavlink_bridge.types import GnssSample, GpsFixType
from slam.geometry import gravity_cam_from_roll_pitch
from slam.types import AttitudePrior, Frame, SlamPose

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


GEOREF_MAX_FIT_AGE_S = 5.0  # a GNSS fit at most this old is what a registration is compared with (gis.align.georef) and refines instead of a straying chain
SCALE_CHECK_EVERY_S = 1.0  # the barometer checks the map under the camera this often between registrations
RETRY_FRAMES = 10  # frames before fine-tuning tries again when the map had too few points
MAX_EVENTS = 10_000  # alignment timeline entries kept (~200 per 10 min of flight: days of service)


class Localizer:
    """SLAM + alignment + globalisation for one camera; ``process`` is the per-frame hot path."""

    def __init__(self, slam, tuner: FineTuner | None, globalizer: Globalizer, finetune_every_frames: int = 200,
                 finetune_every_frames_denied: int = 50,
                 initial_alignment: Alignment | None = None, bootstrap: BootstrapCollector | None = None,
                 min_points_for_finetune: int = 200, finetune_min_parallax_deg: float = 0.0,
                 finetune_recent_keyframes: int = 0, repeatable_lag_s: float | None = None,
                 denial_sigma_per_m: float = 0.0):
        """``repeatable_lag_s``: offline, repeatable runs only (``settle``); None live.
        ``denial_sigma_per_m``: alignment.denial_sigma_per_m (companion.fusion.sigma.DenialFloor)."""
        self.slam = slam
        self.globalizer = globalizer
        self.repeatable = repeatable_lag_s is not None
        self.every = finetune_every_frames
        self.every_denied = finetune_every_frames_denied
        self.min_points = min_points_for_finetune
        self.min_parallax_deg = finetune_min_parallax_deg
        self.recent_keyframes = finetune_recent_keyframes
        self.denial_floor = DenialFloor(denial_sigma_per_m)
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
        self.baro = BaroOffset()  # ellipsoidal height − barometric altitude (learned from GNSS)
        self.rebootstrap_every = 30  # frames between GNSS re-fits while GNSS is trusted
        self._last_pose: SlamPose | None = None
        self._cloud: Cloud | None = None      # the current alignment's points (_follow_map)
        self._lm_prev = None                   # the local map the previous frame's pose was solved against
        self._submitted: Cloud | None = None  # the last registration's points, as submitted
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
                    self.baro.learn(pair, item.prior)
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
                h_cam = self.baro.camera_h_ell_m(item.prior)
                h_sigma = None if h_cam is None else self.baro.camera_h_sigma_m()
                if len(points) >= self.min_points and self.worker.submit(
                        points, prior, pose.T_slam_cam[:3, 3].copy(), pose.t_s, h_cam, h_sigma):
                    self._frames_since_tune = 0
                    self._georef_job = (pose.t_s, pose.T_slam_cam[:3, 3].copy(), fit) if fit is not None else None
                    crop = self._tuner.in_crop(points, prior.T_ecef_slam, pose.T_slam_cam[:3, 3])
                    order = np.argsort(ids[crop], kind="stable")
                    self._submitted = Cloud(prior, ids[crop][order], points[crop][order], t_s=pose.t_s)
                else:  # too few well-triangulated points: retry soon, not every frame (a
                    # snapshot of a big map costs tens of ms on this, the tracking, thread)
                    self._frames_since_tune = every - RETRY_FRAMES
            if alignment is not None:
                self._check_scale(pose, alignment, item.prior)
        self._settle_speed_check(pose.t_s)
        self.globalizer.hold_jumps(pose.t_s, not item.gnss_trusted)
        fix = None if self.speed_check.suspect else self.globalizer.fix(pose)
        self._after_jump(pose.t_s)
        fix = self.denial_floor.apply(item.gnss_trusted, pose, alignment, fix)
        fix = self._walk_floor(item.gnss_trusted, pose, fix)
        return FrameRecord(pose.seq, pose.t_s, pose, fix, alignment.source if alignment else None, time.monotonic())

    def _follow_map(self, pose: SlamPose, alignment: Alignment, lm, lm_prev) -> Alignment:
        """Carry a registration along when local mapping moves its points (module doc, "Alignments
        follow their points"). A registration keeps the SLAM points it was computed on (Cloud:
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
            self._cloud = Cloud(alignment, sub.point_ids, sub.p_slam)
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
        moved = follow_points(cloud, alignment, lm, pose.T_slam_cam[:3, 3], widen)
        if moved is None:
            return alignment
        followed, p_now, held, moved_m = moved
        with self._lock:
            if self.alignment is not alignment:  # the worker adopted a new one meanwhile
                return self.alignment
            self.alignment = followed
            self.globalizer.update_alignment(followed, follows=alignment if follows else None)
        self._cloud = Cloud(followed, cloud.point_ids, p_now, lm.version)
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
        h = self.baro.camera_h_ell_m(prior)
        pts = self.slam.tracked_points_slam()
        if h is not None and len(pts) >= NADIR_MIN_POINTS and self.worker.check_scale(
                pts, alignment, pose.T_slam_cam[:3, 3].copy(), h, pose.t_s):
            self._scale_check_t_s = pose.t_s

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
        """The floor of how far the GNSS fits walked (companion.fusion.sigma.walk_floor) under a fix
        while GNSS is trusted and a fresh fit exists."""
        fit = self._fresh_gnss_fit(pose) if gnss_trusted and fix is not None else None
        if fit is None:
            return fix
        return walk_floor(fix, self._gnss_fits, fit, pose.T_slam_cam[:3, 3], self.globalizer.slam_drift_fraction)

    def _sigma_here_m(self, a: Alignment, c_slam: np.ndarray) -> float:
        """companion.fusion.sigma.sigma_here_m with the Globalizer's SLAM drift."""
        return sigma_here_m(a, c_slam, self.globalizer.slam_drift_fraction)

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
