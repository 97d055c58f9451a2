"""SlamPose + current alignment → GlobalFix (TerraSLAM §4.4.2: p_ecef = T_fine·p, then WGS-84).

The covariance is propagated, not guessed: the alignment's information (Eq. 8–10, about its
centre) is inverted and carried to the vehicle with the lever arm d from that centre
(J = [−[d]×, I]), plus the scale uncertainty (scale_sigma·|d|), SLAM drift away from the
alignment's centre (slam_drift_fraction·|d|, only beyond its drift_free_radius_m: a survey map's
T_rough), the GIS model's georeference accuracy
(model_sigma_m, for GIS-based alignments; the Localizer replaces it with the correction's σ when
the model is found metres off against GNSS, gis.align.georef), recent jumps of the SLAM track (below) and a floor. No
fix when tracking has no pose, no alignment was accepted, or the alignment belongs to another
SLAM map (reset_counter / map_id). The fix's velocity is a fit to the last second of fixes
(gis.fix_velocity), its speed accuracy the fit's σ with velocity_sigma_floor_mps added.

SLAM jumps (beyond the papers): when local mapping refreshes the points the tracker follows, the
pose can jump by metres in one frame, and the track before such a jump was off by about as much.
Measured on this project's demo flight (450 frames, loss at 30 s): jumps of +1.9 m at 36.2 s and
+2.2 m at 38.3 s (fix-to-fix motion against truth's 0.7 m), between which the error grew to 4.5 m
against a σ of 1.45 m — 2.7 % of that flight's fixes beyond 3σ. Each fix is compared with a
constant-velocity prediction from the previous poses, placed with the current alignment (the
innovation of a constant-velocity model; covariance matching from innovations, Mehra 1972); the largest recent
innovation, decaying with JUMP_MEMORY_S, is added to the fix's covariance as an isotropic term.
The decay assumes something will re-anchor the track: GNSS fits do, every few seconds. In a GNSS
denial nothing independent does (a GIS registration converges next to its prior, docs/BENCHMARKS.md
"Registrations replayed offline"), so while the Localizer holds the term (``hold_jumps``) it does
not decay: an 8 m jump at a `loop` flight's GNSS loss left every later fix 7–10 m off while the
decayed term let the claim fall to 1.4 m within 12 s (docs/BENCHMARKS.md, "Long denials: honest by default").
Nor does it decay after a jump larger than 3× the alignment's own σ at the fix (UNANCHOR_SIGMAS)
until a new alignment is adopted (``unanchored``): while GNSS was trusted, a 5 m jump after a relocalisation left a GIS
registration 5 m off, its smaller σ kept the GNSS fits out, and the decayed claim (1.2 m) made the
bridge take the disagreement for spoofing (docs/BENCHMARKS.md, "A SLAM jump while GNSS is trusted").
"""
from __future__ import annotations

import math
import threading
from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from gis import fix_velocity
from gis.config import AlignmentConfig
from gis.geodesy import R_NED_ENU, LocalFrame, ecef_to_geodetic, ellipsoid_to_msl
from gis.types import Alignment, AlignmentSource, GlobalFix
from slam.types import SlamPose

JUMP_MEMORY_S = 5.0     # e-folding time of a SLAM jump's term in the fix covariance
VELOCITY_SMOOTHING = 0.3  # weight of the newest fix-to-fix velocity in the prediction (exponential)
UNANCHOR_SIGMAS = 3.0   # a jump beyond this many of the alignment's own horizontal σ at the fix unanchors it


