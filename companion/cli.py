"""The ``terraslam`` command line (one entry point; subcommands live beside their owners).

Heavy libraries (open3d, torch, cv2) are imported inside commands so ``--help`` stays fast.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from companion import __version__

app = typer.Typer(
    name="terraslam",
    help="TerraSLAM companion: GNSS-denied global positioning from monocular SLAM aligned to a 3D GIS model.",
    no_args_is_help=True,
    add_completion=False,
)
config_app = typer.Typer(help="Inspect configuration.", no_args_is_help=True)
app.add_typer(config_app, name="config")


def _version(value: bool) -> None:
    if value:
        typer.echo(f"terraslam {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version and exit."),
) -> None:
    """TerraSLAM companion."""


def fail(message: str, code: int = 2) -> None:
    """Print a clear error to stderr and exit non-zero."""
    typer.secho(f"error: {message}", err=True, fg=typer.colors.RED)
    raise typer.Exit(code)


@config_app.command("dump")
def config_dump(config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML config file (default: built-in defaults)")) -> None:
    """Print the effective configuration (file + TERRASLAM_* environment overrides)."""
    from companion.config import ConfigError, dump_config, load_config

    try:
        cfg = load_config(config)
    except ConfigError as e:
        fail(str(e))
    typer.echo(dump_config(cfg), nl=False)


def _register_subcommands() -> None:
    # Each owner module adds its commands to `app`; kept in separate files so the pieces stay small.
    from companion import cli_commands  # noqa: F401


def main() -> None:
    _register_subcommands()
    app()


if __name__ == "__main__":
    main()
