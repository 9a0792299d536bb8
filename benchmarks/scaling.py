"""Scale: columns of 10 to 10,000 beads and piles of 8 to 1000 free boxes, against MuJoCo (issue 24).

A benchmark, not a test. Two families of scenes built in code, each size measured in a child
process of its own (its peak RSS is that size's alone):

- a column of N beads: column_of_beads_100's construction (balls r = 0.1 m, 1 kg, each on a vertical
  prismatic joint, over the ground; e = 0.9, h = 5e-4) started touching, with no [collisions] list:
  the model has N (N - 1) / 2 + N pairs, above model.LAZY_PAIRS never listed (moreau_sim/pair_table.py),
  and the detection's broad phase (moreau_sim/broad_phase.py) keeps the neighbours. Every step of a
  short run from rest closes all N contacts. `ms.step` is timed on those states (best of `repeat` per
  state, median over states) with each step_impl, saying which path took the steps (compiled.counts);
- a pile of N free 0.1 m cubes (1 kg) dropped from a grid into a bin (the ground and four walls,
  half-spaces), e = 0.1, h = 1e-3, run for T seconds with the Python step and, where a Data of the whole
  model fits, with the compiled step (which hands back the steps it does not take: compiled.counts; the two
  runs must end in the same state, bit for bit): every step timed, the contacts counted, the total energy
  checked against its start (no gain), and the largest |u| at the end (at rest?).

For each: the model's build time (build_model), the Data's (make_data), the peak RSS of the child
after stepping, and MuJoCo (peers.mujoco's soft contacts, condim 1) on the same scene in the same
child: mj_step timed in a Python loop after the same warm-up, its contact count (ncon). Sizes whose
Pinocchio Data would take more than half the free memory (32 nv^3 bytes, stack-of-tasks/pinocchio#2949)
are not run with the compiled step (it needs a Data of the whole model); the Python step runs on the
forest of the bodies' own models (moreau_sim/trees.py) at every size, with coal queried pair by pair
on the broad phase's candidates (no GeometryModel of the pairs). Columns over LARGE beads are timed on
fewer states (3, best of 1). The peak RSS is also taken right after build_model. Also the impact QP alone
(no model) to 3000 beads. The slope of log(cost) against log(contacts) is fitted by least squares
(target <= 1.1: linear).
Writes scaling.json and scaling.png to out/ (--out docs/bench: the committed files). --build-only measures
build_model alone (CPU seconds, peak RSS), each size in --repeat children: scaling_build.json, its own table.

    python -m benchmarks.scaling [--out docs/bench] [--sizes 10 100 500] [--boxes 8 27] [--mujoco-boxes 125 1000]
    python -m benchmarks.scaling --table docs/bench/scaling.json docs/benchmarks.md
    python -m benchmarks.scaling --plot docs/bench/scaling.json   # redraw the chart from the JSON
    python -m benchmarks.scaling --build-only --repeat 2 --boxes 1000 --out docs/bench   # build_model alone
    python -m benchmarks.scaling --runs --sizes 10 100 300 1000 3000 --out docs/bench   # whole runs, both run loops
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pinocchio as pin

import moreau_sim as ms
from moreau_sim import compiled, energy, qp
from moreau_sim.recording import versions

from . import OUT, REPO, add_plot_option, add_table_option, pyplot, redraw, rewrite_tables

CLOCK = time.process_time  # CPU time of this process: the shared 2-core machine runs at load 5-15


def best(f, repeat: int) -> float:
    """The least CPU time of `repeat` calls of f, us."""
    out = []
    for _ in range(repeat):
        t0 = CLOCK()
        f()
        out.append(CLOCK() - t0)
    return min(out) * 1e6


SIZES = (10, 30, 100, 300, 1000, 3000, 10000)
LARGE = 1000  # above this many beads: fewer states and repeats (a step takes seconds)
BOXES = (8, 27, 64, 125, 343)  # MuJoCo's 1000-box pile: over 8 min for its 800 steps here
QP_SIZES = (100, 300, 1000, 3000)
TARGET_SLOPE = 1.1
IMPLS = ("compiled", "python")
NAMES = {"compiled": "compiled", "python": "Python", "mujoco": "MuJoCo mj_step"}
CUBE = 0.1  # [m] side of the pile's cubes (models/cube.urdf: 1 kg, I = m s^2 / 6)
SPACING = 0.18  # [m] the pile's grid (more than a cube's diagonal, 0.173 m: tilted neighbours stay apart)
PILE_H, PILE_E, PILE_T = 1e-3, 0.1, 0.8


def column(n: int, *, step_impl: str = "compiled") -> ms.Scene:
    """A column of n touching beads on vertical prismatic joints over the ground (no exclusions)."""
    b = ms.SceneBuilder(f"column_of_beads_{n}", folder=REPO / "scenes", restitution=0.9, dt=5e-4, duration=0.01,
                        step_impl=step_impl,
                        description=f"{n} beads (column_of_beads_100's construction), touching, from rest")
    for k in range(n):
        b.add_body(f"bead{k}", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1), q0=[0.1 + 0.2 * k])
    b.add_halfspace("ground")
    return b.build()


def pile_layout(n: int) -> tuple[list, float]:
    """Positions and rpy of n cubes on a k x k grid of layers (seeded small tilts), and the bin's half-width."""
    k = int(np.ceil(n ** (1 / 3)))
    rng = np.random.default_rng(n)
    out = []
    for i in range(n):
        z, rest = divmod(i, k * k)
        y, x = divmod(rest, k)
        out.append(((x - (k - 1) / 2) * SPACING, (y - (k - 1) / 2) * SPACING, 0.1 + z * SPACING,  # 0.1 > diagonal / 2
                    tuple(rng.uniform(-0.3, 0.3, 3))))
    return out, k * SPACING / 2 + CUBE / 2


