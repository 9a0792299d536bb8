"""What every command shares: its one-line error and exit status (docs/cli.md)."""

from __future__ import annotations

import sys

import click


def fail(msg: str, code: int = 2) -> None:
    """Print `moreau-sim: error: MSG` on stderr and exit with `code` (2: bad input)."""
    click.echo(f"moreau-sim: error: {msg}", err=True)
    sys.exit(code)
