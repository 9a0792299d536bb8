"""Benchmarks of moreau-sim (docs/benchmarks.md): not part of the installed package; run from the
source tree's root as `python -m benchmarks.NAME [--help]`. Benchmarks are measurements, not tests:
they never fail on a bad number, and nothing here asserts a time. The exact references and error
metrics they measure against are moreau_sim.testing.references and moreau_sim.testing.metrics.

Modules:
- spec: the neutral scene spec every peer runner reads (spheres and boxes on free or slide joints,
  half-space and box statics), built from a moreau-sim model, and the way back to its coordinates.
- peers: MuJoCo, PyBullet and Siconos, one runner each (peers.mujoco / .pybullet / .siconos, each
  with its documented DEFAULTS), `available()` and `run()` / `run_model()`.
- work_precision: error against exact references vs CPU time, for moreau-sim and the peers.
- stability: the stress suite side by side.
- step_costs: the cost of one step split into dynamics, collision, QP and the rest of the step.
- compiled_costs: the compiled step against the Python step, Siconos's Moreau-Jean step and MuJoCo's
  mj_step per step, whole runs per step, and the cost targets' verdicts, one run.
- adaptive_costs: the adaptive integrator against the event-driven one and the fixed step.
- events: the ball and the touching cradle under the adaptive integrator against Siconos's event-driven
  integrator, the whole ms.simulate call and its loop (meta run.cpu_seconds), at equal sampling.
- scaling: columns of 10 to 10,000 beads and piles of free boxes against MuJoCo: per step, build, memory.
- big_pile: a pile of 1000 free boxes under the compiled step alone, against MuJoCo on the same pile.
- robots_table: the bundled robot scenes' figures (docs/robots.md).
- actuated_costs: actuated whole runs (the scene's PD, a Python controller) against the passive run per step.
- doc_tables: every table of docs/*.md generated from the committed JSON, and the drift check.
- check_peers: every available peer against the exact references.

Every driver writes to out/ by default; `--out docs/bench` (work_precision, step_costs,
compiled_costs, adaptive_costs, events, robots_table, stability) regenerates the committed files. The
tables of figures in docs/*.md are generated from the committed JSON, never typed: each sits
between the markers of `splice_table`, and each driver's `--table JSON DOC` rewrites its own
(doc_tables: all of them at once, and the check that none drifted).

Peers, install:

    pip install -e '.[peers]'                 # MuJoCo, PyBullet (or a venv of their own: $PEERS_PYTHON)
    apt-get install -y python3-siconos        # Siconos: Debian's Python only (peers.SICONOS_PYTHON)

Peer settings (each runner's module doc has the details and why):
- MuJoCo: soft contacts, solref "-k -b" with constant impedance 0.95, sqrt(k) = omega_h / h with
  omega_h = 0.2, damping from the Schwager-Poschel map for e, condim 1, Euler, Newton solver, 100
  iterations, tolerance 1e-10, stepped by mujoco.rollout.
- PyBullet: every body and static at restitution sqrt(e) (a pair multiplies them), no friction or
  damping, no sleeping; config "default" (Bullet's defaults: restitution threshold 0.2 m/s,
  speculative contacts within 0.02 m, contact ERP) or "tuned" (those three at 0). Bullet keeps
  contactBreakingThreshold process-global, so the runner always sets it.
- Siconos: MoreauJeanOSI(1/2), NewtonImpactNSL(e), one LCP per step (Lemke); spheres on collinear
  slide joints (gaps exactly as the floating-point positions give them, or exact_gaps=True), and
  one free box over the ground through its Bullet mechanics (NewtonImpactFrictionNSL with mu = 0).
CPU time is time.process_time() around each peer's stepping loop only (MuJoCo a C rollout,
PyBullet and Siconos through their Python bindings: not apples to apples). Siconos and MuJoCo also
take timing_repeats=R: R whole runs' wall time, and per step the best of R runs with a timer around
each step and its contact count (the result's "timing"; compiled_costs reads it).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

# CPU time is what every benchmark compares: a BLAS or OpenMP pool would add its threads' spinning to a process's
# CPU time (measured 2026-11-28 on an idle machine: Siconos's event-driven ball 0.54 ms per simulated second with
# one thread, 1.15 with the default pool), so every library here runs on one thread unless the caller says otherwise
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

REPO = Path(__file__).resolve().parents[1]  # the source tree: scenes/, docs/
SCENES = REPO / "scenes"
OUT = Path("out")  # default output folder of every driver, relative to the current directory


def pyplot():
    """matplotlib.pyplot on the Agg backend (files, no display), imported where a chart is drawn: a benchmark that
    only measures never loads it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def scene_path(name: str) -> Path:
    """The bundled scene file scenes/<name>.toml."""
    return SCENES / f"{name}.toml"


