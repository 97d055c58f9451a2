"""`terraslam gis ...` and `terraslam align-offline` — GIS cache and offline alignment (issue 5)."""
import typer

from companion.cli import app, fail

gis_app = typer.Typer(help="GIS model cache: import, list, fetch.", no_args_is_help=True)
app.add_typer(gis_app, name="gis")


@gis_app.command("ls")
def gis_ls() -> None:
    """List cached GIS models and transforms (not available yet)."""
    fail("`gis ls` is not available yet")


@app.command("align-offline")
def align_offline() -> None:
    """Compute T_rough for a site from a survey dataset (not available yet)."""
    fail("`align-offline` is not available yet")
