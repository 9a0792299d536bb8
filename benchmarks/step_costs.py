"""Per-step cost of every bundled scene, split into dynamics, collision, QP and Python glue.

A benchmark, not a test. For each scene it runs the simulation once (the Python step,
step_impl = "python") to collect states, then times the Python step on those states (free-flight
steps and contact steps apart), and each stage on the same states:
  dyn   Pinocchio: integrate x 2, the free velocity (ABA; several with Bias.MIDPOINT when the
        bias depends on u), + CRBA and M^-1 in contact steps
  coll  coal through Pinocchio: geometry placements + narrow phase (+ contact patches), C++ only
  qp    the impact QP (law.project: the dual active set; piqp where it does not settle, or above 12 rows)
  glue  the rest: Python and numpy (reading coal results, vertices, rows W, bookkeeping)
and the QP in both forms (primal M-metric vs dual Delassus) on the contact states.
Medians over states of the best of `repeat` timings (us). Writes step_costs.json and
step_costs.png to out/ (--out docs/bench: the committed files).

    python -m benchmarks.step_costs [--out docs/bench] [--repeat 5] [--states 300]
    python -m benchmarks.step_costs --plot docs/bench/step_costs.json   # redraw the chart from the JSON
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
import pinocchio as pin

import moreau_sim as ms
from moreau_sim.options import QPForm
from moreau_sim.recording import versions
from moreau_sim.stepper import assemble, free_velocity

from . import OUT, SCENES, add_plot_option, add_table_option, pyplot, redraw, rewrite_tables, scene_path

TARGETS = {"bouncing_ball": {"flight": 10, "contact": 40}, "newton_cradle_5": {"contact": 150},
           "box_drop": {"contact": 80}}


def best(f, repeat):
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        out.append(time.perf_counter() - t0)
    return min(out) * 1e6


def bench_scene(name: str, repeat: int, n_states: int) -> dict:
    # the Python step (the split below is of the Python step's stages; the default is the compiled one)
    model = ms.build_model(ms.load_scene(scene_path(name)).with_options(step_impl="python"))
    opts = model.options
    h, e = opts.dt, opts.restitution
    traj = ms.simulate(model, progress=False)
    data = ms.make_data(model)
    idx = np.unique(np.linspace(0, len(traj.t) - 2, min(n_states, len(traj.t) - 1)).astype(int))
    pm, gm, gd = model.pin, model.geom, data.geom
    forest, kin = model.forest, data.kinematics  # the Python step's dynamics and kinematics (trees.py)
    rows = {"flight": [], "contact": []}
    qp_forms = {"primal": [], "dual": []}
    for i in idx:
        st = ms.State(float(traj.t[i]), traj.q[i], traj.u[i])
        r = ms.step(model, data, st, h=h, e=e)
        kind = "contact" if r.contacts.m else "flight"
        q, u = st.q, st.u
        qm = pin.integrate(pm, q, 0.5 * h * u)
        total = best(lambda: ms.step(model, data, st, h=h, e=e), repeat)
        bias = opts.bias
        if kind == "flight":
            dyn = best(lambda: (pin.integrate(pm, q, 0.5 * h * u), free_velocity(model, data, qm, u, h, bias),
                                pin.integrate(pm, qm, 0.5 * h * u)), repeat)
            qp_t = 0.0
        else:
            dyn = best(lambda: (pin.integrate(pm, q, 0.5 * h * u), forest.mass_matrix(kin, qm),
                                forest.inverse_mass_matrix(kin, qm), free_velocity(model, data, qm, u, h, bias),
                                pin.integrate(pm, qm, 0.5 * h * u)), repeat)
            p = assemble(model, data, st, h=h, e=e)
            M, W, Minv, v_free = p.M, p.W, p.Minv, p.v_free
            qp_t = 0.0  # the step's contacts came from its history (a kept pair, a swept contact): none here
            if W is not None:
                qp_t = best(lambda: ms.project(M, W, v_free, Minv=Minv), repeat)
                for form in QPForm:
                    qp_forms[form.value].append(best(lambda: ms.project(M, W, v_free, Minv=Minv, form=form), repeat))

        def coll():
            forest.place(kin, qm, gm.geometryObjects, gd.oMg)
            if pin.computeCollisions(gm, gd, False) and kind == "contact":
                pin.computeContactPatches(gm, gd)
        coll_t = best(coll, repeat)
        rows[kind].append({"total": total, "dyn": dyn, "coll": coll_t, "qp": qp_t,
                           "glue": max(0.0, total - dyn - coll_t - qp_t), "m": int(r.contacts.m)})
    out = {"nq": model.nq, "nv": model.nv, "pairs": len(model.pairs), "h": h, "e": e}
    for kind, rs in rows.items():
        if rs:
            out[kind] = {k: statistics.median(r[k] for r in rs) for k in ("total", "dyn", "coll", "qp", "glue", "m")}
            out[kind]["states"] = len(rs)
    for form, ts in qp_forms.items():
        if ts:
            out[f"qp_{form}"] = statistics.median(ts)
    out["run_us_per_step"] = traj.meta["run"]["us_per_step"]
    out["target"] = TARGETS.get(name, {})
    return out


# The parts of a step as the chart names them (the JSON's keys: dyn, coll, qp, glue).
PARTS = (("dyn", "dynamics (Pinocchio)", "tab:blue"), ("coll", "collision detection (coal)", "tab:orange"),
         ("qp", "impact QP (piqp)", "tab:green"),
         ("glue", "the rest: Python and numpy (contacts, rows W, bookkeeping)", "tab:red"))


def plot(results: dict, png: Path) -> None:
    """One row per scene and state (a step in flight, a step with contacts): left, the time of one
    step (log scale); right, the share of each part of it. `results`: a step_costs.json's "scenes"."""
    plt = pyplot()

    def state(kind: str, m: float) -> str:
        return "in flight" if kind == "flight" else f"{m:.0f} contact" + ("" if m == 1 else "s")

    rows = [(f"{name}, {state(kind, r[kind]['m'])}", r[kind])
            for name, r in sorted(results.items()) for kind in ("flight", "contact") if kind in r]
    rows.reverse()  # the first scene at the top
    y = np.arange(len(rows))
    fig, (ax_t, ax_s) = plt.subplots(1, 2, figsize=(11, 0.22 * len(rows) + 1.6), sharey=True,
                                     gridspec_kw={"width_ratios": [1, 1.3]}, layout="constrained")
    ax_t.barh(y, [r["total"] for _, r in rows], color="0.45", height=0.7)
    ax_t.set_xscale("log")
    ax_t.set_xlabel("µs per step (median over states, log scale)")
    ax_t.set_yticks(y, [label for label, _ in rows], fontsize=8)
    ax_t.set_ylim(-0.6, len(rows) - 0.4)
    ax_t.grid(axis="x", which="both", alpha=0.3)
    ax_t.set_title("time of one step", fontsize=10)
    left = np.zeros(len(rows))
    for key, name, color in PARTS:
        share = np.array([100 * r[key] / r["total"] if r["total"] else 0.0 for _, r in rows])
        ax_s.barh(y, share, left=left, color=color, height=0.7, label=name)
        left += share
    ax_s.set_xlim(0, 100)
    ax_s.set_xlabel("share of the step [%]")
    ax_s.set_title("where the time goes", fontsize=10)
    fig.suptitle("moreau-sim: cost of one time step, per bundled scene (Python step)", fontsize=11)
    fig.legend(*ax_s.get_legend_handles_labels(), fontsize=8, loc="outside lower center", ncol=2, frameon=False)
    fig.savefig(png, dpi=110)
    plt.close(fig)


