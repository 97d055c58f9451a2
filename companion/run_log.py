"""What a run produced (RunLog: records, truth, GNSS, events, timings) and what is made of it: the
accuracy, availability and latency figures (summarize) and the output files and plots
(write_outputs). companion.app's demo and replay and the benchmark (companion.bench_run) fill it."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from companion.evaluate import (
    FixErrors,
    fix_errors,
    stats,
    velocity_errors,
    write_csv,
    write_geojson,
    write_report,
    write_tum,
)
from companion.pipeline import FrameRecord
from gis.align.fine import ScaleCheck

if TYPE_CHECKING:
    from companion.app import GnssDenial


@dataclass
class RunLog:
    """Everything a run produced, for evaluation and plots (records in frame order)."""

    records: list[FrameRecord] = field(default_factory=list)
    truth_ecef_m: dict[int, np.ndarray] = field(default_factory=dict)     # seq → body-origin ECEF truth (what a fix reports)
    truth_cam_ecef_m: dict[int, np.ndarray] = field(default_factory=dict)  # seq → camera-centre ECEF truth (SLAM's ATE)
    gnss_ecef_m: list[tuple[float, np.ndarray, bool]] = field(default_factory=list)  # (t, ECEF, had fix)
    wall_track_ms: list[float] = field(default_factory=list)
    camera_to_wire_ms: list[float] = field(default_factory=list)
    switch_events: list[tuple[float, str]] = field(default_factory=list)
    alignment_events: list[tuple[float, str]] = field(default_factory=list)
    autopilot_err_m: list[tuple[float, float, str]] = field(default_factory=list)  # (t, horiz. error, source)
    finetune_ms: list[float] = field(default_factory=list)      # wall time of each registration
    finetune_cpu_ms: list[float] = field(default_factory=list)  # CPU time the worker used for it
    scale_checks: list[ScaleCheck] = field(default_factory=list)  # the barometer's checks between registrations
    takeover_t_s: float | None = None
    denial: "GnssDenial | None" = None  # replay: GNSS withheld from the pipeline over this span
    reference: dict[int, tuple[np.ndarray, float]] = field(default_factory=dict)  # seq → withheld GNSS (ECEF, h_acc 1-σ)


def reference_errors(run: RunLog) -> FixErrors:
    """Errors of the fixes a replay sent while GNSS was withheld, against the withheld GNSS."""
    fixes = [r.fix for r in run.records if r.fix is not None and r.seq in run.reference]
    return fix_errors(fixes, np.array([run.reference[f.seq][0] for f in fixes]).reshape(-1, 3),
                      np.array([run.reference[f.seq][1] for f in fixes]))


def summarize(run: RunLog, *, name: str) -> dict:
    """Accuracy, availability and latency figures of a run (JSON-ready)."""
    fixes = [r.fix for r in run.records if r.fix is not None and r.seq in run.truth_ecef_m]
    errs = fix_errors(fixes, np.array([run.truth_ecef_m[f.seq] for f in fixes]).reshape(-1, 3))
    after = [f for f in fixes if run.takeover_t_s is not None and f.t_s >= run.takeover_t_s]
    errs_after = fix_errors(after, np.array([run.truth_ecef_m[f.seq] for f in after]).reshape(-1, 3))
    n = len(run.records)
    frames_after = [r for r in run.records if run.takeover_t_s is not None and r.t_s >= run.takeover_t_s]
    denial = {}
    if run.denial is not None:
        in_denial = [r for r in run.records if r.t_s >= run.denial.start_t_s and r.t_s < run.denial.end_t_s]
        denial = {
            "gnss_denial": {"from_s": run.denial.from_s,
                            "until_s": run.denial.until_s if math.isfinite(run.denial.until_s) else None,
                            "frames": len(in_denial),
                            "fix_ratio": float(np.mean([r.fix is not None for r in in_denial])) if in_denial else None},
            "against_withheld_gnss": reference_errors(run).summary(),
        }
    return {
        "name": name,
        "frames": n,
        "frames_with_truth": len(run.truth_ecef_m),
        "tracking_ratio": float(np.mean([r.pose.state.has_pose for r in run.records])) if n else None,
        "fix_ratio_all": float(np.mean([r.fix is not None for r in run.records])) if n else None,
        "fix_ratio_after_takeover": float(np.mean([r.fix is not None for r in frames_after])) if frames_after else None,
        "takeover_t_s": run.takeover_t_s,
        "all_fixes": errs.summary(),
        "after_takeover": errs_after.summary(),
        "velocity_after_takeover": velocity_errors(after, *_truth_track(run)),
        "frame_latency_ms": stats(np.array(run.wall_track_ms)),
        "camera_to_wire_ms": stats(np.array(run.camera_to_wire_ms)),
        "finetune_ms": stats(np.array(run.finetune_ms)),
        "finetune_cpu_ms": stats(np.array(run.finetune_cpu_ms)),
        "barometer_scale_checks": _ratio_summary(run.scale_checks),
        "autopilot_horizontal_error_m_after_takeover": stats(np.array([e for t, e, _ in run.autopilot_err_m
                                                                        if run.takeover_t_s is not None and t >= run.takeover_t_s + 1.0])),
        "tracking_events": tracking_events(run.records),
        "switch_events": run.switch_events,
        "alignment_events": run.alignment_events,
        **denial,
    }


def _truth_track(run: RunLog) -> tuple[np.ndarray, np.ndarray]:
    """The truth positions (ECEF) at the frames' times, in time order."""
    pairs = sorted((r.t_s, run.truth_ecef_m[r.seq]) for r in run.records if r.seq in run.truth_ecef_m)
    return np.array([t for t, _ in pairs]), np.array([p for _, p in pairs]).reshape(-1, 3)


