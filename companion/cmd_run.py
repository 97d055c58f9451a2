"""`terraslam run|demo|replay` — the service, the built-in demo, offline replay (issue 7)."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

from companion.cli import app, fail


def _load(config: Optional[Path]):
    from companion.config import ConfigError, load_config

    try:
        return load_config(config)
    except ConfigError as e:
        fail(str(e))


def _progress_bar(description: str):
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[state]}"),
                    TimeElapsedColumn(), TimeRemainingColumn(), transient=False)


def _print_summary(summary: dict, out: Path) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console()
    t = Table(title=summary["name"], show_header=True)
    t.add_column("figure")
    t.add_column("value", justify="right")

    def fmt(x, unit=""):
        return "n/a" if x is None else f"{x:.3f}{unit}" if isinstance(x, float) else f"{x}{unit}"

    t.add_row("frames", fmt(summary["frames"]))
    t.add_row("tracking ratio", fmt(summary["tracking_ratio"]))
    t.add_row("GNSS lost → we took over at", fmt(summary["takeover_t_s"], " s"))
    t.add_row("fix ratio after takeover", fmt(summary["fix_ratio_after_takeover"]))
    with_truth = (("all fixes", "all_fixes"), ("after takeover", "after_takeover")) if summary.get("frames_with_truth", 1) else ()
    if not with_truth:
        t.add_row("errors against the truth", "none: the dataset has no truth.csv")
    for label, key in with_truth:
        ge = summary[key]["global_error_m"]
        t.add_row(f"3D error, {label} (mean / P99)", f"{fmt(ge['mean'])} / {fmt(ge['p99'])} m  (n={summary[key]['n']})")
        he = summary[key]["horizontal_error_m"]
        t.add_row(f"horizontal error, {label} (mean / P99)", f"{fmt(he['mean'])} / {fmt(he['p99'])} m")
        t.add_row(f"integrity violations, {label}", fmt(summary[key]["integrity_violation_ratio"]))
    ref = summary.get("against_withheld_gnss")
    if ref is not None:
        den = summary["gnss_denial"]
        t.add_row("simulated GNSS denial (s after the first frame)",
                  f"{fmt(den['from_s'])} – {'end' if den['until_s'] is None else fmt(den['until_s'])}, fix ratio {fmt(den['fix_ratio'])}")
        ge, he = ref["global_error_m"], ref["horizontal_error_m"]
        t.add_row("3D error vs withheld GNSS (mean / P99)", f"{fmt(ge['mean'])} / {fmt(ge['p99'])} m  (n={ref['n']})")
        t.add_row("horizontal error vs withheld GNSS (mean / P99)", f"{fmt(he['mean'])} / {fmt(he['p99'])} m")
        if ref["n"]:
            t.add_row("  the receiver's own h_acc there (median)", fmt(ref["reference_h_acc_m"]["p50"], " m"))
        t.add_row("integrity violations vs withheld GNSS (3 × both σ)", fmt(ref["integrity_violation_ratio"]))
    ap = summary.get("autopilot_horizontal_error_m_after_takeover")
    if ap and ap["mean"] is not None:
        t.add_row("autopilot EKF horizontal error after takeover (mean / P99)", f"{fmt(ap['mean'])} / {fmt(ap['p99'])} m")
    lat = summary["frame_latency_ms"]
    t.add_row("per-frame pipeline latency (mean / P99)", f"{fmt(lat['mean'])} / {fmt(lat['p99'])} ms")
    pace = summary.get("pace")
    if pace is not None:
        note = {"realtime": "frames fed at the camera's rate",
                "repeatable": "mapping and fine-tuning waited for at every frame",
                "unpaced": "as fast as possible" + ("; local mapping and fine-tuning get less time per frame than "
                                                     "in flight (--realtime feeds the camera's rate)" if pace["speed_x"] > 1.2 else "")}[pace["mode"]]
        t.add_row("replay pace (recorded span / wall time)", f"{fmt(pace['speed_x'])}× real time: {note}")
    rt = summary.get("realtime")
    if rt is not None:
        t.add_row("real time: frames more than one interval late", f"{rt['late_frames']} of {rt['frames']} "
                  f"(late by {fmt(rt['late_ms_mean'])} ms mean, {fmt(rt['late_ms_max'])} ms at most)")
    ft = summary["finetune_ms"]
    t.add_row("GIS fine-tune wall time (mean / P99)", f"{fmt(ft['mean'])} / {fmt(ft['p99'])} ms")
    fc = summary["finetune_cpu_ms"]
    t.add_row("GIS fine-tune worker CPU time (mean / P99)", f"{fmt(fc['mean'])} / {fmt(fc['p99'])} ms")
    events = [text for _, text in summary.get("alignment_events", ())]
    accepted = sum("alignment fine accepted" in e for e in events)
    t.add_row("GIS fine alignments accepted / tried", f"{accepted} / {accepted + sum('fine-tuning rejected' in e for e in events)}")
    console.print(t)
    if summary.get("switch_events"):
        console.print("[bold]Switch timeline[/bold]")
        for ts, text in summary["switch_events"]:
            console.print(f"  t={ts:7.2f} s  {text}")
    if summary.get("tracking_events"):
        console.print("[bold]SLAM timeline[/bold] (first 12)")
        for ts, text in summary["tracking_events"][:12]:
            console.print(f"  t={ts:7.2f} s  {text}")
    if summary.get("alignment_events"):
        console.print("[bold]Alignment timeline[/bold] (first 12)")
        for ts, text in summary["alignment_events"][:12]:
            console.print(f"  t={ts:7.2f} s  {text}")
    console.print(f"Outputs in {out}/ (report.md, report.json, trajectory.csv/.tum/.geojson, PNG plots)")


@app.command("demo")
def demo(
    out: Path = typer.Option(Path("out/demo"), "--out", "-o", help="output folder for report, trajectory and plots"),
    frames: int = typer.Option(800, "--frames", min=60, help="camera frames to simulate (10 fps)"),
    autopilot: str = typer.Option("ardupilot", "--autopilot", help="simulated autopilot personality: ardupilot | px4"),
    seed: int = typer.Option(0, "--seed"),
    loss_at: float = typer.Option(40.0, "--gnss-loss-at", help="flight time (s) at which GNSS is lost"),
    gnss: Optional[str] = typer.Option(None, "--gnss", help="GNSS event timeline instead of the loss, MODE@START[-END],...: "
                                       "dropout, jamming, spoof_drift (0.5 m/s walk-off), spoof_jump (40 m), dgps, standalone; e.g. 'spoof_drift@40'"),
    receiver: str = typer.Option("dgps", "--receiver", help="simulated GNSS receiver grade before the loss: dgps (SBAS/DGPS, ~0.8 m 1-σ) | standalone (~4 m) | urban"),
    repeatable: bool = typer.Option(False, "--repeatable", help="local mapping and fine-tuning keep step with the flight clock: the same flight gives the same fixes to the bit (as `bench --repeatable`)"),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
) -> None:
    """Built-in simulated flight: GNSS lost mid-flight, our fixes take over; prints accuracy and the switch timeline."""
    from companion.app import DemoOptions, run_demo

    if autopilot not in ("ardupilot", "px4"):
        fail(f"--autopilot must be ardupilot or px4, got {autopilot!r}")
    if receiver not in ("dgps", "standalone", "urban"):
        fail(f"--receiver must be dgps, standalone or urban, got {receiver!r}")
    cfg = _load(config)
    if gnss is not None:
        from companion.sim.gnss import parse_timeline

        try:
            parse_timeline(gnss)
        except ValueError as e:
            fail(str(e))
    opts = DemoOptions(seed=seed, n_frames=frames, gnss_loss_at_s=loss_at, autopilot=autopilot, gnss_timeline=gnss,
                       receiver=receiver, repeatable=repeatable)
    with _progress_bar("demo") as bar:
        task = bar.add_task("simulated flight", total=frames, state="")

        def progress(k, n, state):
            bar.update(task, completed=k, state=state)

        summary = run_demo(cfg, out, opts, progress=progress)
    _print_summary(summary, out)


@app.command("replay")
def replay(
    dataset: Path = typer.Argument(..., help="dataset folder (docs/DATASET.md)"),
    out: Path = typer.Option(..., "--out", "-o", help="output folder"),
    frames: Optional[int] = typer.Option(None, "--frames", min=1, help="replay only the first N frames"),
    repeatable: bool = typer.Option(False, "--repeatable", help="local mapping and fine-tuning keep step with the recorded clock: the same replay gives the same fixes to the bit (as `bench --repeatable`)"),
    deny_from: Optional[float] = typer.Option(None, "--deny-gnss-from", help="simulated GNSS denial: from this many seconds after the first frame, GNSS reaches the pipeline as 'no fix'; the fixes sent meanwhile are judged against the withheld GNSS (a recorded flight's yardstick)"),
    deny_until: Optional[float] = typer.Option(None, "--deny-gnss-until", help="end of the simulated denial, seconds after the first frame (default: to the end)"),
    gis_model: Optional[Path] = typer.Option(None, "--gis-model", help="GIS model file to use instead of those site.yaml names (a recording copied off the drone)"),
    realtime: bool = typer.Option(False, "--realtime", help="feed the frames at their recorded rate, as the camera would (mapping and fine-tuning get the idle time they get in flight); reports the frames that came late. Not with --repeatable"),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
) -> None:
    """Replay a dataset offline; writes trajectory CSV/TUM/GeoJSON and a report (errors when truth
    exists, and against the withheld GNSS under --deny-gnss-from)."""
    from companion.app import GnssDenial, run_replay
    from companion.dataset import DatasetError

    if deny_until is not None and deny_from is None:
        fail("--deny-gnss-until needs --deny-gnss-from")
    try:
        deny = None if deny_from is None else GnssDenial(deny_from, math.inf if deny_until is None else deny_until)
    except ValueError as e:
        fail(str(e))
    cfg = _load(config)
    try:
        with _progress_bar("replay") as bar:
            task = bar.add_task(str(dataset), total=frames or 0, state="")

            def progress(k, n, state):
                bar.update(task, completed=k, total=n)

            summary = run_replay(cfg, dataset, out, frames, progress=progress, repeatable=repeatable, deny=deny,
                                 gis_model=gis_model, realtime=realtime)
    except (DatasetError, ValueError, FileNotFoundError) as e:
        fail(str(e))
    _print_summary(summary, out)


@app.command("run")
def run(config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML config (default: config/default.yaml)")) -> None:
    """Run the companion service (camera → SLAM → GIS alignment → MAVLink), supervised, systemd-aware."""
    from companion.service import run_service

    cfg = _load(config)
    raise typer.Exit(run_service(cfg))
