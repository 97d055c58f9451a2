"""`terraslam sim ...` — synthetic datasets (issue 3)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from companion.cli import app, fail

sim_app = typer.Typer(help="Synthetic world, flights and GNSS: generate datasets.", no_args_is_help=True)
app.add_typer(sim_app, name="sim")


@sim_app.command("generate")
def generate(
    scenario: str = typer.Option("nominal", "--scenario", "-s", help="scenario name (see `terraslam sim list`)"),
    out: Path = typer.Option(..., "--out", "-o", help="output dataset directory (created)"),
    seed: int = typer.Option(0, "--seed", help="world / flight / noise seed"),
    frames: Optional[int] = typer.Option(None, "--frames", "-n", min=1, help="number of frames (default: whole flight)"),
    fps: Optional[float] = typer.Option(None, "--fps", min=1.0, max=60.0, help="camera frame rate (default: the scenario's)"),
    gnss_timeline: Optional[str] = typer.Option(None, "--gnss", help="scripted GNSS events, e.g. 'dropout@60-90,spoof_drift@120'"),
    stale: Optional[str] = typer.Option(None, "--stale", help="GIS model staleness preset: fresh | F-A | F-B (default: the scenario's)"),
    registration_error_m: Optional[float] = typer.Option(None, "--registration-error-m", min=0.0, max=50.0,
                                                         help="global geo-registration error of the GIS model (m)"),
    jpg: bool = typer.Option(False, "--jpg", help="write JPEG (q95) instead of lossless PNG"),
    force: bool = typer.Option(False, "--force", help="write into a non-empty directory"),
) -> None:
    """Render a named scenario and write it in the dataset layout (docs/DATASET.md)."""
    from dataclasses import replace

    from companion.dataset import write_dataset
    from companion.sim import SCENARIOS, make_scenario
    from companion.sim.gnss import parse_timeline
    from companion.sim.stale import STALE_PRESETS

    if scenario not in SCENARIOS:
        fail(f"unknown scenario {scenario!r}; choose one of: {', '.join(SCENARIOS)}")
    if out.exists() and any(out.iterdir()) and not force:
        fail(f"{out} exists and is not empty (use --force to write into it)")
    overrides = {}
    if gnss_timeline:
        try:
            overrides["gnss"] = replace(SCENARIOS[scenario].gnss, events=parse_timeline(gnss_timeline))
        except ValueError as e:
            fail(f"--gnss: {e}")
    if stale is not None:
        if stale not in STALE_PRESETS:
            fail(f"--stale: unknown preset {stale!r}; choose one of: {', '.join(STALE_PRESETS)}")
        overrides["stale"] = STALE_PRESETS[stale]
    if registration_error_m is not None:
        overrides["stale"] = replace(overrides.get("stale", SCENARIOS[scenario].stale), registration_error_m=registration_error_m)
    if fps is not None:
        overrides["fps"] = fps
    try:
        sc = make_scenario(scenario, seed=seed, n_frames=frames, **overrides)
    except ValueError as e:
        fail(str(e))
    write_dataset(sc, out, progress=True, image_ext=".jpg" if jpg else ".png")
    typer.echo(f"wrote {sc.n_frames} frames ({sc.duration_s:.1f} s) of scenario {scenario!r} to {out}")


@sim_app.command("list")
def list_scenarios() -> None:
    """List the named scenarios."""
    from rich.console import Console
    from rich.table import Table

    from companion.sim import SCENARIOS
    from companion.sim.flight import make_trajectory

    t = Table("scenario", "flight", "speed m/s", "alt m", "camera pitch °", "lighting", "GNSS", "GIS model")
    for name, s in SCENARIOS.items():
        f = s.flight
        ev = ",".join(f"{e.mode}@{e.start_s:g}" for e in s.gnss.events)
        stale = "stale" if s.stale.changed_frac or s.stale.n_new or s.stale.registration_error_m else "fresh"
        t.add_row(name, f"{f.kind} ({make_trajectory(f).duration_s:.0f} s)", f"{f.speed_mps:g}", f"{f.altitude_m:g}",
                  f"{s.camera_pitch_deg:g}", s.lighting, s.gnss.base + (f" + {ev}" if ev else ""), stale)
    Console().print(t)
