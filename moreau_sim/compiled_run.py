"""The time-stepping run at compiled speed (docs/theory.md §2.8, §9): src/run.cpp's Runner loops the compiled
step and records into the Recorder's columns what driver._Loop.account records per step (percussion log,
ledger, samples, the invariant checks), operation by operation, so that the arrays are the Python run's bit for
bit. It returns to the driver at a coarse poll (progress, Ctrl-C, checkpoints), when a group of columns is full,
at the run's end, and for each step it hands back (the compiled step's fallback, a failure, a check that
fires): the Python run takes that step, then the Runner resumes. Every figure the run carries goes back to the
Python objects at each return, so a checkpoint or an error sees the Python run's state."""

from __future__ import annotations

from . import compiled, invariants
from .invariants import Invariant, Invariants
from .ledger import REST_ACCURACY
from .options import StepImpl
from .recording import LOG_RELATIVE
from .state import State

POLL_SECONDS = 0.05  # [s of wall time] the Runner returns to the driver at least this often
MAX_BACKOFF = 256  # steps: the most the Python run takes in a row before the Runner tries again


def unsupported(model, check) -> str | None:
    """Why the compiled run does not take this time-stepping run (None: it does)."""
    if model.options.step_impl is not StepImpl.COMPILED:
        return "step_impl python"
    if not compiled.available():
        return f"the compiled step is unavailable: {compiled.unavailable_reason()}"
    if not hasattr(compiled._module, "Runner"):
        return "the compiled step predates the run loop (rebuild)"
    if not model.whole_data_fits():
        return "the whole model's Data exceeds the memory limit"
    why = compiled.unsupported(model)
    if why is not None:
        return why
    if model.actuation is not None:
        return "joint torques (actuators or a controller)"
    if model.polytope_pair_set:
        # a step the Runner undoes (a check that fires) has moved coal's GJK guesses and the warm start of the
        # box pairs' detection, which the Python step retaking it would not see
        return "pairs of two boxes (the run loop does not carry their detection's warm start)"
    if check is not None and type(check) is not Invariants:
        return "an invariant hook of the caller's"
    return None


_REC = {"smooth": "_smooth", "diss": "_diss", "law": "_law", "E": "_E", "smooth_deficit": "smooth_deficit"}
_INV = ("E0", "E", "Ehat", "Emin", "scale", "booked", "external", "residual", "Es", "v_app", "deep_points",
        "deep_samples", "last_depth", "last_allowed", "points")
_INTS = ("deep_points", "deep_samples", "points")
_WORSE = {"w_gain": Invariant.ENERGY_GAIN, "w_speed": Invariant.SPEED, "w_depth": Invariant.PENETRATION,
          "w_ledger": Invariant.LEDGER}