WALLS = (((1.0, 0.0, 0.0), "x0"), ((-1.0, 0.0, 0.0), "x1"), ((0.0, 1.0, 0.0), "y0"), ((0.0, -1.0, 0.0), "y1"))


def pile(n: int) -> ms.Scene:
    """n free cubes dropped into a bin: the ground and four walls (half-spaces), frictionless."""
    layout, half = pile_layout(n)
    b = ms.SceneBuilder(f"box_pile_{n}", folder=REPO / "scenes", restitution=PILE_E, dt=PILE_H, duration=PILE_T,
                        step_impl="python", description=f"{n} cubes dropped into a bin")
    for i, (x, y, z, rpy) in enumerate(layout):
        b.add_body(f"box{i}", "../models/cube.urdf", root_joint="free", position=(x, y, z), rpy=rpy)
    b.add_halfspace("ground")
    for normal, name in WALLS:
        b.add_halfspace(f"wall_{name}", normal=normal, offset=-half)
    return b.build()


def mujoco_xml(kind: str, n: int) -> tuple[str, float]:
    """The same column or pile for MuJoCo (peers.mujoco's MJCF and contact settings), and its step h."""
    from .peers import mujoco as mj

    if kind == "beads":
        h, e = 5e-4, 0.9
        bodies = [{"shape": "sphere", "radius": 0.1, "mass": 1.0, "inertia": [0.004] * 3, "joint": "slide",
                   "origin": [0.0, 0.0, 0.1 + 0.2 * k], "axis": [0.0, 0.0, 1.0]} for k in range(n)]
        statics = [{"shape": "halfspace", "normal": [0.0, 0.0, 1.0], "offset": 0.0}]
    else:
        h, e = PILE_H, PILE_E
        layout, half = pile_layout(n)
        bodies = []
        for x, y, z, rpy in layout:
            qx, qy, qz, qw = pin.Quaternion(pin.rpy.rpyToMatrix(*rpy)).coeffs()
            bodies.append({"shape": "box", "half_extents": [CUBE / 2] * 3, "mass": 1.0,
                           "inertia": [CUBE ** 2 / 6] * 3, "joint": "free", "pos": [x, y, z], "quat": [qw, qx, qy, qz]})
        statics = [{"shape": "halfspace", "normal": [0.0, 0.0, 1.0], "offset": 0.0}]
        statics += [{"shape": "halfspace", "normal": list(nrm), "offset": -half} for nrm, _ in WALLS]
    P = mj.merge_params("mujoco", mj.DEFAULTS, {})
    spec = {"h": h, "gravity": [0.0, 0.0, -9.81], "statics": statics, "bodies": bodies}
    return mj.xml(spec, P, mj.contact_settings(e, h, P)), h


def mujoco_run(kind: str, n: int, warm: int, timed: int) -> dict:
    """mj_step in a Python loop: `warm` steps, then `timed` steps each timed; median us and ncon."""
    import mujoco

    xml, h = mujoco_xml(kind, n)
    t0 = CLOCK()
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    build = CLOCK() - t0
    for _ in range(warm):
        mujoco.mj_step(m, d)
    times, ncon = [], []
    for _ in range(timed):
        t = CLOCK()
        mujoco.mj_step(m, d)
        times.append(CLOCK() - t)
        ncon.append(d.ncon)
    return {"us": statistics.median(times) * 1e6, "contacts": statistics.median(ncon), "build_s": build,
            "version": mujoco.__version__}


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def beads_one(n: int, repeat: int, n_states: int) -> dict:
    """One column size, in this process: build, Data, steps of both step_impls, peak RSS, then MuJoCo.
    The Python step runs on the forest (moreau_sim/trees.py: no Data of the whole model) at every size
    built; the compiled step where it takes the model (compiled.unsupported: since it runs on the forest too, no Data
    of the whole model is needed; its dense M and M^-1 must fit the memory limit)."""
    out = {"beads": n}
    why = None
    if n > LARGE:
        repeat, n_states = 1, min(n_states, 3)
    if why is None:
        t0 = CLOCK()
        scene = column(n)
        out["scene_s"], t0 = CLOCK() - t0, CLOCK()
        base = ms.build_model(scene)
        out["build_s"] = CLOCK() - t0
        big = compiled.unsupported(base)
        impls = IMPLS if big is None else ("python",)
        out["build_rss_mb"] = peak_rss_mb()
        t0 = CLOCK()
        data = ms.make_data(base)
        out["data_s"] = CLOCK() - t0
        models = {"compiled": base, "python": copy.copy(base)}  # the same model but for step_impl
        object.__setattr__(models["python"], "scene", base.scene.with_options(step_impl="python"))
        st, states = ms.initial_state(models["python"], data), []
        for _ in range(n_states):
            r = ms.step(models["python"], data, st)
            if not r.qp or not r.qp.ok:
                raise RuntimeError(f"{n} beads: the step at t = {st.t} failed ({r.qp and r.qp.status})")
            states.append((st, r.contacts.m))
            st = r.state
        from moreau_sim import broad_phase

        bp = broad_phase.of(base, max(base.options.contact_tolerance, ms.data.GATE_MARGIN))
        base.forest.place(data.kinematics, states[-1][0].q)
        out.update(nv=base.nv, pairs=len(base.pairs), listed=base.listed,
                   contacts=statistics.median(m for _, m in states),
                   candidates=len(bp.candidates(data)) if bp else len(base.pairs), states=len(states))
        if big is not None:
            out["compiled"] = {"skipped": big}
        for impl in impls:
            model = models[impl]
            ms.step(model, data, states[0][0])  # the compiled stepper is set up at its first step: not timed
            times = [best(lambda st=st, model=model: ms.step(model, data, st), repeat) for st, _ in states]
            paths = dict(compiled.counts(data)) if impl == "compiled" else {"python": repeat * len(states)}
            out[impl] = {"us": statistics.median(times), "paths": paths}
        out["peak_rss_mb"] = peak_rss_mb()
        del data, models, base
    else:
        out["skipped"] = why
    out["mujoco"] = mujoco_run("beads", n, warm=200, timed=200) if n <= LARGE else mujoco_run("beads", n, 20, 10)
    return out


