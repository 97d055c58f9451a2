"""`terraslam run|demo|replay` — the service, the built-in demo, offline replay (issue 7)."""
from companion.cli import app, fail


@app.command("demo")
def demo() -> None:
    """Built-in simulated flight with GNSS loss (not available yet)."""
    fail("`demo` is not available yet")


@app.command("run")
def run() -> None:
    """Run the companion service (not available yet)."""
    fail("`run` is not available yet")


@app.command("replay")
def replay() -> None:
    """Replay a dataset offline (not available yet)."""
    fail("`replay` is not available yet")
