"""`moreau-sim view`: browser replay of a trajectory NPZ (moreau_sim.viewer, docs/viewer.md)."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from ..errors import MoreauSimError
from .paths import output_path


@click.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--port", type=int, default=8765, show_default=True, help="Port to serve on (0: any free port).")
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to listen on.")
@click.option("-o", "--out", "html", type=click.Path(),
              help="Write the replay as one HTML file (opens offline from file://, no server) and exit.")
@click.option("--export", "html_alias", type=click.Path(), hidden=True)  # the old name of --out
@click.option("--fps", type=float, default=100.0, show_default=True,
              help="Frames kept per simulated second (0: every sample).")
@click.option("--colors", type=click.Choice(["link", "model"]), default="link", show_default=True,
              help="A colour per link, or the model's own colours (URDF materials, MJCF rgba and materials).")
@click.option("--no-browser", is_flag=True, help="Do not open a browser.")
def view(file, port, host, html, html_alias, fps, colors, no_browser):
    """3D replay of a trajectory FILE in the browser (viser): the models' meshes, play/pause, time
    slider, contact arrows, energy and gap plot. Serves on 127.0.0.1 until Ctrl-C, or writes one
    HTML file with -o/--out."""
    from .. import viewer
    from ..trajectory import load_trajectory

    try:
        traj = load_trajectory(file)
        html = html or html_alias
        if html:
            html = output_path(html, default=Path(file).with_suffix(".html"), suffix=(".html", ".htm"),
                               where="--out", inputs=[file], roots=[Path(file).parent])
            click.echo(f"wrote {viewer.export_html(traj, html, fps=fps, colors=colors)}")
            return
        viewer.serve(traj, port, host, open_browser=not no_browser, fps=fps, colors=colors,
                     ready=lambda url: click.echo(f"serving {file} at {url}  (Ctrl-C to stop)"))
    except (ValueError, MoreauSimError, OSError) as exc:
        click.echo(f"moreau-sim: error: {exc}", err=True)
        sys.exit(2)