class Globalizer:
    def __init__(self, T_body_cam: np.ndarray, slam_drift_fraction: float = 0.01, sigma_floor_m: float = 0.05,
                 model_sigma_m: float = 0.25, max_velocity_dt_s: float = 1.0, velocity_sigma_floor_mps: float = 0.3) -> None:
        self.T_cam_body = np.linalg.inv(np.asarray(T_body_cam, float))
        self.slam_drift_fraction = slam_drift_fraction
        self.sigma_floor_m = sigma_floor_m
        self.model_sigma_m = model_sigma_m
        self.max_velocity_dt_s = max_velocity_dt_s
        self.velocity_sigma_floor_mps = velocity_sigma_floor_mps
        self._lock = threading.Lock()
        self._alignment: Alignment | None = None
        self._cov_center: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        # (t_s, ECEF body position, its alignment, T_slam_cam, (reset_counter, map_id)) of the last fix
        self._prev: tuple[float, np.ndarray, Alignment, np.ndarray, tuple[int, int]] | None = None
        self._v_ecef: np.ndarray | None = None           # smoothed fix velocity (ECEF m/s)
        self._jump: tuple[float, float] = (0.0, 0.0)     # (t_s, m) of the largest recent innovation
        self._hold_jumps = False                         # no decay (``hold_jumps``)
        self._unanchored = False                         # no decay: a jump beyond 3× the alignment's σ since it was adopted
        self._reanchored = False                         # a new alignment since: release at the next fix
        self._unanchoring_jump_m = 0.0                   # the jump that set _unanchored
        # (t_s, ECEF body position, segment, (reset_counter, map_id)) of the last second's fixes (velocity)
        self._track: list[tuple[float, np.ndarray, int, tuple[int, int]]] = []
        self._new_segment = False                        # a new alignment since the last fix

    @classmethod
    def from_config(cls, T_body_cam: np.ndarray, config: AlignmentConfig) -> "Globalizer":
        """With the fix-covariance terms of the ``alignment`` config section."""
        return cls(T_body_cam, config.slam_drift_fraction, config.sigma_floor_m, config.model_sigma_m,
                   velocity_sigma_floor_mps=config.velocity_sigma_floor_mps)

    @property
    def alignment(self) -> Alignment | None:
        return self._alignment

    def clear_alignment(self) -> None:
        """Forget the alignment: no fix until a new one is adopted (the map it described is suspect)."""
        with self._lock:
            self._alignment = None
            self._cov_center = None
            self._prev = None
            self._v_ecef = None
            self._track.clear()
            self._jump = (0.0, 0.0)
            self._unanchored = self._reanchored = False

    @property
    def unanchored(self) -> bool:
        """The SLAM track jumped by more than UNANCHOR_SIGMAS × the alignment's σ since the alignment was adopted:
        the alignment no longer holds to its σ (the jump term stands in for it, undecayed)."""
        return self._unanchored

    @property
    def unanchoring_jump_m(self) -> float:
        """The jump (metres) that unanchored the alignment; 0 while it is anchored."""
        return self._unanchoring_jump_m if self._unanchored else 0.0

    def hold_jumps(self, t_s: float, hold: bool) -> None:
        """While held (GNSS not trusted: nothing re-anchors the track), the SLAM-jump term keeps the
        value it has at ``t_s`` and grows with new jumps, but does not decay; released, it decays
        from ``t_s`` on (module doc)."""
        with self._lock:
            self._set_hold(t_s, hold, self._unanchored)

    def _set_hold(self, t_s: float, denied: bool, unanchored: bool) -> None:
        """Change the reasons to hold the jump term; the term is re-based at ``t_s`` when whether
        it decays changes (call with the lock held)."""
        was = self._hold_jumps or self._unanchored
        value = self._decayed_m(t_s)
        self._hold_jumps, self._unanchored = denied, unanchored
        if (denied or unanchored) != was:
            self._jump = (t_s, value)

    def update_alignment(self, a: Alignment, follows: Alignment | None = None) -> None:
        """Adopt an accepted alignment (called from the fine-tuning worker; thread-safe).
        ``follows``: the alignment ``a`` replaces as the same alignment carried along with a moved
        map (companion.pipeline, _follow_map), so fixes stay continuous: the velocity and SLAM-jump
        history of the previous fixes carries over instead of starting again. If no fix used
        ``follows`` yet (a new alignment, carried along in the frame it arrived), the previous pose
        is placed with it, not with ``a``: that pose was solved against the map before the move."""
        T = a.T_ecef_slam
        c_ecef = T.apply(a.center_slam) if a.center_slam is not None else T.t
        lat, lon, _ = ecef_to_geodetic(c_ecef)
        R_ecef_enuC = LocalFrame(float(lat), float(lon)).R_ecef_enu
        cov6 = a.covariance_6x6()
        with self._lock:
            self._alignment = a
            self._cov_center = (c_ecef, R_ecef_enuC, cov6)
            prev = self._prev
            if prev is not None and follows is not None and prev[2] is follows:
                self._prev = (*prev[:2], a, *prev[3:])  # the same alignment, carried along: fixes continuous
                return
            self._new_segment = True  # the velocity track: the new alignment's shift is not motion
            if prev is not None:  # a new alignment: the previous pose placed with it (or with the one it was carried from)
                self._prev = (prev[0], self._place(follows if follows is not None else a, prev[3]), a, *prev[3:])
            if self._unanchored:  # a new alignment: the jump's term decays from the next fix on
                self._reanchored = True

    def fix(self, pose: SlamPose) -> GlobalFix | None:
        with self._lock:
            a, cc = self._alignment, self._cov_center
        if a is None or not pose.state.has_pose:
            return None
        if a.reset_counter != pose.reset_counter or a.map_id != pose.map_id:
            return None
        T_slam_cam = np.array(pose.T_slam_cam, float)  # a copy: kept as the previous pose
        T_ecef_body = a.T_ecef_slam.apply_pose(T_slam_cam) @ self.T_cam_body
        p = T_ecef_body[:3, 3]
        lat, lon, h = (float(x) for x in ecef_to_geodetic(p))
        frame = LocalFrame(lat, lon, h)
        R_ned_ecef = R_NED_ENU @ frame.R_ecef_enu.T
        R_ned_body = R_ned_ecef @ T_ecef_body[:3, :3]
        step = self._step(pose.t_s, p, a, T_slam_cam, (pose.reset_counter, pose.map_id))
        cov_ned = self._cov_ned(p, a, cc, R_ned_ecef)
        with self._lock:
            if self._reanchored:
                self._reanchored = False
                self._set_hold(pose.t_s, self._hold_jumps, False)
            jump_m, now_m = self._jump_m(pose.t_s, step)
            if not self._unanchored and now_m > UNANCHOR_SIGMAS * math.sqrt(np.linalg.eigvalsh(cov_ned[:2, :2])[-1]):
                self._set_hold(pose.t_s, self._hold_jumps, True)
                self._unanchoring_jump_m = now_m
            anchored = not self._unanchored
            v_ned, speed_acc = self._track_velocity(pose.t_s, p, (pose.reset_counter, pose.map_id), R_ned_ecef)
        cov_ned = cov_ned + jump_m ** 2 * np.eye(3)
        x, y, z, w = Rotation.from_matrix(R_ned_body).as_quat()
        return GlobalFix(
            t_s=pose.t_s, seq=pose.seq, p_ecef_m=p, lat_deg=lat, lon_deg=lon, h_ellipsoid_m=h,
            h_msl_m=float(ellipsoid_to_msl(lat, lon, h)), cov_ned_m2=cov_ned,
            h_acc_m=float(np.sqrt(np.linalg.eigvalsh(cov_ned[:2, :2])[-1])), v_acc_m=float(np.sqrt(cov_ned[2, 2])),
            source=a.source, v_ned_mps=v_ned, speed_acc_mps=speed_acc,
            yaw_deg=float(np.degrees(np.arctan2(R_ned_body[1, 0], R_ned_body[0, 0])) % 360.0),
            q_ned_body=np.array([w, x, y, z]), reset_counter=pose.reset_counter, anchored=anchored,
        )

    def _cov_ned(self, p_ecef: np.ndarray, a: Alignment, cc, R_ned_ecef: np.ndarray) -> np.ndarray:
        c_ecef, R_ecef_enuC, cov6 = cc
        d = R_ecef_enuC.T @ (p_ecef - c_ecef)  # lever arm from the alignment centre, ENU at the centre
        dist = float(np.linalg.norm(d))
        J = np.hstack([-np.array([[0, -d[2], d[1]], [d[2], 0, -d[0]], [-d[1], d[0], 0]]), np.eye(3)])
        if a.center_slam is None:  # information not about a known point: isotropic sigma only
            cov_enu = np.eye(3) * a.sigma_m**2
        else:
            cov_enu = J @ cov6 @ J.T
        iso = (a.scale_sigma * dist) ** 2 + (self.slam_drift_fraction * a.drift_distance_m(dist)) ** 2 + self.sigma_floor_m**2
        if a.source is not AlignmentSource.GNSS:  # GIS-based: the model's own georeference error
            iso += self.model_sigma_m**2
        R = R_ned_ecef @ R_ecef_enuC
        return R @ (cov_enu + iso * np.eye(3)) @ R.T

    def _step(self, t_s: float, p: np.ndarray, a: Alignment, T_slam_cam: np.ndarray,
              slam_map: tuple[int, int]) -> tuple[float, np.ndarray] | None:
        """(dt, ECEF velocity) from the previous fix to p (the body at T_slam_cam under alignment a)
        when both are poses of the same SLAM map at most max_velocity_dt_s apart, else None; p
        becomes the previous fix. Under a new alignment the previous pose is placed with it too,
        so the step is SLAM's own motion: a new alignment's shift is not a jump, and a SLAM jump in
        the frame a new alignment arrives is not hidden by it (`loop` seed 1 with full loop
        closing: a 2.3 m jump as a registration was adopted, two fixes 3.7-3.9 m off claiming
        0.89 m). An alignment carried along with its moved map (``follows``) is the same one."""
        prev, self._prev = self._prev, (t_s, p, a, T_slam_cam, slam_map)
        if prev is None or prev[4] != slam_map or not 0 < t_s - prev[0] <= self.max_velocity_dt_s:
            return None
        # (prev is re-placed by update_alignment; only one adopted after this fix read it is not)
        p_prev = prev[1] if prev[2] is a else self._place(a, prev[3])
        dt = t_s - prev[0]
        return dt, (p - p_prev) / dt

    def _place(self, a: Alignment, T_slam_cam: np.ndarray) -> np.ndarray:
        """ECEF position of the body at SLAM pose T_slam_cam under alignment a."""
        return (a.T_ecef_slam.apply_pose(T_slam_cam) @ self.T_cam_body)[:3, 3]

    def _jump_m(self, t_s: float, step: tuple[float, np.ndarray] | None) -> tuple[float, float]:
        """The SLAM-jump term (module doc): the distance of this fix from the constant-velocity
        prediction of the previous fixes (``step``: _step's), or the largest earlier one decayed by
        exp(−Δt / JUMP_MEMORY_S) (not decayed while held: ``hold_jumps``, ``unanchored``),
        whichever is larger; and that distance itself."""
        now_m = 0.0
        if step is None:
            self._v_ecef = None
        else:
            dt, v = step
            if self._v_ecef is not None:
                now_m = float(np.linalg.norm(v - self._v_ecef) * dt)
            self._v_ecef = v if self._v_ecef is None else self._v_ecef + VELOCITY_SMOOTHING * (v - self._v_ecef)
        decayed_m = self._decayed_m(t_s)
        if now_m >= decayed_m:
            self._jump = (t_s, now_m)
            return now_m, now_m
        return decayed_m, now_m

    def _decayed_m(self, t_s: float) -> float:
        """The recorded jump term at t_s: decayed since it was recorded, or as it is while held."""
        t_j, j_m = self._jump
        held = self._hold_jumps or self._unanchored
        return j_m if held else j_m * math.exp(-max(t_s - t_j, 0.0) / JUMP_MEMORY_S)

    def _track_velocity(self, t_s: float, p: np.ndarray, slam_map: tuple[int, int], R_ned_ecef: np.ndarray):
        """NED velocity and its 1-σ at this fix from the last second's fixes (gis.fix_velocity),
        (None, None) until there are enough. The track restarts on another SLAM map or after a gap;
        a new alignment (not one carried along with its map) or a SLAM jump starts a new segment."""
        track = self._track
        if track and (track[-1][3] != slam_map or not 0 < t_s - track[-1][0] <= self.max_velocity_dt_s):
            track.clear()
        while track and t_s - track[0][0] > fix_velocity.MAX_WINDOW_S:
            track.pop(0)
        seg = track[-1][2] if track else 0
        track.append((t_s, p, seg, slam_map))
        used = track[fix_velocity.window_start(np.array([e[0] for e in track])):]
        t = np.array([e[0] for e in used])
        ned = (np.array([e[1] for e in used]) - p) @ R_ned_ecef.T
        segment = np.array([e[2] for e in used])
        if len(used) > 1 and (self._new_segment or fix_velocity.breaks(t[:-1], ned[:-1], segment[:-1], t_s, ned[-1])):
            segment[-1] = seg + 1
            track[-1] = (t_s, p, seg + 1, slam_map)
        self._new_segment = False
        fit = fix_velocity.fit_velocity(t, ned, segment)
        if fit is None:
            return None, None
        return fit.v_ned_mps, float(np.hypot(fit.sigma_mps, self.velocity_sigma_floor_mps))


def with_horizontal_floor(fix: GlobalFix, sigma_h_m: float) -> GlobalFix:
    """``fix`` with no horizontal direction of its NED covariance below ``sigma_h_m`` (1-σ, metres):
    eigenvalues of the horizontal block raised to sigma_h_m², directions kept, the vertical and
    the cross terms with it left alone; h_acc_m follows. The fix itself when it already is."""
    w, V = np.linalg.eigh(fix.cov_ned_m2[:2, :2])
    if w[0] >= sigma_h_m ** 2:
        return fix
    cov = np.array(fix.cov_ned_m2, float)
    cov[:2, :2] = (V * np.maximum(w, sigma_h_m ** 2)) @ V.T
    return replace(fix, cov_ned_m2=cov, h_acc_m=float(np.sqrt(np.linalg.eigvalsh(cov[:2, :2])[-1])))
