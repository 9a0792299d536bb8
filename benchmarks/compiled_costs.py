"""Per-step cost of the compiled step against the Python step and the peers, side by side in one run.

A benchmark, not a test. For each case the scene is run once to collect its states; on the same
states one step is timed with step_impl = "compiled" and with step_impl = "python" (ms.step, best
of `repeat` per state, median over up to `states` states of the phase, us), with the share of those
steps the compiled step took itself (the rest it hands back to Python) and, where it took them all,
the extension's call alone (the C++ step and its crossing, without ms.step's Python around it).
In the same run each peer that can express the scene (peers.siconos: Moreau-Jean theta 1/2 with its LCP; peers.mujoco:
mj_step; their runners' settings) runs the whole scene `repeat` times with a timer around each step
inside its own stepping loop; per step the best of those runs, median over the steps of the same
phase (the phase rule `phase` applied to the peer's own contact count per step). Whole runs: the
scene by ms.simulate (recording included, compiled and Python step) against the peers' whole runs
of the same scene and step size (their loop with its recording), wall time per step, the best of
`repeat` rounds that run every side in turn. The cost targets (TARGETS) get their verdicts from
these figures. The 10^6-step run (--million): a ball run of MILLION steps with the default sampling through
ms.run against Siconos's loop over the same steps, CPU per step and peak memory, each side in a child process
of its own (its VmHWM). Writes compiled_costs.json and compiled_costs.png to out/ (or --out).

    python -m benchmarks.compiled_costs [--out docs/bench] [--repeat 7] [--states 200] [--million]
    python -m benchmarks.compiled_costs --table docs/bench/compiled_costs.json docs/benchmarks.md
    python -m benchmarks.compiled_costs --plot docs/bench/compiled_costs.json   # redraw the chart from the JSON
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np

import moreau_sim as ms
from moreau_sim import compiled
from moreau_sim.recording import versions

from . import OUT, add_plot_option, add_table_option, pyplot, redraw, rewrite_tables, scene_path
from .step_costs import best  # best of `repeat` timings, us

# (label, scene, phase: "flight", "contact", or "late-contact" = the last third of the run's contact states)
CASES = (("ball, flight", "bouncing_ball", "flight"),
         ("ball, in contact (resting)", "zeno_ball", "contact"),
         ("cradle, contacts closed", "newton_cradle_5", "contact"),
         ("box, resting", "box_drop", "late-contact"),
         ("ten boxes, resting", "box_stack_10", "late-contact"),
         ("100 beads, in contact", "column_of_beads_100", "contact"),
         ("quadruped, resting", "quadruped_drop", "late-contact"))
# ms.simulate, recording included: (scene, duration s or None for the scene's own)
WHOLE_RUNS = (("bouncing_ball", None), ("zeno_ball", 6.0), ("zeno_ball", None), ("newton_cradle_5", None),
              ("box_drop", None), ("quadruped_drop", None), ("box_stack_10", None))
# What a peer's figure on a scene is, where it is not the same model (peers.siconos's module doc)
PEER_NOTES = {("siconos", "box_drop"): "Siconos's mechanics toolbox (Bullet detection, FrictionContact(3) with "
                                       "mu = 0 by NSGS in a Newton loop): a different formulation"}
MILLION = 10**6  # steps of the 10^6-step run (--million)
MILLION_SCENE = "bouncing_ball"
PEERS = ("siconos", "mujoco")
PEER_NAMES = {"siconos": "Siconos", "mujoco": "MuJoCo"}
# The cost targets: (what, kind, case or scene, bound). kind "us": the compiled step's median
# (us) <= bound; "x siconos": the compiled step over Siconos's per step <= bound; "run x siconos":
# ms.simulate's wall per step (compiled) over Siconos's whole run per step <= bound.
TARGETS = (("ball contact step <= 1.5x Siconos", "x siconos", "zeno_ball", 1.5),
           ("ball contact step in place (ms.step_in_place) <= 1.5x Siconos", "in place x siconos", "zeno_ball", 1.5),
           ("whole run of the ball scene <= 1.5x Siconos per step", "run x siconos", "bouncing_ball", 1.5),
           ("whole run of the ball, 6 s (bounces, then rests) <= 1.5x Siconos per step", "run x siconos",
            "zeno_ball 6 s", 1.5),
           ("whole run of the resting ball <= 1.5x Siconos per step", "run x siconos", "zeno_ball", 1.5),
           ("whole run of the cradle <= 1.5x Siconos per step", "run x siconos", "newton_cradle_5", 1.5),
           ("cradle <= Siconos per step", "x siconos", "newton_cradle_5", 1.0),
           ("box_drop resting <= 20 µs", "us", "box_drop", 20.0),
           ("box_stack_10 resting <= 0.5 ms", "us", "box_stack_10", 500.0),
           ("quadruped resting <= 60 µs", "us", "quadruped_drop", 60.0),
           ("10^6 ball steps (ms.run, default sampling) <= 1.5x Siconos's loop, CPU per step", "million x siconos",
            MILLION_SCENE, 1.5),
           ("10^6 ball steps: peak memory <= 200 MiB", "million MiB", MILLION_SCENE, 200.0))


def phase(contacts, which: str) -> np.ndarray:
    """Which steps of a run (their contact counts, in order) belong to the phase `which`."""
    c = np.asarray(contacts)
    mask = c == 0 if which == "flight" else c > 0
    if which.startswith("late-"):
        idx = np.flatnonzero(mask)
        mask = np.zeros_like(mask)
        mask[idx[2 * len(idx) // 3:]] = True
    return mask


def bench_case(label: str, scene: str, which: str, repeat: int, n_states: int) -> dict:
    sc = ms.load_scene(scene_path(scene))
    mods = {impl: ms.build_model(sc.with_options(step_impl=impl)) for impl in ("python", "compiled")}
    datas = {impl: ms.make_data(m) for impl, m in mods.items()}
    # the states: the scene's run with the compiled step (the same trajectory as the Python step's,
    # tests/test_compiled.py), each step's contact count from a data of its own (counts untouched)
    traj = ms.simulate(mods["compiled"], progress=False)
    h, e = sc.options.dt, sc.options.restitution
    m, d = mods["compiled"], ms.make_data(mods["compiled"])
    states = [ms.State(float(traj.t[i]), traj.q[i], traj.u[i]) for i in range(len(traj.t) - 1)]
    counts = [ms.step(m, d, st, h=h, e=e).contacts.m for st in states]
    idx = np.flatnonzero(phase(counts, which))
    idx = idx[np.unique(np.linspace(0, len(idx) - 1, min(n_states, len(idx))).astype(int))]
    out = {"label": label, "scene": scene, "which": which, "states": len(idx),
           "contacts": float(np.median([counts[i] for i in idx]))}
    for impl in ("python", "compiled"):
        m, d = mods[impl], datas[impl]
        t = [best(lambda st=states[i], m=m, d=d: ms.step(m, d, st, h=h, e=e), repeat) for i in idx]
        out[impl] = statistics.median(t)
    # ms.step_in_place: the same step, q and u overwritten, no result objects (reset to the state each call)
    m, d = mods["compiled"], datas["compiled"]
    q, u = np.empty(m.nq), np.empty(m.nv)

    def in_place(st):
        q[:], u[:] = st.q, st.u
        ms.step_in_place(m, d, st.t, q, u, h=h, e=e)

    out["in_place"] = statistics.median(best(lambda st=states[i]: in_place(st), repeat) for i in idx)
    c = compiled.counts(datas["compiled"])  # every timed call of the compiled model's step
    # the extension's call alone (no ms.step around it, no StepResult), where it takes every step
    stepper = compiled._context(mods["compiled"], ms.make_data(mods["compiled"])).stepper
    out["extension"] = None if stepper is None or c["flight"] + c["contact"] < sum(c.values()) else statistics.median(
        best(lambda st=states[i]: stepper.step(st.q, st.u, h, e), repeat) for i in idx)
    out["compiled_share"] = (c["flight"] + c["contact"]) / max(1, sum(c.values()))
    out["handed_back"] = {k.removeprefix("python: "): v for k, v in c.items() if k.startswith("python")}
    out["ratio"] = out["python"] / out["compiled"]
    return out


def load(scene: str, duration: float | None = None) -> ms.Scene:
    """A bundled scene, its duration replaced by `duration` (s) if given."""
    sc = ms.load_scene(scene_path(scene))
    return sc if duration is None else sc.with_options(duration=duration)


def run_peer(peer: str, scene: str, repeat: int, duration: float | None = None) -> dict:
    """The peer's timed runs of the scene (its runner's `timing`), or {"why": ...} if it cannot run it."""
    from .peers import run
    from .spec import PeerError, make_spec

    try:
        res = run(peer, make_spec(ms.build_model(load(scene, duration))), timing_repeats=repeat)
    except PeerError as err:  # NotExpressible included
        return {"why": str(err).splitlines()[0]}
    tm = res["timing"]
    return {"version": res["version"], "steps": len(tm["step_us"]), "step_us": np.asarray(tm["step_us"]),
            "contacts": np.asarray(tm["contacts"]), "wall_seconds": tm["wall_seconds"], "timer": tm["timer"],
            "settings": {k: v for k, v in res["settings"].items() if k != "xml"}}


def peer_phase(run: dict, which: str) -> dict | None:
    """A peer's figure for one phase: median over the phase's steps of the best-of-repeats step, us."""
    if "why" in run:
        return None
    mask = phase(run["contacts"], which)
    if not mask.any():
        return None
    return {"us": float(np.median(run["step_us"][mask])), "steps": int(mask.sum()),
            "contacts": float(np.median(run["contacts"][mask]))}


def whole_run(scene: str, repeat: int, peers: tuple, duration: float | None = None) -> dict:
    """ms.simulate of the scene (recording included), wall per step: the compiled step in the compiled run
    loop (compiled_run.py, the default), the compiled step in the Python loop (python_run=True), the Python
    step; and a bare Python loop of the compiled ms.step over the same steps (nothing recorded), against
    each peer's whole run of the same scene per step (`peers`: those
    available): `repeat` rounds, each running every side once in turn (so that all see the same
    load), the best round of each side. `duration` (s): the scene's own if None."""
    sc = load(scene, duration)
    n = int(round(sc.options.duration / sc.options.dt))
    models = {impl: ms.build_model(sc.with_options(step_impl=impl)) for impl in ("compiled", "python")}
    loops = {"compiled": False, "compiled_python_loop": True, "python": True}  # side: python_run
    walls: dict = {side: [] for side in (*loops, "step_loop", *PEERS)}
    versions_: dict = {}
    h, e = sc.options.dt, sc.options.restitution

    loop_data = ms.make_data(models["compiled"])

    def step_loop(model=models["compiled"], data=loop_data):
        st = ms.initial_state(model)
        for _ in range(n):
            st = ms.step(model, data, st, h=h, e=e).state

    why: dict = {}
    for _ in range(repeat):
        for side, python_run in loops.items():
            model = models["python" if side == "python" else "compiled"]
            walls[side].append(best(lambda model=model, p=python_run: ms.simulate(model, progress=False,
                                                                                  python_run=p), 1) / n)
        walls["step_loop"].append(best(step_loop, 1) / n)
        for peer in peers:
            r = run_peer(peer, scene, 1, duration)
            if "why" not in r:
                walls[peer].append(r["wall_seconds"] * 1e6 / r["steps"])
                versions_[peer] = r["version"]
            else:
                why[peer] = r["why"]
        peers = tuple(p for p in peers if p not in why)  # a peer that cannot express it is asked once
    key = scene if duration is None else f"{scene} {duration:g} s"
    notes = {p: PEER_NOTES[p, scene] for p in PEERS if (p, scene) in PEER_NOTES and walls[p]}
    return {"scene": key, "steps": n, **{side: min(w) if w else None for side, w in walls.items()},
            "peer_versions": versions_, "not_expressible": why, "peer_notes": notes}


