"""Figure from a sweep table: energy the bouncing ball has lost by t = 0.55 s against the
restitution e, for two time steps, with the exact value.

The exact value: after n impacts (their instants: docs/theory.md §4.1) the 1 kg ball, dropped
with a 0.9 m gap, has lost (1 - e^(2n)) m g 0.9 J of T + V (moreau_sim.testing.references
.ball_energy_lost): by T = 0.55 s one impact for e >= 0.2, at rest for e <= 0.1.

    python scripts/plot_sweep.py [--out-dir out/sweep_restitution] [--png out/sweep_restitution.png]
    python scripts/plot_sweep.py --png docs/img/sweep_restitution.png   # the committed figure

Runs (or resumes) `moreau-sim sweep scenes/bouncing_ball.toml --param restitution=0:1:11
--param dt=1e-2,1e-3 --param duration=0.55`, then plots from the sweep's CSV table alone.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from moreau_sim.sweep import parse_param, run_sweep
from moreau_sim.testing.references import ball_energy_lost

SCENE = Path(__file__).resolve().parents[1] / "scenes" / "bouncing_ball.toml"  # in the source tree
OUT = Path("out")  # default output folder, relative to the current directory

PARAMS = ("restitution=0:1:11", "dt=1e-2,1e-3", "duration=0.55")
T = 0.55  # [s]


def exact_loss(e: float, t_end: float = T) -> float:
    """T + V lost by t_end [J] (the 1 kg bundled ball)."""
    return ball_energy_lost(e, t_end)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out-dir", type=Path, default=OUT / "sweep_restitution")
    ap.add_argument("--png", type=Path, default=OUT / "sweep_restitution.png",
                    help="the figure (docs/img/sweep_restitution.png: the committed one)")
    args = ap.parse_args()
    res = run_sweep(SCENE, [parse_param(p) for p in PARAMS], args.out_dir)
    print(f"{res.computed} computed, {res.skipped} already done, {res.failed} failed -> {res.table}")

    with open(res.table, newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["status"] == "complete" and r["duration"] == str(T)]

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax_err) = plt.subplots(2, 1, figsize=(6.4, 6.4), sharex=True, constrained_layout=True,
                                     gridspec_kw={"height_ratios": [2, 1]})
    e = np.linspace(0, 1, 1001)
    ax.plot(e, [exact_loss(x) for x in e], color="k", lw=1, label="exact")
    for dt, marker in (("0.01", "o"), ("0.001", "x")):
        pts = sorted((float(r["restitution"]), float(r["energy_lost"])) for r in rows if r["dt"] == dt)
        x, lost = np.array(pts).T
        ax.plot(x, lost, marker, ms=6, mfc="none", label=f"h = {float(dt):g} s")
        ax_err.semilogy(x, np.abs(lost - [exact_loss(v) for v in x]) + 1e-16, marker + "-", ms=6, mfc="none",
                        label=f"h = {float(dt):g} s")
    ax.set_ylabel(f"energy lost by t = {T:g} s [J]")
    ax.set_title("bouncing_ball: sweep over the restitution e and the step h")
    ax.legend()
    ax_err.set_xlabel("restitution e")
    ax_err.set_ylabel("|lost - exact| [J]")
    ax_err.legend()
    args.png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.png, dpi=110)
    print(f"wrote {args.png}")


if __name__ == "__main__":
    main()
