"""SLAM benchmark on the simulator's scenarios (issue 4 targets, TerraSLAM Fig. 14 ablation).

    python -m slam.bench --scenario nominal --frames 600 [--ablation] [--force-loss 300:15]
    python -m slam.bench --memory --minutes 10 [--fps 10] [--sample-every 300]
    python -m slam.bench --scenario loop --frames 600 --camera-fps 10 --attitude-prior both --repeat 3
    python -m slam.bench --frames 300 --export seq.npz --jpeg-quality 75   # then, on a board or GPU machine:
    python -m slam.bench --sequence seq.npz --ablation --device cuda:0 [--features]

Prints per-frame tracking latency (wall and tracking-thread CPU, mean/P99), tracking ratio,
ATE after Sim(3) alignment as % of path length, local-mapping and loop-closing times, map size
and process memory. Frames are fed at the scenario's frame rate (real-time pacing) so the
background threads compete with tracking as they would in flight.

``--memory``: one lap of the scenario's loop is rendered once to --cache-dir (a child process, one
frame at a time read back from disk) and flown out and back for --minutes of flight time; every
--sample-every frames it prints RSS, the BA worker's RSS and the map's sizes, then the RSS slope
over the second half (MB per flight minute) and RSS(end) / RSS(at 2 min).
"""
from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass, field, replace

import numpy as np
import psutil

from slam.config import SlamConfig
from slam.geometry import DOWN_SLAM, project, sim3_scale, umeyama_sim3
from slam.mapping import MapMemory
from slam.system import SlamSystem
from slam.types import AttitudePrior, CameraModel, Frame, TrackingState


@dataclass
class Sequence:
    name: str
    camera: CameraModel
    images: np.ndarray  # (N,H,W) uint8 gray
    T_enu_cam: np.ndarray  # (N,4,4) truth
    t_s: np.ndarray
    fps: float
    priors: list[AttitudePrior] | None = None  # the simulated autopilot's attitude at each frame


def simulated_priors(sc, t_s: np.ndarray) -> list[AttitudePrior]:
    """The simulator's autopilot attitude (companion/sim/autopilot_signals.py: AHRS bias + noise)
    at each frame time — the newest sample at or before it, as the pipeline gets it — with its
    gravity direction in the camera from the scenario's camera mount (companion.pipeline's own
    attitude_prior + with_gravity)."""
    from companion.pipeline import attitude_prior, with_gravity  # the benchmark, not slam/, uses the pipeline

    samples = sc.attitude_samples
    t_att = np.array([a.t_s for a in samples])
    R_cam_body = np.linalg.inv(sc.T_body_cam)[:3, :3]
    return [with_gravity(attitude_prior(samples[max(0, int(np.searchsorted(t_att, t + 1e-9)) - 1)]), R_cam_body)
            for t in t_s]


def render_sequence(scenario: str = "nominal", n_frames: int = 300, seed: int = 0,
                    cache_dir: str | None = None, start: int = 0, fps: float | None = None) -> Sequence:
    """Render frames [start, start+n_frames) of a simulator scenario (optionally cached as .npz).
    fps: camera frame rate instead of the scenario's (the same flight sampled more sparsely)."""
    import cv2

    from companion.sim import make_scenario  # the benchmark, not slam/ itself, uses the simulator

    tag = f"_{fps:g}fps" if fps else ""
    path = os.path.join(cache_dir, f"slam_{scenario}_{seed}_{start}_{n_frames}{tag}.npz") if cache_dir else None
    sc = make_scenario(scenario, seed=seed, n_frames=start + n_frames, **({"fps": fps} if fps else {}))
    if path and os.path.exists(path):
        d = np.load(path)
        return Sequence(scenario, sc.camera, d["images"], d["T"], d["t"], sc.fps, simulated_priors(sc, d["t"]))
    imgs, T, t = [], [], []
    for st in sc.steps(start=start):
        im = st.frame.image
        imgs.append(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) if im.ndim == 3 else im)
        T.append(st.truth.T_enu_cam)
        t.append(st.frame.t_s)
    seq = Sequence(scenario, sc.camera, np.array(imgs), np.array(T), np.array(t), sc.fps, simulated_priors(sc, np.array(t)))
    if path:
        os.makedirs(cache_dir, exist_ok=True)
        np.savez(path, images=seq.images, T=seq.T_enu_cam, t=seq.t_s)
    return seq


