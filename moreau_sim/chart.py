"""Speed against accuracy for one scene: each integrator that accepts it over a ladder of steps
(time-stepping) or tolerances (adaptive, event-driven), its error against a reference on a common
sample grid and its CPU time per simulated second, as a work-precision chart (PNG), a JSON file
and a Markdown table (docs/cli.md, "chart"; the integrators: docs/theory.md §2, §7, §8; the
checks each run makes of itself: §10).

The reference is the agreement of two methods at tight tolerance (event-driven and adaptive), or,
for a scene only the time-stepper takes (actuators, drives), of its two smallest steps; how well
the two agree is stated, and beyond a stated level the reference is called uncertain."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pinocchio as pin

from .adaptive import simulate_adaptive
from .errors import SceneError, SimulationError, SimulationInterrupted
from .event_driven import simulate_event_driven
from .gaps import UnsupportedModel
from .invariants import Invariants
from .model import Model, build_model
from .options import Integrator
from .scene import Scene, load_scene
from .simulate import simulate
from .trajectory import Trajectory

INTEGRATORS = tuple(i.value for i in Integrator)  # time-stepping, event-driven, adaptive
DTS = (1e-2, 5e-3, 2e-3, 1e-3, 5e-4, 2e-4, 1e-4)  # [s] the default dt ladder (each divides 1e-2 s)
TOLERANCES = (1e-3, 1e-4, 1e-6, 1e-8, 1e-10)  # the default rtol ladder (atol = rtol * ATOL_RATIO)
ATOL_RATIO = 1e-2  # atol / rtol of every adaptive and event-driven run [m, rad, m/s, rad/s per unit rtol]
REFERENCE_RTOL = 1e-12  # the reference runs' rtol
AGREEMENT = 1e-8  # the stated level: two reference methods further apart make the reference "uncertain"
SAMPLE_STEP = 1e-2  # [s] the default sample grid step (smaller for runs shorter than 20 samples of it)
TOL_RANGE = (1e-14, 1e-1)  # admissible rtol
DEFAULT_ORDER = 6  # the adaptive integrator's default extrapolation order (its second reference: order 8)
NORM = ("q: max over the sample instants t_k of |q(t_k) (-) q_ref(t_k)|_inf (pin.difference: m, rad); "
        "u: mean over t_k of |u(t_k) - u_ref(t_k)|_inf (m/s, rad/s; a velocity jump whose instant differs "
        "by d weighs d/T, not its full size)")


class ChartInterrupted(SimulationInterrupted):
    """Ctrl-C or SIGTERM during a chart: ``path`` is the partial JSON holding the runs measured so far."""

    def __init__(self, message, *, path: Path):
        super().__init__(message)
        self.path = path


@dataclass
class Run:
    """One point of the chart: `integrator` at `setting` (dt [s] or rtol), its CPU time per
    simulated second (min over repeats) [s/s] and its errors against the reference (NORM)."""

    integrator: str
    setting: float
    status: str = "complete"  # complete | flagged | failed: ... | reference (the reference run itself)
    cpu_per_second: float | None = None
    cpu_seconds: list = field(default_factory=list)
    q_error: float | None = None
    q_error_mean: float | None = None
    u_error: float | None = None
    u_error_max: float | None = None
    branching_steps: int = 0
    fixed_steps: int = 0  # the adaptive integrator's fixed midpoint steps of the scene's dt (its fallback)
    below_reference: bool = False  # its q error is below the reference runs' difference, which is beyond the level

    @property
    def setting_name(self) -> str:
        return "dt" if self.integrator == Integrator.TIME_STEPPING.value else "rtol"


@dataclass
class Reference:
    """What the errors are measured against: `method` (the reference run), `check` (the second
    run), their agreement in the chart's norms, and whether it exceeds the stated level."""

    kind: str  # "two methods" | "one method, two orders" | ... | "two smallest dt (Richardson-style)"
    method: str
    check: str
    why: str = ""  # why this pair (an integrator refused the scene)
    q_agreement: float = math.nan
    u_agreement: float = math.nan
    level: float = AGREEMENT
    branching_steps: int = 0

    @property
    def uncertain(self) -> bool:
        return not max(self.q_agreement, self.u_agreement) <= self.level

    def sentence(self) -> str:
        apart = f"differ by {self.q_agreement:.1e} in q and {self.u_agreement:.1e} in u"
        why = f" ({self.why})" if self.why else ""
        if self.uncertain:
            return (f"reference UNCERTAIN at {max(self.q_agreement, self.u_agreement):.1e} [{self.kind}]: "
                    f"{self.method} and {self.check} {apart}, beyond the stated level {self.level:.0e}; errors "
                    f"below that are not measured{why}")
        return (f"reference [{self.kind}]: {self.method}; it and {self.check} {apart} (within the stated level "
                f"{self.level:.0e}){why}")


