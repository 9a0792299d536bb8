"""Whole actuated runs per step against the passive run of the same scene (docs/robots.md#actuation).

A benchmark, not a test. For each scene: the passive run (the scene without its [[actuators]]), the scene's PD
(a zero-gain PD on every joint of its first body where it has none: the passive motion, torques evaluated in the
Runner) and a Python controller returning zeros on top of the scene's own actuators (called back once a step),
each by ms.simulate (recording, ledger and checks included), wall time per step, the best of `repeat` rounds that
run the three in turn; the ratios to the passive run are what counts on a loaded machine. Saves
actuated_costs.json and a bar chart of the ratios, actuated_costs.png (the target: 1.5x), in --out.

    python -m benchmarks.actuated_costs [--repeat 15] [--out docs/bench] [SCENE ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np

import moreau_sim as ms
from moreau_sim.recording import versions
from moreau_sim.scene import Actuator

from . import OUT, add_plot_option, pyplot, redraw, scene_path

SCENES = {"bouncing_ball": 3.0, "pendulum_wall": 3.0, "quadruped_drop": 1.0, "solo12_stand": 2.0,
          "a1_drop_recover": 1.0}  # scene: duration [s]
CASES = ("passive", "pd", "controller")
TARGET = 1.5  # issue 25: an actuated run within 1.5x of the passive run per step


def models(name: str, duration: float) -> dict:
    """The three runs of one scene: case -> (model, simulate's keywords)."""
    sc = ms.load_scene(scene_path(name)).with_options(duration=duration)
    pd = sc if sc.actuators else dataclasses.replace(
        sc, actuators=(Actuator(body=sc.bodies[0].name, joints=None, kp=0.0, where="benchmark"),))
    passive = ms.build_model(dataclasses.replace(sc, actuators=()))
    nv = passive.nv
    return {"passive": (passive, {}), "pd": (ms.build_model(pd), {}),
            "controller": (ms.build_model(sc), {"controller": lambda t, q, u: np.zeros(nv)})}


def measure(names, repeat: int) -> tuple[dict, set]:
    """scene -> case -> best wall time per step [us] (every case of every scene in turn, `repeat` rounds), and the
    loops the runs took (meta run.loop: "compiled" unless the extension is missing)."""
    runs = {n: models(n, SCENES[n]) for n in names}
    best = {n: dict.fromkeys(CASES, np.inf) for n in names}
    loops = set()
    for k in range(repeat + 1):  # round 0 warms up (imports, the extension's first calls), not timed
        for n, cases in runs.items():
            for case, (model, kw) in cases.items():
                t0 = time.perf_counter()
                tr = ms.simulate(model, progress=False, **kw)
                wall = time.perf_counter() - t0
                if k:
                    best[n][case] = min(best[n][case], wall / tr.meta["run"]["steps"] * 1e6)
                loops.add(tr.meta["run"]["loop"])
    return best, loops


def plot(res: dict, png: Path) -> None:
    """Bars: each scene's PD run and zero-controller run per step over its passive run, the target line."""
    plt = pyplot()

    names = list(res["us_per_step"])
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(7.5, 3.6))
    for k, (case, label) in enumerate((("pd", "the scene's PD (torques in the Runner)"),
                                       ("controller", "a zero Python controller (called once a step)"))):
        r = [res["ratios"][n][case] for n in names]
        ax.bar(x + (k - 0.5) * 0.38, r, 0.36, label=label)
    ax.axhline(TARGET, color="k", ls="--", lw=1, label=f"target {TARGET}x")
    ax.axhline(1.0, color="0.5", lw=0.8)
    ax.set_xticks(x, names)
    ax.set_ylabel("per step / passive run")
    ax.set_title(f"actuated whole runs against the passive run (best of {res['repeat']}, load {res['load']:.1f})")
    ax.set_ylim(0, max(TARGET, *(max(v.values()) for v in res["ratios"].values())) * 1.12)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=3, frameon=False)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", help=f"of {list(SCENES)} (default: all)")
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--out", type=Path, default=OUT)
    add_plot_option(ap, "actuated_costs.json")
    args = ap.parse_args(argv)
    if redraw(args, plot):
        return
    unknown = sorted(set(args.scenes) - set(SCENES))
    if unknown:
        ap.error(f"unknown scene(s) {unknown}: choose from {list(SCENES)}")
    best, loops = measure(args.scenes or list(SCENES), args.repeat)
    print(f"{'scene':18s} {'passive':>9s} {'PD':>9s} {'ratio':>6s} {'ctrl':>9s} {'ratio':>6s}   (us per step, best of "
          f"{args.repeat})")
    for n, b in best.items():
        p = b["passive"]
        print(f"{n:18s} {p:9.2f} {b['pd']:9.2f} {b['pd'] / p:6.2f} {b['controller']:9.2f} {b['controller'] / p:6.2f}")
    if loops != {"compiled"}:
        print(f"the runs took the {' and '.join(sorted(loops))} loop(s), not only the compiled one: see meta run.why")
    res = {"us_per_step": best, "ratios": {n: {c: b[c] / b["passive"] for c in CASES} for n, b in best.items()},
           "durations": {n: SCENES[n] for n in best}, "loops": sorted(loops), "repeat": args.repeat,
           "load": os.getloadavg()[0], "cpus": os.cpu_count(), "versions": versions(), "target": TARGET,
           "note": "wall time of ms.simulate per step, best of `repeat` rounds that run the three cases in turn"}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "actuated_costs.json").write_text(json.dumps(res, indent=1))
    plot(res, args.out / "actuated_costs.png")
    print(f"wrote {args.out / 'actuated_costs.json'} and actuated_costs.png")


if __name__ == "__main__":
    main()