def save_sequence(seq: Sequence, path: str, jpeg_quality: int | None = None) -> None:
    """Write a rendered sequence to one .npz that ``load_sequence`` reads without the simulator
    (open3d): frames rendered on a workstation can then be replayed on a companion board or a
    GPU machine. jpeg_quality: store the frames as JPEG (lossy, ~1/6 of the raw size at 75;
    every configuration replayed from the file sees the same frames) instead of raw pixels."""
    pr = seq.priors or []
    arrays = dict(
        name=np.array(seq.name), K=seq.camera.K, dist=seq.camera.dist,
        size_px=np.array([seq.camera.width_px, seq.camera.height_px]), T=seq.T_enu_cam, t=seq.t_s,
        fps=np.array(seq.fps),
        prior_rpy_t=np.array([[a.t_s, a.roll_rad, a.pitch_rad, a.yaw_rad,
                               np.nan if a.baro_alt_m is None else a.baro_alt_m,
                               np.nan if a.gravity_sigma_rad is None else a.gravity_sigma_rad] for a in pr]).reshape(-1, 6),
        prior_gravity=np.array([np.full(3, np.nan) if a.gravity_cam is None else a.gravity_cam for a in pr]).reshape(-1, 3))
    if jpeg_quality is None:
        arrays["images"] = seq.images
    else:
        import cv2

        blobs = []
        for im in seq.images:
            ok, buf = cv2.imencode(".jpg", im, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
            if not ok:
                raise ValueError(f"JPEG encoding of a {im.shape} frame failed")
            blobs.append(buf.ravel())
        arrays["jpeg"] = np.concatenate(blobs)
        arrays["jpeg_end"] = np.cumsum([len(b) for b in blobs])
    np.savez(path, **arrays)


def load_sequence(path: str) -> Sequence:
    """Read a sequence written by ``save_sequence`` (numpy and OpenCV only)."""
    import cv2

    d = np.load(path, allow_pickle=False)
    if "images" in d:
        images = d["images"]
    else:
        ends = d["jpeg_end"]
        starts = np.r_[0, ends[:-1]]
        images = np.array([cv2.imdecode(d["jpeg"][a:b], cv2.IMREAD_GRAYSCALE) for a, b in zip(starts, ends)])
    w, h = (int(x) for x in d["size_px"])
    if images.shape[1:] != (h, w) or len(images) != len(d["T"]):
        raise ValueError(f"{path}: {images.shape} frames do not match {len(d['T'])} poses of {w}x{h} px")
    priors = [AttitudePrior(float(r[0]), float(r[1]), float(r[2]), float(r[3]),
                            None if np.isnan(r[4]) else float(r[4]), None if np.isnan(g).any() else g.copy(),
                            None if np.isnan(r[5]) else float(r[5]))
              for r, g in zip(d["prior_rpy_t"], d["prior_gravity"])]
    return Sequence(str(d["name"]), CameraModel(w, h, d["K"], d["dist"]), images, d["T"], d["t"], float(d["fps"]),
                    priors or None)


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
        rows.append(f"  {name:24s} mean {np.mean(ms):6.2f} ms  P50 {_p(ms, 50):6.2f}  P99 {_p(ms, 99):6.2f}  "
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


def _local_window_ms(r: RunResult, local_window: int) -> float:
    """Mean solve time of the BAs over at most the local window (ba_window[i] pairs with local_ba_ms[i])."""
    n = min(len(r.ba_window), len(r.local_ba_ms))
    ms = [t for win, t in zip(r.ba_window[:n], r.local_ba_ms[:n]) if win <= local_window]
    return float(np.mean(ms)) if ms else float("nan")


def _p(x, q) -> float:
    return float(np.percentile(x, q)) if len(x) else float("nan")


def report(r: RunResult) -> str:
    rmse, length, pct = r.ate()
    tilt = tilt_errors_deg(r.kf_T_slam_cam, r.kf_T_enu_cam)
    lines = [
        f"[{r.name}] frames {len(r.states)}  tracked {100 * r.tracking_ratio:.1f} % (after init {100 * r.ratio_after_init:.1f} %)"
        f"  resets {r.reset_counter}  relocalized {sum(s == TrackingState.RELOCALIZED for s in r.states)}"
        f"  dropped late {r.dropped}",
        f"  tracking wall ms: mean {r.tracking_ms.mean():.1f}  P99 {_p(r.tracking_ms, 99):.1f}   "
        f"tracking-thread CPU ms: mean {r.tracking_cpu_ms.mean():.1f}  P99 {_p(r.tracking_cpu_ms, 99):.1f}",
        f"  ATE after Sim(3): {rmse:.3f} m over {length:.1f} m path = {pct:.2f} %",
        f"  keyframe tilt error (deg, orientation-aligned): RMS {tilt['rms']:.2f}  max {tilt['max']:.2f}; "
        f"SLAM z vs true up {tilt['slam_z']:.2f}; scale end/start {scale_ratio_end_to_start(r.est_centers, r.true_centers):.2f}",
        f"  local mapping per keyframe: thread ms mean {np.mean(r.local_mapping_ms or [np.nan]):.0f}; local BA "
        f"(async, worker process) solve ms mean {np.mean(r.local_ba_ms or [np.nan]):.0f} P99 {_p(r.local_ba_ms, 99):.0f} "
        f"(CPU ms mean {np.mean(r.local_ba_cpu_ms or [np.nan]):.0f}), "
        f"window mean {np.mean(r.ba_window or [np.nan]):.1f} kf; {len(r.local_mapping_ms)} keyframes",
        f"  loops closed {len(r.loops)}  loop-correction ms: {', '.join(f'{x:.0f}' for x in r.loop_ms) or '-'}",
        f"  map points {r.n_points} (fusing joined {r.fused[0]} observations, merged {r.fused[1]} duplicates)  RSS MB: {', '.join(f'{x:.0f}' for x in r.rss_mb)}",
        f"  observations' reprojection error in the final map: median {_p(r.reproj_px, 50):.2f} px, P90 {_p(r.reproj_px, 90):.2f} px",
        f"  load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs (shared machine: wall times include contention)",
    ]
    return "\n".join(lines)



# --------------------------------------------------------------------------------------------
# memory benchmark: a long flight, RSS and map sizes sampled every N frames (issue 4)

MEM_CHUNK_FRAMES = 100  # frames per file of the rendered lap


@dataclass
class LapFrames:
    """One lap of a loop flight rendered to disk (gray uint8, raw chunks of MEM_CHUNK_FRAMES frames).
    ``image(i)`` reads one frame from its file, so the lap never sits in the measured process's
    memory (no mmap either: mapped file pages would count in its RSS)."""

    root: str
    camera: CameraModel
    fps: float
    n_frames: int
    T_enu_cam: np.ndarray  # (n_frames,4,4) truth

    def _chunk(self, k: int) -> str:
        return os.path.join(self.root, f"chunk_{k:04d}.u8")

    def image(self, i: int) -> np.ndarray:
        h, w = self.camera.height_px, self.camera.width_px
        with open(self._chunk(i // MEM_CHUNK_FRAMES), "rb") as f:
            f.seek((i % MEM_CHUNK_FRAMES) * h * w)
            return np.frombuffer(f.read(h * w), np.uint8).reshape(h, w).copy()


def _lap_scenario(scenario: str, seed: int, fps: float):
    """``scenario``'s loop flown exactly once: it starts and ends at rest, so an out-and-back
    replay of it is a continuous flight of any length."""
    from companion.sim.scenario import make_scenario, scenario_spec

    spec = scenario_spec(scenario, fps=fps)
    if spec.flight.kind != "loop":
        raise ValueError(f"--memory needs a loop scenario, {scenario!r} flies {spec.flight.kind!r}")
    return make_scenario(scenario, seed=seed, spec=replace(spec, flight=replace(spec.flight, laps=1.0)))


def _render_lap_chunks(scenario: str, seed: int, fps: float, root: str) -> None:
    import cv2

    sc = _lap_scenario(scenario, seed, fps)
    os.makedirs(root, exist_ok=True)
    for k in range(0, sc.n_frames, MEM_CHUNK_FRAMES):
        path = os.path.join(root, f"chunk_{k // MEM_CHUNK_FRAMES:04d}.u8")
        if os.path.exists(path):
            continue  # resumable: chunks already rendered are kept
        frames = []
        for i in range(k, min(k + MEM_CHUNK_FRAMES, sc.n_frames)):
            im = sc.render(i).image_bgr
            frames.append(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) if im.ndim == 3 else im)
        np.ascontiguousarray(np.array(frames, np.uint8)).tofile(path + ".tmp")
        os.replace(path + ".tmp", path)
        print(f"  rendered frames {k}-{k + len(frames) - 1} of {sc.n_frames}", flush=True)


def render_lap(scenario: str = "nominal", seed: int = 0, fps: float = 10.0,
               cache_dir: str = os.path.expanduser("~/.cache/terraslam/slam_bench")) -> LapFrames:
    """Render (once, in a child process so the renderer's memory is not measured) or load a lap."""
    import multiprocessing as mp

    sc = _lap_scenario(scenario, seed, fps)
    root = os.path.join(cache_dir, f"lap_{scenario}_{seed}_{fps:g}fps")
    n_chunks = -(-sc.n_frames // MEM_CHUNK_FRAMES)
    if not all(os.path.exists(os.path.join(root, f"chunk_{k:04d}.u8")) for k in range(n_chunks)):
        p = mp.get_context("fork").Process(target=_render_lap_chunks, args=(scenario, seed, fps, root))
        p.start()
        p.join()
        if p.exitcode != 0:
            raise RuntimeError(f"rendering the lap failed (exit code {p.exitcode})")
    return LapFrames(root, sc.camera, fps, sc.n_frames, sc.truth.T_enu_cam.copy())


def out_and_back(n_lap: int, n_frames: int) -> np.ndarray:
    """Frame indices of a lap flown forwards, backwards, forwards ... for n_frames frames."""
    period = np.r_[np.arange(n_lap), np.arange(n_lap - 2, 0, -1)]
    return period[np.arange(n_frames) % len(period)]



@dataclass
class MemorySample:
    frame: int
    flight_s: float
    wall_s: float
    rss_mb: float  # this process (VmRSS)
    rss_anon_mb: float  # its anonymous part (heap): file-backed pages excluded
    children_rss_mb: float  # the BA worker process
    threads: int
    loops: int
    mem: MapMemory


def _status_mb(key: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    return float("nan")


def run_memory(lap: LapFrames, config: SlamConfig, minutes: float, sample_every: int = 300,
               realtime: bool = True, lockstep: bool = False, progress: bool = True) -> tuple[list[MemorySample], RunResult]:
    """Fly the lap out and back for ``minutes`` of flight time and sample memory every
    ``sample_every`` frames. Map updates are not polled, as in the pipeline (companion.pipeline).
    lockstep: after each keyframe wait until local mapping (and its BA) is done, as on a machine
    where mapping keeps up with the camera (on 2 shared cores it does not, and the map resets in turns)."""
    proc = psutil.Process()
    n = int(round(minutes * 60 * lap.fps))
    order = out_and_back(lap.n_frames, n)
    est, tru = np.full((n, 3), np.nan), lap.T_enu_cam[order][:, :3, 3]
    states: list[TrackingState] = []
    ms = np.zeros(n)
    samples: list[MemorySample] = []
    t_start = time.perf_counter()

    def sample(k: int, s: SlamSystem) -> None:
        kids = sum(c.memory_info().rss for c in proc.children(recursive=True)) / 2**20
        samples.append(MemorySample(k, k / lap.fps, time.perf_counter() - t_start, proc.memory_info().rss / 2**20,
                                    _status_mb("RssAnon"), kids, proc.num_threads(), s.mapper.stats.n_loops,
                                    s.mapper.memory()))
        if progress:
            print(memory_row(samples[-1]), flush=True)

    if progress:
        print(memory_header(), flush=True)
    with SlamSystem(lap.camera, config) as s:
        for k, i in enumerate(order):
            pose = s.track(Frame(lap.image(int(i)), k / lap.fps, k))
            ms[k] = pose.tracking_ms
            states.append(pose.state)
            if pose.state.has_pose:
                est[k] = pose.T_slam_cam[:3, 3]
            if lockstep:
                s.wait_mapping()  # returns at once when mapping is idle
            if k % sample_every == 0:
                sample(k, s)
            if realtime:
                time.sleep(max(0.0, t_start + (k + 1) / lap.fps - time.perf_counter()))
        s.wait_mapping()
        sample(n, s)
        ok = np.isfinite(est[:, 0])
        st = s.mapper.stats
        run = RunResult("memory", ms, np.full(n, np.nan), states, est[ok], tru[ok], s.reset_counter,
                        list(st.local_mapping_ms), list(st.local_ba_ms), list(st.ba_window), list(st.loop_ms),
                        list(st.loops), len(s.mapper.map.points), fused=(st.fused_observations, st.fused_points))
    return samples, run


def memory_header() -> str:
    return ("| frame | flight min | wall s | RSS MB | anon MB | BA worker MB | threads | keyframes all / with features | "
            "anchors | points | observations | place entries | features+points+place MB | queued kf / updates (dropped) | loops |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")


def memory_row(x: MemorySample) -> str:
    m = x.mem
    data_mb = (m.map.feature_bytes + m.map.point_bytes + m.place_bytes) / 2**20
    return (f"| {x.frame} | {x.flight_s / 60:.1f} | {x.wall_s:.0f} | {x.rss_mb:.0f} | {x.rss_anon_mb:.0f} | "
            f"{x.children_rss_mb:.0f} | {x.threads} | {m.map.keyframes} / {m.map.keyframes_with_features} | {m.loop_anchors} | "
            f"{m.map.map_points} | {m.map.observations} | {m.place_entries} | {data_mb:.1f} | "
            f"{m.queued_keyframes} / {m.queued_updates} ({m.dropped_updates}) | {x.loops} |")


def memory_summary(samples: list[MemorySample]) -> dict:
    """RSS slope over the second half of the flight (MB per flight minute, least squares) and
    RSS(end) / RSS(at 2 min)."""
    t_min = np.array([x.flight_s for x in samples]) / 60
    rss = np.array([x.rss_mb for x in samples])
    half = t_min >= t_min[-1] / 2
    slope = float(np.polyfit(t_min[half], rss[half], 1)[0]) if half.sum() >= 2 else float("nan")
    at2 = int(np.argmin(np.abs(t_min - 2.0)))
    return {"rss_start_mb": float(rss[0]), "rss_2min_mb": float(rss[at2]), "rss_end_mb": float(rss[-1]),
            "rss_peak_mb": float(rss.max()), "slope_second_half_mb_per_min": slope,
            "ratio_end_to_2min": float(rss[-1] / rss[at2]), "flight_min": float(t_min[-1])}


def cli_config(a: argparse.Namespace) -> SlamConfig:
    """The SlamConfig of the command line: --backend, --device, then every --set KEY=VALUE."""
    overrides = dict(kv.split("=", 1) for kv in a.set)
    return SlamConfig(**{**SlamConfig().model_dump(), "feature_backend": a.backend, "torch_device": a.device, **overrides})


def memory_main(a: argparse.Namespace) -> None:
    t0 = time.perf_counter()
    lap = render_lap(a.scenario, a.seed, a.fps, a.cache_dir)
    print(f"lap of '{a.scenario}': {lap.n_frames} frames at {a.fps:g} fps, ready in {time.perf_counter() - t0:.0f} s "
          f"(cache {lap.root})", flush=True)
    if a.render_only:
        return
    cfg = cli_config(a)
    samples, run = run_memory(lap, cfg, a.minutes, a.sample_every, realtime=not a.no_realtime, lockstep=a.lockstep)
    f = memory_summary(samples)
    rmse, length, pct = run.ate()
    print(f"\nRSS MB: start {f['rss_start_mb']:.0f}, at 2 min {f['rss_2min_mb']:.0f}, end {f['rss_end_mb']:.0f}, "
          f"peak {f['rss_peak_mb']:.0f}; slope over the second half {f['slope_second_half_mb_per_min']:+.2f} MB/min; "
          f"RSS(end)/RSS(2 min) {f['ratio_end_to_2min']:.3f} over {f['flight_min']:.1f} min of flight")
    print(f"SLAM: tracked {100 * run.tracking_ratio:.1f} % of {len(run.states)} frames, resets {run.reset_counter}, "
          f"loops closed {len(run.loops)}, ATE after Sim(3) {rmse:.2f} m over {length:.0f} m = {pct:.2f} %; "
          f"config max_keyframes {cfg.max_keyframes}, loop_anchor_every {cfg.loop_anchor_every}, "
          f"max_loop_anchors {cfg.max_loop_anchors}, max_trajectory_keyframes {cfg.max_trajectory_keyframes}")
    print(f"  load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; {'real-time' if not a.no_realtime else 'as fast as possible'}"
          f"{', lockstep with local mapping' if a.lockstep else ''}; overrides {', '.join(a.set) or 'none'}")


def prior_row(r: RunResult) -> dict[str, float]:
    """The attitude-prior comparison's figures of one run."""
    tilt = tilt_errors_deg(r.kf_T_slam_cam, r.kf_T_enu_cam)
    return {"ate_pct": r.ate()[2], "tilt_rms_deg": tilt["rms"], "tilt_max_deg": tilt["max"], "slam_z_deg": tilt["slam_z"],
            "tracked": r.tracking_ratio, "track_ms_mean": float(r.tracking_ms.mean()), "track_ms_p99": _p(r.tracking_ms, 99),
            "scale_end_start": scale_ratio_end_to_start(r.est_centers, r.true_centers), "resets": r.reset_counter,
            "loops": len(r.loops), "ba_ms_mean": float(np.mean(r.local_ba_ms or [np.nan]))}


def prior_main(seq: Sequence, base: SlamConfig, a: argparse.Namespace) -> None:
    """Without / with the attitude prior on the same frames, runs alternated so both see the same
    machine load; one line per run, then mean [min, max] per configuration."""
    modes = {"off": [False], "on": [True], "both": [False, True]}[a.attitude_prior]
    rows: dict[bool, list[dict]] = {m: [] for m in modes}
    for k in range(a.repeat):
        for use in modes:
            cfg = base.model_copy(update=dict(use_attitude_prior=use))
            r = run_sequence(seq, cfg, f"prior {'on' if use else 'off'} #{k + 1}", realtime=not a.no_realtime,
                             drop_late=a.drop_late, lockstep=a.lockstep)
            print(report(r), flush=True)
            rows[use].append(prior_row(r))
    keys = list(rows[modes[0]][0])
    pacing = "lockstep with local mapping" if a.lockstep else ("as fast as possible" if a.no_realtime else "real-time")
    print(f"\n{seq.name}, {len(seq.images)} frames at {seq.fps:g} fps ({pacing}), {a.repeat} run(s) each: mean [min, max]")
    print("| prior | " + " | ".join(keys) + " |\n|---|" + "---|" * len(keys))
    for use in modes:
        cells = []
        for key in keys:
            v = np.array([row[key] for row in rows[use]], float)
            cells.append(f"{np.nanmean(v):.3g} [{np.nanmin(v):.3g}, {np.nanmax(v):.3g}]" if np.isfinite(v).any() else "nan")
        print(f"| {'on' if use else 'off'} | " + " | ".join(cells) + " |")
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")


def start_frame(scenario: str, seed: int, fps: float | None, start_s: str, n_frames: int) -> int:
    """First frame of a run of n_frames: ``start_s`` seconds of flight, or 'turn': the start of
    the pipeline benchmark's window (companion.bench.bench_window_s: 10 s before the first turn)."""
    from companion.sim import make_scenario

    sc = make_scenario(scenario, seed=seed, **({"fps": fps} if fps else {}))
    if start_s == "turn":
        from companion.bench import bench_window_s  # the benchmark, not slam/, uses the pipeline's window

        t = bench_window_s(sc, n_frames)[0]
    else:
        t = float(start_s)
    return int(round(t * sc.fps))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", default="nominal")
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ablation", action="store_true", help="run baseline/+GA/+PLM/+RLC (Fig. 14)")
    ap.add_argument("--force-loss", default=None, help="FIRST:COUNT black frames to force a tracking loss")
    ap.add_argument("--no-ga", action="store_true", help="ablation without the torch (GA) step, for CPU-only machines")
    ap.add_argument("--loop-ablation", action="store_true", help="RLC vs full-loop correction on a constructed drifted revisit")
    ap.add_argument("--backend", choices=["cpu", "torch"], default="cpu")
    ap.add_argument("--device", default="cpu", help="torch device for the torch backend")
    ap.add_argument("--cache-dir", default=os.path.expanduser("~/.cache/terraslam/slam_bench"))
    ap.add_argument("--no-realtime", action="store_true", help="feed frames as fast as possible")
    ap.add_argument("--drop-late", action="store_true", help="skip frames tracking is too late for (live camera)")
    ap.add_argument("--memory", action="store_true", help="long out-and-back flight; RSS and map sizes every --sample-every frames")
    ap.add_argument("--minutes", type=float, default=10.0, help="--memory: flight time")
    ap.add_argument("--fps", type=float, default=10.0, help="--memory: camera frame rate")
    ap.add_argument("--sample-every", type=int, default=300, help="--memory: frames between samples")
    ap.add_argument("--render-only", action="store_true", help="--memory: render the lap into --cache-dir and stop")
    ap.add_argument("--lockstep", action="store_true", help="wait for local mapping after each frame (--memory: each keyframe)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="SlamConfig override, e.g. --set max_keyframes=200 (repeatable)")
    ap.add_argument("--camera-fps", type=float, default=None, help="render the scenario at this frame rate instead of its own")
    ap.add_argument("--start-s", default="0",
                    help="flight time of the first frame (s), or 'turn': 10 s before the first turn, as terraslam bench's window")
    ap.add_argument("--attitude-prior", choices=["off", "on", "both"], default="off",
                    help="feed the simulated autopilot's gravity direction (slam.use_attitude_prior); both: alternate off/on runs")
    ap.add_argument("--repeat", type=int, default=1, help="runs per configuration (SLAM is not bit-reproducible)")
    ap.add_argument("--export", metavar="FILE.npz", help="write the rendered frames, truth and priors to FILE and stop")
    ap.add_argument("--jpeg-quality", type=int, default=None, help="--export: store frames as JPEG of this quality")
    ap.add_argument("--sequence", metavar="FILE.npz", help="replay a sequence written by --export (no simulator needed)")
    ap.add_argument("--features", action="store_true",
                    help="time feature extraction alone: OpenCV ORB and the torch extractor on cpu and --device")
    a = ap.parse_args(argv)
    if a.memory:
        memory_main(a)
        return
    t0 = time.perf_counter()
    if a.sequence:
        seq = load_sequence(a.sequence)
        print(f"loaded {len(seq.images)} frames of '{seq.name}' from {a.sequence} in {time.perf_counter() - t0:.0f} s")
    else:
        start = start_frame(a.scenario, a.seed, a.camera_fps, a.start_s, a.frames)
        seq = render_sequence(a.scenario, a.frames, a.seed, a.cache_dir, start=start, fps=a.camera_fps)
        print(f"rendered/loaded {len(seq.images)} frames of '{a.scenario}' from frame {start} in {time.perf_counter() - t0:.0f} s")
    if a.export:
        save_sequence(seq, a.export, a.jpeg_quality)
        print(f"wrote {a.export} ({os.path.getsize(a.export) / 1e6:.1f} MB)")
        return
    base = cli_config(a)
    if a.features:
        cpu = base.model_copy(update=dict(feature_backend="cpu"))
        configs = [("OpenCV ORB (cpu)", cpu)] + [(f"torch patch-parallel ({d})", cpu.model_copy(
            update=dict(feature_backend="torch", torch_device=d))) for d in dict.fromkeys(["cpu", a.device])]
        print(f"feature extraction per frame, {seq.camera.width_px}x{seq.camera.height_px}, {len(seq.images)} frames:")
        print("\n".join(time_features(seq, configs)))
        return
    if a.loop_ablation:
        res = loop_ablation(seq, base)
        for mode, ms, loops, err in res:
            print(f"[loop {mode}] loops {loops}  correction ms {', '.join(f'{x:.0f}' for x in ms) or '-'}  "
                  f"revisit error after correction {err:.4f} (map units)")
        if all(r[1] for r in res):
            print(f"  RLC loop-correction time change vs full: {100 * (res[1][1][0] / res[0][1][0] - 1):+.0f} %")
        return
    blackout = tuple(int(x) for x in a.force_loss.split(":")) if a.force_loss else None
    if a.attitude_prior != "off" and not a.ablation:
        prior_main(seq, base, a)
        return
    runs = ablation_configs(base, with_ga=not a.no_ga) if a.ablation else [(f"{a.backend}", base)]
    results = []
    for name, cfg in runs:
        cfg = cfg.model_copy(update=dict(torch_device=a.device))
        r = run_sequence(seq, cfg, name, realtime=not a.no_realtime, blackout=blackout, drop_late=a.drop_late,
                         lockstep=a.lockstep)
        print(report(r), flush=True)
        results.append(r)
    if a.ablation:
        print("\nablation (vs baseline):")
        for r in results:
            print(f"  {r.name:9s} track mean {r.tracking_ms.mean():6.1f} ms  P99 {_p(r.tracking_ms, 99):6.1f} ms  "
                  f"local BA {np.mean(r.local_ba_ms or [np.nan]):6.0f} ms  loop {np.mean(r.loop_ms or [np.nan]):6.0f} ms  "
                  f"ATE {r.ate()[2]:.2f} %")
        plm, ga = results[-2], results[-3]
        print(f"  PLM local-BA solve time change: {100 * (np.mean(plm.local_ba_ms) / np.mean(ga.local_ba_ms) - 1):+.0f} %"
              f", ATE change {100 * (plm.ate()[0] / ga.ate()[0] - 1):+.0f} %")
        print(f"  PLM local-BA solve CPU time change (worker CPU, not slowed by other processes): "
              f"{100 * (np.mean(plm.local_ba_cpu_ms) / np.mean(ga.local_ba_cpu_ms) - 1):+.0f} %")
        w = base.local_window
        loc = [_local_window_ms(r, w) for r in (ga, plm)]
        print(f"  PLM on the local-window BAs only (the periodic BAs of up to {base.periodic_ba_window} keyframes "
              f"left out): {loc[0]:.0f} → {loc[1]:.0f} ms, {100 * (loc[1] / loc[0] - 1):+.0f} %")
        if results[-1].loop_ms and results[-2].loop_ms:
            print(f"  RLC loop-correction time change: {100 * (np.mean(results[-1].loop_ms) / np.mean(results[-2].loop_ms) - 1):+.0f} %")
        else:
            print("  RLC: no loop closed in this sequence (see --loop-ablation, or --scenario loop with enough frames)")


if __name__ == "__main__":
    main()
