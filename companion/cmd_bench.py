"""`terraslam bench` — TerraSLAM's evaluation figures on our own system (issue 8, docs/BENCHMARKS.md)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from companion.cli import app, fail


@app.command("bench")
def bench(
    scenario: Optional[str] = typer.Option(None, "--scenario", "-s", help="simulator scenario (nominal, stale, dark, bright, fast, loop, ...)"),
    dataset: Optional[Path] = typer.Option(None, "--dataset", help="dataset folder with truth (docs/DATASET.md) instead of a scenario"),
    suite: bool = typer.Option(False, "--suite", help="all of nominal, stale, dark, bright, fast, loop + one comparison table"),
    frames: int = typer.Option(300, "--frames", min=30, help="camera frames per run: from 10 s before the first turn, GNSS lost after 70 % of them"),
    fps: float = typer.Option(10.0, "--fps", min=1.0, max=60.0, help="simulated camera rate"),
    out: Path = typer.Option(Path("out/bench"), "--out", "-o", help="output folder (bench.json, bench.md, PNG plots)"),
    ablation: bool = typer.Option(False, "--ablation", help="also run baseline / +GA / +PLM / +RLC (TerraSLAM Fig. 14)"),
    sweep: Optional[str] = typer.Option(None, "--sweep", help="map-size sweep of fine-tuning cost: box-city extents in m, e.g. 1000,10000"),
    seed: int = typer.Option(0, "--seed"),
    seeds: Optional[str] = typer.Option(None, "--seeds", help="with --suite: run it once per seed (e.g. 0,1,2,3) into OUT/seed_N/ and print the error after the loss per seed, mean and median (one run is not reproducible to better than ~0.5 m)"),
    receiver: Optional[str] = typer.Option(None, "--receiver", help="simulated GNSS receiver grade before the loss: standalone (~4 m 1-σ) | dgps (SBAS/DGPS, ~0.8 m) | urban; default: the scenario's (standalone)"),
    repeatable: bool = typer.Option(False, "--repeatable", help="local mapping and fine-tuning keep step with the flight clock (each keyframe mapped before the next frame, registrations adopted 0.3 s of flight time after submission): the same run gives the same fixes to the bit, for A/B comparisons; optimistic about mapping latency, so free-running (the default) is what a live system sees"),
    journal: bool = typer.Option(False, "--journal", help="write every registration's inputs and outcome, and the true camera track, to OUT/registrations/ for offline replay: python -m gis.align.replay OUT/registrations"),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
) -> None:
    """Run the real pipeline over a scenario / dataset / the suite and write bench.json, bench.md and plots."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from companion.bench import bench_one, bench_suite
    from companion.bench_report import markdown_summary, seeds_table, suite_table
    from companion.config import ConfigError, load_config
    from companion.sim.scenario import SCENARIOS

    if sum(x is not None and x is not False for x in (scenario, dataset, suite or None)) != 1:
        fail("give exactly one of --scenario NAME, --dataset DIR or --suite")
    if scenario is not None and scenario not in SCENARIOS:
        fail(f"--scenario: unknown scenario {scenario!r}; choose one of {', '.join(SCENARIOS)}")
    if receiver is not None and receiver not in ("standalone", "dgps", "urban"):
        fail(f"--receiver must be standalone, dgps or urban, got {receiver!r}")
    if dataset is not None and not dataset.is_dir():
        fail(f"--dataset: {dataset} is not a folder")
    try:
        seed_list = tuple(int(x) for x in seeds.split(",")) if seeds else ()
    except ValueError:
        fail(f"--seeds: expected comma-separated integers, got {seeds!r}")
    if seed_list and not suite:
        fail("--seeds goes with --suite")
    if journal and suite:
        fail("--journal goes with one --scenario or --dataset, not --suite")
    try:
        extents = tuple(float(x) for x in sweep.split(",")) if sweep else ()
    except ValueError:
        fail(f"--sweep: expected comma-separated extents in metres, got {sweep!r}")
    if any(e < 500.0 for e in extents):  # gis.bench.finetune_timing crops 200 m inside the model's edges
        fail(f"--sweep: every extent must be at least 500 m, got {sweep!r}")
    try:
        cfg = load_config(config)
    except ConfigError as e:
        fail(str(e))
    console = Console()
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[state]}"),
                  TimeElapsedColumn(), console=console) as bar:
        tasks: dict[str, int] = {}

        def progress(label, k, n, state):
            if label not in tasks:
                tasks[label] = bar.add_task(label, total=n, state="")
            bar.update(tasks[label], completed=k, total=n, state=state)

        try:
            if seed_list:
                by_seed = {s: bench_suite(cfg, out / f"seed_{s}", n_frames=frames, seed=s, fps=fps, ablation=ablation,
                                          progress=progress, receiver=receiver, repeatable=repeatable) for s in seed_list}
            elif suite:
                figs = bench_suite(cfg, out, n_frames=frames, seed=seed, fps=fps, ablation=ablation, progress=progress,
                                   receiver=receiver, repeatable=repeatable)
            else:
                fig, _ = bench_one(cfg, out, scenario=scenario, dataset=dataset, n_frames=frames, seed=seed, fps=fps,
                                   ablation=ablation, sweep_extents_m=extents, progress=progress, receiver=receiver,
                                   repeatable=repeatable, journal=journal)
        except (ValueError, FileNotFoundError) as e:
            fail(str(e))
    if seed_list:  # plain: Markdown tables must not wrap
        table = seeds_table(by_seed)
        (out / "seeds.md").write_text("# Benchmark suite over seeds: 3D error after the GNSS loss, mean [m]\n\n" + table)
        typer.echo(table)
    else:
        typer.echo(suite_table(figs) if suite else markdown_summary(fig))
    typer.echo(f"Outputs in {out}/")
