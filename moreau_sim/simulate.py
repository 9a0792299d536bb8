"""The loop: steps, recorder, progress, stop conditions, errors naming the step and time."""

from __future__ import annotations

import os
import time
from pathlib import Path

from tqdm import tqdm

from .adaptive import simulate_adaptive
from .data import Data, make_data
from . import checkpoint as ckpt
from .checkpoint import Checkpoint
from .errors import SceneError, SimulationError, named_stops
from .event_driven import simulate_event_driven
from .model import Model, build_model, initial_state
from .options import Integrator
from .recording import Recorder, run_metadata
from .scene import Scene, load_scene
from .state import State
from .stepper import step
from .trajectory import Trajectory

# An impact ("log_impact") is a logged percussion of a contact that was not closed in the previous step.
# [s] the progress bar appears on runs longer than this (MOREAU_SIM_PROGRESS_DELAY overrides it)
_PROGRESS_DELAY = float(os.environ.get("MOREAU_SIM_PROGRESS_DELAY", "2.0"))


def simulate(model: Model, *, data: Data | None = None, state: State | None = None,
             progress: bool = True, checkpoint: Checkpoint | None = None,
             spill: str | Path | None = None) -> Trajectory:
    """Run the scene's options (restitution, dt, duration) from `state` (default: the scene's
    initial state). Returns a complete :class:`Trajectory` or raises :class:`SimulationError`
    (naming the step and time) whose ``.trajectory`` holds the samples up to the failure,
    marked ``status = "failed: ..."``; Ctrl-C raises :class:`SimulationInterrupted` likewise.

    checkpoint: save a checkpoint every so often and/or resume from one (time-stepping only;
    :class:`~moreau_sim.checkpoint.Checkpoint`); a resumed run gives the same arrays, bit for
    bit, as an uninterrupted one. The checkpoint file is removed when the run completes unless
    ``checkpoint.keep``.

    spill: a folder where a time-stepping run keeps all but the last block of its recorded rows, in
    unnamed temporary files (recording.Recorder): the memory of a long run stays that of the
    libraries and one block, and the returned arrays are read-only maps of those files (they
    disappear with the arrays)."""
    data = data or make_data(model)
    state = state or initial_state(model)
    opts = model.options
    if checkpoint is not None and opts.integrator is not Integrator.TIME_STEPPING:
        raise SceneError(f"checkpoint: the {opts.integrator.value} integrator cannot checkpoint; "
                         "only time-stepping runs can")
    if opts.integrator is Integrator.EVENT_DRIVEN:
        return simulate_event_driven(model, data=data, state=state)
    if opts.integrator is Integrator.ADAPTIVE:
        return simulate_adaptive(model, data=data, state=state)
    h, e, n, every = opts.dt, opts.restitution, opts.n_steps, opts.save_every
    rec = Recorder(model, data, min(1 + n // every + 1, 1 << 16), spill=spill)  # columns grow beyond this
    t0, k0, previous, work, corr, wall_before = state.t, 0, set(), 0.0, 0.0, 0.0
    if checkpoint is not None and checkpoint.resume and Path(checkpoint.path).exists():
        r = ckpt.load(Path(checkpoint.path), model, rec, data)
        t0, k0, state, work, corr, previous, wall_before = r.t0, r.steps, r.state, r.work, r.corr, r.previous, r.wall
    else:
        rec.sample(state, 0.0, 0.0, 0)
    ck_every = checkpoint.steps(h) if checkpoint is not None else None
    wall0 = time.perf_counter()
    bar = tqdm(total=n, initial=k0, delay=_PROGRESS_DELAY, disable=not progress, unit="step", mininterval=0.5,
               leave=False)
    k = k0

    def wall() -> float:
        return wall_before + time.perf_counter() - wall0

    def partial(status: str) -> Trajectory:
        return rec.trajectory(_meta(model, status, k, wall()))

    with named_stops(lambda: (k + 1, state.t), partial):
        try:
            for k in range(k0, n):
                r = step(model, data, state, h=h, e=e, t_next=t0 + (k + 1) * h)
                if r.qp is not None and not r.qp.ok:
                    raise SimulationError(f"step {k + 1} (t = {state.t:.6g} s -> {r.state.t:.6g} s): the impact QP "
                                          f"failed with status {r.qp.status} after {r.qp.iterations} iterations "
                                          f"({r.contacts.m} closed contacts)", step=k + 1, t=state.t)
                if not r.state.finite():
                    raise SimulationError(f"step {k + 1} (t = {state.t:.6g} s -> {r.state.t:.6g} s): the state "
                                          "became non-finite (NaN or inf)", step=k + 1, t=state.t)
                work += r.contact_work
                corr += r.correction_energy
                previous = rec.log_percussions(k + 1, state.t + 0.5 * h, r.contacts, r.P, r.gamma_minus,
                                               r.gamma_plus, previous)
                rec.account_step(k + 1, state.t + 0.5 * h, state, r, h, e)
                if r.branch is not None:
                    sol, chosen, u_plus = r.branch
                    rec.branch(k + 1, state.t + 0.5 * h, chosen,
                               [(up, c.distance, c.global_min) for up, c in zip(u_plus, sol.candidates)])
                state = r.state
                if (k + 1) % every == 0 or k == n - 1:
                    rec.sample(state, work, corr, r.contacts.m)
                    work = corr = 0.0
                    if not rec.finite():
                        raise SimulationError(f"step {k + 1} (t = {state.t:.6g} s): the energies or gaps became "
                                              "non-finite (an overflow: check gravity, masses and initial "
                                              "velocities)", step=k + 1, t=state.t)
                if ck_every is not None and (k + 1) % ck_every == 0 and k < n - 1:
                    ckpt.save(Path(checkpoint.path), rec, _meta(model, "checkpoint", k + 1, wall()), steps=k + 1,
                              t0=t0, state=state, work=work, corr=corr, previous=previous, data=data)
                if (k & 1023) == 1023:
                    bar.update(1024)
        finally:
            bar.close()
    traj = rec.trajectory(_meta(model, "complete", n, wall()))
    if checkpoint is not None and not checkpoint.keep:
        Path(checkpoint.path).unlink(missing_ok=True)
    return traj


def _meta(model: Model, status: str, steps: int, wall: float) -> dict:
    return run_metadata(model, status, {"steps": steps, "wall_seconds": wall,
                                        "us_per_step": 1e6 * wall / steps if steps else None})


def run(scene: Scene | str | Path, *, dt: float | None = None, duration: float | None = None,
        restitution: float | None = None, progress: bool = False, checkpoint: str | Path | None = None,
        checkpoint_every: float | None = None, resume: bool = False, spill: str | Path | None = None,
        **options) -> Trajectory:
    """Load (if a path), override options (dt [s], duration [s], restitution, any other
    :class:`~moreau_sim.options.Options` field, e.g. integrator="adaptive", rtol=1e-10,
    atol=1e-12), build and simulate. Returns the Trajectory.

    checkpoint: a checkpoint file, written every `checkpoint_every` seconds of simulated time
    (rounded to whole steps) and removed when the run completes; resume: continue from it when
    it exists (checkpoint.py); spill: a folder for the recorded rows instead of memory (simulate)."""
    sc = scene if isinstance(scene, Scene) else load_scene(scene)
    sc = sc.with_options(dt=dt, duration=duration, restitution=restitution, **options)
    ck = None if checkpoint is None else Checkpoint(path=Path(checkpoint), every=checkpoint_every, resume=resume)
    return simulate(build_model(sc), progress=progress, checkpoint=ck, spill=spill)


def summary(traj: Trajectory) -> dict:
    """The figures the CLI prints: steps, impacts, energies, penetration, timing."""
    a, run_ = traj.arrays, traj.meta.get("run", {})
    E = a["kinetic_energy"] + a["potential_energy"]
    gaps = a["gap"]
    return {
        "scene": traj.meta.get("scene", {}).get("name"),
        "status": traj.meta.get("status"),
        "integrator": traj.meta.get("integrator", "time-stepping"),
        "steps": run_.get("steps"),  # None for the event-driven integrator
        "steps_fixed": run_.get("steps_fixed"),  # the adaptive integrator's fixed steps
        "events": run_.get("events"),  # the event-driven and adaptive integrators' events
        "samples": int(len(a["t"])),
        "t_end": float(a["t"][-1]) if len(a["t"]) else None,
        "impacts": traj.impacts,
        "branching_steps": int(len(a["branch_step"])),
        "percussions_logged": int(len(a["log_P"])),
        "energy_start": float(E[0]) if len(E) else None,
        "energy_end": float(E[-1]) if len(E) else None,
        "energy_max_increase": float(E.max() - E[0]) if len(E) else None,  # = max(E - E[0]): rounding is monotone
        "contact_work_total": float(a["contact_work"].sum()),
        "correction_energy_total": float(a["correction_energy"].sum()),
        "smooth_error_total": float(a["smooth_error"].sum()),  # the ledger (docs/theory.md §5, ms.ledger)
        "law_difference_max": traj.meta.get("ledger", {}).get("max_law_difference"),
        "min_gap": float(gaps.min()) if gaps.size else None,
        "wall_seconds": run_.get("wall_seconds"),
        "us_per_step": run_.get("us_per_step"),
    }
