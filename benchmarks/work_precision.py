"""Work-precision benchmark: error against independent references vs CPU time per simulated
second, for moreau-sim (fixed step, adaptive) and the peers (MuJoCo, PyBullet default/tuned,
Siconos time-stepping and event-driven). One command reproduces the JSON, the charts and the table:

    pip install -e '.[peers]'; apt-get install -y python3-siconos   # the peers (optional)
    python -m benchmarks.work_precision --out docs/bench # regenerates the committed JSON, tables and figures
    python -m benchmarks.work_precision --quick --out /tmp/wp        # tiny sweep (smoke test)
    python -m benchmarks.work_precision --table docs/bench/work_precision.json docs/benchmarks.md  # its tables

Equal output: every method is asked for its state at the same instants, every OUTPUT_DT = 0.01 s
in [0, T], and every error is read there: the fixed-step methods (ours and the peers') step with
h dividing OUTPUT_DT and hand back the state at those steps; the adaptive integrator records its
dense output there inside the timed run; Siconos event-driven runs once per case with time events
at those instants (no step size: its "h" is OUTPUT_DT). Each point of the JSON carries its
settings and its sampling.

Errors: bouncing ball - the first three rebound heights against e^(2n) d0 (closed form); touching
cradle - the final velocities against the simultaneous result (closed form, docs/theory.md §4);
rocking block, pendulum into a wall, box drop - q at the output instants against the event-driven
integrator (DOP853, rtol = atol = 1e-12), checked against a second method, the adaptive integrator
at rtol 1e-12 (their agreement is in the case's reference_info: the reference is trusted to it).
Levels of the summary: relative errors 1e-3, 1e-6, 1e-10. CPU time: time.process_time() around the
stepping loop only (moreau-sim: ms.step in a loop storing q, u; the adaptive integrator:
driver.drive of AdaptiveRun; peers: their runners' own loops), median over repeats, all methods
interleaved in each repeat so machine drift hits all alike. The peers run the neutral spec of each
bundled scene (benchmarks.spec) with their runners' defaults (benchmarks.peers), the touching
cradle with Siconos' exact_gaps. Plus a micro-benchmark of the impact solver inside our step:
piqp (primal, dual), the closed form for one contact, Pinocchio's ADMM and PGS, on contact problems
of our scenes (stepper.assemble: the step's own free velocity, i.e. the scene's bias).
Writes OUT/work_precision.json, OUT/wp_<case>.png and OUT/work_precision_table.md.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin

import moreau_sim as ms
from moreau_sim.adaptive import AdaptiveRun
from moreau_sim.driver import drive
from moreau_sim.event_driven import simulate_event_driven
from moreau_sim.options import Options, QPForm
from moreau_sim.recording import versions
from moreau_sim.stepper import assemble
from moreau_sim.testing import metrics
from moreau_sim.testing.references import ball_apex_gaps, cradle_simultaneous

from . import OUT, REPO, add_table_option, peers, pyplot, rewrite_tables, scene_path
from .spec import min_corner_height, to_jsonable

STEPS = (1e-2, 2e-3, 1e-3, 2e-4, 1e-4, 2e-5, 1e-5)  # each divides OUTPUT_DT
QUICK_STEPS = (1e-2, 1e-3)
OUTPUT_DT = 1e-2  # [s] every method is asked for its state at the multiples of this in [0, T], and errors read there
QUICK_SKIP = ("bouncing_ball_e0.5", "bouncing_ball_e1")  # --quick: one bouncing-ball case is enough
FULL_REPEAT_H = 1e-4  # steps >= this are repeated --repeats times; smaller ones (>= 1 s CPU each) once
LEVELS = (1e-3, 1e-6, 1e-10)  # relative accuracy levels of the summary table
FLOOR = 1e-16  # errors below this (exact to round-off) are drawn at this level
PEER_CONFIGS = {"mujoco": ("mujoco", {}), "pybullet-default": ("pybullet", {"config": "default"}),
                "pybullet-tuned": ("pybullet", {"config": "tuned"}), "siconos": ("siconos", {}),
                "siconos-event-driven": ("siconos", {"simulation": "event-driven"})}
SAMPLED = ("siconos-event-driven",)  # no step size: one run, time events at the output instants (h = OUTPUT_DT)
ADAPTIVE = "moreau-sim adaptive"  # integrator = "adaptive" (docs/theory.md §8), swept over rtol
RTOLS = (1e-4, 1e-6, 1e-8, 1e-10, 1e-12)  # its sweep (atol = rtol / 100); a point's "h" holds its rtol
QUICK_RTOLS = (1e-6, 1e-10)
METHODS = ("moreau-sim", ADAPTIVE) + tuple(PEER_CONFIGS)


@dataclass(frozen=True)
class Case:
    """One benchmark problem: a bundled scene at restitution e over T [s] (T_quick in --quick);
    metric: what the error is; scale: the error's natural size (relative error = error / scale);
    peer_scene: the scene the peers run (its neutral spec), or None when they cannot express it
    (a state error reads q at the output instants, output_grid);
    peer_params: {peer: parameters} on top of that peer's defaults."""

    key: str
    scene: str
    e: float
    T: float
    T_quick: float
    metric: str
    scale: float
    unit: str
    reference: str
    peer_scene: str | None = None
    peer_params: dict = field(default_factory=dict)


