"""The cost of one contact step against the number of contacts: columns of 10 to 1000 beads.

A benchmark, not a test. A column of N beads is column_of_beads_100's construction built in code
(balls r = 0.1 m, 1 kg, each on a vertical prismatic joint; pairs between neighbours and the
bottom bead with the ground; e = 0.9, h = 5e-4), here started touching (centres at 0.1 + 0.2 k m)
so that every step of a short run from rest has all N contacts closed: m = N, M diagonal, the
Delassus matrix W'M^-1 W tridiagonal. `ms.step` is timed on the states of that run (best of
`repeat` per state, median over states) with each step_impl, saying which path took the steps
(compiled.counts: the compiled step hands more than 12 velocities or contacts to the Python one),
and the stages of the step are split by cProfile (cumulative time of the stage functions). The
slope of log(cost) against log(m) is fitted by least squares (target <= 1.1: cost linear in m).
Writes scaling.json and scaling.png to out/ (--out docs/bench: the committed files).

    python -m benchmarks.scaling [--out docs/bench] [--sizes 10 20 50 100 200 500 1000]
    python -m benchmarks.scaling --table docs/bench/scaling.json docs/benchmarks.md
    python -m benchmarks.scaling --plot docs/bench/scaling.json   # redraw the chart from the JSON
"""

from __future__ import annotations

import argparse
import copy
import cProfile
import dataclasses
import json
import os
import platform
import pstats
import statistics
import time
from pathlib import Path

import numpy as np
import pinocchio as pin

import moreau_sim as ms
from moreau_sim import compiled, qp
from moreau_sim.recording import versions
from moreau_sim.scene import Collisions

from . import OUT, REPO, add_plot_option, add_table_option, redraw, rewrite_tables
from .step_costs import best  # best of `repeat` timings, us

SIZES = (10, 20, 50, 100, 200, 500, 1000)
QP_SIZES = (100, 300, 1000, 3000)
TARGET_SLOPE = 1.1
IMPLS = ("compiled", "python")
NAMES = {"compiled": "compiled", "python": "Python"}  # the step implementations as the chart names them
# the stages of a Python step: (label, module file, function) for cProfile's cumulative times (file "~": a
# built-in, matched by the end of its name; no file: Pinocchio's, which cProfile does not see, timed apart)
STAGES = (("detect", "contacts.py", "detect"), ("CRBA", "", ""), ("rows W", "constraints.py", "contact_rows"),
          ("distinct", "constraints.py", "distinct"), ("M^-1", "", ""),
          ("free velocity", "stepper.py", "free_velocity"), ("impact QP", "law.py", "project"),
          ("position correction", "stepper.py", "correct_positions"), ("step", "stepper.py", "step"))


def column(n: int, *, step_impl: str = "compiled") -> ms.Scene:
    """A column of n touching beads on vertical prismatic joints over the ground (neighbour pairs only)."""
    b = ms.SceneBuilder(f"column_of_beads_{n}", folder=REPO / "scenes", restitution=0.9, dt=5e-4, duration=0.01,
                        step_impl=step_impl,
                        description=f"{n} beads (column_of_beads_100's construction), touching, from rest")
    for k in range(n):
        b.add_body(f"bead{k}", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1), q0=[0.1 + 0.2 * k])
    b.add_halfspace("ground")
    scene = b.build()
    # every pair but neighbours and bead0-ground excluded (the scene file lists them; here in code: O(n^2) names)
    names = [f"bead{k}" for k in range(n)]
    exclude = [(names[i], names[j]) for i in range(n) for j in range(i + 2, n)]
    exclude += [(names[k], "ground") for k in range(1, n)]
    return dataclasses.replace(scene, collisions=Collisions(exclude=tuple(exclude)))


