"""Replay a registration journal (gis.align.journal) against its GIS model, offline.

    python -m gis.align.replay out/bench/registrations [--after T] [--chain] [--scan] [--set key=value ...]

Each recorded registration runs again through ``FineTuner.register`` with its recorded inputs
(prior, points, crop centre, barometer, georeference correction) and, by default, the recorded
alignment configuration; ``--set`` changes a setting of it (``--set slam_drift_fraction=0.06``),
so a change to the measurement model is judged on a flight's real registrations in seconds; each
line also gives the registration's CPU time (thread time, with the GIS crops cached as in flight
order), and the last line their mean, for the cost of a change to the registration.
With the journal's ``truth.npz`` each line says how far from the true camera (horizontally) the
prior, the ICP alone and the fused result were, against what they claimed. ``--chain`` starts each
registration from the one the replay accepted before it, as in a GNSS denial, so a changed setting
carries through (``--after`` the loss's time, to begin at the denial). ``--scan`` also starts
the ICP from 24 points 3/6/9 m about the prior (``FineTuner.optima``) and says how many distinct
optima those starts reach, how far apart, and how far the best-fitting one is from the truth;
with the truth, also where the ICP settles when started *at* the true camera position (the prior
moved there): the registration's own accuracy floor on that flight's SLAM points, whatever the prior.
"""
from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from gis.align.fine import FineTuner
from gis.align.journal import JournalRecord, read_journal, read_meta, read_truth
from gis.config import AlignmentConfig
from gis.geodesy import R_ecef_enu, ecef_to_geodetic
from gis.model import GisModel
from gis.sim3 import Sim3, compose
from gis.types import Alignment

CLUSTER_M = 1.0  # optima closer than this are one


@dataclass(frozen=True)
class Scan:
    n_starts: int
    n_optima: int          # distinct optima (CLUSTER_M apart)
    rms_m: float           # horizontal RMS of the converged camera positions about their mean
    best_err_h_m: float    # the best-fitting optimum's horizontal distance from the truth (nan without truth)
    from_truth_err_h_m: float = math.nan  # the ICP started at the true camera: where it settles, from the truth


@dataclass(frozen=True)
class Replayed:
    """One recorded registration run again. Errors are horizontal distances of the camera from the
    truth (nan without truth); sigmas what the registration claimed."""

    t_s: float
    reason: str
    as_in_flight: bool          # accepted/refused as in flight, and the same alignment (1e-6 relative)
    prior_err_h_m: float
    icp_err_h_m: float
    icp_sigma_h_m: float
    fused_err_h_m: float
    sigma_m: float
    fitness: float
    spread_m: float
    nis: float
    cpu_ms: float               # the registration's thread CPU time in this replay (crop cache as in flight order)
    scan: Scan | None = None


def _h_err(p_ecef: np.ndarray | None, truth: np.ndarray | None) -> float:
    if p_ecef is None or truth is None:
        return math.nan
    lat, lon, _ = ecef_to_geodetic(truth)
    return float(np.hypot(*(R_ecef_enu(float(lat), float(lon)).T @ (np.asarray(p_ecef) - truth))[:2]))


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return bool(np.allclose(a.T_ecef_slam.matrix(), b.T_ecef_slam.matrix(), rtol=1e-6, atol=1e-6))


def _scan(tuner: FineTuner, points_slam: np.ndarray, prior: Alignment, center_slam: np.ndarray,
          truth: np.ndarray | None) -> Scan:
    found = tuner.optima(points_slam, prior, center_slam)
    p = np.array([x[0] for x in found])
    lat, lon, _ = ecef_to_geodetic(p[0])
    en = (p - p[0]) @ R_ecef_enu(float(lat), float(lon))[:, :2]  # horizontal offsets from the prior's optimum
    reps: list[np.ndarray] = []
    for q in en:
        if not any(np.linalg.norm(q - r) < CLUSTER_M for r in reps):
            reps.append(q)
    best = int(np.argmax([x[1] for x in found]))
    floor = math.nan
    if truth is not None:  # the prior moved (translation only) so that it puts the camera at the truth
        camera = prior.T_ecef_slam.apply(np.asarray(center_slam, float)[None])[0]
        at_truth = replace(prior, T_ecef_slam=compose(Sim3(1.0, np.eye(3), np.asarray(truth) - camera), prior.T_ecef_slam))
        floor = _h_err(tuner.optima(points_slam, at_truth, center_slam, radii_m=())[0][0], truth)
    return Scan(len(found), len(reps), float(np.sqrt(((en - en.mean(axis=0)) ** 2).sum(axis=1).mean())),
                _h_err(p[best], truth), floor)