def forest_one(n: int, repeat: int) -> dict:
    """The model part of a column of n beads without its pairs (no collision pairs are made: those are
    issue 24 item 2), in this process: each body read and placed, the forest (moreau_sim/trees.py) and
    the whole model assembled (trees.whole_model), the trees' Datas, and the forest's dynamics of one step
    (M^-1 and the free acceleration at q0): CPU times and the peak RSS."""
    from moreau_sim.bodies import load_body
    from moreau_sim.trees import Forest, Kinematics, whole_model

    sc = column(n)
    t0 = CLOCK()
    placed = []
    for i, body in enumerate(sc.bodies):
        m, g, _, _ = load_body(body, f"[[bodies]][{i}]")
        placed.append((*pin.appendModel(pin.Model(), m, pin.GeometryModel(), g, 0, pin.SE3.Identity()), body.name))
    t1 = CLOCK()
    forest = Forest.of_placed([tm for tm, _, _ in placed], sc.options.gravity)
    t2 = CLOCK()
    whole = whole_model(placed, "column")[0]
    t3 = CLOCK()
    kin = Kinematics(forest)
    kin.datas()
    t4 = CLOCK()
    q = np.concatenate([pin.neutral(tm) for tm, _, _ in placed])
    u, tau = np.zeros(forest.nv), np.zeros(forest.nv)
    acc = best(lambda: forest.acceleration(kin, q, u, tau), repeat)
    blocks = best(lambda: forest.mass_blocks(kin, q), repeat)
    return {"beads": n, "nv": forest.nv, "bodies_s": t1 - t0, "forest_s": t2 - t1, "whole_model_s": t3 - t2,
            "whole_model_nv": whole.nv, "datas_s": t4 - t3, "aba_us": acc, "mass_blocks_us": blocks,
            "peak_rss_mb": peak_rss_mb()}


