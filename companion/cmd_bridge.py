"""`terraslam sitl-check` — verify a real PX4/ArduPilot SITL fuses our source (issue 6)."""
from __future__ import annotations

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