CASES = (
    Case("bouncing_ball_e0.5", "bouncing_ball", 0.5, 1.2, 1.2, "max |apex - e^(2n) d0|, n = 1..3", 0.9, "m",
         "closed form (docs/theory.md §4)", "bouncing_ball"),
    Case("bouncing_ball_e0.8", "bouncing_ball", 0.8, 2.0, 2.0, "max |apex - e^(2n) d0|, n = 1..3", 0.9, "m",
         "closed form (docs/theory.md §4)", "bouncing_ball"),
    Case("bouncing_ball_e1", "bouncing_ball", 1.0, 2.7, 2.7, "max |apex - e^(2n) d0|, n = 1..3", 0.9, "m",
         "closed form (docs/theory.md §4)", "bouncing_ball"),
    Case("newton_cradle_5", "newton_cradle_5", 1.0, 0.5, 0.1, "max |u(T) - (-0.6, 0.4, 0.4, 0.4, 0.4)|", 1.0,
         "m/s", "closed form (docs/theory.md §4)", "newton_cradle_5", peer_params={"siconos": {"exact_gaps": True}}),
    Case("rocking_block", "rocking_block", 0.5, 0.25, 0.1, "max |q(t_k) - q_ref(t_k)|, t_k every 0.01 s", 0.1,
         "m, rad", "event-driven reference (rtol = atol = 1e-12)", None),
    Case("pendulum_wall", "pendulum_wall", 0.9, 2.0, 0.8, "max |q(t_k) - q_ref(t_k)|, t_k every 0.01 s", 1.0,
         "rad", "event-driven reference (rtol = atol = 1e-12)", None),
    Case("box_drop", "box_drop", 0.5, 0.6, 0.4, "max |q(t_k) (-) q_ref(t_k)|, t_k every 0.01 s (m, rad)", 1.0,
         "m, rad", "event-driven reference (rtol = atol = 1e-12, Lie-group chart)", "box_drop"),
)


# ---------------------------------------------------------------- runs
def run_moreau(model: ms.Model, h: float, T: float) -> dict:
    """The stepping loop (ms.step, storing q and u), timed with process_time; nothing else."""
    data, st = ms.make_data(model), ms.initial_state(model)
    e, n = model.options.restitution, max(1, int(round(T / h)))
    Q, U = np.empty((n + 1, model.nq)), np.empty((n + 1, model.nv))
    Q[0], U[0] = st.q, st.u
    step = ms.step
    c0 = time.process_time()
    for k in range(n):
        r = step(model, data, st, h=h, e=e, t_next=(k + 1) * h)
        if r.qp is not None and not r.qp.ok:
            raise ms.SimulationError(f"step {k + 1}: QP {r.qp.status}")
        st = r.state
        Q[k + 1], U[k + 1] = st.q, st.u
    cpu = time.process_time() - c0
    return {"t": np.arange(n + 1) * h, "q": Q, "u": U, "cpu_seconds": cpu, "steps": n}


def run_adaptive(model: ms.Model, rtol: float, T: float, t_eval: np.ndarray) -> dict:
    """The adaptive integrator at rtol (atol = rtol / 100), default order: the driver's run (driver.drive)
    recording at t_eval (the output instants every method is asked for), timed with process_time."""
    data = ms.make_data(model)
    integ = AdaptiveRun(model, data, model.options.restitution, rtol, rtol / 100, 6, 1.0, 10 ** 6, t_end=T)
    c0 = time.process_time()
    traj = drive(integ, model, data, grid=t_eval)
    cpu = time.process_time() - c0
    a, run = traj.arrays, traj.meta["run"]
    return {"t": a["t"], "q": a["q"], "u": a["u"], "cpu_seconds": cpu, "steps": run["steps"],
            "steps_fixed": run["steps_fixed"], "events": run["events"], "nfev": run["nfev"],
            "nfev_constrained": run["nfev_constrained"]}


def output_grid(T: float) -> np.ndarray:
    """The output instants of every method: the multiples of OUTPUT_DT in [0, T] (T one of them)."""
    n = int(round(T / OUTPUT_DT))
    return np.arange(n + 1) * OUTPUT_DT


def series(case: Case, out: dict) -> dict:
    """A run in the model's coordinates (t, q, u: ours, or a peer's through spec.to_model_coordinates)
    as the arrays metrics.py reads (t, q, u, gap, u_final)."""
    t, q, u = out["t"], out["q"], out["u"]
    if case.scene == "bouncing_ball":
        gap = q[:, :1] - 0.1
    elif case.scene == "newton_cradle_5":
        gap = np.diff(q, axis=1) - 0.2
    elif case.scene == "box_drop":
        quat = q[:, 3:7]
        gap = min_corner_height(q[:, :3], np.c_[quat[:, 3:], quat[:, :3]], [0.1, 0.1, 0.2])[:, None]
    else:
        gap = np.zeros((len(t), 0))
    return {"t": t, "q": q, "u": u, "gap": gap, "u_final": u[-1]}


