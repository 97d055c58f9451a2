"""`terraslam sitl-check` — verify a real PX4/ArduPilot SITL fuses our source (issue 6)."""
from companion.cli import app, fail


@app.command("sitl-check")
def sitl_check() -> None:
    """Check a running SITL fuses our fixes (not available yet)."""
    fail("`sitl-check` is not available yet")
