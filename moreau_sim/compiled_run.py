"""The time-stepping run at compiled speed (docs/theory.md §2.8, §9): src/run.cpp's Runner loops the compiled
step and records into the Recorder's columns what driver._Loop.account records per step (percussion log,
ledger, samples, the invariant checks), operation by operation, so that the arrays are the Python run's bit for
bit. It returns to the driver at a coarse poll (progress, Ctrl-C, checkpoints), when a group of columns is full,
at the run's end, and for each step it hands back (the compiled step's fallback, a failure, a check that
fires): the Python run takes that step, then the Runner resumes. Every figure the run carries goes back to the
Python objects at each return, so a checkpoint or an error sees the Python run's state. Joint torques are
evaluated in the Runner (src/actuation.hpp, the Python run's actuation.py operation by operation); a Python
controller is called back from it once per step, its errors raised here as the Python run raises them. Moving
statics and driven joints (docs/theory.md §2.9, §2.13) are the compiled step's (src/rheonomic.hpp): the Runner
places the statics at each sample's time and books the work of prescribed motion as the Recorder does."""

from __future__ import annotations

import numpy as np

from . import compiled, invariants
from .actuation import PDGroup
from .invariants import Invariant, Invariants
from .ledger import REST_ACCURACY
from .recording import LOG_RELATIVE
from .state import State

LOG_ROWS = 1000  # log rows reserved a call at least (more where one step has needed more: Runner.log_need)
POLL_SECONDS = 0.05  # [s of wall time] the Runner returns to the driver at least this often
MAX_BACKOFF = 256  # steps: the most the Python run takes in a row before the Runner tries again


def unsupported(model, check) -> str | None:
    """Why the compiled run does not take this time-stepping run (None: it does)."""
    why = compiled.loop_refusal(model, "Runner", "the run loop", whole=False)  # on the forest (§2.12)
    if why is not None:
        return why
    why = compiled._prepared(model).why  # compiled.unsupported, once per model (the compiled step's own verdict)
    if why is not None:
        return why
    if check is not None and type(check) is not Invariants:
        return "an invariant hook of the caller's"
    return None


_REC = {"smooth": "_smooth", "diss": "_diss", "law": "_law", "E": "_E", "smooth_deficit": "smooth_deficit",
        "act": "_act", "obs": "_obs"}
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
        c = check
        consts = {"log_relative": LOG_RELATIVE, "rest_accuracy": REST_ACCURACY, "acceleration": invariants.ACCELERATION,
                  "gap_round_off": invariants.GAP_ROUND_OFF, "persist": invariants.PERSIST,
                  "rel": c.rel if c else 0.0, "rel_ledger": c.rel_ledger if c else 0.0, "tol": c.tol if c else 0.0,
                  "g": c.g if c else 0.0}
        self.controller = None if m.actuation is None or m.actuation.controller is None else _Callback(m.actuation)
        self.stepper, self.boxes = stepper, bool(m.polytope_pair_set)
        self.runner = compiled._module.Runner(stepper, *compiled.forest_args(m, data), consts, c is not None,
                                              _actuation(m.actuation, self.controller))
        self.python_steps = 0  # steps the Python run took in this run
        self._skip = 0  # steps the Python run takes before the Runner tries again
        self._misses = 0  # hand-backs in a row without a compiled step
        self._loop_meta()

    def _loop_meta(self) -> None:
        self.integ.loop_meta = {"loop": "compiled", "python_steps": self.python_steps,
                                **({"python_calls": "the controller, once a step"} if self.controller else {})}

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
        starts = [g.reserve(k) for g, k in zip(groups, (1, max(LOG_ROWS, r.log_need()), 1))]
        rooms = [len(next(iter(g.cols.values()))) - i for g, i in zip(groups, starts)]
        data = integ.data
        if self.boxes:  # contacts.detect's warm start, kept in data between steps whichever loop takes them
            self.stepper.warm = sorted(data.warm_start_pairs)
        if data.active_holder is not self.stepper:  # the projection's warm start (stepper.keep_active), likewise
            self.stepper.active = sorted(data.active_rows)
        stop = r.advance(st.t, st.q, st.u, integ.k, integ.n, integ.every, integ.h, integ.e, integ.t0, t_stop,
                         POLL_SECONDS, *(g.cols for g in groups), starts, rooms)
        if self.boxes:  # as the last step the Runner kept left it (a step it undoes leaves it as it was)
            data.warm_start_pairs = set(self.stepper.warm)
        data.hold_active(self.stepper)  # as the last step the Runner kept left it (read where asked)
        t, q, u, k = r.where()
        Stop = compiled._module.Stop
        unfit = stop is Stop.FULL and k == integ.k  # a step's log rows did not fit: undone, r.log_need() says how many
        if unfit and self.controller is None:
            return self.advance(t_stop)  # taken again with its rows reserved
        handed = stop is Stop.HAND_BACK or unfit  # (a controller's answer: replayed by the Python run, not asked again)
        failed = None if self.controller is None else self.controller.take_error()
        if handed and failed is None and self.controller is not None:
            # the Python run retakes the step: the controller's answer is replayed, not asked again
            integ.model.actuation.replay = self.controller.last
        if failed is not None and k == integ.k:
            raise failed
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
        if failed is not None:  # the steps before it are recorded; the error names the step the controller failed in
            raise failed
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
        d["rest"] = float(rec._log.keep)  # the stretch of persistent steps the log ends with (Recorder._log_step)
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
        rec._log.keep = int(d["rest"])  # the log's last rows a persistent step may add to (§5.2)
        loop.work, loop.corr, loop.points = d["work"], d["corr"], int(d["points"])
        loop.previous = {tuple(p) for p in previous}
        if c is not None:
            for k in _INV:
                setattr(c, k, int(d["i_" + k]) if k in _INTS else d["i_" + k])
            c.held = {int(p): float(a) for p, a in held}


