"""The invariants every run checks of itself (docs/theory.md §10), through the driver's hook
(driver.Check) at the start, every accepted point and every sample, for every integrator: a
finite state, no penetration beyond the method's, no energy gain beyond the integrator's stated
bound, no speed the energy cannot pay for, a closed ledger, no start inside an obstacle; and at the
end, from the recorded samples and percussion log, no kinetic energy paid by a load sinking into its
support (sinking.py) and no motion below the energy's round-off (creep.py).
Each check is a few float reductions; a violation is a dict kept in meta["invariants"].
"""

from __future__ import annotations

import functools
import math
from enum import Enum

import numpy as np

from .creep import first_creep
from .data import Data, make_data, spares
from .energy import kinetic, potential
from .errors import SimulationError
from .sinking import first_paid
from .model import Model
from .options import Integrator
from .sums import ordered
from .protocol import FixedStep, Impact, Report, RunStatus
from .recording import Recorder, SampleBlock
from .state import State

FIXED_RTOL = 1e-8  # the fixed step's stated bound on a gain of T + V in its contact steps, of the energy scale
EXACT_FACTOR = 100.0  # the adaptive and event-driven integrators' bound: EXACT_FACTOR * rtol of the energy scale
ROUND_OFF = 64 * np.finfo(float).eps  # relative round-off of T + V and of the ledger's sums (a few ulps of many terms)
GAP_ROUND_OFF = 1e-12  # [m] the round-off of a gap
ACCELERATION = 2.0  # a gap's free acceleration, of |gravity|: gravity, and as much again (a rotating contact point)
PERSIST = 3  # penetration beyond the allowance at this many consecutive points (or samples) is a fault
WORSEN = 10.0  # a violation already reported is reported again when it has grown by this factor

class Invariant(Enum):
    """What a run checks of itself (docs/theory.md §10)."""

    START_INSIDE = "start inside"
    PENETRATION = "penetration"
    ENERGY_GAIN = "energy gain"
    SPEED = "speed beyond the energy"
    LEDGER = "ledger residual"
    SINKING = "speed paid by sinking"
    CREEP = "motion below round-off"


class InvariantViolation(SimulationError):
    """A strict run (strict=True, --strict) broke an invariant: ``trajectory`` holds the samples up to it."""


