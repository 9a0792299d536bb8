"""Running a scene: the integrator its options name, driven by driver.drive; and the summary the CLI prints."""

from __future__ import annotations

import dataclasses
import inspect
import math
from pathlib import Path

from .actuation import Controller, for_controller
from .adaptive import simulate_adaptive
from . import compiled_run
from .checkpoint import Checkpoint
from .data import Data
from .driver import Check, drive, run_data
from .errors import SimulationError, out_of_memory
from .event_driven import simulate_event_driven
from .invariants import Invariants
from .model import Model, build_model, initial_state
from .options import Integrator
from .scene import Scene, load_scene
from .state import State
from .time_stepping import TimeStepping
from .trajectory import Summary, Trajectory

_EVENT_RTOL = inspect.signature(simulate_event_driven).parameters["rtol"].default  # its smooth phases' rtol

# An impact ("log_impact") is a logged percussion of a contact that was not closed in the previous step.


def simulate(model: Model, *, data: Data | None = None, state: State | None = None,
             progress: bool = True, checkpoint: Checkpoint | None = None,
             spill: str | Path | None = None, check: Check | None = None, strict: bool = False,
             controller: Controller | None = None, python_run: bool = False) -> Trajectory:
    """Run the scene's options (integrator, restitution, dt, duration) from `state` (default: the
    scene's initial state). Returns a complete :class:`Trajectory` or raises :class:`SimulationError`
    (naming the step and time) whose ``.trajectory`` holds the samples up to the failure,
    marked ``status = "failed: ..."``; Ctrl-C raises :class:`SimulationInterrupted` likewise.

    data: the run's scratch (default: one the model kept from an earlier run, or a new one); the run starts by
    resetting it (data.Data.reset), so it takes the same steps whatever ran on it before (docs/theory.md §2.8).

    checkpoint: save a checkpoint every so often and/or resume from one
    (:class:`~moreau_sim.checkpoint.Checkpoint`); a resumed run gives the same arrays, bit for
    bit, as an uninterrupted one. The checkpoint file is removed when the run completes unless
    ``checkpoint.keep``.

    spill: a folder where the run keeps all but the last block of its recorded rows, in unnamed
    temporary files (recording.Recorder): the memory of a long run stays that of the libraries and
    one block, and the returned arrays are read-only maps of those files (they disappear with the
    arrays).

    The run checks its own invariants (invariants.py, docs/theory.md §10): a run that broke one
    ends with meta status "flagged" (not "complete") and the violations in meta["invariants"];
    strict: raise InvariantViolation (a SimulationError) at the first one instead, its
    ``.trajectory`` the samples so far. check: another hook instead of the invariants (driver.Check).

    controller: f(t, q, u) -> tau (nv,) [N or N m], joint torques added to the scene's PD targets,
    called once per step at (t_m, q_m, u_k) (docs/theory.md §2.1; actuation.py). Torques and
    prescribed motion run with the time-stepping integrator only.

    python_run: a time-stepping run steps and records in Python even where the compiled run loop takes it
    (compiled_run.py; meta["run"]["loop"] says which ran)."""
    if controller is not None:
        model = dataclasses.replace(model, actuation=for_controller(model.pin, model.bodies, model.actuation,
                                                                    controller))
    try:
        return _simulate(model, data, state, progress, checkpoint, spill, check, strict, python_run)
    except (MemoryError, RuntimeError) as exc:  # a failed allocation: one line naming the scene and its size
        msg = out_of_memory(exc, str(model.scene.path or model.scene.name), "running it",
                            f"{len(model.bodies)} bodies, nv = {model.nv}, {len(model.pairs)} collision pairs")
        if msg is None:
            raise
        raise SimulationError(msg) from None


def _simulate(model, data, state, progress, checkpoint, spill, check, strict, python_run) -> Trajectory:
    opts = model.options
    if check is None:
        rtol = opts.rtol if opts.integrator is Integrator.ADAPTIVE else _EVENT_RTOL
        check = Invariants(model, rtol=rtol, strict=strict)
    if opts.integrator is Integrator.EVENT_DRIVEN:
        return simulate_event_driven(model, data=data, state=state, progress=progress, checkpoint=checkpoint,
                                     spill=spill, check=check)
    if opts.integrator is Integrator.ADAPTIVE:
        return simulate_adaptive(model, data=data, state=state, progress=progress, checkpoint=checkpoint,
                                 spill=spill, check=check)
    n, every = opts.n_steps, opts.save_every
    with run_data(model, data) as data:
        state = state or initial_state(model, data)
        return drive(TimeStepping(model, data, state), model, data, progress=progress, checkpoint=checkpoint,
                     spill=spill, check=check, capacity=1 + n // every + 1,  # the samples (columns.RESERVE_BYTES)
                     fast=None if python_run else compiled_run.runner)


def run(scene: Scene | str | Path, *, dt: float | None = None, duration: float | None = None,
        restitution: float | None = None, progress: bool = False, checkpoint: str | Path | None = None,
        checkpoint_every: float | None = None, resume: bool = False, spill: str | Path | None = None,
        strict: bool = False, controller: Controller | None = None, **options) -> Trajectory:
    """Load (if a path), override options (dt [s], duration [s], restitution, any other
    :class:`~moreau_sim.options.Options` field, e.g. integrator="adaptive", rtol=1e-10,
    atol=1e-12), build and simulate. Returns the Trajectory.

    checkpoint: a checkpoint file, written every `checkpoint_every` seconds of simulated time
    (rounded to whole steps) and removed when the run completes; resume: continue from it when
    it exists (checkpoint.py); spill: a folder for the recorded rows instead of memory; strict: a
    broken invariant is an error (simulate); controller: joint torques f(t, q, u) -> tau (simulate)."""
    sc = scene if isinstance(scene, Scene) else load_scene(scene)
    sc = sc.with_options(dt=dt, duration=duration, restitution=restitution, **options)
    ck = None if checkpoint is None else Checkpoint(path=Path(checkpoint), every=checkpoint_every, resume=resume)
    return simulate(build_model(sc), progress=progress, checkpoint=ck, spill=spill, strict=strict,
                    controller=controller)


def summary(traj: Trajectory) -> Summary:
    """The figures the CLI prints: steps, impacts, energies, penetration, timing (a dict that prints
    readably)."""
    a, run_ = traj.arrays, traj.meta.get("run", {})
    E = a["kinetic_energy"] + a["potential_energy"]
    min_gap = float(a["gap"].min()) if a["gap"].size else math.inf
    return Summary({
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
        # None also where no two geometries came within reach (gaps per geometry are +inf there)
        "min_gap": None if min_gap == math.inf else min_gap,
        "wall_seconds": run_.get("wall_seconds"),
        "cpu_seconds": run_.get("cpu_seconds"),  # the run loop's CPU time (driver.drive)
        "us_per_step": run_.get("us_per_step"),
    })