def error_of(case: Case, series: dict, ref: dict, model: ms.Model) -> dict:
    """The case's error (module doc) and extras (max penetration where the gaps are known)."""
    out = {"penetration": metrics.max_penetration(series["gap"]) if series["gap"].size else None}
    if case.scene == "bouncing_ball":
        r = metrics.apex_error(series, ref["apex"], count=3)
        out.update(error=r.max_abs, missing_apexes=r.missing, apexes=r.heights.tolist())
    elif case.scene == "newton_cradle_5":
        out.update(error=float(np.abs(series["u_final"] - ref["u_final"]).max()), u_final=series["u_final"].tolist())
    else:
        lie = model.pin if model.nq != model.nv else None
        out.update(error=metrics.state_error(series, ref["traj"], ref["instants"], model=lie).q_max)
    return out


def reference(case: Case, T: float, model: ms.Model) -> dict:
    if case.scene == "bouncing_ball":
        apex = ball_apex_gaps(case.e, 3)
        return {"apex": apex, "info": {"apex_heights": apex}}
    if case.scene == "newton_cradle_5":
        u = cradle_simultaneous(case.e)
        return {"u_final": np.array(u), "info": {"u_final": u}}
    grid = output_grid(T)
    instants = grid[1:]
    c0 = time.process_time()
    tr = simulate_event_driven(model, t_end=T, t_eval=grid)
    print(f"  reference {case.key}: {tr.meta['run']['impacts']} impacts, {len(tr.meta['zeno'])} accumulation "
          f"points, {time.process_time() - c0:.1f} s CPU", flush=True)
    # a second, different method on the same instants: the extrapolated midpoint steps of §8 at rtol 1e-12
    # (its own smooth integrator and error control; the event rules are shared): the reference is
    # trusted to their agreement
    other = run_adaptive(model, 1e-12, T, grid)
    lie = model.pin if model.nq != model.nv else None
    agree = metrics.state_error({"t": other["t"], "q": other["q"], "u": other["u"]}, tr, instants, model=lie)
    print(f"  reference {case.key}: event-driven and adaptive (rtol 1e-12) agree to {agree.q_max:.1e}", flush=True)
    info = {"impacts": tr.meta["run"]["impacts"], "events": tr.meta["run"]["events"],
            "accumulation_points": [z["t_accumulation"] for z in tr.meta["zeno"]], "instants": len(instants),
            "tolerances": tr.meta["reference"], "second_method": "moreau-sim adaptive, rtol 1e-12, atol 1e-14",
            "agreement_q": agree.q_max, "agreement_u": agree.u_max}
    return {"traj": tr, "instants": instants, "info": info}


# ---------------------------------------------------------------- impact solvers inside the step
def _frame(n: np.ndarray) -> np.ndarray:
    """A rotation whose z axis is n."""
    a = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    x = a - (a @ n) * n
    x /= np.linalg.norm(x)
    return np.c_[x, np.cross(n, x), n]


def solver_states(case_scene: str, e: float, h: float, T: float, count: int) -> list:
    """(M, W, Minv, v_free, constraint models, datas) at contact steps of a moreau-sim run: the
    impact problems of stepper.assemble (the step's own free velocity)."""
    model = ms.build_model(ms.load_scene(scene_path(case_scene)).with_options(restitution=e, dt=h, duration=T))
    traj = ms.simulate(model, progress=False)
    data = ms.make_data(model)
    pm, pd = model.pin, data.pin
    out = []
    for i in np.flatnonzero(traj.n_contacts[1:] > 0):
        problem = assemble(model, data, ms.State(float(traj.t[i]), traj.q[i], traj.u[i]), h=h, e=e)
        c = problem.contacts
        if c.m == 0 or c.corners:
            continue
        qm, M, W, Minv, v_free = problem.q_m, problem.M, problem.W, problem.Minv, problem.v_free
        pin.computeJointJacobians(pm, pd, qm)  # also the joint placements oMi at q_m
        cms, cds = pin.StdVec_ConstraintModel(), pin.StdVec_ConstraintData()
        for k in range(c.m):
            R = _frame(c.normal[k])
            ja, jb = int(c.joint_a[k]), int(c.joint_b[k])
            pb = pd.oMi[jb].actInv(pin.SE3(R, c.point_b[k]))  # joint1 = B (normal points into A)
            pa = pd.oMi[ja].actInv(pin.SE3(R, c.point_a[k]))
            cm = pin.PointContactConstraintModel(pm, jb, pb, ja, pa)
            cm.setFriction(0.0)
            cms.append(pin.ConstraintModel(cm))
            cds.append(cms[-1].createData())
        for cm, cd in zip(cms, cds):
            cm.calc(pm, pd, cd)
        J = np.asarray(pin.getConstraintsJacobian(pm, pd, cms, cds)).reshape(3 * c.m, model.nv)
        if np.abs(J[2::3].T - W).max() > 1e-9 * (1 + np.abs(W).max()):
            raise RuntimeError(f"{case_scene}: Pinocchio's contact Jacobian normal rows differ from ours")
        if (W.T @ v_free).min() < -1e-9:  # an impact or a push: something to solve
            out.append((M, W, Minv, v_free, J.copy(), cms, cds))
        if len(out) == count:
            break
    return out


