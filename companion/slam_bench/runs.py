"""SLAM runs over a rendered sequence and their figures: tracking latency, tracking ratio, ATE after
Sim(3), keyframe tilt, scale kept, local-mapping / loop-closing times, the TerraSLAM Fig. 14
ablation's configurations, and a constructed loop for RLC against full-loop correction."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field, replace

import numpy as np
import psutil

from companion.slam_bench.sequence import Sequence
from slam.config import SlamConfig
from slam.geometry import DOWN_SLAM, project, sim3_scale, umeyama_sim3
from slam.system import SlamSystem
from slam.types import Frame, TrackingState


def time_features(seq: Sequence, configs: list[tuple[str, SlamConfig]], warmup: int = 5) -> list[str]:
    """Feature extraction alone, per frame (ms, wall): each configuration's extractor over every
    frame of the sequence after ``warmup`` frames (the first call on a GPU loads its kernels). The
    extractors return host arrays, so GPU work is finished when a call returns."""
    from slam.features import make_extractor

    rows = []
    for name, cfg in configs:
        ex = make_extractor(seq.camera, cfg)
        for im in seq.images[:warmup]:
            ex(im)
        ms, n = [], []
        for im in seq.images:
            t0 = time.perf_counter()
            f = ex(im)
            ms.append((time.perf_counter() - t0) * 1e3)
            n.append(len(f))
        rows.append(f"  {name:24s} mean {np.mean(ms):6.2f} ms  P50 {percentile(ms, 50):6.2f}  P99 {percentile(ms, 99):6.2f}  "
                    f"features/frame {np.mean(n):.0f}")
    return rows


@dataclass
class RunResult:
    name: str
    tracking_ms: np.ndarray
    tracking_cpu_ms: np.ndarray
    states: list[TrackingState]
    est_centers: np.ndarray  # (M,3) SLAM frame, frames with a pose
    true_centers: np.ndarray  # (M,3) ENU
    reset_counter: int
    local_mapping_ms: list[float]
    local_ba_ms: list[float]
    ba_window: list[int]
    loop_ms: list[float]
    loops: list[tuple[int, int]]
    n_points: int
    rss_mb: list[float] = field(default_factory=list)
    dropped: int = 0  # frames skipped because tracking was more than a frame period late
    kf_T_slam_cam: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # final keyframe poses
    kf_T_enu_cam: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # their truth
    local_ba_cpu_ms: list[float] = field(default_factory=list)  # CPU time of the local BAs (contention-free)
    fused: tuple[int, int] = (0, 0)  # local mapping's fuse_points: (observations joined, duplicate points merged)
    reproj_px: np.ndarray = field(default_factory=lambda: np.zeros(0))  # every observation's reprojection error in the final map

    @property
    def tracking_ratio(self) -> float:
        return float(np.mean([s.has_pose for s in self.states]))

    @property
    def ratio_after_init(self) -> float:
        first = next((i for i, s in enumerate(self.states) if s != TrackingState.INITIALIZING), len(self.states))
        rest = self.states[first:]
        return float(np.mean([s.has_pose for s in rest])) if rest else 0.0

    def ate(self) -> tuple[float, float, float]:
        """(RMSE m, path length m, RMSE % of path) after a Sim(3) fit of the estimate to truth."""
        return ate_after_sim3(self.est_centers, self.true_centers)


def tilt_errors_deg(T_slam_cam: np.ndarray, T_enu_cam: np.ndarray) -> dict[str, float]:
    """How far the keyframes' gravity direction is off (the map's tilt), in degrees.

    The SLAM frame is put on ENU by the rotation that best fits all keyframe orientations
    (chordal L2 mean of R_enu_cam·R_slam_camᵀ, as a GNSS + attitude bootstrap does); a keyframe's
    tilt error is then the angle between its true gravity direction in the camera
    (R_enu_camᵀ·down) and the estimated one ((R_enu_slam·R_slam_cam)ᵀ·down). ``rms``/``max``: over
    keyframes (how much the map's tilt varies along the flight). ``slam_z``: angle between the
    SLAM frame's z axis and true up (meaningful with the attitude prior, which makes z up).
    """
    if len(T_slam_cam) < 2:
        return {"rms": float("nan"), "max": float("nan"), "slam_z": float("nan")}
    R_est, R_true = T_slam_cam[:, :3, :3], T_enu_cam[:, :3, :3]
    U, _, Vt = np.linalg.svd(np.einsum("kij,klj->il", R_true, R_est))  # Σ R_true R_estᵀ
    R_enu_slam = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    down_enu = np.array([0.0, 0.0, -1.0])
    g_true = np.einsum("kji,j->ki", R_true, down_enu)
    g_est = np.einsum("kji,j->ki", np.einsum("ij,kjl->kil", R_enu_slam, R_est), down_enu)
    err = np.degrees(np.arccos(np.clip(np.einsum("ki,ki->k", g_true, g_est), -1, 1)))
    slam_z = np.degrees(np.arccos(np.clip((R_enu_slam @ -DOWN_SLAM) @ -down_enu, -1, 1)))
    return {"rms": float(np.sqrt((err**2).mean())), "max": float(err.max()), "slam_z": float(slam_z)}


def scale_ratio_end_to_start(est: np.ndarray, truth: np.ndarray) -> float:
    """Monocular scale of the last quarter of the tracked trajectory over that of the first (the
    scale of a Sim(3) fit of each quarter to truth; path lengths would count pose jitter while the
    vehicle is slow): 1 = kept, << 1 = collapsed."""
    if len(est) < 12:
        return float("nan")
    q = len(est) // 4
    s_first = sim3_scale(umeyama_sim3(est[:q], truth[:q]))
    s_last = sim3_scale(umeyama_sim3(est[-q:], truth[-q:]))
    return s_first / s_last  # the fit's scale maps SLAM units to metres: a shrinking map has a growing one


def ate_after_sim3(est: np.ndarray, truth: np.ndarray) -> tuple[float, float, float]:
    if len(est) < 3:
        return float("nan"), 0.0, float("nan")
    S = umeyama_sim3(est, truth)
    err = np.linalg.norm(est @ S[:3, :3].T + S[:3, 3] - truth, axis=1)
    rmse = float(np.sqrt((err**2).mean()))
    length = float(np.linalg.norm(np.diff(truth, axis=0), axis=1).sum())
    return rmse, length, 100 * rmse / max(length, 1e-9)


def run_sequence(seq: Sequence, config: SlamConfig, name: str = "", realtime: bool = True,
                 blackout: tuple[int, int] | None = None, order: np.ndarray | None = None,
                 drop_late: bool = False, lockstep: bool = False) -> RunResult:
    """Feed the sequence to a SlamSystem. blackout=(first, count) replaces frames with black images
    (a forced tracking loss); ``order`` replays frame indices in a custom order (e.g. out and back).
    realtime: frames are due at the scenario's frame rate; drop_late: a frame more than one period
    late is skipped, as a live camera source that keeps only the newest frame would. lockstep:
    wait for local mapping after every frame (the algorithm without CPU contention; not real-time).
    The simulated autopilot priors go with each frame when ``config.use_attitude_prior``."""
    proc = psutil.Process()
    order = np.arange(len(seq.images)) if order is None else order
    ms, cpu, states, est, tru, rss = [], [], [], [], [], []
    dropped = 0
    t_start = time.perf_counter()
    with SlamSystem(seq.camera, config) as s:
        for n, i in enumerate(order):
            due = t_start + n / seq.fps
            if drop_late and time.perf_counter() > due + 1 / seq.fps:
                dropped += 1
                continue
            img = seq.images[i]
            if blackout and blackout[0] <= n < blackout[0] + blackout[1]:
                img = np.zeros_like(img)
            prior = None
            if config.use_attitude_prior and seq.priors is not None:
                a = seq.priors[i]
                prior = replace(a, t_s=n / seq.fps + (a.t_s - seq.t_s[i]))
            c0 = time.thread_time()
            pose = s.track(Frame(img, n / seq.fps, n), prior)
            cpu.append((time.thread_time() - c0) * 1e3)
            ms.append(pose.tracking_ms)
            states.append(pose.state)
            if pose.state.has_pose:
                est.append(pose.T_slam_cam[:3, 3])
                tru.append(seq.T_enu_cam[i][:3, 3])
            if n % 100 == 0:
                rss.append(proc.memory_info().rss / 2**20)
            if lockstep:
                s.wait_mapping()
            elif realtime:
                time.sleep(max(0.0, due + 1 / seq.fps - time.perf_counter()))
            s.poll_map_updates()
        s.wait_mapping()
        st = s.mapper.stats
        kf_t, kf_T = s.keyframe_poses()
        kf_truth = seq.T_enu_cam[order[np.rint(kf_t * seq.fps).astype(int)]]
        with s.mapper.map.lock:
            reproj = map_reprojection_px(s.mapper.map, np.asarray(seq.camera.K, float))
        return RunResult(name, np.array(ms), np.array(cpu), states, np.array(est).reshape(-1, 3),
                         np.array(tru).reshape(-1, 3), s.reset_counter, list(st.local_mapping_ms),
                         list(st.local_ba_ms), list(st.ba_window), list(st.loop_ms), list(st.loops),
                         len(s.mapper.map.points), rss, dropped, kf_T, kf_truth, list(st.local_ba_cpu_ms),
                         (st.fused_observations, st.fused_points), reproj)


def map_reprojection_px(m, K: np.ndarray) -> np.ndarray:
    """Reprojection error [px] of every observation of every map point in the keyframes that
    still hold their features: how well a map's points and poses agree with what was observed
    (bundle adjustment minimises it; observations of different scene points under one point raise
    it). Caller holds m.lock."""
    errs = []
    for kf in m.keyframes.values():
        f = np.flatnonzero(kf.point_ids >= 0)
        f = f[[int(kf.point_ids[i]) in m.points for i in f.tolist()]]
        if len(f) == 0:
            continue
        P = np.array([m.points[int(kf.point_ids[i])].p_slam for i in f.tolist()])
        uv, z = project(K, kf.T_cam_slam, P)
        errs.append(np.linalg.norm(uv - kf.uv_px[f], axis=1)[z > 0])
    return np.concatenate(errs) if errs else np.zeros(0)


def inject_drifted_revisit(system: SlamSystem, source_kf_ids: list[int], S_drift: np.ndarray) -> list:
    """Constructed loop: append copies of ``source_kf_ids`` (same features) whose poses and freshly
    created points are moved by ``S_drift`` and share no map point with the originals — a revisit
    of an old place after drift. Returns the copies (newest last); feed the last to loop closing."""
    from slam.geometry import correct_pose_by_sim3
    from slam.map import Keyframe

    m = system.mapper.map
    dup: dict[int, int] = {}
    copies = []
    with m.lock:
        base = max(m.kf_ids()) + 1000
        for n, k in enumerate(source_kf_ids):
            kf = m.keyframes[k]
            kc = Keyframe(base + n, kf.t_s + 1e4, kf.seq + 10**7, correct_pose_by_sim3(kf.T_cam_slam, S_drift),
                          kf.uv_px, kf.desc, np.full(len(kf.point_ids), -1, np.int64))
            m.add_keyframe(kc)
            for f, pid in enumerate(kf.point_ids.tolist()):
                if pid < 0 or pid not in m.points:
                    continue
                if pid not in dup:
                    p = m.points[pid]
                    dup[pid] = m.add_point(S_drift[:3, :3] @ p.p_slam + S_drift[:3, 3], p.desc, {kc.kf_id: f})
                else:
                    m.points[dup[pid]].obs[kc.kf_id] = f
                    kc.point_ids[f] = dup[pid]
            copies.append(kc)
    return copies


def loop_ablation(seq: Sequence, base: SlamConfig) -> list[tuple[str, list[float], list[tuple[int, int]], float]]:
    """RLC vs full-loop optimisation on the same constructed loop: after the sequence, the first
    keyframes are revisited with a 3 deg / 8 % / 3 %-of-depth drift. Returns (mode, loop ms, loops,
    mean camera-centre error of the revisit after correction, in map units)."""
    from slam.geometry import camera_center, sim3_matrix

    out = []
    for mode in ("full", "recursive"):
        cfg = base.model_copy(update=dict(loop_closing=mode))
        with SlamSystem(seq.camera, cfg) as s:
            for i in range(len(seq.images)):
                s.track(Frame(seq.images[i], i / seq.fps, i))
            s.wait_mapping()
            m = s.mapper.map
            a = np.deg2rad(3.0)
            R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
            depth = float(np.median([np.linalg.norm(p.p_slam) for p in m.points.values()]))
            src = m.kf_ids()[1:4]
            copies = inject_drifted_revisit(s, src, sim3_matrix(1.08, R, np.array([0.03, -0.02, 0.01]) * depth))
            s.mapper._loop(copies[-1])
            err = np.mean([np.linalg.norm(camera_center(c.T_cam_slam) - camera_center(m.keyframes[k].T_cam_slam))
                           for c, k in zip(copies, src)])
            print(f"  [{mode}] keyframes in the map {len(m.keyframes)}, optimised in loop BA(s): "
                  f"{s.mapper.stats.loop_ba_keyframes}", flush=True)
            out.append((mode, list(s.mapper.stats.loop_ms), list(s.mapper.stats.loops), float(err)))
    return out


def ablation_configs(base: SlamConfig, with_ga: bool = True) -> list[tuple[str, SlamConfig]]:
    """TerraSLAM Fig. 14: baseline, +GA (torch features), +PLM, +RLC (cumulative). Without GA (no
    GPU: torch on a CPU is slower than OpenCV) the later steps build on the CPU baseline."""
    b = base.model_copy(update=dict(feature_backend="cpu", progressive_local_mapping=False, loop_closing="full"))
    ga = b.model_copy(update=dict(feature_backend="torch"))
    plm = (ga if with_ga else b).model_copy(update=dict(progressive_local_mapping=True))
    rlc = plm.model_copy(update=dict(loop_closing="recursive"))
    return [("baseline", b)] + ([("+GA", ga)] if with_ga else []) + [("+PLM", plm), ("+RLC", rlc)]


def local_window_ms(r: RunResult, local_window: int) -> float:
    """Mean solve time of the BAs over at most the local window (ba_window[i] pairs with local_ba_ms[i])."""
    n = min(len(r.ba_window), len(r.local_ba_ms))
    ms = [t for win, t in zip(r.ba_window[:n], r.local_ba_ms[:n]) if win <= local_window]
    return float(np.mean(ms)) if ms else float("nan")


def percentile(x, q) -> float:
    """np.percentile of x, NaN when x is empty."""
    return float(np.percentile(x, q)) if len(x) else float("nan")


def report(r: RunResult) -> str:
    rmse, length, pct = r.ate()
    tilt = tilt_errors_deg(r.kf_T_slam_cam, r.kf_T_enu_cam)
    lines = [
        f"[{r.name}] frames {len(r.states)}  tracked {100 * r.tracking_ratio:.1f} % (after init {100 * r.ratio_after_init:.1f} %)"
        f"  resets {r.reset_counter}  relocalized {sum(s == TrackingState.RELOCALIZED for s in r.states)}"
        f"  dropped late {r.dropped}",
        f"  tracking wall ms: mean {r.tracking_ms.mean():.1f}  P99 {percentile(r.tracking_ms, 99):.1f}   "
        f"tracking-thread CPU ms: mean {r.tracking_cpu_ms.mean():.1f}  P99 {percentile(r.tracking_cpu_ms, 99):.1f}",
        f"  ATE after Sim(3): {rmse:.3f} m over {length:.1f} m path = {pct:.2f} %",
        f"  keyframe tilt error (deg, orientation-aligned): RMS {tilt['rms']:.2f}  max {tilt['max']:.2f}; "
        f"SLAM z vs true up {tilt['slam_z']:.2f}; scale end/start {scale_ratio_end_to_start(r.est_centers, r.true_centers):.2f}",
        f"  local mapping per keyframe: thread ms mean {np.mean(r.local_mapping_ms or [np.nan]):.0f}; local BA "
        f"(async, worker process) solve ms mean {np.mean(r.local_ba_ms or [np.nan]):.0f} P99 {percentile(r.local_ba_ms, 99):.0f} "
        f"(CPU ms mean {np.mean(r.local_ba_cpu_ms or [np.nan]):.0f}), "
        f"window mean {np.mean(r.ba_window or [np.nan]):.1f} kf; {len(r.local_mapping_ms)} keyframes",
        f"  loops closed {len(r.loops)}  loop-correction ms: {', '.join(f'{x:.0f}' for x in r.loop_ms) or '-'}",
        f"  map points {r.n_points} (fusing joined {r.fused[0]} observations, merged {r.fused[1]} duplicates)  "
        f"RSS MB: {', '.join(f'{x:.0f}' for x in r.rss_mb)}",
        f"  observations' reprojection error in the final map: median {percentile(r.reproj_px, 50):.2f} px, P90 {percentile(r.reproj_px, 90):.2f} px",
        f"  load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs (shared machine: wall times include contention)",
    ]
    return "\n".join(lines)



def prior_row(r: RunResult) -> dict[str, float]:
    """The attitude-prior comparison's figures of one run."""
    tilt = tilt_errors_deg(r.kf_T_slam_cam, r.kf_T_enu_cam)
    return {"ate_pct": r.ate()[2], "tilt_rms_deg": tilt["rms"], "tilt_max_deg": tilt["max"], "slam_z_deg": tilt["slam_z"],
            "tracked": r.tracking_ratio, "track_ms_mean": float(r.tracking_ms.mean()), "track_ms_p99": percentile(r.tracking_ms, 99),
            "scale_end_start": scale_ratio_end_to_start(r.est_centers, r.true_centers), "resets": r.reset_counter,
            "loops": len(r.loops), "ba_ms_mean": float(np.mean(r.local_ba_ms or [np.nan]))}


