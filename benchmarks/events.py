"""Issue 27's cases against Siconos's event-driven integrator, in one run: CPU per simulated second.

A benchmark, not a test. The ball at e = 0.5, 0.8, 1 over its first 7 impacts and the touching cradle
(e = 1) over 1 s, every method sampling at the same instants, every 0.025 s:
- moreau-sim's adaptive integrator at rtol 1e-10 (atol 1e-12) through `ms.simulate`, measured two ways: the
  whole call (time.process_time around it: the run's set-up, its loop, the trajectory's assembly) and its loop
  (meta["run"]["cpu_seconds"]: from the initial state to the last, recording and checks included);
- Siconos EventDriven + LsodarOSI with time events every 0.025 s (its runner's cpu_seconds: the advanceToEvent
  loop with the recording; benchmarks.peers.siconos), the cradle with exact gaps.
Rounds interleave the methods (the machine is shared); per round ours is the median of `calls` calls, Siconos's
of 3; the figures are the medians over the rounds. Errors: ours against the closed forms (the ball's impact
instants, docs/theory.md §4.1; the cradle's u(T), §4.2), Siconos's cradle u(T) likewise and its ball q at the
samples against ours (two different methods agreeing). Saves events.json and events.png in --out; --table
rewrites the table of docs/benchmarks.md from the JSON.

    python -m benchmarks.events [--rounds 7] [--calls 5] [--out docs/bench]
    python -m benchmarks.events --table docs/bench/events.json docs/benchmarks.md
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
from moreau_sim.recording import versions
from moreau_sim.testing.references import ball_impact_times, cradle_simultaneous

from . import OUT, add_plot_option, add_table_option, pyplot, redraw, rewrite_tables, scene_path

SAMPLE = 0.025  # [s] every method's output interval
RTOL, ATOL = 1e-10, 1e-12  # the adaptive integrator's tolerances
TARGET = 3.0  # issue 27: >= 3x less CPU than Siconos's event-driven integrator


def _ball_T(e: float) -> float:
    """Between the 7th and the 8th impact, on the sample grid (every method samples at the same instants)."""
    t = ball_impact_times(e, 8)
    return round(0.5 * (t[-2] + t[-1]) / SAMPLE) * SAMPLE


CASES = {"ball e = 0.5": ("bouncing_ball", 0.5, _ball_T(0.5)), "ball e = 0.8": ("bouncing_ball", 0.8, _ball_T(0.8)),
         "ball e = 1": ("bouncing_ball", 1.0, _ball_T(1.0)), "touching cradle, e = 1": ("newton_cradle_5", 1.0, 1.0)}


def _model(scene: str, e: float, T: float):
    sc = ms.load_scene(scene_path(scene)).with_options(restitution=e, integrator="adaptive", rtol=RTOL, atol=ATOL,
                                                       dt=SAMPLE, save_every=1, duration=T)
    return ms.build_model(sc)


def ours(model, calls: int) -> tuple[float, float, ms.Trajectory]:
    """(whole call, loop) CPU [s], each the median of `calls` calls, and the last trajectory."""
    whole, loop = [], []
    for _ in range(calls):
        c = time.process_time()
        tr = ms.simulate(model, progress=False)
        whole.append(time.process_time() - c)
        loop.append(tr.meta["run"]["cpu_seconds"])
    return statistics.median(whole), statistics.median(loop), tr


def siconos(model, scene: str, e: float, T: float) -> tuple[float, np.ndarray, np.ndarray, dict]:
    """Siconos ED's loop CPU [s] (median of 3 runs), its samples q, u and its settings."""
    from .peers import run_model

    params = {"simulation": "event-driven"} | ({"exact_gaps": True} if scene == "newton_cradle_5" else {})
    cpus = []
    for _ in range(3):
        _, q, u, res = run_model("siconos", model, e=e, h=SAMPLE, T=T, **params)
        cpus.append(res["cpu_seconds"])
    return statistics.median(cpus), q, u, {**res.get("settings", {}), **params}


def errors(scene: str, e: float, tr: ms.Trajectory, q_sic: np.ndarray, u_sic: np.ndarray) -> tuple[float, float]:
    """(ours, Siconos's) error: the ball's impact instants [s] against the closed form and Siconos's q [m] against
    ours at the samples; the cradle's u(T) [m/s] against the simultaneous result, each."""
    if scene == "newton_cradle_5":
        ref = np.array(cradle_simultaneous(e))
        return float(np.abs(tr.u[-1] - ref).max()), float(np.abs(u_sic[-1] - ref).max())
    t_imp = np.asarray(tr.arrays["impact_t"])
    ref = np.array(ball_impact_times(e, len(t_imp)))
    n = min(len(q_sic), len(tr.q))
    return float(np.abs(t_imp - ref).max()), float(np.abs(q_sic[:n] - tr.q[:n]).max())