def _solve_all(M, W, Minv, v0, J, cms, cds):
    """{solver: function() -> v}."""
    G = J @ Minv @ J.T
    g = J @ v0
    fs = {"piqp primal": lambda: ms.project(M, W, v0, Minv=Minv).v,
          "piqp dual": lambda: ms.project(M, W, v0, Minv=Minv, form=QPForm.DUAL).v}
    if W.shape[1] == 1:
        w = W[:, 0]

        def closed():
            Miw = Minv @ w
            return v0 + Miw * max(0.0, -(w @ v0) / (w @ Miw))
        fs["closed form (1 contact)"] = closed

    def admm():
        s = pin.ADMMConstraintSolver(G.shape[0])
        st, res = pin.ADMMSolverSettings(), pin.ADMMSolverResult()
        st.absolute_feasibility_tol = st.absolute_complementarity_tol = 1e-10
        st.relative_feasibility_tol = st.relative_complementarity_tol = 1e-10
        s.solve(pin.DelassusOperatorDense(G), g, cms, cds, st, res)
        return v0 + Minv @ (J.T @ res.retrieveConstraintImpulses())

    def pgs():  # with mu = 0 one call of Pinocchio 4.1's PGS is one sweep (docs/benchmarks.md): repeat, warm-started
        s, D = pin.PGSConstraintSolver(G.shape[0]), pin.DelassusOperatorDense(G)
        st, res = pin.PGSSolverSettings(), pin.PGSSolverResult()
        s.solve(D, g, cms, cds, st, res)
        for _ in range(1000):
            lam = res.retrieveConstraintImpulses().copy()
            sig = (G @ lam + g)[2::3]
            if abs(sig @ lam[2::3]) < 1e-12 and sig.min() > -1e-9:
                break
            res.setConstraintImpulseGuess(lam)
            s.solve(D, g, cms, cds, st, res)
        return v0 + Minv @ (J.T @ res.retrieveConstraintImpulses())
    fs["pinocchio ADMM"] = admm
    fs["pinocchio PGS"] = pgs
    return fs


def solver_benchmark(quick: bool) -> list[dict]:
    """Time per solve (median over states of the best of 3 batches) and max |v - v_piqp|."""
    plan = [("bouncing_ball", 0.5, 1e-3, 2.0), ("newton_cradle_5", 1.0, 1e-3, 0.3),
            ("rocking_block", 0.5, 1e-3, 0.3), ("box_drop", 0.5, 1e-3, 1.5)]
    rows = []
    for scene, e, h, T in plan:
        states = solver_states(scene, e, h, T, 4 if quick else 40)
        if not states:
            continue
        times: dict[str, list] = {}
        diff: dict[str, float] = {}
        for st in states:
            fs = _solve_all(*st)
            v_ref = fs["piqp primal"]()
            for name, f in fs.items():
                reps = 5 if quick else 50
                best = []
                for _ in range(3):
                    c0 = time.process_time()
                    for _ in range(reps):
                        v = f()
                    best.append((time.process_time() - c0) / reps)
                times.setdefault(name, []).append(min(best) * 1e6)
                diff[name] = max(diff.get(name, 0.0), float(np.abs(v - v_ref).max()))
        m = sorted({s[1].shape[1] for s in states})
        for name in times:
            rows.append({"scene": scene, "states": len(states), "contacts": m, "solver": name,
                         "us_per_solve": statistics.median(times[name]), "max_abs_v_diff": diff[name]})
            print(f"  solver {scene:16s} {name:24s} {rows[-1]['us_per_solve']:9.1f} us  "
                  f"max|v - v_piqp| = {diff[name]:.1e}", flush=True)
    return rows


# ---------------------------------------------------------------- summary and plots
def cost_at(points: list, method: str, level: float, reliable: bool = True) -> float | None:
    """CPU s / sim s `method` needs for a relative error <= level: reliable (default) - at the
    largest step from which every smaller step of the sweep stays within the level (an accuracy
    met by luck at one step and lost at the next does not count); else the cheapest such point."""
    pts = sorted([p for p in points if p["method"] == method], key=lambda p: -p["h"])
    ok = [p.get("rel_error") is not None and p["rel_error"] <= level for p in pts]
    if not reliable:
        return min((p["cpu_per_sim_s"] for p, k in zip(pts, ok) if k), default=None)
    return next((pts[i]["cpu_per_sim_s"] for i in range(len(pts)) if all(ok[i:])), None)


