"""`terraslam bench`: the TerraSLAM evaluation tables reproduced on our own system (issue 8).

One benchmark run drives the real pipeline (``companion.app.build_localizer`` → ``Localizer.process``
→ ``mavlink_bridge.Bridge`` → simulated autopilot over UDP loopback, the same code as ``run demo``)
over a simulator scenario or a recorded dataset, then computes the figures of TerraSLAM §7 from
what the run produced:

- global / horizontal error of the emitted fixes vs truth (TerraSLAM Table 1, Fig. 12a),
- per-frame tracking latency (Fig. 12d) and capture → MAVLink bytes written,
- tracking / fix availability, integrity (true error > 3 × reported 1-σ),
- SLAM-only ATE after a Sim(3) (Umeyama) alignment to truth, % of path length,
- alignment error of the SLAM map under the first and the last fine alignment (Table 4 metric:
  mean point-to-model distance, ``gis.align.rough.alignment_error_m``),
- GNSS baselines (standalone GPS and DGPS) re-simulated on the same flight,
- process RSS / CPU sampled by a psutil thread, and optionally the GA/PLM/RLC ablation (Fig. 14).

Every figure is a number or None; a None has its reason in ``bench["reasons"][key]``.
This module is the command (one run with its ablation and sweep, the suite); the run is in
companion.bench_run, its figures in companion.bench_figures, what is written in companion.bench_report.
"""
from __future__ import annotations

import gc
import json
from pathlib import Path
from typing import Callable

from companion.bench_figures import ablation_row, figures
from companion.bench_report import SuiteBoxes, json_default, plot_suite, suite_table, write_bench
from companion.bench_run import BenchRun, bench_dataset, bench_scenario
from companion.config import AppConfig

#: scenarios of ``--suite`` (the simulator's names)
SUITE = ("nominal", "stale", "dark", "bright", "fast", "loop")

#: TerraSLAM Fig. 14 ablation, cumulative: baseline, + GPU-accelerated features (GA),
#: + progressive local mapping (PLM), + recursive loop closing (RLC). SlamConfig field overrides.
ABLATION: tuple[tuple[str, dict], ...] = (
    ("baseline", {"feature_backend": "cpu", "progressive_local_mapping": False, "loop_closing": "full"}),
    ("+GA", {"feature_backend": "torch", "progressive_local_mapping": False, "loop_closing": "full"}),
    ("+PLM", {"feature_backend": "torch", "progressive_local_mapping": True, "loop_closing": "full"}),
    ("+RLC", {"feature_backend": "torch", "progressive_local_mapping": True, "loop_closing": "recursive"}),
)



Progress = Callable[[str, int, int, str], None]  # (run label, frame, total, bridge state)


def bench_one(cfg: AppConfig, out_dir: Path, *, scenario: str | None = None, dataset: Path | None = None,
              n_frames: int = 300, seed: int = 0, fps: float = 10.0, ablation: bool = False, sweep_extents_m: tuple[float, ...] = (),
              progress: Progress | None = None, receiver: str | None = None, repeatable: bool = False,
              journal: bool = False) -> tuple[dict, BenchRun]:
    """One scenario (or dataset): run, figures, optional ablation and map-size sweep, outputs.
    journal: the main run's registration journal in ``out_dir/registrations`` (gis.align.journal)."""
    if (scenario is None) == (dataset is None):
        raise ValueError("give exactly one of scenario or dataset")

    def go(c: AppConfig, label: str, journal_dir: Path | None = None) -> BenchRun:
        cb = (lambda k, n, st: progress(label, k, n, st)) if progress else None
        if dataset is not None:
            return bench_dataset(c, dataset, n_frames, cb, repeatable=repeatable, journal_dir=journal_dir)
        return bench_scenario(c, scenario, n_frames, seed=seed, fps=fps, work_dir=out_dir, progress=cb, receiver=receiver,
                              repeatable=repeatable, journal_dir=journal_dir)

    br = go(cfg, scenario or str(dataset), out_dir / "registrations" if journal else None)
    fig = figures(br, cfg)
    if ablation:
        rows = []
        for label, over in ABLATION:
            c = cfg.model_copy(update={"slam": cfg.slam.model_copy(update=over)})
            rows.append(ablation_row(label, figures(go(c, f"ablation {label}"), c)))
        fig["ablation"] = rows
    else:
        fig["reasons"]["ablation"] = "not requested (--ablation)"
    if sweep_extents_m:
        from gis.bench import size_sweep

        fig["finetune_map_size_sweep"] = size_sweep(sweep_extents_m)
    fig["outputs"] = [str(p) for p in write_bench(br, fig, out_dir)]
    (out_dir / "bench.json").write_text(json.dumps(fig, indent=2, default=json_default))
    return fig, br


def bench_suite(cfg: AppConfig, out_dir: Path, *, n_frames: int = 300, seed: int = 0, fps: float = 10.0, ablation: bool = False,
                scenarios: tuple[str, ...] = SUITE, progress: Progress | None = None, receiver: str | None = None,
                repeatable: bool = False) -> list[dict]:
    """Every scenario into out_dir/NAME/, then suite.md (comparison table), suite.json, suite_boxes.png."""
    figs, boxes = [], []
    for name in scenarios:
        fig, br = bench_one(cfg, out_dir / name, scenario=name, n_frames=n_frames, seed=seed, fps=fps,
                            ablation=ablation and name == "nominal", progress=progress, receiver=receiver,
                            repeatable=repeatable)
        figs.append(fig)
        boxes.append(SuiteBoxes.of(br))
        del br  # the run's GIS model, records and SLAM map go now, not after the last scenario
        gc.collect()
    (out_dir / "suite.json").write_text(json.dumps(figs, indent=2, default=json_default))
    (out_dir / "suite.md").write_text("# Benchmark suite\n\n" + suite_table(figs))
    plot_suite(boxes, out_dir)
    return figs
