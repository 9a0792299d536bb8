"""A large pile of free cubes under the compiled step alone, against MuJoCo on the same pile (issue 24's 1000-box
pile; benchmarks.scaling runs the Python step beside the compiled one, which takes hours at that size).

    python -m benchmarks.big_pile --boxes 1000 --out docs/bench   # ~25 min CPU at 1000 boxes
    python -m benchmarks.big_pile --plot docs/bench/big_pile.json  # redraw the chart only

scaling.pile(N) (N cubes dropped into a bin, frictionless, e = 0.1, h = 1 ms, 0.8 s): every step of the compiled
step timed (CPU, ms.step), its contacts and the largest rise of T + V over its start [J]; progress every 50 steps
(the JSON is rewritten as it goes, so an interrupted run keeps what it measured); then MuJoCo's mj_step on the same
pile (scaling.mujoco_run: the last third of the steps timed). Writes big_pile.json and big_pile.png (ms per step
and contacts along the run, MuJoCo's median beside them).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np

import moreau_sim as ms
from moreau_sim import compiled, energy

from . import OUT, add_plot_option, pyplot, redraw
from .scaling import CLOCK, PILE_H, PILE_T, _commit, mujoco_run, peak_rss_mb, pile, pile_steps


def run(n: int, path: Path) -> dict:
    """The compiled pile of n cubes, then MuJoCo's; the JSON written to `path` every 50 steps and at the end."""
    t0 = CLOCK()
    scene = pile(n).with_options(step_impl="compiled")
    model = ms.build_model(scene)
    build = CLOCK() - t0
    why = compiled.unsupported(model)
    if why is not None:
        raise SystemExit(f"error: the compiled step does not take a pile of {n} cubes: {why}")
    data = ms.make_data(model)
    st = ms.initial_state(model, data)
    e0 = energy.total(model, data, st.q, st.u)
    steps = int(round(PILE_T / PILE_H))
    out = {"meta": {"date": time.strftime("%Y-%m-%d", time.gmtime()), "commit": _commit(), "cpus": os.cpu_count(),
                    "load": os.getloadavg()[0], "h": PILE_H, "T": PILE_T},
           "boxes": n, "nv": model.nv, "build_s": build, "energy0": e0, "ms": [], "contacts": [], "gain": 0.0}
    for k, (seconds, m, gain, now) in enumerate(pile_steps(model, data, st, e0)):
        out["ms"].append(seconds * 1e3)
        out["contacts"].append(m)
        out["gain"] = gain
        if k % 50 == 49 or k == steps - 1:
            out.update(steps=k + 1, energy=energy.total(model, data, now.q, now.u),
                       max_speed=float(np.abs(now.u).max()), paths=dict(compiled.counts(data)),
                       peak_rss_mb=peak_rss_mb())
            path.write_text(json.dumps(out), encoding="utf-8")
            print(f"step {k + 1}/{steps}: {out['ms'][-1]:.1f} ms, {out['contacts'][-1]} contacts, "
                  f"largest gain {out['gain']:.2g} J", flush=True)
    out["mujoco"] = mujoco_run("boxes", n, warm=steps - steps // 3, timed=steps // 3)
    path.write_text(json.dumps(out), encoding="utf-8")
    return out


def summary(d: dict) -> str:
    med, mj = statistics.median(d["ms"]), d["mujoco"]["us"] * 1e-3
    return (f"{d['boxes']} cubes (nv {d['nv']}, git {d['meta']['commit']}, load {d['meta']['load']:.1f}): compiled "
            f"{med:.4g} ms a step (median of {d['steps']}; {statistics.median(d['contacts']):.0f} contacts), MuJoCo "
            f"{mj:.4g} ms ({d['mujoco']['contacts']:.0f}): {med / mj:.0f}x; largest energy gain {d['gain']:.2g} J of "
            f"{d['energy0']:.4g} J, {d['energy']:.4g} J at the end, largest |u| at the end {d['max_speed']:.3g}; "
            f"paths {d['paths']}; peak RSS {d['peak_rss_mb']:.0f} MB")


def plot(d: dict, png: Path) -> None:
    plt = pyplot()

    t = (np.arange(len(d["ms"])) + 1) * d["meta"]["h"]
    fig, ax = plt.subplots(figsize=(8, 4.5))
    ax.semilogy(t, d["ms"], ".", ms=2, label="moreau-sim compiled step, ms")
    ax.axhline(d["mujoco"]["us"] * 1e-3, color="tab:green", label="MuJoCo mj_step, ms (median, last third)")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("ms per step (CPU)")
    ax2 = ax.twinx()
    ax2.plot(t, d["contacts"], color="tab:orange", lw=0.8, label="contacts")
    ax2.set_ylabel("contacts")
    lines = ax.get_legend_handles_labels()[0] + ax2.get_legend_handles_labels()[0]
    ax.legend(lines, [h.get_label() for h in lines], fontsize=8, loc="upper left")
    ax.set_title(f"{d['boxes']} cubes dropped into a bin, h = {d['meta']['h']} s (git {d['meta']['commit']})",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--boxes", type=int, default=1000, help="cubes in the pile")
    ap.add_argument("--out", default=str(OUT), help="output folder (docs/bench: the committed files)")
    add_plot_option(ap, "big_pile.json")
    a = ap.parse_args(argv)
    if redraw(a, plot):
        return 0
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    d = run(a.boxes, out / "big_pile.json")
    plot(d, out / "big_pile.png")
    print(summary(d))
    print(f"wrote {out / 'big_pile.json'} and {out / 'big_pile.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
