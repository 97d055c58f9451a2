"""Imports every subcommand module so their commands register on ``companion.cli.app``."""
from companion import cmd_bench, cmd_bridge, cmd_gis, cmd_run, cmd_sim  # noqa: F401
