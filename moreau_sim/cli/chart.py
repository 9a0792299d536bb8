"""`moreau-sim chart`: speed against accuracy for one scene (moreau_sim.chart, docs/cli.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from .. import interrupts
from ..chart import AGREEMENT, INTEGRATORS, REFERENCE_RTOL, ChartInterrupted, chart as make_chart
from ..errors import MoreauSimError
from ..scene import load_scene
from ..sweep import parse_settings
from .common import fail
from .paths import output_dir

# the keyword a chart() error names -> the option of this command
_OPTIONS = {"integrators": "--integrators", "dts": "--dt", "tolerances": "--tol", "duration": "--duration",
            "sample_step": "--sample-step", "repeats": "--repeats", "reference_rtol": "--reference-rtol",
            "agreement": "--agreement"}


def _floats(text: str | None, option: str) -> list[float] | None:
    if text is None:
        return None
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        fail(f"{option} {text}: give comma-separated numbers, e.g. {option} 1e-2,1e-3")


@click.command()
@click.argument("scene", type=click.Path(dir_okay=False))
@click.option("--out", "-o", "out_dir", type=click.Path(),
              help="Output folder for chart.png, chart.json and chart.md (default: charts/SCENE_NAME).")
@click.option("--integrators", "-i", metavar="NAME,...",
              help=f"Which integrators to chart (default: all that accept the scene): {', '.join(INTEGRATORS)}.")
@click.option("--dt", "dts", metavar="H,...",
              help="The time-stepping ladder [s] (default: 1e-2,5e-3,2e-3,1e-3,5e-4,2e-4,1e-4, those dividing the "
                   "sample step); each must divide --sample-step.")
@click.option("--tol", "tols", metavar="RTOL,...",
              help="The adaptive and event-driven ladder of rtol (atol = rtol/100; default 1e-3,1e-4,1e-6,1e-8,1e-10).")
@click.option("--duration", type=float, help="Simulated time [s] (default: the scene's).")
@click.option("--repeats", "-r", type=int, default=3, show_default=True,
              help="Runs per point; the CPU time is their minimum.")
@click.option("--sample-step", type=float,
              help="Spacing [s] of the instants where errors are measured (default 0.01 s, or finer for short runs).")
@click.option("--reference-rtol", type=float, default=REFERENCE_RTOL, show_default=True,
              help="rtol of the two reference runs.")
@click.option("--agreement", type=float, default=AGREEMENT, show_default=True,
              help="The stated level: reference methods further apart than this are reported as uncertain.")
@click.option("--set", "-s", "settings", multiple=True, metavar="NAME=VALUE",
              help="Any option of the scene's [simulation] table, as in `run --set` (repeatable).")
@click.option("--json", "as_json", is_flag=True, help="Print the chart's JSON instead of the table.")
def chart(scene, out_dir, integrators, dts, tols, duration, repeats, sample_step, reference_rtol, agreement,
          settings, as_json):
    """Work-precision chart of SCENE: each integrator that accepts it over a ladder of steps or
    tolerances, its error against a reference (two methods agreeing at tight tolerance) on a common
    sample grid, against its CPU time per simulated second. Writes chart.png, chart.json and
    chart.md into the output folder; an interruption keeps the runs so far in chart.partial.json."""
    try:
        options = parse_settings(settings)
        name = load_scene(scene).name
    except MoreauSimError as exc:
        fail(str(exc))
    out = output_dir(out_dir, default=Path("charts") / name, where="--out", roots=[Path(scene).parent])
    names = None if integrators is None else [x.strip() for x in integrators.split(",") if x.strip()]
    lines = (lambda msg: None) if as_json else (lambda msg: click.echo(msg, err=True))
    try:
        res = make_chart(scene, out_dir=out, integrators=names, dts=_floats(dts, "--dt"),
                         tolerances=_floats(tols, "--tol"), duration=duration, repeats=repeats,
                         sample_step=sample_step, reference_rtol=reference_rtol, agreement=agreement,
                         options=options, log=lines)
    except ChartInterrupted as exc:
        where = f"; the runs measured so far are in {exc.path}" if exc.path else ""
        fail(f"interrupted by {interrupts.signal_name()} {str(exc).removeprefix('interrupted ')}{where}",
             interrupts.exit_status())
    except MoreauSimError as exc:
        msg = str(exc)
        keyword = msg.split(":", 1)[0]
        fail(_OPTIONS[keyword] + msg[len(keyword):] if keyword in _OPTIONS else msg)
    if as_json:
        click.echo(json.dumps({**res.to_json(), "files": res.files}, indent=1))
        sys.exit(0)
    click.echo(Path(res.files["markdown"]).read_text(encoding="utf-8"), nl=False)
    click.echo(f"-> {res.files['png']}, {res.files['json']}, {res.files['markdown']}")
