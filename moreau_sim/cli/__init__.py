"""`moreau-sim`: the command line over the public API, one module per group of commands
(docs/cli.md). `main` is the click group and the console script's entry point."""

from __future__ import annotations

import click

from .. import interrupts
from .common import fail

from .chart import chart
from .regress import regress
from .run import info, outcomes, plot, run
from .sweep import sweep
from .viewer import view


class _Main(click.Group):
    """The group whose commands run with SIGINT and SIGTERM raising KeyboardInterrupt: a command
    keeps what it can (run: FILE.partial.npz; sweep: the finished points) and any interruption
    ends in one line and exit status 130 (SIGINT) or 143 (SIGTERM), docs/cli.md."""

    def invoke(self, ctx):
        previous = interrupts.raising()
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt:
            fail(f"interrupted by {interrupts.signal_name()}", interrupts.exit_status())
        finally:
            interrupts.restore(previous)


@click.group(cls=_Main, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="moreau-sim")
def main():
    """Rigid multibody impacts: Glocker's impact law in a midpoint Moreau time-stepper."""


for _command in (run, info, outcomes, plot, sweep, view, regress, chart):
    main.add_command(_command)

__all__ = ["main"]