@dataclass
class ChartResult:
    """A chart's runs and what they were measured against; `files`: what was written."""

    scene: str
    duration: float
    sample_step: float
    reference: Reference | None
    runs: list[Run]
    refused: dict[str, str]
    notes: list[str]
    repeats: int
    status: str = "complete"
    files: dict[str, str] = field(default_factory=dict)
    reference_samples: tuple | None = None  # (t [s], q, u) of the reference run at the sample instants (not in JSON)

    def to_json(self) -> dict:
        return {"scene": self.scene, "status": self.status, "duration": self.duration,
                "sample_step": self.sample_step, "samples": int(round(self.duration / self.sample_step)) + 1,
                "norm": NORM, "cpu": f"time.process_time() of the whole run, min over {self.repeats} repeats, "
                                     "per simulated second [s/s]",
                "atol_per_rtol": ATOL_RATIO,
                "reference": None if self.reference is None else {
                    **dataclasses.asdict(self.reference), "uncertain": self.reference.uncertain,
                    "sentence": self.reference.sentence()},
                "refused": self.refused, "notes": self.notes,
                "runs": [{**dataclasses.asdict(r), "setting_name": r.setting_name} for r in self.runs]}


def chart(scene: Scene | str | os.PathLike, *, out_dir: str | os.PathLike | None = None,
          integrators: tuple[str, ...] | list[str] | None = None, dts=None, tolerances=None,
          duration: float | None = None, repeats: int = 3, sample_step: float | None = None,
          reference_rtol: float = REFERENCE_RTOL, agreement: float = AGREEMENT, options: dict | None = None,
          log: Callable[[str], None] | None = None) -> ChartResult:
    """Run `scene` under each of `integrators` (default: all three) that accepts it: time-stepping
    at each dt of `dts` [s] (default DTS, those dividing the sample step), adaptive and event-driven
    at each rtol of `tolerances` (atol = rtol * ATOL_RATIO); measure each run's CPU time per
    simulated second (min over `repeats`) and its errors (NORM) against the reference (module doc)
    at the instants k * `sample_step` [s] (default 0.01 s, or a power of ten giving >= 20 samples)
    up to `duration` [s] (default: the scene's, rounded down to the grid). The reference runs at
    `reference_rtol`; `agreement` is the stated level beyond which it is called uncertain.
    options: scene options to override first (scene-file names, e.g. {"restitution": 0.5}).

    With `out_dir`, writes chart.png, chart.json and chart.md there; Ctrl-C writes
    chart.partial.json with the runs so far and raises ChartInterrupted. Bad input raises
    SceneError naming the keyword; a failed run is recorded as failed, not raised."""
    say = log or (lambda _msg: None)
    sc = scene if isinstance(scene, Scene) else load_scene(scene)
    if options:
        sc = sc.with_options(**options)
    asked = sc.options.duration if duration is None else _positive(duration, "duration")
    step = _sample_step(asked) if sample_step is None else _positive(sample_step, "sample_step")
    if step > asked:
        raise SceneError(f"sample_step: {step:g} s is longer than the duration {asked:g} s")
    n = max(1, int(math.floor(asked / step + 1e-9)))
    T = n * step
    names = _integrators(integrators)
    dts = _dts(dts, step, T)
    tols = _tolerances(tolerances, "tolerances")
    _tolerances([reference_rtol], "reference_rtol")
    if not (isinstance(repeats, int) and repeats >= 1):
        raise SceneError(f"repeats: must be an integer >= 1, got {repeats!r}")
    _positive(agreement, "agreement")
    base = build_model(sc.with_options(duration=T))
    grid = np.arange(n + 1) * step
    res = ChartResult(sc.name, T, step, None, [], {}, [], repeats)
    if abs(T - asked) > 1e-9 * asked:
        res.notes.append(f"duration {T:g} s: {asked:g} s rounded down to the sample grid")
    try:
        _measure(res, base, grid, names, dts, tols, reference_rtol, agreement, repeats, say)
    except (KeyboardInterrupt, SimulationInterrupted):
        res.status = "interrupted"
        path = None
        if out_dir is not None:
            path = Path(out_dir) / "chart.partial.json"
            _write_json(path, res)
        raise ChartInterrupted(f"interrupted after {len(res.runs)} runs", path=path) from None
    if out_dir is not None:
        write(res, out_dir)
    return res


