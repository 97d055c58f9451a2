"""Rendered simulator sequences for the SLAM benchmark: render (or load from the cache) frames of a
scenario with their truth and the simulated autopilot's attitude, and save / load them as one .npz
that replays without the simulator (on a companion board or a GPU machine)."""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from slam.types import AttitudePrior, CameraModel


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
    from companion.pipeline import attitude_prior, with_gravity  # lazily: load_sequence needs no GIS stack

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

    from companion.sim import make_scenario  # lazily: load_sequence needs no simulator (open3d)

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

def start_frame(scenario: str, seed: int, fps: float | None, start_s: str, n_frames: int) -> int:
    """First frame of a run of n_frames: ``start_s`` seconds of flight, or 'turn': the start of
    the pipeline benchmark's window (companion.bench_run.bench_window_s: 10 s before the first turn)."""
    from companion.sim import make_scenario

    sc = make_scenario(scenario, seed=seed, **({"fps": fps} if fps else {}))
    if start_s == "turn":
        from companion.bench_run import bench_window_s

        t = bench_window_s(sc, n_frames)[0]
    else:
        t = float(start_s)
    return int(round(t * sc.fps))