def summarize(points: list, cases, peer_names) -> list[dict]:
    """Per case and level: the reliable cost (cost_at) of our fixed step, our adaptive integrator, the best
    peer and Siconos event-driven, and the ratios best peer / the cheaper of ours and Siconos ED / adaptive."""
    rows = []
    for case in cases:
        pts = [p for p in points if p["case"] == case.key]
        for level in LEVELS:
            mine = cost_at(pts, "moreau-sim", level)
            adaptive = cost_at(pts, ADAPTIVE, level)
            ours = min([c for c in (mine, adaptive) if c is not None], default=None)
            peers = {m: cost_at(pts, m, level) for m in peer_names}
            reached = {m: c for m, c in peers.items() if c is not None}
            best = min(reached, key=reached.get) if reached else None
            if case.peer_scene is None:
                ratio, note = None, "no peer can express this scene (benchmarks.spec cannot carry it)"
            elif best is None:
                ratio, note = None, "no peer reaches this accuracy"
            elif ours is None:
                ratio, note = 0.0, "moreau-sim does not reach this accuracy"
            else:
                ratio, note = reached[best] / ours, ""
            any_mine = min([c for c in (cost_at(pts, "moreau-sim", level, reliable=False),
                                        cost_at(pts, ADAPTIVE, level, reliable=False)) if c is not None], default=None)
            any_peer = [c for c in (cost_at(pts, m, level, reliable=False) for m in peer_names) if c is not None]
            ratio_any = min(any_peer) / any_mine if any_peer and any_mine else None
            sic = peers.get("siconos-event-driven")
            rows.append({"case": case.key, "level": level, "moreau_cpu": mine, "adaptive_cpu": adaptive,
                         "best_peer": best, "best_peer_cpu": reached.get(best), "ratio": ratio, "note": note,
                         "ratio_any_point": ratio_any,
                         "ratio_adaptive": reached[best] / adaptive if best is not None and adaptive else None,
                         "siconos_ed_cpu": sic, "ratio_siconos_ed": sic / adaptive if sic and adaptive else None})
    return rows


def table_md(rows: list) -> str:
    out = ["| case | rel. error ≤ | moreau-sim fixed step | moreau-sim adaptive | best peer "
           "| best peer / cheaper of ours | Siconos event-driven / adaptive |", "|---|---|---:|---:|---|---|---:|"]

    def f(x):
        return "—" if x is None else f"{x:.3g}"
    for r in rows:
        peer = "—" if r["best_peer"] is None else f"{r['best_peer']} ({f(r['best_peer_cpu'])})"
        ratio = r["note"] if r["ratio"] is None else (f"{r['ratio']:.3g}" + (f" ({r['note']})" if r["note"] else ""))
        out.append(f"| {r['case']} | {r['level']:g} | {f(r['moreau_cpu'])} | {f(r['adaptive_cpu'])} | {peer} | {ratio} "
                   f"| {f(r.get('ratio_siconos_ed'))} |")
    return "\n".join(out)


LABELS = {"moreau-sim": "moreau-sim", "mujoco": "MuJoCo", "pybullet-default": "PyBullet default",
          "pybullet-tuned": "PyBullet tuned", "siconos": "Siconos", "siconos-event-driven": "Siconos event-driven"}
EXACT = 1e-12  # relative errors below this are reported as "exact to round-off"


def _pts(points: list, case: str, method: str) -> list:
    """The points of one curve that have an error, coarse to fine (adaptive: loose to tight rtol)."""
    return sorted((p for p in points if p["case"] == case and p["method"] == method
                   and p.get("rel_error") is not None), key=lambda p: -p["h"])


def _errors_cell(pts: list) -> str:
    errs = [(p["rel_error"], p["h"]) for p in pts]
    if not errs:
        return "—"
    worst = max(e for e, _ in errs)
    if worst <= EXACT:
        return f"≤ {worst:.1g} at every h"
    cell = f"{errs[0][0]:.2g} … {errs[-1][0]:.2g}"
    best, h = min(errs)
    if best < errs[-1][0] / 3 and h != errs[0][1]:  # finer steps lose accuracy again: say where it was best
        cell += f" (best {best:.2g} at h = {h:g})"
    return cell