def replay(records: list[JournalRecord], model: GisModel, config: AlignmentConfig,
           truth: dict[float, np.ndarray] | None = None, scan: bool = False, chain: bool = False) -> list[Replayed]:
    """Each record's registration again. chain: from the second record on, the prior is the last
    alignment this replay accepted (as in a GNSS denial, where each registration starts from the
    one before), not the recorded one, so a changed setting carries through the chain."""
    tuner = FineTuner(model, config)
    out = []
    last: Alignment | None = None
    for rec in records:
        job = rec.job
        prior = last if chain and last is not None else job.initial
        tuner.set_correction(job.correction)
        cpu0 = time.thread_time()
        reg = tuner.register(job.points_slam, prior, job.t_s, prior.reset_counter, job.center_slam,
                             prior.map_id, job.camera_h_ell_m, job.camera_h_sigma_m)
        cpu_ms = 1e3 * (time.thread_time() - cpu0)
        last = reg.alignment or last
        tr = None if truth is None else truth.get(round(job.t_s, 3))
        camera = np.asarray(job.center_slam, float)[None]
        a = reg.alignment
        icp_sigma = math.sqrt(np.trace(reg.icp.cov_enu_m2[:2, :2]) / 2) if reg.icp is not None else math.nan
        out.append(Replayed(
            job.t_s, reg.reason, _same(a, rec.alignment), _h_err(prior.T_ecef_slam.apply(camera)[0], tr),
            _h_err(None if reg.icp is None else reg.icp.p_ecef_m, tr), icp_sigma,
            _h_err(None if a is None else a.T_ecef_slam.apply(camera)[0], tr), reg.sigma_m if a is not None else math.nan,
            reg.fitness, reg.spread_m, reg.nis, cpu_ms, _scan(tuner, job.points_slam, prior, job.center_slam, tr) if scan else None))
    return out


def format_rows(rows: list[Replayed]) -> str:
    lines = ["t [s]   prior err | ICP alone err (σ) | fused err (σ)  | fitness spread  NIS |   CPU   | flight | outcome"]
    for r in rows:
        line = (f"{r.t_s:7.1f} {r.prior_err_h_m:6.2f} m | {r.icp_err_h_m:6.2f} m ({r.icp_sigma_h_m:4.2f}) | "
                f"{r.fused_err_h_m:6.2f} m ({r.sigma_m:4.2f}) | {r.fitness:5.2f} {r.spread_m:5.1f} {r.nis:5.1f} | "
                f"{r.cpu_ms:4.0f} ms | {'same' if r.as_in_flight else 'DIFF'}   | {r.reason[:70]}")
        if r.scan is not None:
            s = r.scan
            line += (f"\n        scan: {s.n_starts} starts reach {s.n_optima} optima, RMS {s.rms_m:.2f} m about their mean; "
                     f"best-fitting one {s.best_err_h_m:.2f} m from the truth; "
                     f"started at the truth it settles {s.from_truth_err_h_m:.2f} m from it")
        lines.append(line)
    ok = [r for r in rows if math.isfinite(r.fused_err_h_m)]
    if ok and all(math.isfinite(r.sigma_m) for r in ok):
        beyond = sum(r.fused_err_h_m > 3 * r.sigma_m for r in ok)
        lines.append(f"{len(ok)} of {len(rows)} accepted; fused horizontal error mean {np.mean([r.fused_err_h_m for r in ok]):.2f} m, "
                     f"{beyond} beyond 3σ; {sum(not r.as_in_flight for r in rows)} decided differently from the flight")
    if rows:
        lines.append(f"registration CPU (thread time) mean {np.mean([r.cpu_ms for r in rows]):.1f} ms, "
                     f"max {max(r.cpu_ms for r in rows):.1f} ms over {len(rows)}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("journal", type=Path)
    ap.add_argument("--after", type=float, default=-math.inf, help="only registrations at or after this flight time (s)")
    ap.add_argument("--scan", action="store_true", help="also the optima reached from 24 starts about the prior")
    ap.add_argument("--chain", action="store_true",
                    help="each registration from the one this replay accepted before it (a denial's chain), not its recorded prior")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="alignment setting to change (repeatable)")
    a = ap.parse_args(argv)
    try:
        _run(a)
    except (ValueError, FileNotFoundError) as e:  # unreadable journal or model: say which and why
        raise SystemExit(f"replay: {e}") from e


def _run(a: argparse.Namespace) -> None:
    from gis.loaders import load_model

    meta = read_meta(a.journal)
    over = {}
    for kv in a.set:
        key, sep, value = kv.partition("=")
        if not sep or key not in AlignmentConfig.model_fields:
            raise SystemExit(f"--set {kv!r}: not KEY=VALUE with KEY one of the alignment settings")
        over[key] = value
    config = AlignmentConfig.model_validate({**meta["alignment"], **over})
    if meta.get("model_file") is None:
        raise SystemExit(f"{a.journal}: the journal names no GIS model file")
    dem = meta.get("footprint_ground_dem")
    model = load_model(meta["model_file"], meta["sample_spacing_m"], Path(dem) if dem else meta.get("footprint_ground_h_msl_m"))
    records = [r for r in read_journal(a.journal) if r.job.t_s >= a.after]
    print(format_rows(replay(records, model, config, read_truth(a.journal), scan=a.scan, chain=a.chain)))


if __name__ == "__main__":
    main()