class Invariants:
    """The hook driver.drive calls (driver.Check): check(where, state, report, recorder) -> the
    violations found there (dicts: invariant, t [s], point, size, allowed, unit, message) or None.
    model: the run's model (its options give the integrator, dt, the contact tolerance); rtol: the
    tolerance of the integrator's smooth motion (the adaptive one's rtol, the event-driven one's
    solver rtol; ignored for time-stepping); strict: raise
    InvariantViolation at the first violation instead of recording it.

    Energies are T + V [J] with the booked position correction taken out (docs/theory.md §2.5,
    §5); in a fixed step without contact the change of T + V is the midpoint rule's smooth error,
    booked by the ledger (§5.3) and taken out as well."""

    def __init__(self, model: Model, *, rtol: float, strict: bool = False):
        opts = model.options
        self.model = model
        self.fixed = opts.integrator is Integrator.TIME_STEPPING
        self.rel = FIXED_RTOL if self.fixed else max(EXACT_FACTOR * rtol, FIXED_RTOL if
                                                     opts.integrator is Integrator.ADAPTIVE else 0.0, ROUND_OFF)
        self.rel_ledger = max(self.rel, ROUND_OFF)  # the ledger's sums: at least their round-off
        self.tol, self.h, self.strict = opts.contact_tolerance, opts.dt, strict
        self.g = math.hypot(*opts.gravity)  # [m/s^2] what a step's smooth motion adds to an approach, per second
        self.E0 = self.E = self.Ehat = self.Emin = 0.0  # [J] start, last point, unexplained energy, its minimum
        self.scale = 0.0  # [J] max(|E_0|, max T): the energy the bounds refer to (as ledger.Ledger.scale)
        self.booked = 0.0  # [J] the positive energy booked so far (correction, smooth error): the speed budget
        self.external = 0.0  # [J] the work done on the system so far (torques, moving statics, §5.5)
        self.residual = 0.0  # [J] the ledger's running residual (samples)
        self.Es = math.nan  # [J] T + V at the last sample (NaN before the first)
        self.v_app = 0.0  # [m/s] the largest approach speed |gamma-| of any contact step or impact so far
        # (a sample, after the step's correction, is held to contact_tolerance + h max |gamma-|)
        self.deep_points = self.deep_samples = 0  # consecutive checks with penetration beyond the allowance
        self.held: dict[int, float] = {}  # pair -> [m] the allowance it has carried since it went inside (points)
        self.last_depth = self.last_allowed = 0.0  # [m] the last penetration beyond the allowance, the allowance
        self.points = 0
        self.reported: dict[str, float] = {}  # invariant -> the size last reported

    @functools.cached_property
    def data(self) -> Data:
        """Its own Data (checking changes nothing the run reads), taken where first needed (most points reuse the
        recorder's energies): one a finished run of the model handed back (spares), else a new one."""
        spare = spares(self.model)
        try:
            return spare.pop() if spare else make_data(self.model)
        except IndexError:  # another thread took the last one
            return make_data(self.model)

    def _hand_back(self) -> None:
        """The run's end: its Data to the next run of the model (spares)."""
        data = self.__dict__.pop("data", None)
        if data is not None:
            spares(self.model).append(data)

    # ---- the hook ---------------------------------------------------------------------------------------------
    def __call__(self, where: str, state: State, rep: Report | None, rec: Recorder) -> list[dict] | None:
        if where == "point":
            return self._point(state, rep, rec)
        if where == "sample":
            return self._sample(state, rec)
        if where == "end":
            return self._end(state, rec)
        return self._start(state, rec)

    def _end(self, state: State, rec: Recorder) -> list[dict] | None:
        """A penetration beyond the allowance at the last samples (or steps) persists to the end of the
        run, however few they were; kinetic energy paid by a load sinking into its support (sinking.first_paid,
        docs/theory.md §2.11, §10) and motion below the energy's round-off (creep.first_creep), from the recorded
        arrays."""
        self._hand_back()
        out = None
        if self.deep_samples or self.deep_points:
            out = self._violate(Invariant.PENETRATION, state.t, self.last_depth, self.last_allowed, "m",
                                f"a pair {self.last_depth:.3g} m inside another at the end of the run (allowed "
                                f"{self.last_allowed:.3g} m)") or None
        arrays = rec.arrays()
        found = first_paid(arrays, ACCELERATION * self.g, self.rel, PERSIST)
        if found is not None:
            t, size, allowed = found
            out = (out or []) + self._violate(
                Invariant.SINKING, t, size, allowed, "J",
                f"loads sunk into their supports released {size:.3g} J at t = {t:.6g} s, beyond the {allowed:.3g} J "
                "the energy leaves: kinetic energy paid by penetration (a smaller step resolves it)")
        found = first_creep(arrays, reach=self.model.reach, tol=self.tol, rel=ROUND_OFF, persist=PERSIST)
        if found is not None:
            t, size, allowed = found
            out = (out or []) + self._violate(
                Invariant.CREEP, t, size, allowed, "m",
                f"the bodies moved up to {size:.3g} m (from t = {t:.6g} s) with a kinetic energy within the round-off "
                "of T + V: motion no energy check can tell from round-off (docs/theory.md §10)")
        return out or None

    def _energies(self, state: State, rec: Recorder) -> tuple[float, float]:
        TV = rec.energies(state)
        if TV is None:  # a point the ledger did not evaluate (a smooth step of the event integrators)
            TV = kinetic(self.model, self.data, state.q, state.u), potential(self.model, self.data, state.q)
        T, V = TV
        if not (math.isfinite(T) and math.isfinite(V)):
            raise SimulationError(f"the state at t = {state.t:.6g} s became non-finite (NaN or inf)")
        return T, V

    def _start(self, state: State, rec: Recorder) -> list[dict] | None:
        T, V = self._energies(state, rec)
        self.E0 = self.E = T + V
        self.Ehat = self.Emin = 0.0
        self.scale = max(abs(self.E0), T)
        if rec.n:
            g = rec.last_sample()[-1]
            if g.size:
                depth = -float(g.min())
                if depth > self.tol:  # a start deeper than the rest rule is meant for (model.check_start's rule)
                    return self._violate(Invariant.START_INSIDE, state.t, depth, self.tol, "m",
                                         f"a pair starts {depth:.3g} m inside another (contact_tolerance "
                                         f"{self.tol:g} m)")
        return None

    def _point(self, state: State, rep: Report, rec: Recorder) -> list[dict] | None:
        self.points += 1
        T, V = self._energies(state, rec)
        E = T + V
        dE = E - self.E
        booked = rep.corr
        ext = 0.0  # [J] the work done on the system in this step (§5.5): T + V rises by it legitimately
        deep = allowed = 0.0
        records = rep.records
        for r in records:
            if type(r) is FixedStep:
                res = r.result
                if res.tau is not None:
                    ext += 0.5 * r.h * float(ordered(res.tau, r.before.u + res.state.u))
                ext += res.obstacle_work
                if res.contacts.m:
                    # a contact's transient at the midpoint, h/2 (|gamma-| + 2 h |g|), and as much again that the
                    # previous step may have left: h (...); a pair inside keeps the largest of these since it went
                    # inside (a closed contact does not deepen, and the correction that would lift it may be
                    # dropped, §2.5: the depth a step left persists; a growing one exceeds it)
                    grow = ACCELERATION * r.h * self.g
                    held, before = {}, self.held
                    for gi, vi, p in zip(res.contacts.g.tolist(), res.gamma_minus.tolist(),
                                         res.contacts.pair.tolist()):
                        if -vi > self.v_app:
                            self.v_app = -vi
                        if -gi > self.tol:
                            a = self.tol + r.h * (max(-vi, 0.0) + grow) + GAP_ROUND_OFF
                            a = held[p] = max(a, before.get(p, 0.0), held.get(p, 0.0))
                            if -gi - a > deep - allowed:
                                deep, allowed = -gi, a
                    self.held = held
                else:
                    self.held = {}  # no pair inside
                    if len(records) == 1:  # a contact-free fixed step: its change beyond ext is the smooth error (§5.3)
                        booked = dE - ext
            elif type(r) is Impact and len(r.gamma_minus):
                self.v_app = max(self.v_app, -min(r.gamma_minus.tolist()))
        self.E = E
        if booked > 0.0:
            self.booked += booked
        self.external += ext
        Ehat = self.Ehat = self.Ehat + (dE - booked - ext)
        if T > self.scale:
            self.scale = T
        bound = self.rel * self.scale
        out = None
        if Ehat < self.Emin:
            self.Emin = Ehat
        elif Ehat - self.Emin > bound:
            out = self._violate(Invariant.ENERGY_GAIN, state.t, Ehat - self.Emin, bound, "J",
                                f"T + V rose {Ehat - self.Emin:.3g} J above its running minimum (booked "
                                f"correction, smooth error and work done on it taken out)")
        budget = self.E0 - V + self.booked + self.external + bound
        if T > budget:
            out = (out or []) + self._violate(Invariant.SPEED, state.t, T - budget, bound, "J",
                                              f"kinetic energy {T:.6g} J exceeds what the energy allows, "
                                              f"{budget:.6g} J")
        if deep > allowed:
            self.deep_points += 1
            self.last_depth, self.last_allowed = deep, allowed
            if self.deep_points >= PERSIST:
                out = (out or []) + self._violate(
                    Invariant.PENETRATION, state.t, deep, allowed, "m",
                    f"a contact {deep:.3g} m deep at the step's midpoint for {self.deep_points} steps (allowed "
                    f"{allowed:.3g} m: contact_tolerance + h (|gamma-| + 2 h |g|), the largest since it went inside)")
        elif self.deep_points:
            self.deep_points = 0
        return out or None

    def _sample(self, state: State, rec: Recorder) -> list[dict] | None:
        T, V, work, corr, smooth, external, g = rec.last_sample()
        Es, self.Es = self.Es, T + V
        if Es != Es:  # NaN: the first sample (the start: checked by _start, which follows it)
            return None
        residual = self.residual = self.residual + ((T + V) - Es - (work + corr + smooth + external))
        bound = self.rel_ledger * self.scale
        out = None
        # the fixed step's residual of contact steps with rotation is first order in h (§5.4), an
        # unattributed loss: only a gain is its fault, beyond -S_k of its contact steps (a step the cap of
        # §2.10 held to E* closes the budget up to -S_k); the event integrators' ledger closes either way
        if (residual - rec.smooth_deficit if self.fixed else abs(residual)) > bound:
            out = self._violate(Invariant.LEDGER, state.t, abs(residual), bound, "J",
                                f"the energy budget leaves {residual:+.3g} J (E_end - E_0 - contact work - "
                                "correction - smooth error - work done on it)")
        if len(g):
            depth = -min(g.tolist())
            allowed = self.tol + self.h * self.v_app + GAP_ROUND_OFF
            if depth > allowed:
                self.deep_samples += 1
                self.last_depth, self.last_allowed = depth, allowed
                if self.deep_samples >= PERSIST:
                    out = (out or []) + self._violate(
                        Invariant.PENETRATION, state.t, depth, allowed, "m",
                        f"a pair {depth:.3g} m inside another for {self.deep_samples} samples (allowed "
                        f"{allowed:.3g} m: contact_tolerance + h max |gamma-|)")
            elif self.deep_samples:
                self.deep_samples = 0
        return out or None

    def samples(self, b: SampleBlock, rec: Recorder) -> bool:
        """The checks of _sample on a step's samples at once (recording.SampleBlock, not yet recorded), the same
        floats in the same order: True when none of them finds anything (their figures carried past the block; the
        driver then records it), False when one might (a residual beyond its bound, a gap beyond its allowance, or
        the run's first sample): nothing changed, the driver then records and checks them one by one, so what is
        flagged, when and how is _sample's (docs/theory.md §10)."""
        Es = self.Es
        if Es != Es:  # the first sample (or a NaN energy): one by one
            return False
        residual, bound, deficit = self.residual, self.rel_ledger * self.scale, rec.smooth_deficit
        work, corr, external = b.work, b.corr, b.external  # the first sample's; the others' are 0.0
        for E, smooth in zip(b.E, b.smooth):
            residual = residual + (E - Es - (work + corr + smooth + external))
            if (residual - deficit if self.fixed else abs(residual)) > bound:
                return False
            work = corr = external = 0.0
            Es = E
        G = b.G
        if G.shape[1]:  # the allowance is the same at each of them: the deepest pair of all decides
            if -float(G.min()) > self.tol + self.h * self.v_app + GAP_ROUND_OFF:
                return False
            self.deep_samples = 0
        self.residual, self.Es = residual, Es
        return True

    def _violate(self, what: Invariant, t: float, size: float, allowed: float, unit: str, message: str) -> list[dict]:
        """[the violation's record], or [] when it was reported already and has not grown by WORSEN."""
        if size <= WORSEN * self.reported.get(what.value, 0.0):
            return []
        self.reported[what.value] = size
        v = {"invariant": what.value, "t": float(t), "point": self.points, "size": float(size),
             "allowed": float(allowed), "unit": unit, "message": message}
        if self.strict:
            raise InvariantViolation(f"invariant violated: {what.value}: {message}")
        return [v]

    # ---- a checkpoint carries the running figures --------------------------------------------------------------
    _CARRIED = ("E0", "E", "Ehat", "Emin", "scale", "booked", "external", "residual", "Es", "v_app", "deep_points",
                "deep_samples", "last_depth", "last_allowed", "points")

    def state_dict(self) -> dict:
        return {**{k: getattr(self, k) for k in self._CARRIED}, "reported": dict(self.reported),
                "held": [[p, a] for p, a in self.held.items()]}

    def load_state_dict(self, d: dict) -> None:
        for k in self._CARRIED:
            setattr(self, k, d[k])
        self.reported = dict(d["reported"])
        self.held = {int(p): float(a) for p, a in d["held"]}


def status(violations: list[dict] | None) -> RunStatus:
    """The status of a run that ran to its end: complete when every invariant held, else flagged."""
    return RunStatus.FLAGGED if violations else RunStatus.COMPLETE


def flagged(meta: dict) -> bool:
    """Whether a trajectory's meta says its run broke an invariant."""
    return meta.get("status") == RunStatus.FLAGGED.value


def one_line(violations: list[dict]) -> str:
    """The violations of a run on one line: each invariant with its largest size, where and when."""
    worst: dict[str, dict] = {}
    for v in violations:
        if v.get("invariant") not in worst or v.get("size", 0.0) >= worst[v["invariant"]].get("size", 0.0):
            worst[v.get("invariant", "?")] = v
    return "; ".join(f"{k} {v.get('size', math.nan):.3g} {v.get('unit', '')} (allowed {v.get('allowed', math.nan):.3g})"
                     f" at t = {v.get('t', math.nan):.6g} s" for k, v in worst.items())