# The rows of the table in docs/benchmarks.md: (scene, state, label); the contact target of the
# ball is the resting ball's (zeno_ball), as in the first design.
TABLE_ROWS = (("bouncing_ball", "flight", "bouncing_ball"),
              ("zeno_ball", "contact", "zeno_ball (the ball on the ground)"),
              ("newton_cradle_5", "contact", "newton_cradle_5"), ("box_drop", "flight", "box_drop"),
              ("box_drop", "contact", "box_drop"), ("rocking_block", "contact", "rocking_block"),
              ("pendulum_wall", "flight", "pendulum_wall"), ("quadruped_drop", "contact", "quadruped_drop"),
              ("box_stack_10", "contact", "box_stack_10"))
TABLE_TARGETS = {("zeno_ball", "contact"): TARGETS["bouncing_ball"]["contact"]}


def markdown_table(results: dict) -> str:
    """The step-cost table of docs/benchmarks.md from a step_costs.json's "scenes"."""
    def num(x):
        return "–" if not x else (f"{x:.0f}" if x >= 1000 else f"{x:.1f}")

    out = ["| scene | state | contacts | total | dynamics | collision | QP | glue | target |",
           "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, kind, label in TABLE_ROWS:
        r = results.get(name, {}).get(kind)
        if r is None:
            continue
        target = TABLE_TARGETS.get((name, kind), results[name].get("target", {}).get(kind))
        mark = "" if target is None else f"≤ {target:g} {'✓' if r['total'] <= target else '✗'}"
        out.append(f"| {label} | {kind} | {r['m']:.0f} | {num(r['total'])} | {num(r['dyn'])} | {num(r['coll'])} | "
                   f"{num(r['qp'])} | {num(r['glue'])} | {mark} |")
    return "\n".join(out)


def doc_tables(data: dict) -> dict[str, str]:
    """The tables of docs/benchmarks.md this benchmark's JSON gives (marker name: Markdown)."""
    return {"step-cost table": markdown_table(data["scenes"])}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(OUT), help="output folder (docs/bench: the committed files)")
    add_table_option(ap, "step_costs.json", "docs/benchmarks.md")
    add_plot_option(ap, "step_costs.json")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--states", type=int, default=300)
    ap.add_argument("--scenes", nargs="*", default=sorted(p.stem for p in SCENES.glob("*.toml")))
    a = ap.parse_args()
    if rewrite_tables(a, doc_tables) or redraw(a, plot, select=lambda data: data["scenes"]):
        return
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    print(f"{'scene':24s} {'kind':8s} {'m':>4s} {'total':>8s} {'dyn':>7s} {'coll':>7s} {'qp':>7s} {'glue':>7s}"
          f" {'target':>7s}   qp primal / dual")
    for name in a.scenes:
        r = results[name] = bench_scene(name, a.repeat, a.states)
        for kind in ("flight", "contact"):
            if kind in r:
                k = r[kind]
                tgt = r["target"].get(kind)
                qp = f"{r.get('qp_primal', 0):.1f} / {r.get('qp_dual', 0):.1f}" if kind == "contact" else ""
                print(f"{name:24s} {kind:8s} {k['m']:4.0f} {k['total']:8.1f} {k['dyn']:7.1f} {k['coll']:7.1f}"
                      f" {k['qp']:7.1f} {k['glue']:7.1f} {tgt if tgt else '':>7}   {qp}")
    meta = {"machine": platform.machine(), "cpus": os.cpu_count(), "versions": versions(),
            "repeat": a.repeat, "states": a.states,
            "note": "us per step, median over states of the best of `repeat` timings"}
    (out / "step_costs.json").write_text(json.dumps({"meta": meta, "scenes": results}, indent=2))
    plot(results, out / "step_costs.png")
    print(f"wrote {out / 'step_costs.json'} and {out / 'step_costs.png'}")


if __name__ == "__main__":
    main()