def states_in_contact(model, data, n_states: int) -> list:
    """The states of a short run from the model's initial state (every one with all contacts closed)."""
    st = ms.initial_state(model)
    out = []
    for _ in range(n_states):
        r = ms.step(model, data, st)
        if not r.qp or not r.qp.ok:
            raise RuntimeError(f"{model.pin.name}: the step at t = {st.t} failed ({r.qp and r.qp.status})")
        out.append((st, r.contacts.m))
        st = r.state
    return out


def stage_split(model, data, states) -> dict:
    """us per step in each stage (cProfile's cumulative times over one step of each state, / states;
    Pinocchio's CRBA and M^-1, which cProfile does not see, timed apart: best of 3 at each state's q)."""
    prof = cProfile.Profile()
    for st, _ in states:
        prof.enable()
        ms.step(model, data, st)
        prof.disable()
    stats = pstats.Stats(prof).stats
    pm, pd = model.pin, data.pin
    out = {"CRBA": statistics.median(best(lambda q=st.q: pin.crba(pm, pd, q, pin.Convention.WORLD), 3)
                                     for st, _ in states),
           "M^-1": statistics.median(best(lambda q=st.q: pin.computeMinverse(pm, pd, q), 3) for st, _ in states)}
    for label, file, func in STAGES:
        if label in out:
            continue
        cum = sum(v[3] for (f, _, name), v in stats.items()
                  if ((f == "~" and name.endswith(func)) if file == "~"
                      else (name == func and f.endswith(f"moreau_sim/{file}"))))
        out[label] = cum / len(states) * 1e6
    return out


def bench_size(n: int, repeat: int, n_states: int) -> dict:
    t0 = time.perf_counter()
    base = ms.build_model(column(n, step_impl="python"))
    data = ms.make_data(base)  # one Pinocchio Data: its size grows like N^3 (500 beads: 9 GB, 23 s)
    build = time.perf_counter() - t0
    models = {}
    for impl in IMPLS:  # the same model but for step_impl (building another would build another Data)
        models[impl] = copy.copy(base)
        object.__setattr__(models[impl], "scene", base.scene.with_options(step_impl=impl))
    states = states_in_contact(models["python"], data, n_states)
    out = {"beads": n, "nv": base.nv, "pairs": len(base.pairs),
           "contacts": statistics.median(m for _, m in states), "states": len(states), "build_s": build}
    for impl in IMPLS:
        model = models[impl]
        ms.step(model, data, states[0][0])  # the compiled stepper is set up at its first step: not timed
        times = [best(lambda st=st, model=model: ms.step(model, data, st), repeat) for st, _ in states]
        paths = dict(compiled.counts(data)) if impl == "compiled" else {"python": repeat * len(states)}
        out[impl] = {"us": statistics.median(times), "paths": paths}
    out["stages_python"] = stage_split(models["python"], data, states)
    return out


def qp_alone(n: int, repeat: int) -> dict:
    """The impact QP of a resting column of n unit beads built without a model (M = I, the column's rows, every
    bead at -g h): qp.solve as the stepper calls it, best of `repeat`. It reaches sizes whose Pinocchio Data
    cannot be built (too_big); its inputs are still dense (M, M^-1, W: n^2 each)."""
    W = np.zeros((n, n), order="F")
    W[0, 0] = 1.0
    k = np.arange(1, n)
    W[k, k], W[k - 1, k] = 1.0, -1.0
    M, v0 = np.eye(n), np.full(n, -9.81 * 5e-4)
    r = qp.solve(M, W, v0, Minv=M)
    return {"beads": n, "us": best(lambda: qp.solve(M, W, v0, Minv=M), repeat), "status": r.status,
            "polished": bool(r.polished), "max_abs_v": float(np.abs(r.v).max())}


def fit_slope(rows: list, impl: str) -> float:
    """Least-squares slope of log(us per step) against log(contacts) (nan with fewer than 2 sizes)."""
    if len(rows) < 2:
        return float("nan")
    m = np.log([r["contacts"] for r in rows])
    t = np.log([r[impl]["us"] for r in rows])
    return float(np.polyfit(m, t, 1)[0])


