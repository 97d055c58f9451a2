"""Registration journal: each fine-tuning registration's inputs and outcome on disk, for replay.

A registration is a pure function of its inputs: the SLAM points, the prior alignment, the crop
centre, the barometric camera height and the model's georeference correction (gis.align.fine,
``FineTuner.register``). Written down, a flight's registrations can be replayed offline against
the same GIS model in seconds (``python -m gis.align.replay``) instead of re-flying the flight:
to ask where the ICP alone put the camera, how a change to the measurement model would have
decided, or what other optima lie about the prior. ``terraslam bench --journal`` writes one per
run, with the true camera positions (``truth.npz``) beside it.

Layout of a journal folder:

- ``meta.json``: the GIS model file and its sample spacing (to load the same model), the
  alignment configuration the registrations ran under, the site's origin;
- ``reg_<t_s>_<n>.npz``: one registration (``write_record``/``read_record``), plain arrays
  (no pickles: a journal from another version of this code still loads, or fails by name);
- ``truth.npz`` (optional, simulator/dataset runs): ``t_s`` (N,) and ``p_cam_ecef_m`` (N, 3),
  the true camera centre at each frame time.
"""
from __future__ import annotations

import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gis.align.georef import GeorefCorrection
from gis.sim3 import Sim3
from gis.types import Alignment, AlignmentSource

META = "meta.json"
TRUTH = "truth.npz"


@dataclass(frozen=True)
class RegistrationJob:
    """The inputs of one ``FineTuner.register`` call (argument for argument)."""

    t_s: float
    points_slam: np.ndarray          # (N, 3) SLAM frame
    initial: Alignment               # the prior
    center_slam: np.ndarray          # (3,) the camera, SLAM frame: the crop centre
    camera_h_ell_m: float | None = None    # barometric camera height, ellipsoidal metres
    camera_h_sigma_m: float | None = None  # ... its 1-σ
    correction: GeorefCorrection | None = None  # the model's georeference correction in force


@dataclass(frozen=True)
class JournalRecord:
    job: RegistrationJob
    alignment: Alignment | None  # what the flight's registration returned (None: refused)
    reason: str


def _alignment_arrays(prefix: str, a: Alignment | None) -> dict[str, np.ndarray]:
    if a is None:
        return {}
    T = a.T_ecef_slam  # scale, R and t as they are (a 4x4 matrix would round them on the way back)
    return {f"{prefix}T": np.r_[T.scale, np.ravel(T.R), T.t], f"{prefix}source": np.array(a.source.value),
            f"{prefix}info": np.asarray(a.information_6x6, float),
            f"{prefix}scalars": np.array([a.t_s, a.reset_counter, a.sigma_m, a.fitness, a.rmse_m, a.n_points, a.map_id,
                                          a.scale_sigma, a.drift_free_radius_m], float),
            f"{prefix}center": np.full(3, np.nan) if a.center_slam is None else np.asarray(a.center_slam, float)}


def _alignment_from(d, prefix: str) -> Alignment | None:
    if f"{prefix}T" not in d:
        return None
    s = [float(x) for x in d[f"{prefix}scalars"]]
    t_s, reset, sigma, fitness, rmse, n_points, map_id, scale_sigma = s[:8]
    drift_free_m = s[8] if len(s) > 8 else 0.0  # (journals written before the field: 8 scalars)
    center = d[f"{prefix}center"]
    T = d[f"{prefix}T"]
    return Alignment(Sim3(float(T[0]), T[1:10].reshape(3, 3).copy(), T[10:13].copy()), AlignmentSource(str(d[f"{prefix}source"])), t_s, int(reset),
                     np.array(d[f"{prefix}info"]), sigma, fitness, rmse, int(n_points), int(map_id),
                     None if np.isnan(center).any() else np.array(center), scale_sigma, drift_free_m)


def _opt(x: float | None) -> float:
    return math.nan if x is None else float(x)