def boxes_one(n: int) -> dict:
    """One pile size, in this process: build, Data, a run of PILE_T s with every step timed, then MuJoCo."""
    out = {"boxes": n}
    why = None  # the Python step only: on the forest (moreau_sim/trees.py), no Data of the whole model
    if why is None:
        t0 = CLOCK()
        scene = pile(n)
        out["scene_s"], t0 = CLOCK() - t0, CLOCK()
        model = ms.build_model(scene)
        out["build_s"] = CLOCK() - t0
        t0 = CLOCK()
        data = ms.make_data(model)
        out["data_s"] = CLOCK() - t0
        st0 = ms.initial_state(model, data)
        e0 = energy.total(model, data, st0.q, st0.u)
        py = _pile_run(model, data, st0, e0)
        out.update(nv=model.nv, pairs=len(model.pairs), steps=py["steps"], us=py["us"],
                   us_last_third=py["us_last_third"], contacts=py["contacts"],
                   contacts_last_third=py["contacts_last_third"], energy0=e0, max_energy_gain=py["max_energy_gain"],
                   final_max_speed=py["final_max_speed"])
        fast = ms.build_model(pile(n).with_options(step_impl="compiled"))
        big = compiled.unsupported(fast)
        if big is None:  # the compiled step on the same model: its own Data, the steps it takes counted
            fdata = ms.make_data(fast)
            c = _pile_run(fast, fdata, ms.initial_state(fast, fdata), e0)
            c["paths"] = dict(compiled.counts(fdata))
            q, u = c.pop("q"), c.pop("u")
            c["same_as_python"] = bool(np.array_equal(q, py["q"]) and np.array_equal(u, py["u"]))
            out["compiled"] = c
            del fdata
        else:
            out["compiled"] = {"skipped": big}
        out["peak_rss_mb"] = peak_rss_mb()
        del data, model
    else:
        out["skipped"] = why
    steps = int(round(PILE_T / PILE_H))
    out["mujoco"] = mujoco_run("boxes", n, warm=steps - steps // 3, timed=steps // 3)
    return out


def pile_steps(model, data, st, e0: float):
    """The pile's run of PILE_T s from st, a step at a time: (the step's CPU seconds, its contacts with corners, the
    largest rise of T + V over e0 so far [J], the state after it)."""
    gain = 0.0
    for _ in range(int(round(PILE_T / PILE_H))):
        t = CLOCK()
        r = ms.step(model, data, st)
        seconds = CLOCK() - t
        st = r.state
        gain = max(gain, energy.total(model, data, st.q, st.u) - e0)
        yield seconds, r.contacts.m + len(r.contacts.corners), gain, st


def _pile_run(model, data, st, e0: float) -> dict:
    """The pile's run of PILE_T s from st, every step timed (CPU): per step medians [us], contacts (with corners),
    the largest rise of T + V over e0 [J], the largest |u| at the end, and the final q, u."""
    run = list(pile_steps(model, data, st, e0))
    times, contacts = [r[0] for r in run], [r[1] for r in run]
    gain, st = run[-1][2:]
    third = len(times) // 3
    return {"steps": len(times), "us": statistics.median(times) * 1e6,
            "us_last_third": statistics.median(times[-third:]) * 1e6, "contacts": statistics.median(contacts),
            "contacts_last_third": statistics.median(contacts[-third:]), "max_energy_gain": gain,
            "final_max_speed": float(np.abs(st.u).max()), "q": st.q, "u": st.u}


def build_one(kind: str, n: int) -> dict:
    """One build_model of a column of n beads or a pile of n boxes, in this process: CPU seconds, peak RSS."""
    t0 = CLOCK()
    scene = column(n) if kind == "beads" else pile(n)
    scene_s, t0 = CLOCK() - t0, CLOCK()
    model = ms.build_model(scene)
    return {kind: n, "scene_s": scene_s, "build_s": CLOCK() - t0, "build_rss_mb": peak_rss_mb(), "nv": model.nv,
            "pairs": len(model.pairs)}


def builds(kind: str, sizes, repeat: int) -> list:
    """build_one of each size in `repeat` child processes of its own: the least CPU time, the largest peak RSS."""
    rows = []
    for n in sizes:
        runs = [child(f"build-{kind}", n, argparse.Namespace(repeat=1, states=1)) for _ in range(repeat)]
        ok = [r for r in runs if "failed" not in r]
        row = ({**min(ok, key=lambda r: r["build_s"]), "build_rss_mb": max(r["build_rss_mb"] for r in ok),
                "runs": [r["build_s"] for r in ok]} if ok else runs[0])
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def runs_one(n: int, steps: int, rounds: int) -> dict:
    """Whole runs (ms.simulate: the steps and the records, a gap per geometry above model.LAZY_PAIRS pairs) of a
    column of n beads from rest, `steps` steps, in this process: CPU per call with the Python run loop and the
    compiled one, interleaved over `rounds` rounds (medians), the same arrays asserted; peak RSS."""
    model = ms.build_model(column(n).with_options(duration=steps * 5e-4))
    times: dict[bool, list] = {True: [], False: []}
    ref, loop = None, None
    for r in range(rounds):
        for python_run in (True, False) if r % 2 == 0 else (False, True):
            t0 = CLOCK()
            traj = ms.simulate(model, progress=False, python_run=python_run)
            times[python_run].append(CLOCK() - t0)
            if not python_run:
                loop = traj.meta["run"]["loop"]
            if ref is None:
                ref = traj
            elif any(ref.arrays[k].tobytes() != traj.arrays[k].tobytes() for k in ref.arrays):
                raise AssertionError(f"{n} beads: the two run loops' arrays differ")
    med = {k: statistics.median(v) for k, v in times.items()}
    return {"beads": n, "pairs": len(model.pairs), "listed": model.listed, "gap_columns": int(ref.gap.shape[1]),
            "steps": steps, "rounds": rounds, "python_loop_s": med[True], "compiled_loop_s": med[False],
            "compiled_loop": loop, "python_us_per_step": med[True] / steps * 1e6,
            "compiled_us_per_step": med[False] / steps * 1e6, "peak_rss_mb": peak_rss_mb()}


def runs_table(data: dict) -> str:
    """The whole-run table of docs/benchmarks.md from a scaling_runs.json (--runs)."""
    meta = data["meta"]
    out = [f"Run of {meta['date']} (git `{meta['commit']}`, {meta['cpus']} cores shared, load {meta['load']:.1f}): "
           f"`ms.simulate` of a column from rest, {meta['steps']} steps of 0.5 ms with a sample each, the Python run "
           f"loop and the compiled one interleaved in one child process per size ({meta['rounds']} rounds, medians "
           "of the CPU per call; the two loops' arrays the same bit for bit), its peak RSS.", "",
           "| beads | pairs (model) | gap columns | Python run loop µs/step | compiled run loop µs/step | ratio | "
           "peak RSS MB |", "|---:|---:|---:|---:|---:|---:|---:|"]
    for r in data["beads"]:
        if "failed" in r:
            out.append(f"| {r['beads']} | failed: {r['failed']} | | | | | |")
            continue
        out.append(f"| {r['beads']} | {r['pairs']} | {r['gap_columns']} | {r['python_us_per_step']:.0f} | "
                   f"{r['compiled_us_per_step']:.0f} | {r['python_us_per_step'] / r['compiled_us_per_step']:.1f} | "
                   f"{r['peak_rss_mb']:.0f} |")
    ok = [r for r in data["beads"] if "failed" not in r]
    if len(ok) >= 2:
        x = [r["beads"] for r in ok]
        out += ["", f"Fitted log-log slope against beads, {x[0]}–{x[-1]}: Python run loop "
                f"{slope(x, [r['python_us_per_step'] for r in ok]):.2f}, compiled run loop "
                f"{slope(x, [r['compiled_us_per_step'] for r in ok]):.2f}."]
    return "\n".join(out)


def plot_runs(data: dict, png: Path) -> None:
    """Whole-run cost per step against beads, both run loops, log-log."""
    plt = pyplot()
    ok = [r for r in data["beads"] if "failed" not in r]
    fig, ax = plt.subplots(figsize=(7, 4.5), constrained_layout=True)
    x = [r["beads"] for r in ok]
    for key, label, fmt in (("python_us_per_step", "Python run loop", "o-"),
                            ("compiled_us_per_step", "compiled run loop", "s-")):
        y = [r[key] for r in ok]
        ax.loglog(x, y, fmt, label=f"{label} (slope {slope(x, y):.2f})")
    ax.set_xlabel("beads (contacts)")
    ax.set_ylabel("CPU per step of ms.simulate [µs]")
    ax.set_title(f"column of beads from rest, whole runs ({data['meta']['steps']} steps, a sample each)")
    ax.grid(True, which="both", lw=0.3, alpha=0.5)
    ax.legend()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def build_table(data: dict) -> str:
    """The build table of docs/benchmarks.md from a scaling_build.json (--build-only)."""
    meta = data["meta"]
    out = [f"Run of {meta['date']} (git `{meta['commit']}`, {meta['cpus']} cores shared, load {meta['load']:.1f}): "
           f"CPU seconds of `build_model`, the least of {meta['repeat']} child processes per size, and the "
           "largest peak RSS of those children (the interpreter and its imports included).", "",
           "| scene | size | nv | pairs (model) | scene s (SceneBuilder) | build_model s | peak RSS MB |",
           "|---|---:|---:|---:|---:|---:|---:|"]
    for kind, label in (("beads", "column of beads"), ("boxes", "pile of boxes")):
        for r in data[kind]:
            if "failed" in r:
                out.append(f"| {label} | {r[kind]} | failed: {r['failed']} | | | | |")
                continue
            out.append(f"| {label} | {r[kind]} | {r['nv']} | {r['pairs']} | {_f(r.get('scene_s'))} | "
                       f"{r['build_s']:.3g} | {r['build_rss_mb']:.0f} |")
    b = [r for r in data["beads"] if "failed" not in r]
    large = [r for r in b if r["beads"] >= LARGE]
    if len(b) >= 2:
        out += ["", f"Fitted log-log slope of build_model against beads, {b[0]['beads']}–{b[-1]['beads']}: "
                f"{slope([r['beads'] for r in b], [r['build_s'] for r in b]):.2f}"
                + (f"; from {LARGE}: {slope([r['beads'] for r in large], [r['build_s'] for r in large]):.2f}"
                   if len(large) >= 2 else "") + "."]
    return "\n".join(out)


def child(kind: str, n: int, a) -> dict:
    """One size measured in a child process (its own peak RSS); a failure is recorded, not raised."""
    cmd = [sys.executable, "-m", "benchmarks.scaling", "--one", kind, str(n), "--repeat", str(a.repeat),
           "--states", str(a.states), "--steps", str(getattr(a, "steps", 40)), "--rounds", str(getattr(a, "rounds", 5))]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    if r.returncode != 0:
        tail = (r.stderr.strip().splitlines() or ["no output"])[-1]
        return {"beads" if kind.endswith("beads") else "boxes": n, "failed": tail}
    return json.loads(r.stdout.strip().splitlines()[-1])


def qp_alone(n: int, repeat: int) -> dict:
    """The impact QP of a resting column of n unit beads built without a model (M = I, the column's rows, every
    bead at -g h): qp.solve as the stepper calls it, best of `repeat`."""
    W = np.zeros((n, n), order="F")
    W[0, 0] = 1.0
    k = np.arange(1, n)
    W[k, k], W[k - 1, k] = 1.0, -1.0
    M, v0 = np.eye(n), np.full(n, -9.81 * 5e-4)
    r = qp.solve(M, W, v0, Minv=M)
    return {"beads": n, "us": best(lambda: qp.solve(M, W, v0, Minv=M), repeat), "status": r.status,
            "polished": bool(r.polished)}


def slope(x, y) -> float:
    """Least-squares slope of log(y) against log(x) (nan with fewer than 2 points)."""
    if len(x) < 2:
        return float("nan")
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


def measured(rows: list) -> list:
    return [r for r in rows if "skipped" not in r and "failed" not in r]


def warm_rows(data: dict) -> int:
    """qp.WARM_ROWS of the run: above it a step without a start (the first) goes to the Python step's sparse path,
    and before stop 43 every step did ("compiled_limit" in older files)."""
    return data.get("warm_rows", data.get("compiled_limit"))


def slopes(data: dict) -> dict:
    b, p = measured(data["beads"]), measured(data["boxes"])
    out = {impl: slope([r["contacts"] for r in b if "us" in r[impl]], [r[impl]["us"] for r in b if "us" in r[impl]])
           for impl in IMPLS}
    above = [r for r in b if r["contacts"] > warm_rows(data)]
    out["python_above_warm_rows"] = slope([r["contacts"] for r in above], [r["python"]["us"] for r in above])
    mb = [r for r in data["beads"] if "mujoco" in r]
    out["mujoco_beads"] = slope([r["beads"] for r in mb], [r["mujoco"]["us"] for r in mb])
    out["build_beads"] = slope([r["beads"] for r in b], [r["build_s"] for r in b])
    out["pile"] = slope([r["boxes"] for r in p], [r["us"] for r in p])
    pc = [r for r in p if "us" in r.get("compiled", {})]
    out["pile_compiled"] = slope([r["boxes"] for r in pc], [r["compiled"]["us"] for r in pc]) if len(pc) >= 2 else None
    mp = [r for r in data["boxes"] if "mujoco" in r]
    out["mujoco_pile"] = slope([r["boxes"] for r in mp], [r["mujoco"]["us"] for r in mp])
    return out


def plot(data: dict, png: Path) -> None:
    if data.get("meta", {}).get("runs"):  # a scaling_runs.json (--runs)
        return plot_runs(data, png)
    plt = pyplot()

    s = data["slopes"]
    fig, (a1, a2, a3) = plt.subplots(1, 3, figsize=(16, 6), layout="constrained")
    b = measured(data["beads"])
    n = np.array([r["beads"] for r in b], float)

    def fitted(ax, x, y, fmt, label, **kw):
        line, = ax.loglog(x, y, fmt, label=label, **kw)
        if len(x) >= 2:
            c, t0 = np.polyfit(np.log(x), np.log(y), 1)
            ax.loglog(x, np.exp(t0) * np.asarray(x) ** c, "-", lw=0.8, color=line.get_color())

    for impl, fmt in zip(IMPLS, ("o", "s")):
        x = [k for k, r in zip(n, b) if "us" in r[impl]]
        fitted(a1, x, [r[impl]["us"] * 1e-3 for r in b if "us" in r[impl]], fmt,
               f"moreau-sim, {NAMES[impl]} step: slope {s[impl]:.2f}")
    mb = [r for r in data["beads"] if "mujoco" in r]
    fitted(a1, [r["beads"] for r in mb], [r["mujoco"]["us"] * 1e-3 for r in mb], "^",
           f"{NAMES['mujoco']}: slope {s['mujoco_beads']:.2f}")
    qa = data.get("qp_alone") or []
    if qa:
        a1.loglog([r["beads"] for r in qa], [r["us"] * 1e-3 for r in qa], "v:", color="grey",
                  label="impact QP alone (no model)")
    for r in data["beads"]:
        if "skipped" in r:
            a1.axvline(r["beads"], color="red", lw=0.6, ls="--")
    a1.axvline(warm_rows(data) + 0.5, color="grey", lw=0.8, ls="-.")
    a1.set_xlabel("beads N (= contacts)")
    a1.set_ylabel("ms per step")
    a1.set_title(f"column of N touching beads (red dashes: not built)\n"
                 f"target slope ≤ {TARGET_SLOPE}; dash-dot: {warm_rows(data)} contacts (above: cold steps handed back)",
                 fontsize=9)
    p = measured(data["boxes"])
    mp = [r for r in data["boxes"] if "mujoco" in r]
    fitted(a2, [r["boxes"] for r in p], [r["us"] * 1e-3 for r in p], "s",
           f"moreau-sim, Python step: slope {s['pile']:.2f}")
    pc = [r for r in p if "us" in r.get("compiled", {})]
    if pc:
        fitted(a2, [r["boxes"] for r in pc], [r["compiled"]["us"] * 1e-3 for r in pc], "o",
               "moreau-sim, compiled step" + (f": slope {s['pile_compiled']:.2f}" if s.get("pile_compiled") else ""))
    fitted(a2, [r["boxes"] for r in mp], [r["mujoco"]["us"] * 1e-3 for r in mp], "^",
           f"{NAMES['mujoco']}: slope {s['mujoco_pile']:.2f}")
    for r in data["boxes"]:
        if "skipped" in r:
            a2.axvline(r["boxes"], color="red", lw=0.6, ls="--")
    a2.set_xlabel("boxes N")
    a2.set_ylabel("ms per step (median over the run)")
    a2.set_title(f"a pile of N cubes dropped into a bin, {PILE_T} s at h = {PILE_H}\n(red dashes: not built)",
                 fontsize=9)
    fitted(a3, n, [r["build_s"] for r in b], "o", f"beads: build_model s (slope {s['build_beads']:.2f})")
    if all("scene_s" in r for r in b):  # what a user waits for: the SceneBuilder's scene, then build_model
        a3.loglog(n, [r["scene_s"] + r["build_s"] for r in b], "s:", label="beads: scene + build_model s")
    a3.loglog(n, [r["data_s"] for r in b], "o--", label="beads: make_data s")
    a3.loglog(n, [r["peak_rss_mb"] / 1024 for r in b], "d-", label="beads: peak RSS GB (after stepping)")
    a3.loglog(n, [r["build_rss_mb"] / 1024 for r in b if "build_rss_mb" in r], "d--",
              label="beads: peak RSS GB after build_model")
    if p:
        a3.loglog([r["boxes"] * 6 for r in p], [r["peak_rss_mb"] / 1024 for r in p], "d:",
                  label="pile: peak RSS GB (at nv = 6 N)")
    a3.set_xlabel("nv")
    a3.set_ylabel("s / GB")
    a3.set_title("model building and memory\n(a forest, the pairs a table; target at 10,000 beads: 5 s, 1 GB)",
                 fontsize=9)
    for ax in (a1, a2, a3):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.savefig(png, dpi=100)


def _f(x, fmt="{:.3g}") -> str:
    return "–" if x is None else fmt.format(x)


def markdown_table(data: dict) -> str:
    """The scaling tables of docs/benchmarks.md from a scaling.json."""
    meta, s = data["meta"], data["slopes"]
    out = [f"Run of {meta['date']} (git `{meta['commit']}`, OPENBLAS_NUM_THREADS={meta.get('OPENBLAS_NUM_THREADS')}, "
           f"{meta['cpus']} cores shared, load {meta['load']:.1f}; MuJoCo {meta.get('mujoco', '?')}): µs per step. "
           f"Beads: median over {meta['states']} contact states of the best of {meta['repeat']}; pile: median over "
           f"the run's {int(round(PILE_T / PILE_H))} steps; MuJoCo: median of `mj_step` timed in a Python loop "
           "after the same warm-up. Peak RSS of a child process per size (moreau-sim's part, before MuJoCo runs).",
           "", "| beads | pairs (model) | broad-phase candidates | contacts | compiled | paths (compiled) | Python | "
           "MuJoCo (ncon) | scene s (SceneBuilder) | build_model s | make_data s | peak RSS MB after build_model | "
           "peak RSS MB |",
           "|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in data["beads"]:
        mj = r.get("mujoco")
        mjs = f"{mj['us']:.1f} ({mj['contacts']:.0f})" if mj else "–"
        if "skipped" in r or "failed" in r:
            why = r.get("skipped") or f"failed: {r['failed']}"
            out.append(f"| {r['beads']} | not built: {why} | | | | | | {mjs} | | | | | |")
            continue
        c = r["compiled"]
        paths = ", ".join(f"{k}: {v}" for k, v in sorted(c.get("paths", {}).items())) or "no Data of the whole model"
        us = f"{c['us']:.1f}" if "us" in c else "–"
        out.append(f"| {r['beads']} | {r['pairs']} | {r['candidates']} | {r['contacts']:.0f} | "
                   f"{us} | {paths} | {r['python']['us']:.1f} | {mjs} | {_f(r.get('scene_s'))} | {r['build_s']:.3g} | "
                   f"{r['data_s']:.3g} | {_f(r.get('build_rss_mb'), '{:.0f}')} | {r['peak_rss_mb']:.0f} |")
    out += ["", "| boxes | nv | pairs (model) | contacts (median; last third) | Python step | last third | "
            "compiled step (paths; same bits as Python) | MuJoCo (ncon) | ratio ours / MuJoCo (Python; compiled) | "
            "max energy gain J (E0) | max \\|u\\| at the end | scene s | build_model s | make_data s | peak RSS MB |",
            "|---:|---:|---:|---|---:|---:|---|---:|---|---|---:|---:|---:|---:|---:|"]
    for r in data["boxes"]:
        mj = r.get("mujoco")
        mjs = f"{mj['us']:.1f} ({mj['contacts']:.0f})" if mj else "–"
        if "skipped" in r or "failed" in r:
            why = r.get("skipped") or f"failed: {r['failed']}"
            out.append(f"| {r['boxes']} | {6 * r['boxes']} | not built: {why} | | | | | {mjs} | | | | | | | |")
            continue
        c = r.get("compiled") or {"skipped": "not measured"}
        if "us" in c:
            paths = ", ".join(f"{k}: {v}" for k, v in sorted(c["paths"].items()))
            cs = f"{c['us']:.0f} ({paths}; {'yes' if c['same_as_python'] else 'NO'})"
            ratio = f"{r['us'] / mj['us']:.0f}; {c['us'] / mj['us']:.0f}"
        else:
            cs, ratio = f"– ({c['skipped']})", f"{r['us'] / mj['us']:.0f}; –"
        out.append(f"| {r['boxes']} | {r['nv']} | {r['pairs']} | {r['contacts']:.0f}; {r['contacts_last_third']:.0f} | "
                   f"{r['us']:.0f} | {r['us_last_third']:.0f} | {cs} | {mjs} | {ratio} | "
                   f"{r['max_energy_gain']:.2g} ({r['energy0']:.3g}) | {r['final_max_speed']:.2g} | "
                   f"{_f(r.get('scene_s'))} | {r['build_s']:.3g} | {r['data_s']:.3g} | {r['peak_rss_mb']:.0f} |")
    out += ["", f"Fitted log-log slopes: per step against contacts, beads "
            f"{measured(data['beads'])[0]['beads']}–{measured(data['beads'])[-1]['beads']}: compiled "
            f"{s['compiled']:.2f}, Python {s['python']:.2f} (above {warm_rows(data)} contacts: "
            f"{s.get('python_above_warm_rows', s.get('python_above_compiled_limit')):.2f}); "
            f"MuJoCo {s['mujoco_beads']:.2f}; target ≤ "
            f"{TARGET_SLOPE}. build_model against beads: {s['build_beads']:.2f}. " + _pile_slopes(data, s)]
    if data.get("qp_alone"):
        out += ["", "The impact QP alone (the column's rows, M = I, no model; ms per solve): "
                + ", ".join(f"{r['beads']} beads {r['us'] * 1e-3:.2f}" for r in data["qp_alone"]) + "."]
    return "\n".join(out)


def _pile_slopes(data: dict, s: dict) -> str:
    """The pile's slopes, or in words why there are none (fewer than two sizes ran)."""
    ran = [r["boxes"] for r in data["boxes"] if "skipped" not in r and "failed" not in r]
    if len(ran) >= 2:
        c = f", compiled step {s['pile_compiled']:.2f}" if s.get("pile_compiled") is not None else ""
        return f"Pile, per step against boxes: ours (Python step) {s['pile']:.2f}{c}, MuJoCo {s['mujoco_pile']:.2f}."
    failed = [str(r["boxes"]) for r in data["boxes"] if "failed" in r]
    return (f"Pile: no slope, {len(ran)} size ran" + (f"; {', '.join(failed)} boxes failed (the row says how)"
                                                       if failed else "") + ".")


def doc_tables(data: dict) -> dict[str, str]:
    """The tables of docs/benchmarks.md this benchmark's JSON gives (marker name: Markdown): the scaling
    table from a scaling.json, the build table from a scaling_build.json (--build-only)."""
    if data.get("meta", {}).get("build_only"):
        return {"scaling build table": build_table(data)}
    if data.get("meta", {}).get("runs"):
        return {"scaling runs table": runs_table(data)}
    return {"scaling table": markdown_table(data)}


def _commit() -> str:
    r = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=REPO)
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True,
                           cwd=REPO).stdout.strip()
    return (r.stdout.strip() or "unknown") + (" plus uncommitted changes" if dirty else "")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(OUT), help="output folder (docs/bench: the committed files)")
    add_table_option(ap, "scaling.json", "docs/benchmarks.md")
    add_plot_option(ap, "scaling.json")
    ap.add_argument("--sizes", type=int, nargs="*", default=list(SIZES), help="numbers of beads")
    ap.add_argument("--boxes", type=int, nargs="*", default=list(BOXES), help="numbers of boxes of the pile")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--states", type=int, default=10, help="contact states per column (a run of that many steps)")
    ap.add_argument("--qp-sizes", type=int, nargs="*", default=list(QP_SIZES),
                    help="numbers of beads of the QP alone (no Pinocchio Data)")
    ap.add_argument("--build-only", action="store_true",
                    help="only build_model of each size (--sizes beads, --boxes boxes), --repeat child processes "
                         "per size: writes scaling_build.json")
    ap.add_argument("--runs", action="store_true",
                    help="only whole runs (ms.simulate) of each column (--sizes), both run loops, --rounds rounds of "
                         "--steps steps: writes scaling_runs.json and scaling_runs.png")
    ap.add_argument("--steps", type=int, default=40, help="steps of a whole run (--runs)")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds of the two run loops (--runs)")
    ap.add_argument("--one", nargs=2, metavar=("KIND", "N"), help=argparse.SUPPRESS)  # a child: one size, JSON out
    a = ap.parse_args(argv)
    if rewrite_tables(a, doc_tables) or redraw(a, plot):
        return 0
    if a.one:
        kind, n = a.one[0], int(a.one[1])
        r = (beads_one(n, a.repeat, a.states) if kind == "beads" else forest_one(n, a.repeat) if kind == "forest"
             else build_one(kind.removeprefix("build-"), n) if kind.startswith("build-")
             else runs_one(n, a.steps, a.rounds) if kind == "run-beads" else boxes_one(n))
        print(json.dumps(r))
        return 0
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.time()
    if a.build_only:
        load = os.getloadavg()[0]
        data = {"beads": builds("beads", a.sizes, a.repeat), "boxes": builds("boxes", a.boxes, a.repeat)}
        data["meta"] = {"build_only": True, "date": time.strftime("%Y-%m-%d", time.gmtime()), "commit": _commit(),
                        "machine": platform.machine(), "cpus": os.cpu_count(),
                        "load": max(load, os.getloadavg()[0]), "versions": versions(), "repeat": a.repeat,
                        "wall_s": time.time() - t_start}
        (out / "scaling_build.json").write_text(json.dumps(data, indent=2))
        print(build_table(data))
        print(f"wrote {out / 'scaling_build.json'}")
        return 0
    if a.runs:
        load = os.getloadavg()[0]
        rows = []
        for n in a.sizes:
            rows.append(child("run-beads", n, a))
            print(json.dumps(rows[-1]), flush=True)
        data = {"beads": rows, "meta": {"runs": True, "date": time.strftime("%Y-%m-%d", time.gmtime()),
                                        "commit": _commit(), "machine": platform.machine(), "cpus": os.cpu_count(),
                                        "load": max(load, os.getloadavg()[0]), "versions": versions(),
                                        "steps": a.steps, "rounds": a.rounds, "wall_s": time.time() - t_start,
                                        "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS")}}
        (out / "scaling_runs.json").write_text(json.dumps(data, indent=2))
        plot_runs(data, out / "scaling_runs.png")
        print(runs_table(data))
        print(f"wrote {out / 'scaling_runs.json'} and {out / 'scaling_runs.png'}")
        return 0
    beads, boxes = [], []
    for n in a.sizes:
        beads.append(child("beads", n, a))
        print(json.dumps(beads[-1]), flush=True)
    for n in a.boxes:
        boxes.append(child("boxes", n, a))
        print(json.dumps(boxes[-1]), flush=True)
    qp_rows = [qp_alone(n, a.repeat) for n in a.qp_sizes]
    import mujoco

    meta = {"date": time.strftime("%Y-%m-%d", time.gmtime()), "commit": _commit(), "machine": platform.machine(),
            "cpus": os.cpu_count(), "load": os.getloadavg()[0], "versions": versions(), "repeat": a.repeat,
            "states": a.states, "mujoco": mujoco.__version__, "wall_s": time.time() - t_start,
            "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS")}
    data = {"meta": meta, "beads": beads, "boxes": boxes, "warm_rows": qp.WARM_ROWS,
            "target_slope": TARGET_SLOPE, "qp_alone": qp_rows}
    data["slopes"] = slopes(data)
    print("slopes:", {k: (None if v is None else round(v, 3)) for k, v in data["slopes"].items()})
    (out / "scaling.json").write_text(json.dumps(data, indent=2))
    plot(data, out / "scaling.png")
    print(f"wrote {out / 'scaling.json'} and {out / 'scaling.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