# Peak memory: the process's VmHWM (/proc/self/status), the high-water mark of its own address space since its
# exec; not getrusage's maxrss, which keeps the parent's resident size at the fork (Linux carries it over exec).
_HWM = """
def _hwm_kib():
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
"""
_CHILD_OURS = _HWM + """
import json, sys, time
import moreau_sim as ms
scene, steps = sys.argv[1], int(sys.argv[2])
sc = ms.load_scene(scene)
duration = steps * sc.options.dt
hwm0 = _hwm_kib()
c0, w0 = time.process_time(), time.perf_counter()
tr = ms.run(scene, duration=duration)
cpu, wall = time.process_time() - c0, time.perf_counter() - w0
print(json.dumps({"cpu_seconds": cpu, "wall_seconds": wall, "steps": tr.meta["run"]["steps"],
                  "samples": len(tr.arrays["t"]), "log_rows": len(tr.arrays["log_t"]), "run": tr.meta["run"],
                  "hwm_kib": _hwm_kib(), "hwm_before_kib": hwm0}))
"""
# the peers' subprocess (peers._CHILD in Siconos's interpreter), its VmHWM on stderr as it exits
_CHILD_SICONOS = _HWM + """
import atexit, sys
atexit.register(lambda: print(f"VmHWM-KIB {_hwm_kib()}", file=sys.stderr))
"""