def measure(rounds: int, calls: int) -> dict:
    models = {label: _model(*c) for label, c in CASES.items()}
    for m in models.values():  # warm-up (imports, the extension's first calls, the per-model caches): not timed
        ms.simulate(m, progress=False)
    rows: dict = {label: {"whole": [], "loop": [], "siconos": []} for label in CASES}
    loads, settings, err = [], {}, {}
    for _ in range(rounds):
        loads.append(os.getloadavg()[0])
        for label, (scene, e, T) in CASES.items():
            whole, loop, tr = ours(models[label], calls)
            sic, q, u, settings[label] = siconos(models[label], scene, e, T)
            r = rows[label]
            r["whole"].append(whole / T)
            r["loop"].append(loop / T)
            r["siconos"].append(sic / T)
            err[label] = errors(scene, e, tr, q, u)
    out = {}
    for label, r in rows.items():
        med = {k: statistics.median(v) for k, v in r.items()}
        out[label] = {"ours_whole_ms_per_s": 1e3 * med["whole"], "ours_loop_ms_per_s": 1e3 * med["loop"],
                      "siconos_ms_per_s": 1e3 * med["siconos"], "ratio_whole": med["siconos"] / med["whole"],
                      "ratio_loop": med["siconos"] / med["loop"], "T": CASES[label][2],
                      "error_ours": err[label][0], "error_siconos": err[label][1],
                      "rounds": {k: [1e3 * x for x in v] for k, v in r.items()}}
    return {"cases": out, "siconos_settings": settings, "rounds": rounds, "calls": calls,
            "load": [min(loads), max(loads)], "cpus": os.cpu_count(), "versions": versions(), "target": TARGET,
            "sample": SAMPLE, "rtol": RTOL, "atol": ATOL,
            "note": "CPU per simulated second [ms/s], medians over interleaved rounds; ratio = Siconos / ours"}


def doc_tables(res: dict) -> dict:
    """{marker name: Markdown} of docs/benchmarks.md."""
    lines = ["| case | ours, whole call [ms/s] | ours, loop [ms/s] | Siconos ED, loop [ms/s] | Siconos / ours, "
             f"whole call | Siconos / ours, loop to loop (target ≥ {res['target']:g}) | error ours | error Siconos |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for label, c in res["cases"].items():
        lines.append(f"| {label} | {c['ours_whole_ms_per_s']:.3g} | {c['ours_loop_ms_per_s']:.3g} | "
                     f"{c['siconos_ms_per_s']:.3g} | {c['ratio_whole']:.2f} | {c['ratio_loop']:.2f} | "
                     f"{c['error_ours']:.1e} | {c['error_siconos']:.1e} |")
    lo, hi = res["load"]
    lines.append("")
    lines.append(f"{res['rounds']} interleaved rounds, ours the median of {res['calls']} calls a round, Siconos's "
                 f"of 3; load {lo:.2f} – {hi:.2f}; moreau-sim {res['versions'].get('moreau-sim')}.")
    return {"events": "\n".join(lines)}


def plot(res: dict, png: Path) -> None:
    """Bars per case: ours (whole call, loop) and Siconos ED's loop, CPU per simulated second, log scale."""
    plt = pyplot()

    labels = list(res["cases"])
    x = np.arange(len(labels))
    fig, ax = plt.subplots(figsize=(7.5, 4.4))
    for k, (key, name) in enumerate((("ours_whole_ms_per_s", "moreau-sim adaptive, whole ms.simulate"),
                                     ("ours_loop_ms_per_s", "moreau-sim adaptive, its loop"),
                                     ("siconos_ms_per_s", "Siconos event-driven, its loop"))):
        ax.bar(x + (k - 1) * 0.27, [res["cases"][c][key] for c in labels], 0.25, label=name)
    sic = [res["cases"][c]["siconos_ms_per_s"] / res["target"] for c in labels]
    ax.scatter(x, sic, marker="_", s=900, color="k", zorder=3, label=f"target: Siconos / {res['target']:g}")
    ax.set_yscale("log")
    ax.set_xticks(x, labels, fontsize=8)
    ax.set_ylabel("CPU ms per simulated s")
    lo, hi = res["load"]
    ax.set_title(f"events against Siconos (rtol {res['rtol']:g}, samples every {res['sample']:g} s; load "
                 f"{lo:.1f}-{hi:.1f})", fontsize=9)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2, frameon=False)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--calls", type=int, default=5)
    ap.add_argument("--out", type=Path, default=OUT)
    add_plot_option(ap, "events.json")
    add_table_option(ap, "events.json", "docs/benchmarks.md")
    args = ap.parse_args(argv)
    if redraw(args, plot) or rewrite_tables(args, doc_tables):
        return
    from .peers import available

    why = available().get("siconos")
    if why is not None:
        raise SystemExit(f"error: Siconos cannot run here: {why}")
    res = measure(args.rounds, args.calls)
    print(doc_tables(res)["events"])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "events.json").write_text(json.dumps(res, indent=1))
    plot(res, args.out / "events.png")
    print(f"wrote {args.out / 'events.json'} and events.png")


if __name__ == "__main__":
    main()