def splice_table(text: str, name: str, table: str, *, where: str = "the document") -> str:
    """`text` with the table between `<!-- NAME: generated by ... -->` and `<!-- end of NAME -->`
    replaced by `table` (the markers stay). ValueError naming `where` if the markers are missing."""
    found = re.search(rf"(<!-- {re.escape(name)}: generated by [^\n]*?-->\n).*?(<!-- end of {re.escape(name)} -->)",
                      text, re.S)
    if found is None:
        raise ValueError(f"{where} has no '<!-- {name}: generated by ... -->' ... '<!-- end of {name} -->' markers")
    return text[:found.start()] + found.group(1) + table.rstrip("\n") + "\n" + found.group(2) + text[found.end():]


def write_tables(json_path: Path, doc: Path, render) -> list[str]:
    """Rewrite in `doc` every table `render(data)` gives ({marker name: Markdown}) from the JSON file
    `json_path`; the names written. SystemExit with one line naming the file on bad input."""
    import json

    try:
        tables = render(json.loads(Path(json_path).read_text(encoding="utf-8")))
        text = Path(doc).read_text(encoding="utf-8")
        for name, table in tables.items():
            text = splice_table(text, name, table, where=str(doc))
    except (OSError, ValueError, KeyError, TypeError) as err:
        kind = "" if isinstance(err, (OSError, ValueError)) else f"{json_path}: missing or malformed entry "
        raise SystemExit(f"error: {kind}{err}") from None
    Path(doc).write_text(text, encoding="utf-8")
    return list(tables)


def add_table_option(ap, json_name: str, doc: str) -> None:
    """The --table JSON DOC option every benchmark's command line has (argparse parser `ap`)."""
    ap.add_argument("--table", nargs=2, type=Path, metavar=("JSON", "DOC"),
                    help=f"only rewrite the generated tables in DOC ({doc}) from a {json_name}, and exit")


def rewrite_tables(args, render) -> bool:
    """With --table given, rewrite DOC's tables `render` gives from JSON and say which; whether it
    was given (the caller then exits)."""
    if not args.table:
        return False
    names = write_tables(args.table[0], args.table[1], render)
    print(f"wrote {', '.join(names)} into {args.table[1]}")
    return True


def add_plot_option(ap, json_name: str) -> None:
    """The --plot JSON option of the benchmarks that draw a chart (argparse parser `ap`)."""
    ap.add_argument("--plot", type=Path, metavar="JSON",
                    help=f"only redraw the chart from a saved {json_name} (the PNG beside it: "
                         f"{json_name.replace('.json', '.png')}), and exit")


def redraw(args, plot, *, select=lambda data: data) -> bool:
    """With --plot given, draw `plot(select(data), png)` from the saved JSON into the PNG of the same
    name beside it, and say so; whether it was given (the caller then exits). SystemExit with one
    line naming the file on bad input."""
    import json

    if not args.plot:
        return False
    png = Path(args.plot).with_suffix(".png")
    try:
        plot(select(json.loads(Path(args.plot).read_text(encoding="utf-8"))), png)
    except (OSError, ValueError) as err:
        raise SystemExit(f"error: {err}") from None
    except (KeyError, TypeError) as err:
        raise SystemExit(f"error: {args.plot}: missing or malformed entry {err}") from None
    print(f"wrote {png}")
    return True