# ---------------------------------------------------------------- checks of the input
def _positive(x, name: str) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or x <= 0:
        raise SceneError(f"{name}: must be a finite number > 0, got {x!r}")
    return float(x)


def _sample_step(T: float) -> float:
    """0.01 s, or the power of ten giving at least 20 samples over T [s]."""
    return min(SAMPLE_STEP, 10.0 ** math.floor(math.log10(T / 20)))


def _integrators(names) -> tuple[str, ...]:
    names = INTEGRATORS if names is None else tuple(names)
    bad = [x for x in names if x not in INTEGRATORS]
    if bad or not names:
        raise SceneError(f"integrators: unknown integrator {bad[0] if bad else '(none)'!r}; choose among "
                         f"{', '.join(INTEGRATORS)}")
    return names


def _divides(h: float, step: float) -> bool:
    r = step / h
    return abs(r - round(r)) <= 1e-9 * r


def _dts(dts, step: float, T: float) -> tuple[float, ...]:
    if dts is None:
        out = tuple(h for h in DTS if h <= step and _divides(h, step))
        return out or (step, step / 2, step / 5, step / 10)
    out = tuple(_positive(h, "dts") for h in dts)
    for h in out:
        if h > step or not _divides(h, step):
            raise SceneError(f"dts: {h:g} s does not divide the sample step {step:g} s; choose steps h with "
                             "(sample step) / h a whole number, or change the sample step")
    if not out:
        raise SceneError("dts: give at least one step [s]")
    return tuple(sorted(set(out), reverse=True))


def _tolerances(tols, name: str) -> tuple[float, ...]:
    if tols is None:
        return TOLERANCES
    lo, hi = TOL_RANGE
    out = []
    for r in tols:
        if isinstance(r, bool) or not isinstance(r, (int, float)) or not lo <= r <= hi:
            raise SceneError(f"{name}: {r!r} is outside [{lo:g}, {hi:g}] (a relative tolerance)")
        out.append(float(r))
    if not out:
        raise SceneError(f"{name}: give at least one tolerance")
    return tuple(sorted(set(out), reverse=True))


# ---------------------------------------------------------------- runs
def _configured(model: Model, integrator: str, setting: float, grid: np.ndarray, *, dt: float | None = None) -> Model:
    """The model of one point: `integrator` at dt = setting [s] recording every grid step
    (time-stepping), or at rtol = setting, atol = setting * ATOL_RATIO (the adaptive integrator's
    fixed steps at the scene's dt, or `dt` [s]); the invariant checks read these options."""
    kind = Integrator(integrator)
    if kind is Integrator.TIME_STEPPING:
        changes = {"dt": setting, "save_every": int(round((grid[1] - grid[0]) / setting))}
    else:
        changes = {"rtol": setting, "atol": setting * ATOL_RATIO} | ({"dt": dt} if dt else {})
    return build_model(dataclasses.replace(model.scene, options=model.options.replace(integrator=kind, **changes)))


def _run(model: Model, grid: np.ndarray, *, order: int = DEFAULT_ORDER, method: str = "DOP853"):
    """One run of a _configured model sampled at `grid`, through the calls ms.simulate makes (with
    its invariant checks; the event integrators given the grid as t_eval): (Trajectory, CPU [s])."""
    opts = model.options
    if opts.integrator is Integrator.TIME_STEPPING:
        c0 = time.process_time()
        traj = simulate(model, progress=False)
        return traj, time.process_time() - c0
    check = Invariants(model, rtol=opts.rtol)
    c0 = time.process_time()
    if opts.integrator is Integrator.ADAPTIVE:
        traj = simulate_adaptive(model, order=order, t_eval=grid, check=check)
    else:
        traj = simulate_event_driven(model, rtol=opts.rtol, atol=opts.atol, method=method, t_eval=grid, check=check)
    return traj, time.process_time() - c0


