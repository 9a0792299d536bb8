"""Whole actuated runs per step against the passive run of the same scene (docs/robots.md#actuation).

A benchmark, not a test. For each scene: the passive run (the scene without its [[actuators]]), the scene's PD
(a zero-gain PD on every joint of its first body where it has none: the passive motion, torques evaluated in the
Runner) and a Python controller returning zeros on top of the scene's own actuators (called back once a step),
each by ms.simulate (recording, ledger and checks included), wall time per step, the best of `repeat` rounds that
run the three in turn; the ratios to the passive run are what counts on a loaded machine.

    python -m benchmarks.actuated_costs [--repeat 15] [SCENE ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

import moreau_sim as ms
from moreau_sim.scene import Actuator

from . import scene_path

SCENES = {"bouncing_ball": 3.0, "pendulum_wall": 3.0, "quadruped_drop": 1.0, "solo12_stand": 2.0,
          "a1_drop_recover": 1.0}  # scene: duration [s]
CASES = ("passive", "pd", "controller")


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


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", help=f"of {list(SCENES)} (default: all)")
    ap.add_argument("--repeat", type=int, default=15)
    args = ap.parse_args(argv)
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


if __name__ == "__main__":
    main()
