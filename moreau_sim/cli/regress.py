"""`moreau-sim regress`: the command over :mod:`moreau_sim.regress` (docs/regression.md).

Exit status: 0 every scene within tolerance (or recorded), 1 a ledger drifted, a run failed or
broke an invariant (flagged), 2 bad input (scene, option, tolerance, a missing or unreadable baseline)."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from ..errors import MoreauSimError
from ..ledger import DEFAULT_TOLERANCE, QUANTITIES
from ..regress import FAILURES, Result, check_scene, junit
from ..sweep import parse_settings
from .common import fail
from .paths import output_dir, output_path


def _tolerances(rtol, atol, specs) -> dict | None:
    """--rtol/--atol (every quantity) and --tol NAME=RTOL,ATOL (one quantity) -> {name: (rtol, atol)}."""
    out = {}
    if rtol is not None or atol is not None:
        r0, a0 = DEFAULT_TOLERANCE
        out["default"] = (r0 if rtol is None else rtol, a0 if atol is None else atol)
    for spec in specs:
        name, _, value = spec.partition("=")
        try:
            r, a = (float(x) for x in value.split(","))
        except ValueError:
            fail(f"command line: --tol {spec}: expected NAME=RTOL,ATOL (e.g. energy_end=1e-6,1e-9)")
        if name not in QUANTITIES:
            fail(f"command line: --tol {spec}: unknown quantity {name!r}; one of {', '.join(QUANTITIES)}")
        if r < 0 or a < 0:
            fail(f"command line: --tol {spec}: expected NAME=RTOL,ATOL with RTOL, ATOL >= 0")
        out[name] = (r, a)
    return out or None


@click.command()
@click.argument("scenes", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--baseline", "-b", "directory", required=True, type=click.Path(file_okay=False),
              help="Folder of the baseline files, one SCENE_NAME.json per scene.")
@click.option("--update", is_flag=True, help="Run the scenes and (re)write their baselines instead of comparing.")
@click.option("--set", "-s", "settings", multiple=True, metavar="NAME=VALUE",
              help="Override a [simulation] option (repeatable); a baseline records its overrides and later "
                   "runs reuse them.")
@click.option("--rtol", type=click.FloatRange(min=0), help="Relative tolerance of every quantity (default 1e-6).")
@click.option("--atol", type=click.FloatRange(min=0), help="Absolute tolerance of every quantity [J] (default 1e-9).")
@click.option("--tol", "tol_specs", multiple=True, metavar="NAME=RTOL,ATOL",
              help="Tolerance of one quantity (repeatable): a total (energy_end, dissipation, ...), impact_t, "
                   "impact_dissipated, energy (E(t)) or impacts (the count, exact by default).")
@click.option("--junit", "-o", "--out", "junit_file", type=click.Path(),
              help="Also write a JUnit XML report to this file.")
def regress(scenes, directory, update, settings, rtol, atol, tol_specs, junit_file):
    """Run SCENES and compare their energy ledgers with the baselines in --baseline (docs/regression.md).
    Exits 0 when every scene is within tolerance, 1 when a ledger drifted or a run failed or was
    flagged (broke an invariant), 2 on bad input."""
    tolerances = _tolerances(rtol, atol, tol_specs)
    try:
        overrides = parse_settings(settings)
    except MoreauSimError as exc:
        fail(f"command line: {exc}")
    if junit_file is not None:
        junit_file = output_path(junit_file, default=Path("regress.xml"), suffix=".xml", where="--junit",
                                 inputs=list(scenes), roots=[Path(s).parent for s in scenes])
    if update:
        output_dir(directory, default=Path(directory), where="--baseline", roots=[Path(s).parent for s in scenes])
    results, errors = [], 0
    for scene in scenes:
        try:
            r = check_scene(scene, directory, update=update, overrides=overrides, tolerances=tolerances)
        except (MoreauSimError, ValueError, OSError) as exc:  # bad input: named, the other scenes still run
            click.echo(f"moreau-sim: error: {exc}", err=True)
            r = Result(Path(scene).stem, scene, "error", message=str(exc))
            errors += 1
        else:
            click.echo(r.report())
        results.append(r)
    if junit_file:
        try:
            junit(results, junit_file)
        except OSError as exc:
            fail(f"{junit_file}: cannot write the JUnit report ({exc.strerror or exc})")
    bad = [r for r in results if r.status in FAILURES]
    click.echo(f"{len(results)} scene{'' if len(results) == 1 else 's'}: {len(results) - len(bad) - errors} within "
               "tolerance"
               + ("" if not bad else f", {len(bad)} drifted, failed or flagged: {', '.join(r.scene for r in bad)}")
               + ("" if not errors else f", {errors} not run (bad input)"))
    sys.exit(2 if errors else 1 if bad else 0)