class _Callback:
    """The controller as the Runner calls it (src/actuation.hpp's Actuation.call): `controller`, called directly with
    q_m and u_k in read-only arrays from `array` (rewritten in place each step unless the controller kept a
    reference to them: what it keeps is never rewritten), its answer taken as it is where it is an (nv,) float64
    buffer, finite and zero on `root_rows` (actuation.Actuation.checked's checks), and passed to `check` otherwise;
    `failed` keeps an error for compiled_run to raise (the Runner returns to Python instead); `last`: the answer
    (t, q, u, tau) the Runner took last, replayed where it hands that step back."""

    def __init__(self, actuation):
        self.actuation, self.controller = actuation, actuation.controller
        self.root_rows = np.flatnonzero(actuation.root).tolist()
        self.error: BaseException | None = None
        self.last: tuple | None = None

    @staticmethod
    def array(n: int) -> np.ndarray:
        a = np.empty(n)
        a.flags.writeable = False
        return a

    def failed(self, t: float, exc: BaseException) -> None:
        self.error = self.actuation.failure(t, exc)

    def check(self, t: float, f) -> np.ndarray | None:
        try:
            return np.ascontiguousarray(self.actuation.checked(t, f))
        except BaseException as exc:  # noqa: BLE001 - raised by advance once the steps before are recorded
            self.error = exc
            return None

    def take_error(self) -> BaseException | None:
        err, self.error = self.error, None
        return err


def _actuation(act, controller) -> tuple | None:
    """The model's actuation.Actuation as src/actuation.hpp's Actuation reads it (None: no torques)."""
    if act is None:
        return None
    groups = []
    for g in act.groups:
        if isinstance(g, PDGroup):
            groups.append(("pd", g.q_index.tolist(), g.v_index.tolist(), float(g.kp), float(g.kd), float(g.effort),
                           compiled.schedule(g.target), compiled.schedule(g.velocity)))
        else:  # mjcf_actuators.Servos
            groups.append(("mjcf", g.q_index.tolist(), g.v_index.tolist(),
                           *(np.asarray(a, float).tolist() for a in (g.gear, g.gain, g.kp, g.kv, g.clo, g.chi, g.flo,
                                                                      g.fhi)),
                           [compiled.schedule(c) for c in g.ctrl],
                           [(idx.tolist(), float(lo), float(hi)) for idx, (lo, hi) in g.joint_clamps]))
    return act.nv, np.asarray(act.limit, float).tolist(), groups, controller


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
