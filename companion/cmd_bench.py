"""`terraslam bench` — benchmarks (issue 8)."""
from companion.cli import app, fail


@app.command("bench")
def bench() -> None:
    """Run benchmarks (not available yet)."""
    fail("`bench` is not available yet")
