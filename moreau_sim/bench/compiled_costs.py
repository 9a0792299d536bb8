"""Per-step cost of the compiled step against the Python step, side by side in one run.

A benchmark, not a test. For each case the scene is run once (Python step) to collect states; on the
same states one step is timed with step_impl = "compiled" and with step_impl = "python" (ms.step,
best of `repeat` per state, median over states, us), and the share of those states the compiled
step took itself (the rest it hands back to Python). MuJoCo's mj_step on the ball (its runner's
settings, peers.mujoco) is timed in the same run when mujoco is importable. Writes
compiled_costs.json and compiled_costs.png to out/ (or --out).

    python -m moreau_sim.bench.compiled_costs [--out docs/bench] [--repeat 7] [--states 200]
    python -m moreau_sim.bench.compiled_costs --table docs/bench/compiled_costs.json docs/benchmarks.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

import moreau_sim as ms
from moreau_sim import compiled
from moreau_sim.recording import versions

from . import OUT, add_table_option, rewrite_tables, scene_path
from .step_costs import best  # best of `repeat` timings, us

# (label, scene, which states: "flight", "contact", or "late-contact" = the last third of the run's contact states)
CASES = (("ball, flight", "bouncing_ball", "flight"),
         ("ball, in contact (resting)", "zeno_ball", "contact"),
         ("cradle, contacts closed", "newton_cradle_5", "contact"),
         ("box_drop, resting (4 contacts)", "box_drop", "late-contact"))


def bench_case(label: str, scene: str, which: str, repeat: int, n_states: int) -> dict:
    sc = ms.load_scene(scene_path(scene))
    mods = {impl: ms.build_model(sc.with_options(step_impl=impl)) for impl in ("python", "compiled")}
    datas = {impl: ms.make_data(m) for impl, m in mods.items()}
    traj = ms.simulate(mods["python"], progress=False)
    h, e = sc.options.dt, sc.options.restitution
    states = []
    m, d = mods["python"], datas["python"]
    for i in range(len(traj.t) - 1):
        st = ms.State(float(traj.t[i]), traj.q[i], traj.u[i])
        kind = "contact" if ms.step(m, d, st, h=h, e=e).contacts.m else "flight"
        if kind == which.replace("late-", ""):
            states.append(st)
    if which.startswith("late-"):
        states = states[2 * len(states) // 3:]
    states = [states[i] for i in np.unique(np.linspace(0, len(states) - 1, min(n_states, len(states))).astype(int))]
    out = {"label": label, "scene": scene, "which": which, "states": len(states)}
    for impl in ("python", "compiled"):
        m, d = mods[impl], datas[impl]
        t = [best(lambda st=st, m=m, d=d: ms.step(m, d, st, h=h, e=e), repeat) for st in states]
        out[impl] = statistics.median(t)
    c = compiled.counts(datas["compiled"])  # every timed call of the compiled model's step
    out["compiled_share"] = (c["flight"] + c["contact"]) / max(1, sum(c.values()))
    out["ratio"] = out["python"] / out["compiled"]
    return out


def bench_mujoco(repeat: int) -> dict | None:
    """mj_step on the ball (the MuJoCo runner's model and settings): flight and contact medians, us."""
    try:
        import mujoco
    except ImportError:
        return None
    from .peers import mujoco as mj
    from .spec import make_spec, merge_params

    model = ms.build_model(ms.load_scene(scene_path("bouncing_ball")))
    spec = make_spec(model)
    P = merge_params("MuJoCo", mj.DEFAULTS, {})
    mm = mujoco.MjModel.from_xml_string(mj.xml(spec, P, mj.contact_settings(float(spec["e"]), float(spec["h"]), P)))
    md = mujoco.MjData(mm)
    md.qpos[0] = spec["bodies"][0]["q0"]
    n = int(round(float(spec["T"]) / float(spec["h"])))
    times = {"flight": [], "contact": []}
    for _ in range(n):
        kind = "contact" if md.ncon else "flight"
        t0 = time.perf_counter()
        mujoco.mj_step(mm, md)
        times[kind].append((time.perf_counter() - t0) * 1e6)
    return {"version": mujoco.__version__, **{k: statistics.median(v) for k, v in times.items() if v},
            "steps": {k: len(v) for k, v in times.items()}}


def plot(res: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = res["cases"]
    x = np.arange(len(cases))
    fig, ax = plt.subplots(figsize=(8, 3.8))
    ax.bar(x - 0.2, [c["python"] for c in cases], 0.4, label="Python step")
    ax.bar(x + 0.2, [c["compiled"] for c in cases], 0.4, label="compiled step")
    mj = res.get("mujoco")
    if mj:
        for i, c in enumerate(cases):
            key = "flight" if "flight" in c["label"] else "contact"
            if c["scene"] in ("bouncing_ball", "zeno_ball") and key in mj:
                ax.plot([i + 0.2], [mj[key]], "k*", ms=10, label="MuJoCo mj_step" if key == "flight" else None)
    ax.set_xticks(x, [c["label"] for c in cases], fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("µs per step (median)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def markdown_table(res: dict) -> str:
    """The compiled-step table of docs/benchmarks.md from a compiled_costs.json."""
    mj = res.get("mujoco") or {}
    reps = f"the best of {res['repeat']}" if "repeat" in res else "the best of several timings"
    states = sorted({c["states"] for c in res["cases"]})
    out = [f"Medians over {'/'.join(map(str, states))} states of {reps}, µs per step"
           + (f"; MuJoCo {mj['version']}" if mj else "; MuJoCo not installed in that run") + ":", "",
           "| case | Python step | compiled step | Python / compiled | steps taken compiled | MuJoCo mj_step "
           "| compiled / MuJoCo |", "|---|---:|---:|---:|---:|---:|---:|"]
    for c in res["cases"]:
        kind = c.get("which", "flight" if "flight" in c["label"] else "contact").replace("late-", "")
        ref = mj.get(kind) if c["scene"] in ("bouncing_ball", "zeno_ball") else None
        label = f"`{c['scene']}`: {c['label']}"
        vs_mj = ("–", "–") if ref is None else (f"{ref:.2f}", f"{c['compiled'] / ref:.1f}")
        out.append(f"| {label} | {c['python']:.1f} | {c['compiled']:.1f} | {c['python'] / c['compiled']:.1f} | "
                   f"{100 * c['compiled_share']:.1f} % | {vs_mj[0]} | {vs_mj[1]} |")
    return "\n".join(out)


def doc_tables(res: dict) -> dict[str, str]:
    """The tables of docs/benchmarks.md this benchmark's JSON gives (marker name: Markdown)."""
    return {"compiled-step table": markdown_table(res)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--states", type=int, default=200)
    add_table_option(ap, "compiled_costs.json", "docs/benchmarks.md")
    a = ap.parse_args(argv)
    if rewrite_tables(a, doc_tables):
        return
    if not compiled.available():
        raise SystemExit(f"the compiled step is unavailable: {compiled.unavailable_reason()}")
    cases = []
    for label, scene, which in CASES:
        c = bench_case(label, scene, which, a.repeat, a.states)
        print(f"{label:32s} python {c['python']:8.1f} us  compiled {c['compiled']:7.1f} us  "
              f"x{c['ratio']:.1f}  ({c['states']} states)")
        cases.append(c)
    res = {"cases": cases, "mujoco": bench_mujoco(a.repeat), "machine": platform.processor() or platform.machine(),
           "python": platform.python_version(), "cpus": os.cpu_count(), "load": os.getloadavg()[0],
           "repeat": a.repeat, "versions": versions(),
           "note": "us per step, median over states of the best of `repeat` timings"}
    if res["mujoco"]:
        print("MuJoCo mj_step, ball:", {k: res["mujoco"][k] for k in ("flight", "contact") if k in res["mujoco"]})
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "compiled_costs.json").write_text(json.dumps(res, indent=1))
    plot(res, a.out / "compiled_costs.png")
    print(f"wrote {a.out / 'compiled_costs.json'} and .png")


if __name__ == "__main__":
    main()