def _ratio_summary(checks: list[ScaleCheck]) -> dict:
    """The barometer's scale checks between registrations: how many ran, how many withheld fixes,
    and the spread of the tested ratios (1 = the map under the camera at the alignment's scale)."""
    k = np.array([c.ratio for c in checks if np.isfinite(c.ratio)])
    return {"n": len(checks), "tested": int(k.size), "mismatches": sum(c.mismatch for c in checks),
            "ratio_min": float(k.min()) if k.size else None, "ratio_p50": float(np.median(k)) if k.size else None,
            "ratio_max": float(k.max()) if k.size else None}


def tracking_events(records: list[FrameRecord]) -> list[tuple[float, str]]:
    """SLAM state / map changes over the run: (t_s, text) at each transition."""
    out, prev = [], None
    for r in records:
        key = (r.pose.state.value, r.pose.map_id, r.pose.reset_counter)
        if key != prev:
            out.append((r.t_s, f"SLAM {key[0]} (map {key[1]}, reset {key[2]})"))
            prev = key
    return out


def write_outputs(run: RunLog, summary: dict, out_dir: Path, origin, title: str) -> list[Path]:
    """Trajectory files, report and PNG plots into out_dir."""
    from companion import viz

    out_dir.mkdir(parents=True, exist_ok=True)
    fixes = [r.fix for r in run.records if r.fix is not None]
    write_csv(fixes, out_dir / "trajectory.csv")
    write_tum(fixes, origin, out_dir / "trajectory.tum")
    write_geojson(fixes, out_dir / "trajectory.geojson", {"run": title})
    write_report(summary, out_dir / "report.json", out_dir / "report.md", title=title)
    written = [out_dir / n for n in ("trajectory.csv", "trajectory.tum", "trajectory.geojson", "report.json", "report.md")]
    if fixes and (run.truth_ecef_m or run.reference):
        # judged against the truth where there is one, else against the GNSS a replay withheld
        tracks = {}
        if run.truth_ecef_m:
            seqs = sorted(run.truth_ecef_m)
            tracks["truth"] = origin.ecef_to_enu(np.stack([run.truth_ecef_m[s] for s in seqs]))[:, :2]
        tracks["ours"] = origin.ecef_to_enu(np.stack([f.p_ecef_m for f in fixes]))[:, :2]
        if any(ok for *_, ok in run.gnss_ecef_m):
            tracks["GNSS"] = origin.ecef_to_enu(np.stack([p for _, p, ok in run.gnss_ecef_m if ok]))[:, :2]
        viz.plot_track(out_dir / "track.png", tracks)
        if run.truth_ecef_m:
            with_truth = [f for f in fixes if f.seq in run.truth_ecef_m]
            e, against = fix_errors(with_truth, np.stack([run.truth_ecef_m[f.seq] for f in with_truth])), ""
        else:
            e, against = reference_errors(run), " vs withheld GNSS"
        events = run.switch_events + [(t, s) for t, s in run.alignment_events if "accepted (initial" not in s][:12]
        series = {f"ours (horizontal{against})": (e.t_s, e.err_h_m), "ours 3σ (3 × h_acc)": (e.t_s, 3 * e.h_acc_m)}
        if run.autopilot_err_m:
            series["autopilot EKF (horizontal)"] = (np.array([t for t, _, _ in run.autopilot_err_m]),
                                                    np.array([x for _, x, _ in run.autopilot_err_m]))
        viz.plot_error_over_time(out_dir / "error_over_time.png", series, events=events)
        viz.plot_error_cdf(out_dir / "error_cdf.png", {f"ours (3D{against})": e.err_3d_m, f"ours (horizontal{against})": e.err_h_m})
        written += [out_dir / "track.png", out_dir / "error_over_time.png", out_dir / "error_cdf.png"]
    if run.wall_track_ms:
        viz.plot_latency_hist(out_dir / "latency.png", {"tracking (ms)": np.array(run.wall_track_ms)})
        written.append(out_dir / "latency.png")
    return written
