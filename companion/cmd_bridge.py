"""`terraslam sitl-check` (does a real PX4/ArduPilot fuse our source?) and `terraslam sitl` (a closed-loop SITL flight)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from companion.cli import app, fail


@app.command("sitl-check")
def sitl_check(
    autopilot: str = typer.Option(..., "--autopilot", help="px4 | ardupilot"),
    connect: str = typer.Option(..., "--connect", help="MAVSDK URL, e.g. udpin://0.0.0.0:14540 (PX4) or tcpout://127.0.0.1:5762 (ArduPilot)"),
    seconds: float = typer.Option(5.0, "--seconds", min=0.5, help="how long to listen"),
    fix: Optional[str] = typer.Option(None, "--fix", help="our fix 'LAT,LON' to compare with (ArduPilot: read from the MAVLink GPS instance when omitted)"),
) -> None:
    """Report, with evidence, whether the autopilot fuses our source and how far its position is from our fix."""
    from mavlink_bridge.sitl_check import collect, judge

    if autopilot not in ("px4", "ardupilot"):
        fail(f"--autopilot must be px4 or ardupilot, got {autopilot!r}")
    our_fix = None
    if fix is not None:
        try:
            lat, lon = (float(x) for x in fix.split(","))
            our_fix = (lat, lon)
        except ValueError:
            fail(f"--fix must be 'LAT,LON' in degrees, got {fix!r}")
    try:
        obs = collect(connect, autopilot, seconds)
    except (ConnectionError, TimeoutError) as e:
        fail(str(e))
    report = judge(obs, autopilot, our_fix)
    for line in report.evidence:
        typer.echo(f"  - {line}")
    verdict = {True: "FUSING our source", False: "NOT fusing our source", None: "cannot tell (see evidence)"}[report.fusing]
    typer.echo(f"{autopilot}: {verdict}")
    raise typer.Exit(0 if report.fusing else 1)


@app.command("sitl")
def sitl(
    autopilot: str = typer.Option("ardupilot", "--autopilot", help="ardupilot | px4"),
    sitl_dir: Optional[Path] = typer.Option(None, "--sitl-dir", help="SITL bundle (start_arducopter.sh, start_px4.sh, stop.sh); default $TERRASLAM_SITL_DIR"),
    out: Path = typer.Option(Path("out/sitl"), "--out", "-o", help="output folder: report.md/json, trajectory, plots, the SITL's work folder"),
    output: Optional[str] = typer.Option(None, "--output", help="what we feed: ardupilot gps_input (default) | odometry; px4 odometry (default) | global_position_sensor"),
    speed: float = typer.Option(0.5, "--speed", help="SITL speed against real time; lower it when frames are dropped (report: frames_dropped)"),
    gnss_off_after: float = typer.Option(40.0, "--gnss-off-after", help="seconds after the camera starts (the vehicle cruising on the route) before the SITL's GNSS is switched off"),
    gnss_off_for: float = typer.Option(120.0, "--gnss-off-for", help="seconds without GNSS; 0: it stays off"),
    laps: float = typer.Option(1.75, "--laps", help="laps of the 200 m square over the city (mission, then return and land)"),
    max_flight: Optional[float] = typer.Option(None, "--max-flight", help="end this many seconds after the camera starts instead of landing"),
    offset_probe: float = typer.Option(0.0, "--offset-probe", help="metres east added to our fixes over the denial's last 10 s: does the autopilot follow them?"),
    spoof: float = typer.Option(0.0, "--spoof", help="instead of switching GNSS off, move the SITL receiver this many metres north (ArduPilot: SIM_GPS1_GLTCH_X) for --gnss-off-for seconds"),
    seed: int = typer.Option(0, "--seed", help="the simulated city"),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
) -> None:
    """Closed loop with a real autopilot SITL: it flies a mission over the simulated city, our camera is
    rendered from its simulated truth, GNSS is switched off with the SITL's own command; reports our
    fixes, the autopilot's estimate and its failsafes against the truth."""
    from companion.cmd_run import _load
    from companion.sitl.bundle import SitlError
    from companion.sitl.flight import SitlOptions, run_sitl

    try:
        opts = SitlOptions(autopilot=autopilot, output=output, seed=seed, speed=speed, laps=laps,
                           gnss_off_after_s=gnss_off_after, gnss_off_for_s=gnss_off_for or None,
                           max_flight_s=max_flight, offset_probe_m=offset_probe, spoof_m=spoof)
    except (ValueError, SitlError) as e:
        fail(str(e))
    cfg = _load(config)
    try:
        summary = run_sitl(cfg, sitl_dir, out, opts, progress=None)
    except (SitlError, TimeoutError, ConnectionError) as e:
        fail(str(e), code=1)
    s, a = summary["sitl"], summary["after_takeover"]
    h = a.get("horizontal_error_m") or {}
    what = f"GNSS spoofed {spoof:+g} m" if spoof else "GNSS off"
    typer.echo(f"{autopilot} ({s['output']}): {what} at {s['timeline']['gnss_off_s']} s, takeover after "
               f"{s['takeover_after_gnss_off_s']} s, fixes on {summary['fix_ratio_after_takeover']} of frames after it")
    typer.echo(f"  our fixes (horizontal, after takeover): mean {h.get('mean')} m, max {h.get('max')} m; "
               f"beyond 3σ: {a.get('integrity_violation_ratio')}")
    ap = s["autopilot_error_in_denial_m"]
    typer.echo(f"  the autopilot's own estimate in the denial: mean {ap['mean']} m, max {ap['max']} m")
    typer.echo(f"  failsafes: {s['failsafes'] or 'none'}; mission completed: {s['mission_completed']}; "
               f"landed {s['landed_from_home_m']} m from home; source switch {s['source_switch']}")
    typer.echo(f"Outputs in {out}/ (report.md, report.json, trajectory, plots)")
    raise typer.Exit(0 if not s["failsafes"] else 1)
