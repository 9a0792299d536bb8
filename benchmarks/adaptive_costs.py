"""The adaptive integrator against the event-driven integrator and the fixed step: error vs CPU time.

A benchmark, not a test. Per case (a bundled scene at a restitution, over T [s]) and method:
  adaptive      integrator = "adaptive" (docs/theory.md §8), order 6, atol = rtol / 100, max_step 1 s,
                swept over RTOLS
  event-driven  the event-driven integrator (docs/theory.md §7), DOP853, its default tolerances
  fixed step    the midpoint Moreau step at h = 1e-3 and 1e-4 (ms.simulate)
CPU time: time.process_time() around the integration loop alone (driver.drive of AdaptiveRun, EventDrivenRun
recording t = 0 and T; the fixed step: ms.step in a loop storing q and u, benchmarks.work_precision.run_moreau),
best of `repeat` (the fixed step at h = 1e-4: once), per simulated second. The error comes from
the same integrator recorded where the error is read (the samples of the adaptive and event-driven
integrators come from their dense output: their steps do not depend on the sample instants), against
references that are not the method under test:
  ball     the first 7 impact instants [s] and the 6 apexes between them [m] against the closed
           forms of docs/theory.md §4.1 (the larger of the two errors)
  cradle   u(T) [m/s] against the simultaneous result of §4.2
  others   q at 9 instants [m, rad] against the event-driven integrator at rtol = atol = 1e-13
Writes adaptive_costs.json to out/ (--out docs/bench: the committed file); --table rewrites the
tables of docs/benchmarks.md from it.

    python -m benchmarks.adaptive_costs [--out docs/bench] [--repeat 3]
    python -m benchmarks.adaptive_costs --table docs/bench/adaptive_costs.json docs/benchmarks.md
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import time
from pathlib import Path

import numpy as np

import moreau_sim as ms
from moreau_sim.adaptive import DEFAULT_ORDER, AdaptiveRun, simulate_adaptive
from moreau_sim.driver import drive
from moreau_sim.event_driven import EventDrivenRun, simulate_event_driven
from moreau_sim.recording import versions
from moreau_sim.testing import metrics
from moreau_sim.testing.references import ball_apex_gaps, ball_impact_times, cradle_simultaneous

from . import OUT, add_table_option, rewrite_tables, scene_path
from .work_precision import run_moreau

RTOLS = (1e-4, 1e-6, 1e-8, 1e-10, 1e-12)
STEPS = (1e-3, 1e-4)
BALL_IMPACTS = 7
REFERENCE_TOL = 1e-13


def _ball_T(e: float) -> float:
    """Halfway between the 7th and the 8th impact: 7 impacts and 6 whole flights in the run."""
    t = ball_impact_times(e, BALL_IMPACTS + 1)
    return 0.5 * (t[-2] + t[-1])


# (label, scene, restitution or None for the scene's, T [s], kind of error)
CASES = (("ball e = 0.5", "bouncing_ball", 0.5, _ball_T(0.5), "ball"),
         ("ball e = 0.8", "bouncing_ball", 0.8, _ball_T(0.8), "ball"),
         ("ball e = 1", "bouncing_ball", 1.0, _ball_T(1.0), "ball"),
         ("touching cradle, e = 1", "newton_cradle_5", 1.0, 1.0, "cradle"),
         ("box_drop", "box_drop", None, 0.6, "state"),
         ("pendulum_wall", "pendulum_wall", None, 2.0, "state"),
         ("rocking_block", "rocking_block", None, 0.4, "state"),
         ("box_drop to rest", "box_drop", None, 1.5, "state"),
         ("block_on_step (a corner, box on box)", "block_on_step", None, 1.0, "state"))


class Case:
    """One case: its model, the instants where errors are read, and the error of a trajectory."""

    def __init__(self, label, scene, e, T, kind):
        sc = ms.load_scene(scene_path(scene))
        if e is not None:
            sc = sc.with_options(restitution=e)
        self.label, self.scene, self.T, self.kind = label, scene, T, kind
        self.model = ms.build_model(sc)
        self.e = self.model.options.restitution
        if kind == "ball":  # every 1 ms: apexes by the parabola through 3 samples, exact in free flight
            self.grid = np.linspace(0.0, T, int(round(T / 1e-3)) + 1)
        elif kind == "cradle":
            self.grid = np.array([0.0, T])
        else:
            self.instants = np.linspace(0.0, T, 10)[1:]
            self.grid = np.r_[0.0, self.instants]
            self.ref = simulate_event_driven(self.model, t_end=T, t_eval=self.grid, rtol=REFERENCE_TOL,
                                             atol=REFERENCE_TOL)

    def error(self, traj) -> float:
        if self.kind == "ball":
            times = metrics.impact_times(traj).get(0, np.zeros(0))[:BALL_IMPACTS]
            ref = np.array(ball_impact_times(self.e, BALL_IMPACTS))
            dt = np.abs(times - ref[:len(times)]).max(initial=0.0) if len(times) == BALL_IMPACTS else np.inf
            apex = metrics.apex_error(traj, ball_apex_gaps(self.e, BALL_IMPACTS - 1), count=BALL_IMPACTS - 1)
            return float(max(dt, apex.max_abs))
        if self.kind == "cradle":
            return float(np.abs(traj.u[-1] - np.array(cradle_simultaneous(self.e))).max())
        lie = self.model.pin if self.model.nq != self.model.nv else None
        return metrics.state_error(traj, self.ref, self.instants, model=lie).q_max


def _run_cpu(model: ms.Model, T: float, make) -> float:
    """CPU seconds of the driven run alone (integ = make(model, data, T), driver.drive), recording t = 0 and T only."""
    data = ms.make_data(model)
    integ = make(model, data, T)
    c0 = time.process_time()
    drive(integ, model, data, grid=np.array([0.0, T]))
    return time.process_time() - c0


def bench_case(case: Case, repeat: int) -> dict:
    m, T, e = case.model, case.T, case.e
    out = {"label": case.label, "scene": case.scene, "e": e, "T": T, "kind": case.kind, "adaptive": [], "fixed": []}
    for rtol in RTOLS:
        cpu = min(_run_cpu(m, T, lambda mm, d, T, r=rtol: AdaptiveRun(mm, d, e, r, r / 100, DEFAULT_ORDER, 1.0, 10 ** 6,
                                                                       t_end=T))
                  for _ in range(repeat))
        tr = simulate_adaptive(m, t_end=T, rtol=rtol, atol=rtol / 100, t_eval=case.grid)
        out["adaptive"].append({"rtol": rtol, "cpu_per_sim_s": cpu / T, "error": case.error(tr),
                                "impacts": tr.meta["run"]["impacts"], "events": tr.meta["run"]["events"],
                                "nfev": tr.meta["run"]["nfev"], "nfev_constrained": tr.meta["run"]["nfev_constrained"]})
    cpu = min(_run_cpu(m, T, lambda mm, d, T: EventDrivenRun(mm, d, e, 1e-12, 1e-12, "DOP853", 1e-2, 100_000, t_end=T))
              for _ in range(repeat))
    tr = simulate_event_driven(m, t_end=T, t_eval=case.grid)
    out["event_driven"] = {"cpu_per_sim_s": cpu / T, "error": case.error(tr), "impacts": tr.meta["run"]["impacts"]}
    for h in STEPS:
        cpu = min(run_moreau(m, h, T)["cpu_seconds"] for _ in range(repeat if h >= 1e-3 else 1))
        tr = ms.simulate(ms.build_model(m.scene.with_options(dt=h, duration=T)), progress=False)
        out["fixed"].append({"h": h, "cpu_per_sim_s": cpu / T, "error": case.error(tr)})
    return out


# ---------------------------------------------------------------- the tables of docs/benchmarks.md
def _g(x: float | None, digits: int = 2) -> str:
    return "—" if x is None else "∞" if not np.isfinite(x) else f"{x:.{digits}g}"


def _cheapest(points: list, level: float) -> dict | None:
    """The cheapest point whose error is <= level, or None."""
    ok = [p for p in points if p["error"] <= level]
    return min(ok, key=lambda p: p["cpu_per_sim_s"]) if ok else None


def markdown_table(res: dict) -> str:
    """Error at CPU s per simulated second of each method, per case."""
    meta = res["meta"]
    out = [f"Run of {meta['created'][:10]} ({meta['cpus']} cores, load average {meta['load_start']:.1f} → "
           f"{meta['load_end']:.1f}); error at CPU s/sim s, best of {meta['repeat']}:", "",
           "| case | adaptive (rtol " + " → ".join(f"{r:g}" for r in (RTOLS[0], RTOLS[-1])) + ") "
           "| event-driven (DOP853) | fixed step (h = " + ", ".join(f"{h:g}" for h in STEPS) + ") |",
           "|---|---|---|---|"]
    for c in res["cases"]:
        ad = "; ".join(f"{_g(p['error'])} at {_g(p['cpu_per_sim_s'])} ({p['rtol']:g})" for p in c["adaptive"])
        ed = c["event_driven"]
        fx = "; ".join(f"{_g(p['error'])} at {_g(p['cpu_per_sim_s'])}" for p in c["fixed"])
        impacts = f", {c['event_driven']['impacts']} impacts" if c["kind"] != "cradle" else ""
        out.append(f"| {c['label']} ({c['T']:.3g} s{impacts}) | {ad} | {_g(ed['error'])} at "
                   f"{_g(ed['cpu_per_sim_s'])} | {fx} |")
    return "\n".join(out)


def _verdict(ok: bool | None) -> str:
    return "—" if ok is None else "met" if ok else "missed"


def _interpolated(points: list, level: float) -> float | None:
    """The adaptive cost at error = level, log-log interpolated between the loosest rtol within the
    level and the rtol before it (an rtol between them would reach it); None where no interpolation
    applies (every point within the level, or none)."""
    for a, b in zip(points, points[1:]):
        if a["error"] > level >= b["error"] > 0:
            w = np.log(level / a["error"]) / np.log(b["error"] / a["error"])
            return float(np.exp((1 - w) * np.log(a["cpu_per_sim_s"]) + w * np.log(b["cpu_per_sim_s"])))
    return None


def _reach(points: list, level: float, bound: float) -> str:
    p = _cheapest(points, level)
    if p is None:
        return "not reached | missed |"
    cost = p["cpu_per_sim_s"]
    cell = f"{_g(p['error'])} at {_g(cost)} (rtol {p['rtol']:g})"
    x = _interpolated(points, level)
    if x is not None and x < cost:
        cell += f"; {level:g} at {_g(x)} by log-log interpolation between rtols"
        cost = x
    return f"{cell} | {_verdict(cost <= bound)} |"


def targets_table(res: dict) -> str:
    """The adaptive integrator's cost targets that this benchmark measures, and whether they are met."""
    cases = {c["label"]: c for c in res["cases"]}
    rows = ["| target | case | measured | |", "|---|---|---|---|"]
    for label in ("ball e = 0.5", "ball e = 0.8", "ball e = 1", "touching cradle, e = 1"):
        rows.append(f"| error ≤ 1e-10 at ≤ 0.003 CPU s/s | {label} | " + _reach(cases[label]["adaptive"], 1e-10, 3e-3))
    for label in ("box_drop", "pendulum_wall"):
        rows.append(f"| error ≤ 1e-8 at ≤ 0.03 CPU s/s | {label} | " + _reach(cases[label]["adaptive"], 1e-8, 0.03))
    for label in ("box_drop", "pendulum_wall"):
        c = cases[label]
        ed = c["event_driven"]
        p = _cheapest(c["adaptive"], max(ed["error"], 1e-15))
        ratio = None if p is None else p["cpu_per_sim_s"] / ed["cpu_per_sim_s"]
        rows.append(f"| ≤ 0.5x the event-driven integrator's cost at its accuracy | {label} | event-driven "
                    f"{_g(ed['error'])} at {_g(ed['cpu_per_sim_s'])}; adaptive "
                    + ("never as accurate" if p is None else f"{_g(p['error'])} at {_g(p['cpu_per_sim_s'])} "
                       f"({_g(ratio)}x)") + f" | {_verdict(ratio is not None and ratio <= 0.5)} |")
    for label in ("rocking_block", "box_drop to rest"):
        c = cases[label]
        p = _cheapest(c["adaptive"], 1e-4)
        f = _cheapest(c["fixed"], 1e-4)
        if f is None:  # first order: error ~ h, cost ~ 1/h, from the finest step
            fin = c["fixed"][-1]
            fixed_cost = fin["cpu_per_sim_s"] * fin["error"] / 1e-4
            fixed = (f"not reached down to h = {fin['h']:g} ({_g(fin['error'])} at {_g(fin['cpu_per_sim_s'])}; "
                     f"~{_g(fixed_cost)} at 1e-4 extrapolated at first order)")
        else:
            fixed_cost = f["cpu_per_sim_s"]
            fixed = f"{_g(f['error'])} at {_g(fixed_cost)} (h = {f['h']:g})"
        adaptive = "not reached" if p is None else f"{_g(p['error'])} at {_g(p['cpu_per_sim_s'])}"
        ok = p is not None and p["cpu_per_sim_s"] <= 0.1 * fixed_cost
        rows.append(f"| error ≤ 1e-4 at ≤ 1/10 of the fixed step's cost | {label} | adaptive {adaptive}; "
                    f"fixed step {fixed} | {_verdict(ok)} |")
    return "\n".join(rows)


