"""`moreau-sim sweep`: a grid of options over one scene (moreau_sim.sweep, docs/sweeps.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from .. import interrupts
from ..errors import MoreauSimError
from ..sweep import SWEEPABLE, Param, parse_param, parse_settings, run_sweep
from .common import fail
from .paths import output_dir


@click.command()
@click.argument("scene", type=click.Path(dir_okay=False))
@click.option("--param", "-p", "params", multiple=True, metavar="NAME=A:B:N|NAME=V1,V2,...",
              help="A swept option (repeatable; the grid is their cartesian product): A:B:N is N points "
                   "from A to B inclusive, V1,V2,... a list, in SI units (gravity=[x,y,z]). NAME is one of "
                   f"{', '.join(SWEEPABLE)}.")
@click.option("--set", "-s", "settings", multiple=True, metavar="NAME=VALUE",
              help="A fixed option of every point (repeatable), as in `run --set`: a one-value --param.")
@click.option("--out", "-o", "out_dir", type=click.Path(),
              help="Output directory (default: sweeps/ and the scene file's name without .toml). "
                   "Rerunning into it resumes.")
@click.option("--workers", "-j", type=click.IntRange(min=1), help="Local worker processes (default: cores).")
@click.option("--dask", "dask_address", metavar="ADDRESS",
              help="Run on this Dask distributed scheduler (e.g. tcp://host:8786) instead of locally.")
@click.option("--progress/--no-progress", default=None,
              help="Progress bar (default: only when stderr is a terminal).")
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON.")
def sweep(scene, params, settings, out_dir, workers, dask_address, progress, as_json):
    """Simulate SCENE at every point of a grid of options; write a table of summary metrics
    (sweep.csv) and one NPZ per run (runs/) into the output directory. Exits 0 when every point
    ran to its end (complete, or flagged: it broke an invariant, listed on stderr), 1 when some
    failed, 2 on bad input."""
    try:
        parsed = [parse_param(p) for p in params]
        parsed += [Param(k, (v,), f"{k}={v}") for k, v in parse_settings(settings).items()]
        out_dir = output_dir(out_dir, default=Path("sweeps") / Path(scene).stem, where="--out",
                             roots=[Path(scene).parent])
        res = run_sweep(scene, parsed, out_dir, workers=workers, dask_address=dask_address,
                        progress=(sys.stderr.isatty() if progress is None else progress) and not as_json)
    except MoreauSimError as exc:
        fail(str(exc))
    except KeyboardInterrupt:
        fail(f"interrupted by {interrupts.signal_name()}; finished runs are kept in {out_dir}: run the same command "
             "again to resume", interrupts.exit_status())
    status = 1 if any(r["status"] == "failed" for r in res.rows) else 0
    if as_json:
        click.echo(json.dumps({"table": str(res.table), "parquet": str(res.parquet) if res.parquet else None,
                               "points": len(res.rows), "computed": res.computed, "skipped": res.skipped,
                               "failed": res.failed, "flagged": res.flagged, "rows": list(res.rows)}, indent=2))
        sys.exit(status)
    click.echo(f"{len(res.rows)} points: {res.computed} computed, {res.skipped} already done, "
               f"{res.failed} failed -> {res.table}" + (f" and {res.parquet}" if res.parquet else ""))
    for r in res.rows:
        if r["status"] != "complete":
            click.echo(f"  {r['status']} {r['id']}: {r['message']}", err=True)
    sys.exit(status)