def _ours(scene: Path, steps: int) -> dict:
    """ms.run of the scene for `steps` steps in a fresh interpreter (this repository on its path)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (str(Path(__file__).resolve().parents[1]),
                                                                      os.environ.get("PYTHONPATH"))))}
    cp = subprocess.run([sys.executable, "-c", _CHILD_OURS, str(scene), str(steps)], capture_output=True, text=True,
                        env=env)
    if cp.returncode != 0:
        raise SystemExit(f"the 10^6-step run failed: {(cp.stderr.strip().splitlines() or ['?'])[-1]}")
    return json.loads(cp.stdout.strip().splitlines()[-1])


def _siconos(scene: Path, steps: int) -> dict:
    """Siconos's runner (peers.siconos, its defaults) on the scene for `steps` steps, in its interpreter as
    peers.run starts it (the series returned every steps/1000-th step): its loop's CPU, its process's VmHWM."""
    from .peers import _CHILD, _PACKAGE_ROOT, SICONOS_PYTHON
    from .spec import from_jsonable, make_spec, to_jsonable

    sc = ms.load_scene(scene)
    spec = make_spec(ms.build_model(sc.with_options(duration=steps * sc.options.dt)), stride=max(1, steps // 1000))
    cp = subprocess.run([SICONOS_PYTHON, "-P", "-c", _CHILD_SICONOS + _CHILD, str(_PACKAGE_ROOT), "siconos", "{}"],
                        input=json.dumps(to_jsonable(spec)), capture_output=True, text=True)
    hwm = [ln for ln in cp.stderr.splitlines() if ln.startswith("VmHWM-KIB ")]
    if cp.returncode != 0 or not hwm:
        raise SystemExit(f"Siconos's 10^6-step run failed: {(cp.stderr.strip().splitlines() or ['?'])[-1]}")
    res = from_jsonable(json.loads(cp.stdout))
    return {"cpu_seconds": res["cpu_seconds"], "wall_seconds": res["wall_seconds"], "version": res["version"],
            "hwm_kib": int(hwm[-1].split()[1])}


def million(repeat: int, siconos: bool, steps: int = MILLION, scene: str = MILLION_SCENE) -> dict:
    """The 10^6-step run: ms.run of the scene for `steps` steps (the default sampling: every step recorded)
    in a child process, against Siconos's loop over the same steps (its runner's recording of q and v) in
    another; `repeat` rounds, each side in turn. CPU per step: the best round (ours: process_time around
    ms.run, loading and building the scene included; Siconos: its loop's process_time); peak memory: the
    process's VmHWM (ours: the whole interpreter, Pinocchio and coal included, its part before the run
    apart), the largest of the rounds."""
    path = scene_path(scene)
    ours, sic = [], []
    for _ in range(repeat):
        ours.append(_ours(path, steps))
        if siconos:
            sic.append(_siconos(path, steps))
    best_ours = min(ours, key=lambda r: r["cpu_seconds"])
    out = {"scene": scene, "steps": steps, "rounds": repeat, "us_per_step": 1e6 * best_ours["cpu_seconds"] / steps,
           "loop_us_per_step": best_ours["run"]["us_per_step"],
           "wall_us_per_step": 1e6 * best_ours["wall_seconds"] / steps,
           "samples": best_ours["samples"], "log_rows": best_ours["log_rows"], "loop": best_ours["run"].get("loop"),
           "python_steps": best_ours["run"].get("python_steps"),
           "peak_mib": max(r["hwm_kib"] for r in ours) / 1024,
           "before_run_mib": max(r["hwm_before_kib"] for r in ours) / 1024,
           "memory": "VmHWM of the process (/proc/self/status)",
           "siconos": None, "siconos_peak_mib": None, "siconos_version": None}
    if sic:
        b = min(sic, key=lambda r: r["cpu_seconds"])
        out.update(siconos=1e6 * b["cpu_seconds"] / steps, siconos_peak_mib=max(r["hwm_kib"] for r in sic) / 1024,
                   siconos_version=b["version"])
    return out


def verdicts(res: dict) -> list[dict]:
    """Each TARGETS entry with its measured figure and whether it is met (None: not measured)."""
    cases = {c["scene"]: c for c in res["cases"]}
    runs = {w["scene"]: w for w in res.get("whole_runs", [])}
    out = []
    for what, kind, key, bound in TARGETS:
        value = None
        if kind == "us" and key in cases:
            value, shown = cases[key]["compiled"], f"{cases[key]['compiled']:.2f} µs"
        elif not res.get("siconos") and "siconos" in kind:  # Siconos not installed in that run
            pass
        elif kind == "x siconos" and (cases.get(key) or {}).get("siconos"):
            c = cases[key]
            value = c["compiled"] / c["siconos"]["us"]
            shown = f"{value:.2f}× ({c['compiled']:.1f} against {c['siconos']['us']:.2f} µs)"
            if c.get("extension"):
                shown += f"; the extension call alone {c['extension'] / c['siconos']['us']:.2f}×"
        elif kind == "in place x siconos" and (cases.get(key) or {}).get("siconos") and cases[key].get("in_place"):
            c = cases[key]
            value = c["in_place"] / c["siconos"]["us"]
            shown = f"{value:.2f}× ({c['in_place']:.1f} against {c['siconos']['us']:.2f} µs)"
        elif kind == "run x siconos" and (runs.get(key) or {}).get("siconos"):
            w = runs[key]
            value = w["compiled"] / w["siconos"]
            shown = f"{value:.2f}× ({w['compiled']:.1f} against {w['siconos']:.2f} µs per step)"
        elif kind == "million x siconos" and (res.get("million") or {}).get("siconos"):
            mm = res["million"]
            value = mm["us_per_step"] / mm["siconos"]
            shown = f"{value:.2f}× ({mm['us_per_step']:.2f} against {mm['siconos']:.2f} µs of CPU per step)"
        elif kind == "million MiB" and res.get("million"):
            mm = res["million"]
            value = mm["peak_mib"]
            shown = f"{value:.0f} MiB peak ({mm['before_run_mib']:.0f} MiB of it before the run)"
        out.append({"target": what, "value": value, "shown": shown if value is not None else "not measured",
                    "met": None if value is None else bool(value <= bound)})
    return out


def _fmt(x: float | None, digits: int = 1) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def _ratio(a: float, b: float | None) -> str:
    return "–" if b is None else f"{a / b:.2f}"


def markdown_table(res: dict) -> str:
    """The compiled-step table of docs/benchmarks.md from a compiled_costs.json (MuJoCo's columns last)."""
    have = {p: res.get(p) for p in PEERS}
    reps = f"the best of {res['repeat']}" if "repeat" in res else "the best of several timings"
    states = sorted({c["states"] for c in res["cases"]})
    peers = "; ".join(f"{PEER_NAMES[p]} {have[p]['version']}" if have[p]
                      else f"{PEER_NAMES[p]} not installed in that run" for p in PEERS)
    out = [f"µs per step. moreau-sim: `ms.step` on {'/'.join(map(str, states))} states of the phase, {reps} "
           f"per state, median over the states. Peers: the whole scene run {reps.removeprefix('the best of ')} "
           "times in the peer's own stepping loop with a timer around each step (Siconos: `computeOneStep` + "
           "`nextStep`; MuJoCo: `mj_step`, both called from Python), per step the best of the runs, median "
           "over the steps of the same phase by the peer's own contact count (contacts: the median number in the "
           "step, ours detected, Siconos's in its LCP, MuJoCo's `ncon`). " + peers + ":", "",
           "| case | contacts (ours / Siconos / MuJoCo) | Python step | compiled step | `ms.step_in_place` "
           "| its extension call alone | Python / compiled | steps taken compiled | Siconos | compiled / Siconos "
           "| MuJoCo mj_step | compiled / MuJoCo |",
           "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for c in res["cases"]:
        sic = c.get("siconos") if have["siconos"] else None
        mj = c.get("mujoco") if have["mujoco"] else None
        contacts = " / ".join(f"{x:g}" if x is not None else "–"
                              for x in (c["contacts"], sic and sic["contacts"], mj and mj["contacts"]))
        out.append(f"| `{c['scene']}`: {c['label']} | {contacts} | {c['python']:.1f} | {c['compiled']:.1f} | "
                   f"{_fmt(c.get('in_place'))} | {_fmt(c.get('extension'))} | {c['python'] / c['compiled']:.1f} | "
                   f"{100 * c['compiled_share']:.1f} % | "
                   f"{_fmt(sic and sic['us'], 2)} | {_ratio(c['compiled'], sic and sic['us'])} | "
                   f"{_fmt(mj and mj['us'], 2)} | {_ratio(c['compiled'], mj and mj['us'])} |")
    return "\n".join(out)


def whole_run_table(res: dict) -> str:
    """Whole runs, wall per step: ms.simulate (recording included) against the peers' whole runs."""
    sic, mj = res.get("siconos"), res.get("mujoco")
    rounds = res.get("whole_runs_repeat", res.get("repeat", "?"))
    out = [f"Wall time of the whole run over its number of steps, µs, the best of {rounds} rounds "
           "that run every side in turn: "
           "`ms.simulate` (the `Trajectory` recorded: the compiled step in the compiled run loop, the default; the "
           "compiled step in the Python loop, `python_run=True`; the Python step) and a bare Python loop "
           "`state = ms.step(...).state` over the "
           "same steps (nothing recorded), Siconos's stepping loop with its recording of q and v "
           "(the runner's), MuJoCo's `mujoco.rollout` (a C loop storing the full state):", "",
           "| scene | steps | compiled run | compiled step, Python loop | Python step | a bare loop of the compiled "
           "`ms.step` | Siconos whole run | compiled run / Siconos | MuJoCo rollout | compiled run / MuJoCo |",
           "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    notes = []
    for w in res.get("whole_runs", []):
        s = w["siconos"] if sic else None
        m = w["mujoco"] if mj else None
        mark = "*" if w.get("peer_notes") else ""
        out.append(f"| `{w['scene']}` | {w['steps']} | {w['compiled']:.2f} | "
                   f"{_fmt(w.get('compiled_python_loop'), 2)} | {w['python']:.2f} | "
                   f"{_fmt(w.get('step_loop'), 2)} | {_fmt(s, 2)}{mark} | "
                   f"{_ratio(w['compiled'], s)} | {_fmt(m, 2)} | {_ratio(w['compiled'], m)} |")
        whys: dict = {}  # the peers' reasons (the runner's NotExpressible message), peers sharing one together
        for p, why in w.get("not_expressible", {}).items():
            whys.setdefault(why.rsplit("NotExpressible: ", 1)[-1], []).append(PEER_NAMES[p])
        notes += [f"{' and '.join(names)} cannot run `{w['scene']}`: {why}" for why, names in whys.items()]
        notes += [f"\\* `{w['scene']}`, {PEER_NAMES[p]}: {note}" for p, note in w.get("peer_notes", {}).items()]
    load = res.get("whole_runs_load", res.get("load"))
    start = res.get("whole_runs_load_start", res.get("load_start"))
    if load is not None:
        during = f"{start:.1f} as the run started, {load:.1f} as it ended" if start is not None else f"{load:.1f}"
        notes.append(f"Load average {during}, on {res.get('cpus', '?')} cores (a shared machine): compare the ratios, "
                     "measured in the same rounds, rather than the absolute times.")
    return "\n".join(out + ([""] + [f"- {n}" for n in notes] if notes else []))


def million_table(res: dict) -> str:
    """The 10^6-step run: ms.run's CPU per step and peak memory against Siconos's loop."""
    mm = res.get("million")
    if not mm:
        return "The 10^6-step run was not measured in this JSON (`--million`)."
    load = f", load {mm['load']:.1f} on {res.get('cpus', '?')} cores" if "load" in mm else ""
    out = [f"`ms.run` of `{mm['scene']}` for {mm['steps']:,} steps with the default sampling (every step recorded), "
           "in a child process of its own, against Siconos's stepping loop over the same steps (its runner's "
           f"recording of q and v) in another; CPU per step, the best of {mm['rounds']} rounds{load}; peak "
           "memory: the process's high-water resident size, VmHWM (ours: the whole interpreter with Pinocchio "
           "and coal; Siconos: its runner's Debian Python process):", "",
           "| scene | steps | samples | percussion-log rows | loop | `ms.run` CPU per step, µs | its run loop alone, "
           "µs (wall) | Siconos loop CPU per step, µs | `ms.run` / Siconos | peak memory, MiB | of it before the run "
           "| Siconos's peak, MiB |",
           "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|",
           f"| `{mm['scene']}` | {mm['steps']} | {mm['samples']} | {mm['log_rows']} | {mm['loop']} | "
           f"{mm['us_per_step']:.2f} | {mm['loop_us_per_step']:.2f} | {_fmt(mm['siconos'], 2)} | "
           f"{_ratio(mm['us_per_step'], mm['siconos'])} | {mm['peak_mib']:.0f} | {mm['before_run_mib']:.0f} | "
           f"{_fmt(mm['siconos_peak_mib'], 0)} |"]
    return "\n".join(out)


def targets_table(res: dict) -> str:
    """The cost targets with the figures of this run and their verdicts."""
    out = ["| target | measured (compiled step) | verdict |", "|---|---|---|"]
    for v in verdicts(res):
        verdict = "–" if v["met"] is None else ("met" if v["met"] else "**missed**")
        out.append(f"| {v['target']} | {v['shown']} | {verdict} |")
    return "\n".join(out)


def doc_tables(res: dict) -> dict[str, str]:
    """The tables of docs/benchmarks.md this benchmark's JSON gives (marker name: Markdown)."""
    return {"compiled-step table": markdown_table(res), "compiled-step whole runs": whole_run_table(res),
            "compiled-step million-step run": million_table(res), "compiled-step targets": targets_table(res)}


def plot(res: dict, path: Path) -> None:
    """Bars per case (log scale): Python step, compiled step, Siconos, MuJoCo; the whole runs last;
    the cost targets as red marks over their case."""
    plt = pyplot()

    def name(scene: str) -> str:  # a long scene name on two lines
        return scene.replace("_", "_\n", 1) if len(scene) > 11 else scene

    groups = [(name(c["scene"]) + f"\n{c['label'].split(', ', 1)[-1]}"
               + ("" if c["compiled_share"] == 1 else f"\n({100 * c['compiled_share']:.0f} % in C++)"),
               c["python"], c["compiled"],
               (c.get("siconos") or {}).get("us"), (c.get("mujoco") or {}).get("us")) for c in res["cases"]]
    groups += [(f"{name(w['scene'])}\nwhole run", w["python"], w["compiled"], w["siconos"], w["mujoco"])
               for w in res.get("whole_runs", [])]
    mm = res.get("million")
    if mm:  # CPU per step of the 10^6-step run (ms.run; Siconos's loop)
        groups.append((f"{name(mm['scene'])}\n10^6 steps\n(CPU, ms.run)", None, mm["us_per_step"], mm["siconos"],
                       None))
    bars = (("Python step (whole runs: in the Python loop)", "tab:blue"),
            ("compiled step (whole runs: the compiled run loop)", "tab:orange"), ("Siconos Moreau-Jean", "tab:green"),
            ("MuJoCo mj_step", "tab:gray"))
    x = np.arange(len(groups))
    fig, ax = plt.subplots(figsize=(max(12.0, 0.9 * len(groups)), 4.8))
    w = 0.2
    for j, (name, color) in enumerate(bars):
        xs = [x[i] + (j - 1.5) * w for i, g in enumerate(groups) if g[1 + j] is not None]
        ys = [g[1 + j] for g in groups if g[1 + j] is not None]
        ax.bar(xs, ys, w, label=name, color=color)
    ext = [(x[i] - 0.1, c["extension"]) for i, c in enumerate(res["cases"]) if c.get("extension")]
    if ext:
        ax.plot(*zip(*ext), "k_", ms=14, mew=2, label="compiled step: the C++ call alone, no Python around it")
    inplace = [(x[i] - 0.1, c["in_place"]) for i, c in enumerate(res["cases"]) if c.get("in_place")]
    if inplace:
        ax.plot(*zip(*inplace), "k^", ms=6, label="compiled step: ms.step_in_place, no result objects")
    bare = [(x[len(res["cases"]) + i] - 0.1, w["step_loop"]) for i, w in enumerate(res.get("whole_runs", []))
            if w.get("step_loop")]
    if bare:
        ax.plot(*zip(*bare), "kv", ms=6, label="compiled step: a plain loop of ms.step, nothing recorded")
    where = {c["scene"]: i for i, c in enumerate(res["cases"])}
    where_run = {wr["scene"]: len(res["cases"]) + i for i, wr in enumerate(res.get("whole_runs", []))}
    labelled = False
    for (_what, kind, key, bound), v in zip(TARGETS, verdicts(res)):
        if kind == "million MiB":
            continue
        i = len(groups) - 1 if kind.startswith("million") else (where_run if kind.startswith("run") else where).get(key)
        if i is None or v["value"] is None:
            continue
        g = groups[i]
        y = bound if kind == "us" else bound * g[3]
        ax.plot([x[i] - 0.45, x[i] + 0.45], [y, y], color="red", lw=1.5,
                label=None if labelled else "target: the compiled step at or below the red line")
        labelled = True
    ax.set_xticks(x, [g[0] for g in groups], fontsize=7)
    ax.set_yscale("log")
    ax.set_ylim(top=8 * max(max(v for v in g[1:] if v is not None) for g in groups))  # room for the legend
    ax.set_ylabel("µs per step (median; whole runs: wall / steps;\n10^6 steps: CPU / steps)", fontsize=8)
    runs_load = (f"; whole runs in a run of their own, load {res['whole_runs_load']:.1f}"
                 if "whole_runs_load" in res else "")
    ax.set_title(f"One step, side by side in one run ({res['cpus']} cores, load {res['load']:.1f}{runs_load})",
                 fontsize=9)
    ax.grid(axis="y", which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=3, loc="upper center")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _jsonable(x):
    """numpy arrays and scalars in the peers' settings, for json.dumps."""
    if isinstance(x, (np.ndarray, np.generic)):
        return x.tolist()
    raise TypeError(f"not JSON: {type(x).__name__}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--states", type=int, default=200)
    ap.add_argument("--whole-runs", action="store_true",
                    help="only the whole runs (the per-step cases of an existing JSON in --out are kept)")
    ap.add_argument("--million", action="store_true",
                    help=f"also the {MILLION:,}-step ball run against Siconos's loop (CPU, peak memory; "
                         "else an existing JSON's row is kept)")
    ap.add_argument("--million-steps", type=int, default=MILLION, help=argparse.SUPPRESS)  # a quick try
    add_table_option(ap, "compiled_costs.json", "docs/benchmarks.md")
    add_plot_option(ap, "compiled_costs.json")
    a = ap.parse_args(argv)
    if rewrite_tables(a, doc_tables) or redraw(a, plot):
        return
    if not compiled.available():
        raise SystemExit(f"the compiled step is unavailable: {compiled.unavailable_reason()}")
    load_start = os.getloadavg()[0]  # the machine's load average as the run starts (and "load": as it ends)
    from .peers import available

    avail = available()
    for p in PEERS:
        if avail[p]:
            print(f"{PEER_NAMES[p]} skipped: {avail[p]}")
    scenes = [] if a.whole_runs else [s for _, s, _ in CASES]
    peer_runs = {(p, s): run_peer(p, s, a.repeat) if avail[p] is None else {"why": avail[p]}
                 for p in PEERS for s in scenes}
    cases = []
    for label, scene, which in [] if a.whole_runs else CASES:
        c = bench_case(label, scene, which, a.repeat, a.states)
        for p in PEERS:
            c[p] = peer_phase(peer_runs[p, scene], which)
        print(f"{label:34s} python {c['python']:8.1f} us  compiled {c['compiled']:7.1f} us  x{c['ratio']:.1f}  "
              f"({c['states']} states, {c['contacts']:g} contacts, {100 * c['compiled_share']:.0f} % compiled)  "
              + "  ".join(f"{p} {_fmt(c[p] and c[p]['us'], 2)}" for p in PEERS))
        cases.append(c)
    runs = []
    for s, duration in WHOLE_RUNS:
        runs.append(w := whole_run(s, a.repeat, tuple(p for p in PEERS if avail[p] is None), duration))
        print(f"whole run {w['scene']:20s} compiled {w['compiled']:.2f}  python {w['python']:.2f}  "
              f"siconos {_fmt(w['siconos'], 2)}  mujoco {_fmt(w['mujoco'], 2)} us per step")

    mm = None
    if a.million:
        mm = million(min(a.repeat, 3), avail["siconos"] is None, a.million_steps)
        mm["load"] = os.getloadavg()[0]
        print(f"{mm['steps']} steps of {mm['scene']}: ms.run {mm['us_per_step']:.2f} us CPU per step, "
              f"{mm['peak_mib']:.0f} MiB peak; siconos {_fmt(mm['siconos'], 2)} us, "
              f"{_fmt(mm['siconos_peak_mib'], 0)} MiB")

    def peer_info(p):
        done = [r for (q, _), r in peer_runs.items() if q == p and "why" not in r]
        if not done:  # only whole runs (--whole-runs): the version they ran
            v = next((w["peer_versions"][p] for w in runs if p in w["peer_versions"]), None)
            return None if v is None else {"version": v, "timer": None, "settings": {}, "not_expressible": {}}
        return {"version": done[0]["version"], "timer": done[0]["timer"],
                "settings": {s: r["settings"] for (q, s), r in peer_runs.items() if q == p and "why" not in r},
                "not_expressible": {s: r["why"] for (q, s), r in peer_runs.items() if q == p and "why" in r}}

    res = {"cases": cases, "whole_runs": runs, **{p: peer_info(p) for p in PEERS},
           "machine": platform.processor() or platform.machine(), "python": platform.python_version(),
           "cpus": os.cpu_count(), "load": os.getloadavg()[0], "load_start": load_start, "nice": os.nice(0),
           "repeat": a.repeat,
           "versions": versions(),
           "note": "us per step: moreau-sim the median over states of the best of `repeat` timings; peers the "
                   "median over the phase's steps of the best of `repeat` timed whole runs; whole runs wall / steps"}
    kept = a.out / "compiled_costs.json"
    old = json.loads(kept.read_text()) if kept.exists() else {}
    if a.whole_runs and old:  # only the whole runs measured: the JSON's per-step cases are kept
        res = {**old, "whole_runs": runs, "whole_runs_repeat": a.repeat, "whole_runs_load": res["load"],
               "whole_runs_load_start": load_start, "whole_runs_versions": res["versions"]}
    if mm is not None:
        res["million"] = mm
    elif old.get("million"):  # not measured in this run: the JSON's row is kept
        res["million"] = old["million"]
    res["verdicts"] = verdicts(res)
    for v in res["verdicts"]:
        print(f"{v['target']:55s} {v['shown']:40s} {'-' if v['met'] is None else ('met' if v['met'] else 'MISSED')}")
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "compiled_costs.json").write_text(json.dumps(res, indent=1, default=_jsonable))
    plot(res, a.out / "compiled_costs.png")
    print(f"wrote {a.out / 'compiled_costs.json'} and .png")


if __name__ == "__main__":
    main()