def write_meta(folder: Path, model_file: Path | None, sample_spacing_m: float, alignment_config: dict,
               origin_lat_lon_h: tuple[float, float, float], footprint_ground: float | Path | None = None) -> None:
    """What a replay needs besides the records: the model file and how it was loaded
    (gis.loaders.load_model's arguments: a terrain model for footprints as its path), the
    alignment configuration, the site origin."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / META).write_text(json.dumps({
        "model_file": None if model_file is None else str(Path(model_file).resolve()),
        "sample_spacing_m": sample_spacing_m,
        "footprint_ground_h_msl_m": None if isinstance(footprint_ground, Path) else footprint_ground,
        "footprint_ground_dem": str(footprint_ground.resolve()) if isinstance(footprint_ground, Path) else None,
        "alignment": alignment_config, "origin_lat_lon_h": list(origin_lat_lon_h)}, indent=1))


def read_meta(folder: Path) -> dict:
    path = folder / META
    if not path.exists():
        raise FileNotFoundError(f"{folder}: not a registration journal (no {META})")
    return json.loads(path.read_text())


def write_record(folder: Path, seq: int, job: RegistrationJob, alignment: Alignment | None, reason: str) -> Path:
    """One registration as ``reg_<t_s>_<seq>.npz`` in ``folder`` (written to a temporary name and
    renamed, so a reader never sees half a record)."""
    c = job.correction
    arrays = dict(t_s=np.array(job.t_s), points=np.asarray(job.points_slam, float),
                  center=np.asarray(job.center_slam, float),
                  baro=np.array([_opt(job.camera_h_ell_m), _opt(job.camera_h_sigma_m)]), reason=np.array(reason),
                  **_alignment_arrays("initial_", job.initial), **_alignment_arrays("result_", alignment))
    if c is not None:
        arrays.update(correction_offset=np.asarray(c.offset_enu_m, float), correction_sigma_n=np.array([c.sigma_m, c.n]))
    path = folder / f"reg_{job.t_s:010.3f}_{seq:05d}.npz"
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **arrays)
    tmp.replace(path)
    return path


def read_record(path: Path) -> JournalRecord:
    try:
        with np.load(path, allow_pickle=False) as d:
            baro = d["baro"]
            corr = None
            if "correction_offset" in d:
                sigma, n = d["correction_sigma_n"]
                corr = GeorefCorrection(np.array(d["correction_offset"]), float(sigma), int(n))
            job = RegistrationJob(float(d["t_s"]), np.array(d["points"]), _alignment_from(d, "initial_"),
                                  np.array(d["center"]), None if np.isnan(baro[0]) else float(baro[0]),
                                  None if np.isnan(baro[1]) else float(baro[1]), corr)
            return JournalRecord(job, _alignment_from(d, "result_"), str(d["reason"]))
    except (KeyError, ValueError, TypeError, OSError) as e:
        raise ValueError(f"{path}: not a readable registration record ({type(e).__name__}: {e})") from e


def read_journal(folder: Path) -> list[JournalRecord]:
    """Every record in the folder, in flight-time order."""
    read_meta(folder)
    return [read_record(p) for p in sorted(folder.glob("reg_*.npz")) if not p.name.endswith(".tmp.npz")]


def write_truth(folder: Path, t_s: np.ndarray, p_cam_ecef_m: np.ndarray) -> None:
    np.savez(folder / TRUTH, t_s=np.asarray(t_s, float), p_cam_ecef_m=np.asarray(p_cam_ecef_m, float))


def read_truth(folder: Path) -> dict[float, np.ndarray] | None:
    """{t_s rounded to the millisecond: true camera ECEF}, or None without a truth file."""
    path = folder / TRUTH
    if not path.exists():
        return None
    with np.load(path, allow_pickle=False) as d:
        return {round(float(t), 3): np.array(p) for t, p in zip(d["t_s"], d["p_cam_ecef_m"])}


class Journal:
    """Writes each registration to ``folder`` as it is handed over (``FineTuneWorker.journal``)."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self._seq = itertools.count()

    def record(self, job: RegistrationJob, alignment: Alignment | None, reason: str) -> Path:
        return write_record(self.folder, next(self._seq), job, alignment, reason)