def doc_tables(res: dict) -> dict[str, str]:
    """The tables of docs/benchmarks.md this benchmark's JSON gives (marker name: Markdown)."""
    return {"adaptive cost table": markdown_table(res), "adaptive targets table": targets_table(res)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT, help="output folder (docs/bench: the committed file)")
    ap.add_argument("--repeat", type=int, default=3)
    add_table_option(ap, "adaptive_costs.json", "docs/benchmarks.md")
    a = ap.parse_args(argv)
    if rewrite_tables(a, doc_tables):
        return 0
    load0, wall0 = os.getloadavg()[0], time.time()
    cases = []
    for spec in CASES:
        c = bench_case(Case(*spec), a.repeat)
        pts = [("adaptive", p) for p in c["adaptive"]] + [("event-driven", c["event_driven"])] + \
            [("fixed", p) for p in c["fixed"]]
        print(f"{c['label']:24s} " + ", ".join(f"{k} {p['error']:.1e} at {p['cpu_per_sim_s']:.3g}" for k, p in pts),
              flush=True)
        cases.append(c)
    meta = {"created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "wall_seconds": time.time() - wall0, "cpus": os.cpu_count(), "load_start": load0,
            "load_end": os.getloadavg()[0], "repeat": a.repeat, "versions": versions(),
            "cpu_time": "time.process_time() around the integration loop alone, per simulated second "
                        "(driver.drive of AdaptiveRun / EventDrivenRun, recording t = 0 and T; "
                        "work_precision.run_moreau)"}
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "adaptive_costs.json").write_text(json.dumps({"meta": meta, "cases": cases}, indent=1))
    print(f"wrote {a.out / 'adaptive_costs.json'} ({time.time() - wall0:.0f} s wall)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