def errors_table(doc: dict) -> str:
    """Relative errors of every time-stepping method per case, coarse to fine h (docs/benchmarks.md)."""
    methods = [m for m in doc["meta"]["methods"] if m in LABELS]
    steps = doc["meta"]["steps"]
    out = [f"Relative errors per h (coarse → fine, h = {steps[0]:g} … {steps[-1]:g}; "
           f"\"best\" where a finer step loses accuracy again):", "",
           "| case | " + " | ".join(LABELS[m] for m in methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for case in doc["cases"]:
        cells = [_errors_cell(_pts(doc["points"], case["key"], m)) for m in methods]
        out.append(f"| {case['key']} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def summary_table(doc: dict) -> str:
    """The summary table (as in work_precision_table.md) with the run it comes from (docs/benchmarks.md)."""
    meta = doc["meta"]
    git = meta.get("git") or {}
    modified = f" plus {len(git['modified'])} modified files" if git.get("modified") else ""
    load = f"{meta['load_start'][0]:.1f} → {meta['load_end'][0]:.1f}" if meta.get("load_end") else "?"
    return (f"Run of {meta['created'][:10]} (git `{str(git.get('commit', '?'))[:7]}`{modified}; "
            f"{meta['wall_seconds']:.0f} s wall on {meta['cpus']} cores, load average {load}):\n\n"
            + table_md(doc["summary"]))


SOLVERS = ("piqp primal", "piqp dual", "closed form (1 contact)", "pinocchio ADMM", "pinocchio PGS")


def solvers_table(doc: dict) -> str:
    """The impact-solver micro-benchmark, µs per solve (docs/benchmarks.md)."""
    groups: dict = {}
    for r in doc["solvers"]:
        groups.setdefault((r["scene"], r["states"], tuple(r["contacts"])), {})[r["solver"]] = r
    out = ["| scene (contacts), states | piqp primal | piqp dual | closed form | Pinocchio ADMM | Pinocchio PGS "
           "| max \\|v − v_piqp\\| ADMM / PGS |", "|---|---:|---:|---:|---:|---:|---|"]
    for (scene, states, contacts), rs in groups.items():
        cells = [f"{rs[s]['us_per_solve']:.1f}" if s in rs else "—" for s in SOLVERS]
        diff = " / ".join((f"{rs[s]['max_abs_v_diff']:.0e}" if rs[s]["max_abs_v_diff"] else "0") if s in rs else "—"
                          for s in ("pinocchio ADMM", "pinocchio PGS"))
        n = "/".join(map(str, contacts))
        out.append(f"| `{scene}` ({n}), {states} | " + " | ".join(cells) + f" | {diff} |")
    return "\n".join(out)


ED_TARGET = 1e-9  # [relative] the accuracy of the target against Siconos event-driven (>= 3x less CPU)


def adaptive_table(doc: dict) -> str:
    """The adaptive integrator against Siconos event-driven (one run, time events at the output
    instants) and the fixed step (docs/benchmarks.md)."""
    summary = {(r["case"], r["level"]): r for r in doc["summary"]}
    rtols = doc["meta"].get("adaptive_rtols", [])
    out = [f"| case | adaptive: relative error at CPU s/sim s (rtol {rtols[0]:g} → {rtols[-1]:g}) "
           "| Siconos event-driven: error at CPU s/sim s "
           f"| Siconos ED / adaptive at error ≤ {ED_TARGET:g} (target ≥ 3) "
           "| fixed step at rel. error 1e-3 | fixed / adaptive at 1e-3 |", "|---|---|---|---:|---:|---:|"]
    for case in doc["cases"]:
        key = case["key"]
        pts = _pts(doc["points"], key, ADAPTIVE)
        errs = [p["rel_error"] for p in pts]
        cpus = [p["cpu_per_sim_s"] for p in pts]
        if not pts:
            ad = "—"
        elif max(errs) <= EXACT:
            ad = f"{max(errs):.2g} at {min(cpus):.2g}-{max(cpus):.2g} (any rtol)"
        else:
            ad = ", ".join(f"{p['rel_error']:.2g} at {p['cpu_per_sim_s']:.2g}" for p in pts)
        ed = _pts(doc["points"], key, "siconos-event-driven")
        sic = ", ".join(f"{p['rel_error']:.1g} at {p['cpu_per_sim_s']:.2g}" for p in ed) if ed else "—"
        ok = [p for p in ed if p["rel_error"] <= ED_TARGET]
        mine = cost_at(pts, ADAPTIVE, ED_TARGET)
        vs = "—" if not (ok and mine) else f"{min(p['cpu_per_sim_s'] for p in ok) / mine:.2g}"
        row = summary.get((key, 1e-3), {})
        fixed, adapt = row.get("moreau_cpu"), row.get("adaptive_cpu")
        ratio = "—" if not (fixed and adapt) else f"{fixed / adapt:{'.2g' if fixed < 100 * adapt else '.0f'}}"
        out.append(f"| {key} | {ad} | {sic} | {vs} | {'—' if fixed is None else f'{fixed:.2g}'} | {ratio} |")
    return "\n".join(out)


def doc_tables(doc: dict) -> dict[str, str]:
    """The tables of docs/benchmarks.md this benchmark's JSON gives (marker name: Markdown)."""
    return {"work-precision summary": summary_table(doc), "work-precision errors": errors_table(doc),
            "impact-solver table": solvers_table(doc), "adaptive table": adaptive_table(doc)}


def plot(case: Case, points: list, path: Path) -> None:
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(7, 5))
    clamped = False
    for i, m in enumerate(METHODS):
        pts = sorted([p for p in points if p["case"] == case.key and p["method"] == m
                      and p.get("rel_error") is not None], key=lambda p: -p["h"])
        if not pts:
            continue
        x = [p["cpu_per_sim_s"] for p in pts]
        y = [max(p["rel_error"], FLOOR) for p in pts]
        clamped |= min(p["rel_error"] for p in pts) < FLOOR
        ax.loglog(x, y, "o-", color=f"C{i}", label=m + (" (rtol)" if m == ADAPTIVE else ""),
                  lw=2 if m in ("moreau-sim", ADAPTIVE) else 1)
        for p, xi, yi in zip(pts, x, y):
            ax.annotate(f"{p['h']:.0e}".replace("e-0", "e-"), (xi, yi), fontsize=6, color=f"C{i}",
                        xytext=(3, 3), textcoords="offset points")
    if clamped:
        ax.axhline(FLOOR, color="0.5", lw=0.6, ls=":")
        ax.annotate("exact to round-off (drawn at 1e-16)", (0.01, FLOOR), xycoords=("axes fraction", "data"),
                    xytext=(0, 3), textcoords="offset points", fontsize=7, color="0.4")
    ax.set_xlabel("CPU seconds per simulated second (median of repeats)")
    ax.set_ylabel(f"relative error (error / {case.scale:g} {case.unit})")
    ax.set_title(f"{case.key}: {case.metric}\nreference: {case.reference}", fontsize=9)
    ax.grid(True, which="both", lw=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------- main
def _git() -> dict:
    """The commit measured and whether the working tree differed from it (read-only git calls)."""

    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
                               capture_output=True, text=True).stdout.split("\n")
        return {"commit": head, "modified": sorted(x[3:] for x in dirty if x.strip())}
    except OSError:
        return {}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(OUT), help="output folder (docs/bench: the committed files)")
    ap.add_argument("--quick", action="store_true", help="tiny sweep: 2 step sizes, short durations, 1 repeat")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats of runs with h >= 1e-4 (median)")
    ap.add_argument("--peers", default=",".join(peers.PEERS), help="peers to try (comma-separated)")
    ap.add_argument("--no-solvers", action="store_true", help="skip the impact-solver micro-benchmark")
    ap.add_argument("--cases", default="", help="only these cases (comma-separated keys; default: all)")
    ap.add_argument("--steps", default="", help="the fixed steps h [s] (comma-separated, each dividing OUTPUT_DT; "
                                                "default: STEPS)")
    add_table_option(ap, "work_precision.json", "docs/benchmarks.md")
    a = ap.parse_args(argv)
    if rewrite_tables(a, doc_tables):
        return 0
    steps = tuple(float(x) for x in a.steps.split(",") if x) or (QUICK_STEPS if a.quick else STEPS)
    bad = [h for h in steps if not (h > 0 and abs(OUTPUT_DT / h - round(OUTPUT_DT / h)) < 1e-9)]
    if bad:
        ap.error(f"--steps: {bad[0]:g} does not divide OUTPUT_DT = {OUTPUT_DT:g} s")
    keys = [k for k in a.cases.split(",") if k]
    unknown = sorted(set(keys) - {c.key for c in CASES})
    if unknown:
        ap.error(f"--cases: unknown case {unknown[0]!r} (one of {', '.join(c.key for c in CASES)})")
    cases = [c for c in CASES if not (a.quick and c.key in QUICK_SKIP) and (not keys or c.key in keys)]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    repeats = 1 if a.quick else a.repeats
    wanted = [p for p in a.peers.split(",") if p]
    avail = peers.available()
    skipped = []
    for p in peers.PEERS:
        if p not in wanted:
            skipped.append({"peer": p, "reason": "not requested (--peers)"})
        elif avail[p] is not None:
            skipped.append({"peer": p, "reason": avail[p]})
    for s in skipped:
        print(f"NOTE: peer {s['peer']} skipped: {s['reason']}", flush=True)
    peer_methods = [m for m, (p, _) in PEER_CONFIGS.items() if p in wanted and avail[p] is None]
    started = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    load0 = os.getloadavg()
    wall0 = time.time()

    models, refs = {}, {}
    for case in cases:
        T = case.T_quick if a.quick else case.T
        for h in {*steps, STEPS[0]}:  # the reference and the adaptive runs: dt = STEPS[0] whatever --steps says
            models[case.key, h] = ms.build_model(ms.load_scene(scene_path(case.scene)).with_options(
                restitution=case.e, dt=h, duration=T))
        refs[case.key] = reference(case, T, models[case.key, STEPS[0]])
        if case.peer_scene is None:
            print(f"NOTE: {case.key}: no peer can express this scene (the peers' runners cover "
                  f"{', '.join(sorted({c.peer_scene for c in cases if c.peer_scene}))})", flush=True)

    points: dict = {}
    n_rep = max(repeats, 1)
    for rep in range(n_rep):
        for case in cases:
            T = case.T_quick if a.quick else case.T
            for h in steps:
                if rep > 0 and h < FULL_REPEAT_H:
                    continue
                methods = ["moreau-sim"] + (peer_methods if case.peer_scene else [])
                stride = max(1, int(round(OUTPUT_DT / h)))  # the steps landing on the output instants
                for m in methods:
                    if m in SAMPLED and h != OUTPUT_DT:  # one run: time events at the output instants
                        continue
                    key = (case.key, m, h)
                    sampling = ({"output_every": OUTPUT_DT, "time_events_every": OUTPUT_DT} if m in SAMPLED else
                                {"output_every": OUTPUT_DT, "stride": stride, "note": "a step lands on every output "
                                 "instant; its state there is what the error reads"})
                    p = points.setdefault(key, {"case": case.key, "scene": case.scene, "e": case.e, "method": m,
                                                "h": h, "T": T, "cpu_repeats": [], "sampling": sampling})
                    if p.get("failed"):
                        continue
                    try:
                        if m == "moreau-sim":
                            res = run_moreau(models[case.key, h], h, T)
                            res |= {k: res[k][::stride] for k in ("t", "q", "u")}
                            p.setdefault("settings", {"step": "ms.step (midpoint Moreau)", "h": h,
                                                      "options": models[case.key, h].options.to_dict()})
                        else:
                            peer, params = PEER_CONFIGS[m]
                            t, q, u, res = peers.run_model(peer, models[case.key, h], e=case.e, h=h, T=T,
                                                           stride=1 if m in SAMPLED else stride, **params,
                                                           **case.peer_params.get(peer, {}))
                            res |= {"t": t, "q": q, "u": u}
                            p.setdefault("settings", {k: v for k, v in res["settings"].items() if k != "xml"})
                            p.setdefault("version", res.get("version"))
                    except (peers.PeerError, ms.MoreauSimError) as exc:
                        print(f"NOTE: {m} failed on {case.key} h={h:g}: {str(exc).splitlines()[0]}", flush=True)
                        p.update(failed=str(exc).splitlines()[0], error=None, rel_error=None)
                        continue
                    n = max(1, int(round(T / h)))
                    p["cpu_repeats"].append(res["cpu_seconds"] / (n * h))
                    if rep == 0:
                        p.update(error_of(case, series(case, res), refs[case.key], models[case.key, h]))
                        p["rel_error"] = p["error"] / case.scale
                    p["cpu_per_sim_s"] = statistics.median(p["cpu_repeats"])
                    if rep == 0:
                        print(f"{case.key:20s} {m:17s} h={h:7.0e}  cpu/sim-s={p['cpu_per_sim_s']:9.4f}  "
                              f"rel.err={p['rel_error']:.2e}", flush=True)
            for rtol in (QUICK_RTOLS if a.quick else RTOLS):
                key = (case.key, ADAPTIVE, rtol)
                p = points.setdefault(key, {"case": case.key, "scene": case.scene, "e": case.e, "method": ADAPTIVE,
                                            "h": rtol, "rtol": rtol, "T": T, "cpu_repeats": [],
                                            "settings": {"rtol": rtol, "atol": rtol / 100, "order": 6, "max_step": 1.0},
                                            "sampling": {"output_every": OUTPUT_DT,
                                                         "note": "driver.drive records the dense output at the "
                                                                 "output instants, inside the timed run"}})
                if p.get("failed"):
                    continue
                try:
                    res = run_adaptive(models[case.key, STEPS[0]], rtol, T, output_grid(T))
                except ms.MoreauSimError as exc:
                    print(f"NOTE: {ADAPTIVE} failed on {case.key} rtol={rtol:g}: {str(exc).splitlines()[0]}",
                          flush=True)
                    p.update(failed=str(exc).splitlines()[0], error=None, rel_error=None)
                    continue
                p["cpu_repeats"].append(res["cpu_seconds"] / T)
                if rep == 0:
                    p.update(error_of(case, series(case, res), refs[case.key], models[case.key, STEPS[0]]))
                    p.update(rel_error=p["error"] / case.scale, steps=res["steps"], steps_fixed=res["steps_fixed"],
                             events=res["events"], nfev=res["nfev"], nfev_constrained=res["nfev_constrained"])
                p["cpu_per_sim_s"] = statistics.median(p["cpu_repeats"])
                if rep == 0:
                    print(f"{case.key:20s} {ADAPTIVE:17s} rtol={rtol:7.0e}  cpu/sim-s={p['cpu_per_sim_s']:9.4f}  "
                          f"rel.err={p['rel_error']:.2e}", flush=True)
        print(f"-- repeat {rep + 1}/{n_rep} done ({time.time() - wall0:.0f} s wall)", flush=True)

    pts = list(points.values())
    solvers = [] if a.no_solvers else solver_benchmark(a.quick)
    summary = summarize(pts, cases, peer_methods)
    doc = {
        "meta": {"created": started, "wall_seconds": time.time() - wall0, "quick": a.quick, "steps": list(steps),
                 "repeats": repeats, "full_repeat_min_h": FULL_REPEAT_H, "levels": list(LEVELS),
                 "platform": platform.platform(), "cpus": os.cpu_count(), "load_start": load0,
                 "load_end": os.getloadavg(), "versions": versions(), "git": _git(), "peers_available": avail,
                 "peers_skipped": skipped, "methods": ["moreau-sim", ADAPTIVE] + peer_methods,
                 "adaptive_rtols": list(QUICK_RTOLS if a.quick else RTOLS),
                 "moreau_options": Options().to_dict(),
                 "cpu_time": "time.process_time() around the stepping loop only; per simulated second; "
                             "median over repeats (h < 1e-4: one run)"},
        "cases": [{"key": c.key, "scene": c.scene, "e": c.e, "T": c.T_quick if a.quick else c.T, "metric": c.metric,
                   "scale": c.scale, "unit": c.unit, "reference": c.reference, "peer_scene": c.peer_scene,
                   "reference_info": refs[c.key]["info"]}
                  for c in cases],
        "points": pts,
        "summary": summary,
        "solvers": solvers,
    }
    (out / "work_precision.json").write_text(json.dumps(to_jsonable(doc), indent=1))
    for case in cases:
        plot(case, pts, out / f"wp_{case.key}.png")
    (out / "work_precision_table.md").write_text(table_md(summary))
    print(table_md(summary))
    print(f"wrote {out / 'work_precision.json'} and {len(cases)} PNGs ({time.time() - wall0:.0f} s wall)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