def _samples(traj: Trajectory, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """q, u of `traj` at the grid instants (its samples are there: checked)."""
    t = np.asarray(traj.t)
    idx = np.searchsorted(t, grid - 1e-9 * max(1.0, grid[-1]))
    idx = np.minimum(idx, len(t) - 1)
    if len(t) < len(grid) or np.abs(t[idx] - grid).max() > 1e-9 * max(1.0, grid[-1]):
        raise SimulationError(f"samples at {len(t)} instants, not on the {len(grid)}-instant grid")
    return np.asarray(traj.q)[idx], np.asarray(traj.u)[idx]


def _errors(model: Model, a, b) -> tuple[float, float, float, float]:
    """(q max, q mean, u mean, u max) of the differences of samples a = (q, u) against b (NORM)."""
    (qa, ua), (qb, ub) = a, b
    if model.nq != model.nv:
        dq = np.array([pin.difference(model.pin, y, x) for x, y in zip(qa, qb)])
    else:
        dq = qa - qb
    qe, ue = np.abs(dq).max(axis=1), np.abs(ua - ub).max(axis=1)
    return float(qe.max()), float(qe.mean()), float(ue.mean()), float(ue.max())


def _branching(traj: Trajectory) -> int:
    return int(len(traj.arrays["branch_step"]))


def _fixed(traj: Trajectory) -> int:
    """The adaptive integrator's fixed steps (0 for the others)."""
    return int(traj.meta.get("run", {}).get("steps_fixed") or 0) if traj.meta.get("integrator") == "adaptive" else 0


def _fallback(traj: Trajectory, dt: float) -> str:
    """What an adaptive run's fixed steps were, for a sentence ("" when it took none)."""
    n = _fixed(traj)
    if not n:
        return ""
    back = "back to extrapolated steps"
    reasons = sorted({f["reason"] for f in traj.meta.get("fallbacks", []) if f["reason"] != back})
    return (f"the adaptive run took {n} of its {traj.meta['run'].get('steps')} steps as fixed midpoint steps of the "
            f"scene's dt = {dt:g} s ({'; '.join(reasons) or 'fallback'}), where its rtol does not act")


def _measure(res: ChartResult, model: Model, grid, names, dts, tols, ref_rtol, level, repeats, say) -> None:
    """Reference first (it also finds which integrators accept the scene), then every ladder."""
    ref_samples, ref_run = _reference(res, model, grid, names, dts, ref_rtol, level, say)
    ladders = {"time-stepping": dts, "adaptive": tols, "event-driven": tols}
    for name in names:
        if name in res.refused:
            continue
        for setting in ladders[name]:
            run = Run(name, setting)
            res.runs.append(run)
            try:
                point = _configured(model, name, setting, grid)
                for _ in range(repeats):
                    traj, cpu = _run(point, grid)
                    run.cpu_seconds.append(cpu)
            except (SceneError, UnsupportedModel) as exc:  # refused: the integrator's ladder ends
                res.runs.pop()
                res.refused[name] = str(exc)
                say(f"{name}: refused: {exc}")
                break
            except SimulationInterrupted:
                res.runs.pop()
                raise
            except SimulationError as exc:
                run.status = f"failed: {exc}"
                say(f"{name} {run.setting_name} = {setting:g}: {run.status}")
                continue
            run.status = traj.meta.get("status", "complete")
            run.cpu_per_second = min(run.cpu_seconds) / res.duration
            run.branching_steps = _branching(traj)
            run.fixed_steps = _fixed(traj)
            if ref_run is not None and (name, setting) == ref_run:  # the reference itself: its cost only
                run.status = "reference"
                say(f"{name} {run.setting_name} = {setting:g}: {1e3 * run.cpu_per_second:.3g} ms CPU per simulated s "
                    "(the reference)")
                continue
            if ref_samples is not None:
                try:
                    samples = _samples(traj, grid)
                except SimulationError as exc:  # a run that stopped short of the grid
                    run.status = f"failed: {exc}"
                    continue
                run.q_error, run.q_error_mean, run.u_error, run.u_error_max = _errors(model, samples, ref_samples)
                ref = res.reference
                run.below_reference = ref.uncertain and run.q_error < ref.q_agreement
            say(f"{name} {run.setting_name} = {setting:g}: {1e3 * run.cpu_per_second:.3g} ms CPU per simulated s, "
                f"q error {_fmt(run.q_error)}, u error {_fmt(run.u_error)}")
    fixed = [r for r in res.runs if r.fixed_steps]
    if fixed:
        counts = ", ".join(f"rtol {r.setting:g}: {r.fixed_steps}" for r in fixed)
        res.notes.append(f"adaptive runs took fixed midpoint steps of the scene's dt = {model.options.dt:g} s where "
                         f"they could not extrapolate ({counts}): there they are the time-stepper at that dt, and "
                         "their rtol does not act")
    if any(r.branching_steps for r in res.runs) or (res.reference and res.reference.branching_steps):
        res.notes.append("the scene has corner impacts with several admissible outcomes (branching steps logged): "
                         "methods may follow different outcomes, and an error after such an impact then measures "
                         "the choice of outcome, not the accuracy (docs/corner-law.md)"
                         + ("; the two reference methods disagree, possibly for this reason"
                            if res.reference and res.reference.uncertain else ""))


def _reference(res: ChartResult, model: Model, grid, names, dts, rtol, level, say):
    """The reference samples and, when it is one of the ladder's runs, its (integrator, setting).
    Only the integrators of `names` are tried (a slow one left out stays out of the reference)."""
    runs = {}
    events = [x for x in (Integrator.EVENT_DRIVEN.value, Integrator.ADAPTIVE.value) if x in names]
    for name in events:
        try:
            runs[name] = _run(_configured(model, name, rtol, grid), grid)[0]
            say(f"reference {name} rtol = {rtol:g}: {runs[name].meta.get('status')}")
        except (SceneError, UnsupportedModel) as exc:
            res.refused[name] = str(exc)
            say(f"{name}: refused: {exc}")
        except SimulationInterrupted:
            raise
        except SimulationError as exc:
            res.notes.append(f"reference {name} at rtol {rtol:g} failed: {exc}")
            say(res.notes[-1])
    ladder_run = None
    dt = model.options.dt
    fallback = _fallback(runs["adaptive"], dt) if "adaptive" in runs else ""
    if len(runs) == 2:
        ref, other = runs["event-driven"], runs["adaptive"]
        r = Reference("two methods", f"event-driven at rtol {rtol:g}", f"adaptive at rtol {rtol:g}", fallback,
                      level=level)
    elif "adaptive" in runs:
        ref = runs["adaptive"]
        # with fixed steps, the check halves them (else both runs would take the same fixed steps)
        check = _configured(model, "adaptive", rtol, grid, dt=dt / 2 if fallback else None)
        try:
            other = _run(check, grid, order=8)[0]
        except SimulationError as exc:
            res.notes.append(f"no reference: adaptive at order 8 failed: {exc}")
            return None, None
        r = Reference("one method, two orders", f"adaptive at rtol {rtol:g} (order {DEFAULT_ORDER})",
                      "the same at order 8" + (f" with its fixed steps at dt = {dt / 2:g} s" if fallback else ""),
                      f"a self-consistency check: the event-driven integrator {_absent('event-driven', res, names)}"
                      + (f"; {fallback}" if fallback else ""), level=level)
    elif "event-driven" in runs:
        ref = runs["event-driven"]
        try:
            other = _run(_configured(model, "event-driven", rtol, grid), grid, method="RK45")[0]
        except SimulationError as exc:
            res.notes.append(f"no reference: event-driven with RK45 failed: {exc}")
            return None, None
        r = Reference("one method, two ODE solvers", f"event-driven (DOP853) at rtol {rtol:g}",
                      "event-driven with RK45", f"the adaptive integrator {_absent('adaptive', res, names)}",
                      level=level)
    else:
        if len(dts) < 2:
            res.notes.append("no reference: only the time-stepper takes this scene and it needs two dt values")
            return None, None
        h1, h2 = dts[-1], dts[-2]
        try:
            ref = _run(_configured(model, "time-stepping", h1, grid), grid)[0]
            other = _run(_configured(model, "time-stepping", h2, grid), grid)[0]
        except SimulationError as exc:
            res.notes.append(f"no reference: time-stepping at dt {h1:g} or {h2:g} s failed: {exc}")
            return None, None
        why = (f"adaptive {_absent('adaptive', res, names)}, event-driven {_absent('event-driven', res, names)}; "
               f"the two runs' difference estimates the error at dt = {h2:g} s, an upper estimate of the reference's")
        r = Reference("two smallest dt, Richardson-style", f"time-stepping at dt = {h1:g} s", f"dt = {h2:g} s", why,
                      level=level)
        ladder_run = ("time-stepping", h1)
    samples = _samples(ref, grid)
    qa, _qm, ua, _um = _errors(model, _samples(other, grid), samples)
    r.q_agreement, r.u_agreement = qa, ua
    r.branching_steps = max(_branching(ref), _branching(other))
    res.reference = r
    res.reference_samples = (grid, *samples)
    say(r.sentence())
    return samples, ladder_run


def _absent(name: str, res: ChartResult, names) -> str:
    """Why an event integrator is not in the reference."""
    if name in res.refused:
        return "refused the scene"
    return "failed at that tolerance" if name in names else "was not among the integrators asked for"


# ---------------------------------------------------------------- outputs
def write(res: ChartResult, out_dir: str | os.PathLike) -> dict[str, str]:
    """chart.json, chart.md and chart.png of `res` into `out_dir` (created); returns their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    res.files = {"json": str(out / "chart.json"), "markdown": str(out / "chart.md"), "png": str(out / "chart.png")}
    stale = out / "chart.partial.json"
    _write_json(Path(res.files["json"]), res)
    Path(res.files["markdown"]).write_text(table(res), encoding="utf-8")
    fig = figure(res)
    fig.savefig(res.files["png"], dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)
    if stale.exists():
        stale.unlink()
    return res.files


def _write_json(path: Path, res: ChartResult) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(res.to_json(), indent=1, default=float), encoding="utf-8")
    tmp.replace(path)


def _fmt(x, spec=".2e") -> str:
    return "-" if x is None else format(x, spec)


def table(res: ChartResult) -> str:
    """The Markdown table of a chart: one row per run, with the reference and the notes above it."""
    lines = [f"# Work-precision chart of {res.scene}", "",
             f"Duration {res.duration:g} s, samples every {res.sample_step:g} s. "
             f"CPU: {res.to_json()['cpu']}. Errors: {NORM}.", ""]
    lines.append(f"- {res.reference.sentence()}" if res.reference else "- no reference: errors not measured")
    lines += [f"- {name} refused the scene: {msg}" for name, msg in res.refused.items()]
    lines += [f"- note: {note}" for note in res.notes]
    lines += ["", "| integrator | dt [s] or rtol | CPU per simulated s [ms] | q error (max) | u error (mean) "
                  "| u error (max) | status |", "|---|---|---|---|---|---|---|"]
    for r in res.runs:
        status = r.status + (f", {r.fixed_steps} fixed steps" if r.fixed_steps else "") + (
            " (below the reference's uncertainty)" if r.below_reference else "")
        cpu = None if r.cpu_per_second is None else 1e3 * r.cpu_per_second
        lines.append(f"| {r.integrator} | {r.setting_name} = {r.setting:g} | {_fmt(cpu, '.3g')} | {_fmt(r.q_error)} "
                     f"| {_fmt(r.u_error)} | {_fmt(r.u_error_max)} | {status} |")
    return "\n".join(lines) + "\n"


COLOURS = {"time-stepping": "tab:blue", "adaptive": "tab:orange", "event-driven": "tab:green"}
FLOOR = 1e-16  # errors below this (exact to round-off) are drawn at it
LABEL_AT = {"time-stepping": (4, 7), "adaptive": (7, 0), "event-driven": (7, 0)}  # [points] a label's offset


def figure(res: ChartResult):
    """Error against CPU time per simulated second, log-log, one line per integrator, q and u side
    by side; the reference's agreement as a dashed line, each point labelled with its dt or rtol."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib import ticker

    fig, axes = plt.subplots(1, 2, figsize=(12, 5.6), layout="constrained")
    ref = res.reference
    floored = False
    for ax, attr, agree, label in ((axes[0], "q_error", "q_agreement", "q error, max over samples [m, rad]"),
                                   (axes[1], "u_error", "u_agreement", "u error, mean over samples [m/s, rad/s]")):
        # an uncertain reference resolves no error below its runs' difference: such points sit on it
        lowest = max(getattr(ref, agree), FLOOR) if ref is not None and ref.uncertain else FLOOR
        drawn = [r for r in res.runs if getattr(r, attr) is not None]
        if drawn:  # the panel's extent in decades (x: with the room for labels), for grouping labels
            cpu = [r.cpu_per_second for r in drawn]
            err = [max(getattr(r, attr), lowest) for r in drawn]
            spans = (math.log10(3 * max(cpu) / min(cpu)) + 0.2, max(1.0, math.log10(max(err) / min(err))))
        for name in INTEGRATORS:
            pts = [r for r in res.runs if r.integrator == name and getattr(r, attr) is not None]
            if not pts:
                continue
            x = [r.cpu_per_second * 1e3 for r in pts]
            y = [max(getattr(r, attr), lowest) for r in pts]
            floored |= min(y) <= FLOOR
            ax.plot(x, y, "o-", color=COLOURS[name], label=f"{name} (points labelled with {pts[0].setting_name})",
                    ms=5)
            below = [k for k, r in enumerate(pts) if ref is not None and ref.uncertain
                     and getattr(r, attr) < getattr(ref, agree)]
            if below:  # not resolved by the reference: drawn hollow, on its line
                ax.plot([x[k] for k in below], [y[k] for k in below], "o", mfc="white", color=COLOURS[name], ms=5)
            for group in _coinciding(pts, x, y, spans):
                values = [f"{pts[k].setting:g}" for k in group]
                text = ", ".join(values) if len(values) <= 2 else f"{values[0]} ... {values[-1]}"
                ax.annotate(text, (x[group[0]], y[group[0]]), textcoords="offset points", xytext=LABEL_AT[name],
                            fontsize=7, color=COLOURS[name], va="center")
        if ref is not None and np.isfinite(getattr(ref, agree)):
            level = max(getattr(ref, agree), FLOOR)
            ax.axhline(level, color="k", ls="--", lw=0.8, label="reference agreement (the two reference runs' "
                       "difference)" + ("; UNCERTAIN: errors below it are not resolved, drawn on it, hollow"
                                      if ref.uncertain else ""))
            ax.set_title(f"the reference runs differ by {getattr(ref, agree):.1e} (dashed)", fontsize=8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_major_locator(ticker.LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(ticker.FuncFormatter(lambda v, _pos: f"{v:g}"))
        ax.xaxis.set_minor_formatter(ticker.NullFormatter())
        lo, hi = ax.get_ylim()
        ax.set_ylim(lo, max(hi, 10 * lo))
        lo, hi = ax.get_xlim()
        ax.set_xlim(lo, hi * 3)  # room for the labels of the costliest points
        ax.set_xlabel("CPU time per simulated second [ms/s]")
        ax.set_ylabel(label)
        ax.grid(True, which="both", lw=0.3, alpha=0.5)
    handles = {}
    for ax in axes:
        for h, text in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(text, h)
    if floored:
        handles[f"errors below {FLOOR:.0e} (exact to round-off) drawn at {FLOOR:.0e}"] = \
            plt.Line2D([], [], ls="none")
    if handles:
        fig.legend(handles.values(), handles.keys(), loc="outside lower center", ncol=2, fontsize=8, frameon=False)
    title = f"{res.scene}: work-precision over {res.duration:g} s, samples every {res.sample_step:g} s"
    sub = ref.sentence() if ref is not None else "no reference: errors not measured"
    extra = [f"{n} refused" for n in res.refused] + (["corner impacts: methods may pick different outcomes"]
                                                      if any("corner" in n for n in res.notes) else [])
    fig.suptitle(title + "\n" + _wrap(sub + ("; " + "; ".join(extra) if extra else "")), fontsize=9)
    return fig


def _coinciding(pts, x, y, spans) -> list[list[int]]:
    """Indices of the points grouped where they overlap on the log-log chart (within 5 % of the
    panel's decades of CPU and 4 % of its decades of error, `spans`): one label per group,
    "first ... last" beyond two."""
    groups: list[list[int]] = []
    for k in range(len(pts)):
        for g in groups:
            j = g[0]
            if abs(math.log10(x[k] / x[j])) < 0.05 * spans[0] and abs(math.log10(y[k] / y[j])) < 0.04 * spans[1]:
                g.append(k)
                break
        else:
            groups.append([k])
    return groups


def _wrap(text: str, width: int = 150) -> str:
    words, lines, line = text.split(), [], ""
    for w in words:
        if len(line) + len(w) + 1 > width:
            lines.append(line)
            line = w
        else:
            line = f"{line} {w}".strip()
    return "\n".join(lines + [line])


__all__ = ["ChartInterrupted", "ChartResult", "Reference", "Run", "chart", "figure", "table", "write"]