def data_bytes(n: int) -> int:
    """What one Pinocchio Data of an n-velocity model allocates, about: four nv^3 tensors of second-order
    derivatives, whatever the algorithms used (stack-of-tasks/pinocchio#2949; measured 9 GB RSS at nv = 500)."""
    return 4 * 8 * n ** 3


def too_big(n: int) -> str | None:
    """Why a column of n beads is not built here (its Data would take over half the free memory), or None."""
    free = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    need = data_bytes(n)
    if need > free / 2:
        return (f"a Pinocchio Data of nv = {n} allocates ~{need / 1e9:.0f} GB (four nv^3 tensors, "
                f"stack-of-tasks/pinocchio#2949), over half of the {free / 1e9:.0f} GB free")
    return None


def plot(data: dict, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = data["sizes"]
    m = np.array([r["contacts"] for r in rows], float)
    fig, ax = plt.subplots(figsize=(8.5, 7.5), layout="constrained")
    for impl, mark, size in zip(IMPLS, ("o", "s"), (9, 5)):  # the python squares inside the compiled discs
        t = np.array([r[impl]["us"] for r in rows]) * 1e-3
        c, t0 = np.polyfit(np.log(m), np.log(t), 1)
        line, = ax.loglog(m, t, mark, ms=size, label=f"{NAMES[impl]} step")
        ax.loglog(m, np.exp(t0) * m ** c, "-", color=line.get_color(), lw=1, label=f"fit: slope {c:.2f}")
    before = data.get("before")
    if before:
        for impl, mark in zip(IMPLS, ("o", "s")):
            pts = sorted((int(n), v[impl] * 1e-3) for n, v in before["sizes"].items())
            ax.loglog(*zip(*pts), mark, mfc="none", color="grey", ms=7,
                      label=f"{NAMES[impl]} step, older code with a dense QP (git {before['commit']}): "
                            f"slope {before['slopes'][impl]:.2f}")
    qa = data.get("qp_alone") or []
    if qa:
        ax.loglog([r["beads"] for r in qa], [r["us"] * 1e-3 for r in qa], "^-", color="tab:green", lw=0.8,
                  label=f"impact QP alone, no model (M = I): slope {data['qp_alone_slope']:.2f}")
        bq = sorted((int(n), v * 1e-3) for n, v in (before or {}).get("qp_alone", {}).items())
        if bq:
            ax.loglog(*zip(*bq), "^", mfc="none", color="grey", ms=7,
                      label=f"impact QP alone, older code (git {before['commit']})")
    ref = np.array([r["python"]["us"] for r in rows]) * 1e-3
    ax.loglog(m, ref[0] * m / m[0], "k:", lw=1, label="slope 1 (from the first point)")
    ax.axvline(data["compiled_limit"] + 0.5, color="grey", lw=0.8, ls="--")
    ax.axvline(data["sparse_rows"] + 0.5, color="grey", lw=0.8, ls="-.")
    top = ax.get_ylim()[1]
    ax.text(data["compiled_limit"] + 0.5, top, f"compiled step: up to {data['compiled_limit']} contacts ", fontsize=7,
            va="top", ha="right")
    ax.text(data["sparse_rows"] + 0.5, top, f" sparse QP above {data['sparse_rows']} rows", fontsize=7, va="top")
    ax.set_xlabel("contacts m (= beads N)")
    ax.set_ylabel("ms per step (median over states); ms per solve (QP alone)")
    ax.set_title(f"a column of N touching beads: cost of one step (target: fitted slope ≤ {TARGET_SLOPE})")
    ax.grid(True, which="both", alpha=0.3)
    fig.legend(*ax.get_legend_handles_labels(), fontsize=8, loc="outside lower center", ncol=2, frameon=False)
    fig.savefig(png, dpi=110)


def markdown_table(data: dict) -> str:
    """The scaling table of docs/benchmarks.md from a scaling.json."""
    rows = data["sizes"]
    stages = [s for s, _, _ in STAGES if s != "step"]
    before = data.get("before")
    threads = data["meta"].get("OPENBLAS_NUM_THREADS")
    out = [f"Run of {data['meta']['date']} (git `{data['meta']['commit']}`"
           + (f", OPENBLAS_NUM_THREADS={threads}" if threads else "") + f"): ms per step, median over "
           f"{rows[0]['states']} states of the best of {data['meta']['repeat']} timings"
           + (f"; *before*: the same benchmark on the code of git `{before['commit']}` (dense QP path, "
              "all-pairs distinct)" if before else "")
           + "; stages: cProfile's cumulative times in the Python step (profiled, so inflated; CRBA and "
           "M⁻¹ timed apart).", "",
           "| beads | contacts | compiled | paths (compiled) | python | "
           + ("before: compiled / python | " if before else "") + " | ".join(stages) + " |",
           "|---:|---:|---:|---|---:|" + ("---:|" if before else "") + "---:|" * len(stages)]
    for r in rows:
        paths = ", ".join(f"{k}: {v}" for k, v in sorted(r["compiled"]["paths"].items()))
        st = " | ".join(f"{r['stages_python'][s] * 1e-3:.3f}" for s in stages)
        b = before["sizes"].get(str(r["beads"])) if before else None
        was = "" if not before else ("– | " if b is None else
                                     f"{b['compiled'] * 1e-3:.3f} / {b['python'] * 1e-3:.3f} | ")
        out.append(f"| {r['beads']} | {r['contacts']:.0f} | {r['compiled']['us'] * 1e-3:.3f} | {paths} | "
                   f"{r['python']['us'] * 1e-3:.3f} | {was}{st} |")
    s, s2 = data["slopes"], data["slopes_above_compiled_limit"]
    met = {k: "met" if v <= TARGET_SLOPE else "missed" for k, v in s.items()}
    out += ["", f"Fitted log-log slope of the cost against the contacts ({rows[0]['contacts']:.0f} to "
            f"{rows[-1]['contacts']:.0f}): step_impl = compiled {s['compiled']:.2f} ({met['compiled']}), "
            f"python {s['python']:.2f} ({met['python']}); target ≤ {TARGET_SLOPE}. Above "
            f"{data['compiled_limit']} contacts, where every step is the Python step: {s2['compiled']:.2f} and "
            f"{s2['python']:.2f}. The QP runs on sparse matrices above {data['sparse_rows']} rows."]
    if data.get("qp_alone"):
        bq = before.get("qp_alone", {}) if before else {}
        out += ["", "The impact QP alone on the same column built without a model (M = I, no Pinocchio Data, so "
                "beyond what a model can build here), ms per solve:", "",
                "| beads | QP | " + ("before | " if bq else "") + "status |",
                "|---:|---:|" + ("---:|" if bq else "") + "---|"]
        for r in data["qp_alone"]:
            was = "" if not bq else (f"{bq[str(r['beads'])] * 1e-3:.2f} | " if str(r["beads"]) in bq else "– | ")
            out.append(f"| {r['beads']} | {r['us'] * 1e-3:.2f} | {was}{r['status']}"
                       f"{', polished' if r['polished'] else ''} |")
        out.append("")
        out.append(f"Slope of the QP alone: {data['qp_alone_slope']:.2f}.")
    if before:
        out.append(f"Before: slopes {before['slopes']['compiled']:.2f} (compiled) and "
                   f"{before['slopes']['python']:.2f} (python) over the sizes it measured.")
    for n, why in data.get("skipped", {}).items():
        out.append(f"Not measured: {n} beads ({why}).")
    return "\n".join(out)


def doc_tables(data: dict) -> dict[str, str]:
    """The tables of docs/benchmarks.md this benchmark's JSON gives (marker name: Markdown)."""
    return {"scaling table": markdown_table(data)}


def _commit() -> str:
    import subprocess

    r = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=REPO)
    return r.stdout.strip() or "unknown"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(OUT), help="output folder (docs/bench: the committed files)")
    add_table_option(ap, "scaling.json", "docs/benchmarks.md")
    add_plot_option(ap, "scaling.json")
    ap.add_argument("--sizes", type=int, nargs="*", default=list(SIZES), help="numbers of beads")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--states", type=int, default=10, help="contact states per size (a run of that many steps)")
    ap.add_argument("--before", type=Path, help="a scaling.json of earlier code, quoted beside this run's figures")
    ap.add_argument("--qp-sizes", type=int, nargs="*", default=list(QP_SIZES),
                    help="numbers of beads of the QP alone (no Pinocchio Data: beyond what a model can build)")
    a = ap.parse_args(argv)
    if rewrite_tables(a, doc_tables) or redraw(a, plot):
        return 0
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, skipped = [], {}
    print(f"{'beads':>6s} {'m':>6s} {'compiled ms':>12s} {'python ms':>10s}  paths (compiled)")
    for n in a.sizes:
        why = too_big(n)
        if why is not None:
            skipped[str(n)] = why
            print(f"{n:6d} skipped: {why}", flush=True)
            continue
        r = bench_size(n, a.repeat, a.states)
        rows.append(r)
        print(f"{n:6d} {r['contacts']:6.0f} {r['compiled']['us'] * 1e-3:12.3f} {r['python']['us'] * 1e-3:10.3f}  "
              f"{r['compiled']['paths']}", flush=True)
        print("       stages (python, profiled, ms): "
              + ", ".join(f"{k} {v * 1e-3:.3f}" for k, v in r["stages_python"].items()), flush=True)
    qp_rows = []
    for n in a.qp_sizes:
        qp_rows.append(qp_alone(n, a.repeat))
        print(f"QP alone, {n} beads: {qp_rows[-1]['us'] * 1e-3:.3f} ms ({qp_rows[-1]['status']})", flush=True)
    slopes = {impl: fit_slope(rows, impl) for impl in IMPLS}
    above = [r for r in rows if r["contacts"] > compiled.MAX_CONTACTS]  # every step in the Python step
    slopes_python_only = {impl: fit_slope(above, impl) for impl in IMPLS}
    print("slopes:", {k: round(v, 3) for k, v in slopes.items()}, f"(target <= {TARGET_SLOPE}); above "
          f"{compiled.MAX_CONTACTS} contacts:", {k: round(v, 3) for k, v in slopes_python_only.items()})
    meta = {"date": time.strftime("%Y-%m-%d", time.gmtime()), "commit": _commit(), "machine": platform.machine(),
            "cpus": os.cpu_count(), "load": os.getloadavg()[0], "versions": versions(), "repeat": a.repeat,
            "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
            "note": "us per step: median over the states of a short run of the best of `repeat` timings"}
    data = {"meta": meta, "sizes": rows, "skipped": skipped, "slopes": slopes,
            "slopes_above_compiled_limit": slopes_python_only, "compiled_limit": compiled.MAX_CONTACTS,
            "sparse_rows": getattr(qp, "SPARSE_ROWS", None), "target_slope": TARGET_SLOPE, "qp_alone": qp_rows,
            "qp_alone_slope": fit_slope([{"contacts": r["beads"], "qp": r} for r in qp_rows], "qp")}
    if a.before:
        prev = json.loads(a.before.read_text(encoding="utf-8"))
        data["before"] = {"commit": prev["meta"]["commit"], "note": prev["meta"].get("label", ""),
                          "slopes": prev["slopes"],
                          "sizes": {str(r["beads"]): {impl: r[impl]["us"] for impl in IMPLS} for r in prev["sizes"]},
                          "qp_alone": {str(r["beads"]): r["us"] for r in prev.get("qp_alone", [])}}
    (out / "scaling.json").write_text(json.dumps(data, indent=2))
    if len(rows) >= 2:
        plot(data, out / "scaling.png")
    print(f"wrote {out / 'scaling.json'}" + (f" and {out / 'scaling.png'}" if len(rows) >= 2 else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