class CompiledRun:
    """The Runner of one time-stepping run (integ: time_stepping.TimeStepping; rec, loop: the driver's
    Recorder and _Loop; check: its invariant hook, Invariants or None)."""

    def __init__(self, integ, rec, loop, check, stepper):
        self.integ, self.rec, self.loop, self.check = integ, rec, loop, check
        m, data = integ.model, integ.data
        forest = m.forest
        trees = [(tr.model, d, tr.q.start, tr.q.stop - tr.q.start, tr.v.start, tr.v.stop - tr.v.start)
                 for tr, d in zip(forest.trees, data.kinematics.datas())]
        c = check
        consts = {"log_relative": LOG_RELATIVE, "rest_accuracy": REST_ACCURACY, "acceleration": invariants.ACCELERATION,
                  "gap_round_off": invariants.GAP_ROUND_OFF, "persist": invariants.PERSIST,
                  "rel": c.rel if c else 0.0, "rel_ledger": c.rel_ledger if c else 0.0, "tol": c.tol if c else 0.0,
                  "g": c.g if c else 0.0}
        self.runner = compiled._module.Runner(stepper, trees, forest.tree_of_joint.tolist(),
                                              forest.local_joint.tolist(), consts, c is not None)
        self.python_steps = 0  # steps the Python run took in this run
        self._skip = 0  # steps the Python run takes before the Runner tries again
        self._misses = 0  # hand-backs in a row without a compiled step
        self._loop_meta()

    def _loop_meta(self) -> None:
        self.integ.loop_meta = {"loop": "compiled", "python_steps": self.python_steps}

    def python_step(self) -> None:
        """The driver took one step through the Python run."""
        self.python_steps += 1
        self._loop_meta()

    def advance(self, t_stop: float) -> tuple[float, bool] | None:
        """Compiled steps from the integrator's state until the poll, a step ending at t >= t_stop [s], full
        columns, a hand-back or the end: (t of the last step [s], whether the run ended); None: the next step
        goes to the Python run (then call python_step)."""
        integ, rec = self.integ, self.rec
        st = integ.state
        at = rec._at
        if self._skip or at is None or at[0] is not st.q or at[1] is not st.u or rec._E is None:
            self._skip = max(self._skip - 1, 0)
            return None
        r = self.runner
        r.load(self._carry(), sorted(self.loop.previous), list(self.check.held.items()) if self.check else [])
        groups = (rec._samples, rec._log, rec._impacts)
        starts = [g.reserve(k) for g, k in zip(groups, (1, compiled.MAX_CONTACTS, 1))]
        rooms = [len(next(iter(g.cols.values()))) - i for g, i in zip(groups, starts)]
        stop = r.advance(st.t, st.q, st.u, integ.k, integ.n, integ.every, integ.h, integ.e, integ.t0, t_stop,
                         POLL_SECONDS, *(g.cols for g in groups), starts, rooms)
        t, q, u, k = r.where()
        handed = stop is compiled._module.Stop.HAND_BACK
        if k == integ.k:  # not one step: the Python run takes the next ones, fewer as misses repeat
            self._misses += 1
            self._skip = min(1 << (self._misses - 1), MAX_BACKOFF) - 1
            return None
        self._misses = 0
        for g, w in zip(groups, r.written()):
            g.commit(w)
        self._store(r.carry(), r.previous(), r.held())
        flight, contact = r.counts()
        cnt = compiled.counts(integ.data)
        cnt["flight"] += flight
        cnt["contact"] += contact
        integ.state, integ.k = State(t, q, u), k
        rec._at = (q, u)
        if handed:
            self._skip = 1
        return t, stop is compiled._module.Stop.FINISHED

    def _carry(self) -> dict:
        rec, loop, c = self.rec, self.loop, self.check
        d = {k: float(getattr(rec, a)) for k, a in _REC.items()}
        d["T"], d["V"] = map(float, rec._TV)
        d["rise"], d["t_rise"] = map(float, rec._rise)
        d["law_diff"], d["t_law_diff"] = map(float, rec._law_difference)
        d["new_impact"], d["contact_steps"] = float(rec._new_impact), float(rec._contact_steps)
        d["work"], d["corr"], d["points"] = float(loop.work), float(loop.corr), float(loop.points)
        for k in _INV:
            d["i_" + k] = float(getattr(c, k)) if c is not None else 0.0
        reported = c.reported if c is not None else {}
        for k, what in _WORSE.items():  # what Invariants._violate would report again (bigger than this)
            d[k] = invariants.WORSEN * reported.get(what.value, 0.0)
        return d

    def _store(self, d: dict, previous: list, held: list) -> None:
        rec, loop, c = self.rec, self.loop, self.check
        for k, a in _REC.items():
            setattr(rec, a, d[k])
        rec._TV = (d["T"], d["V"])
        rec._rise, rec._law_difference = (d["rise"], d["t_rise"]), (d["law_diff"], d["t_law_diff"])
        rec._new_impact, rec._contact_steps = bool(d["new_impact"]), int(d["contact_steps"])
        loop.work, loop.corr, loop.points = d["work"], d["corr"], int(d["points"])
        loop.previous = {tuple(p) for p in previous}
        if c is not None:
            for k in _INV:
                setattr(c, k, int(d["i_" + k]) if k in _INTS else d["i_" + k])
            c.held = {int(p): float(a) for p, a in held}


def runner(integ, rec, loop, check) -> CompiledRun | None:
    """The compiled run of a time-stepping run where it qualifies (driver.drive's `fast`), else None; the
    integrator's loop_meta says which loop ran (and why not the compiled one)."""
    why = unsupported(integ.model, check)
    if why is None:
        ctx = compiled._context(integ.model, integ.data)
        if ctx.stepper is None:
            why = ctx.why
        else:
            return CompiledRun(integ, rec, loop, check, ctx.stepper)
    integ.loop_meta = {"loop": "python", "why": why}
    return None
