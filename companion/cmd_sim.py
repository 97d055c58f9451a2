"""`terraslam sim ...` — synthetic datasets (issue 3)."""
import typer

from companion.cli import app, fail

sim_app = typer.Typer(help="Synthetic world, flights and GNSS: generate datasets.", no_args_is_help=True)
app.add_typer(sim_app, name="sim")


@sim_app.command("generate")
def generate() -> None:
    """Write a simulated dataset (not available yet)."""
    fail("`sim generate` is not available yet")
