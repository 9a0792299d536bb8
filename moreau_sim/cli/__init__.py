"""`moreau-sim`: the command line over the public API, one module per group of commands
(docs/cli.md). `main` is the click group and the console script's entry point."""

from __future__ import annotations

import click

from .regress import regress
from .run import info, outcomes, plot, run
from .sweep import sweep
from .viewer import view


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="moreau-sim")
def main():
    """Rigid multibody impacts: Glocker's impact law in a midpoint Moreau time-stepper."""


for _command in (run, info, outcomes, plot, sweep, view, regress):
    main.add_command(_command)

__all__ = ["main"]
