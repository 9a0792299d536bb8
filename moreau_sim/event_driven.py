"""The event-driven integrator (docs/theory.md §7): smooth phases integrated to tolerance by
scipy's solve_ivp (a Lie-group chart for a free body's quaternion), impacts at located instants;
the decisions at an event are event_rules.resolve, the loop driver.drive (§9).

    traj = simulate_event_driven(model)            # same Trajectory arrays as ms.simulate
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin

from . import compiled_events
from .actuation import refuse_driven
from .drive import refuse as refuse_drives
from .data import Data
from .errors import SimulationError
from .checkpoint import Checkpoint
from .driver import Check, drive, run_data
from .event_rules import (ACC_TOL, CYLINDER_KINDS, DT_ZENO, G_REGION, G_RES, G_ZENO, IDLE_TOL, LAM_EPS, V_TOL,  # noqa: F401
                          V_ZENO, EventState, UnsupportedModel, dynamics, features, make_rules, phase_sets, resolve,
                          sample_grid, thin_limit)
from .model import Model, initial_state
from .protocol import Report, Segment, Status
from .sums import ordered
from .recording import run_metadata
from .state import State
from .trajectory import Trajectory

CHART_MAX = 1.0  # [rad or m] re-centre the Lie-group chart when |delta|_inf exceeds this
G_DIP = 1e-6  # [m] a free feature starting a phase this close also stops it at its gap's minimum (a dip)


def solve_ivp(fun, t_span, y0, **kwargs):
    """scipy.integrate.solve_ivp, imported on first use: scipy.integrate (with scipy.special and
    scipy.optimize) is ~40 MB of RSS and 0.3 s of import that a time-stepping run never needs
    (the fault tests patch this name)."""
    from scipy.integrate import solve_ivp as ivp

    return ivp(fun, t_span, y0, **kwargs)


@dataclass(eq=False)
class Carried:
    """What the event-driven integrator carries from one accepted point to the next (its checkpoint,
    passed to the event rules): the state there, t [s] (the phase under way), the event rules'
    EventState, the features released there (not re-admitted) and those whose gap jumped open
    there, the events so far and those in a row without time advancing."""

    state: State
    t: float
    ev: EventState = field(default_factory=EventState)
    released: frozenset = frozenset()
    opened: frozenset = frozenset()
    events: int = 0
    stuck: int = 0

    def to_json(self) -> dict:
        s = self.state
        return {"t": s.t, "q": s.q.tolist(), "u": s.u.tolist(), "t_now": self.t, "rules": self.ev.to_json(),
                "released": sorted(self.released), "opened": sorted(self.opened),
                "stuck": self.stuck, "events": self.events}

    @classmethod
    def from_json(cls, d: dict) -> "Carried":
        return cls(State(float(d["t"]), np.array(d["q"], float), np.array(d["u"], float)), float(d["t_now"]),
                   EventState.from_json(d["rules"]), frozenset(d["released"]), frozenset(d["opened"]),
                   int(d["events"]), int(d["stuck"]))


class EventDrivenRun:
    """The event-driven integrator behind the step protocol (protocol.py; the public API is
    simulate_event_driven): a step is the decisions at an event and the smooth phase after it."""

    unit = "phase"  # what position() counts, in error messages
    grid = True

    def __init__(self, model: Model, data: Data, e: float, rtol: float, atol: float, method: str,
                 max_step: float, max_events: int, *, state: State | None = None, t_end: float = np.inf):
        self.rules = make_rules(model, data, e)  # what the event rules read of the model (event_rules.py)
        self.model, self.data, self.e, self.feats, self.gap_tol = model, data, e, self.rules.feats, self.rules.gap_tol
        self.pm, self.pd, self.nv = model.pin, data.pin, model.nv
        self.lie = any(model.pin.joints[j].nq != model.pin.joints[j].nv for j in range(1, model.pin.njoints))
        self.rtol, self.atol, self.method, self.max_step, self.max_events = rtol, atol, method, max_step, max_events
        self.figures = compiled_events.figures(model, data)  # a sample's figures compiled (None: Recorder.sample's)
        state = state or initial_state(model, data)
        self.s = Carried(State(float(state.t), np.array(state.q, float), np.array(state.u, float)), float(state.t))
        self.t0, self.t_end = self.s.state.t, float(t_end)

    @property
    def state(self) -> State:
        """The current accepted state (protocol.Integrator.state)."""
        return self.s.state

    # ---- dynamics --------------------------------------------------------------------------
    def q_of(self, qb: np.ndarray, delta: np.ndarray) -> np.ndarray:
        return pin.integrate(self.pm, qb, delta) if self.lie else qb + delta

    # ---- the run ---------------------------------------------------------------------------
    def _phase_events(self, qb, C, free, low, near=()):
        """Terminal event functions of one phase and a tag per function (module doc): gaps of the
        free features, rise and return of those in `low` (within G_RES at the start), the minima
        of those in `near` (within G_DIP), the multipliers of C, and the chart's extent."""
        cache: dict = {}
        watch = [i for i in free if i not in low]
        rated = list(low) + [i for i in watch if i in near]  # the features whose rates gamma are watched too
        col = {i: k for k, i in enumerate(rated)}

        def evaluate(y):
            key = y.tobytes()
            if key not in cache:
                cache.clear()
                q, u = self.q_of(qb, y[:self.nv]), y[self.nv:]
                _, lam, fc = dynamics(self.rules, self.s.ev, q, u, C)
                margin = fc.margin if C else np.zeros(0)  # C's distances to their regions' ends
                gc = fc.g if C else None  # C's gaps
                fs = features(self.rules, self.s.ev, q, u, watch, rows=False) if watch else None
                fr = features(self.rules, self.s.ev, q, u, rated) if rated else None  # with rows: gamma
                cache[key] = (fs, lam, margin, fr, gc)
            return cache[key]

        def dip(fr, k):
            return fr.gamma[k] + V_TOL if fr.g[k] < G_DIP else 1.0

        fns, tags = [], []
        for k, i in enumerate(watch):
            # an exact 0.0 counts as open: scipy takes (0, 0) for a downward crossing
            fns.append((lambda t, y, k=k: evaluate(y)[0].g[k] or 1e-300, -1.0))  # gap closing: an impact
            tags.append(("gap", i))
            if i in near:  # its approach turning back while within G_DIP: a minimum (a dip below 0 and back)
                fns.append((lambda t, y, k=col[i]: dip(evaluate(y)[3], k), 1.0))
                tags.append(("dip", i))
        for i in low:
            fns.append((lambda t, y, k=col[i]: evaluate(y)[3].g[k] - G_RES, 1.0))  # risen: watch its gap
            tags.append(("rise", i))
            fns.append((lambda t, y, k=col[i]: evaluate(y)[3].gamma[k] + 2.0 * V_TOL, -1.0))  # coming back
            tags.append(("return", i))
        for k, i in enumerate(C):
            fns.append((lambda t, y, k=k: evaluate(y)[1][k] + LAM_EPS, -1.0))  # contact force vanishing
            tags.append(("release", i))
            if self.feats[i].box is not None:  # a box feature passing the end of its region by G_REGION
                # (§7.1): a corner resting on an edge (margin 0 to rounding and drift) stays
                fns.append((lambda t, y, k=k: evaluate(y)[2][k] + G_REGION, -1.0))
                tags.append(("release", i))
            if self.feats[i].kind in CYLINDER_KINDS:  # its gap opening: where it stops being the distance (a
                # cylinder's side leaving the segment's end: the stand-in jumps above contact_tolerance) its
                # constraint would hold a phantom contact
                fns.append((lambda t, y, k=k: evaluate(y)[4][k] - self.gap_tol, 1.0))
                tags.append(("open", i))
        if self.lie:
            fns.append((lambda t, y: np.abs(y[:self.nv]).max() - CHART_MAX, 1.0))  # re-centre the chart
            tags.append(("chart", -1))
        for f, direction in fns:
            f.terminal, f.direction = True, direction
        return [f for f, _ in fns], tags

    def _rhs(self, qb, C):
        nv = self.nv

        def f(t, y):
            delta, u = y[:nv], y[nv:]
            q = self.q_of(qb, delta)
            a = dynamics(self.rules, self.s.ev, q, u, C)[0]
            if self.lie:
                dq = np.linalg.solve(pin.dIntegrate(self.pm, qb, delta, pin.ArgumentPosition.ARG1), u)
            else:
                dq = u
            return np.concatenate((dq, a))
        return f

    def _max_step(self, q, u, C, low) -> float:
        """max_step, or less where a body could pass through a thin obstacle within one ODE step
        (event_rules.thin_limit), or while a feature that just bounced rises: its rise to G_RES
        and its fall back must not fit in one ODE step (a double crossing is invisible), so steps
        stay below half its time to apex gamma / |a_n|."""
        limit = min(self.max_step, thin_limit(self.rules, u, dynamics(self.rules, self.s.ev, q, u, C)[0]))
        if not low:
            return limit
        fs = features(self.rules, self.s.ev, q, u, low)
        a_n = ordered(fs.W.T, dynamics(self.rules, self.s.ev, q, u, C)[0]) + fs.drift
        up = (fs.gamma > V_TOL) & (a_n < 0)
        return float(min(limit, *(0.5 * fs.gamma[up] / -a_n[up]))) if up.any() else limit

    def _crossing(self, sol, qb, t0: float, t1: float, watch: list) -> float | None:
        """The earliest instant in (t0, t1) where a gap of `watch` (open at t0) crossed 0, if one is
        below -G_RES at t1 (its crossing and return fell within one ODE step: the gap events,
        compared at step ends, missed it; the dip event stopped the phase at its minimum)."""
        nv = self.nv

        def gaps(tau):
            y = sol.sol(tau)
            return features(self.rules, self.s.ev, self.q_of(qb, y[:nv]), y[nv:], watch, rows=False).g

        g1 = gaps(t1)
        if not (g1 < -G_RES).any():
            return None
        from scipy.optimize import brentq

        eps = 4 * np.finfo(float).eps
        # disp=False: the estimate, even where a jumping stand-in keeps brentq from its tolerance
        return min(brentq(lambda tau, k=k: gaps(tau)[k] or 1e-300, t0, t1, xtol=eps, rtol=eps, maxiter=200,
                          disp=False) for k in np.flatnonzero(g1 < -G_RES))

    def step(self, t_sample: float = np.inf) -> Report:
        """The decisions at the current point (event_rules.resolve: impact, persistent set),
        then the smooth phase to its first event or t_end (module doc)."""
        nv = self.nv
        t, q, u = self.s.state.t, self.s.state.q, self.s.state.u
        self.s.t = t
        res = resolve(self.rules, self.s.ev, t, q, u, self.s.released)
        u, C, shadow, records, work = res.u, res.C, res.shadow, res.records, res.work
        # (a feature whose gap just jumped open is watched by its gap: it is at the jump, not near 0)
        free, g0, low = phase_sets(self.rules, self.s.ev, q, u, C, shadow, self.s.opened, g=res.g)
        near = {i for i, g in zip(free, g0) if 0.5 * G_RES <= g < G_DIP}
        qb = q.copy()
        events, tags = self._phase_events(qb, C, free, low, near)
        # in the phase's own time tau = t - t_phase (docs/theory.md §7): an event near the phase's start is
        # located to ulp(tau), not ulp(t) (at t >= 64 s one ulp of t moves a ball at 4 m/s by 6e-14 m > G_RES/2)
        sol = solve_ivp(self._rhs(qb, C), (0.0, self.t_end - t), np.concatenate((np.zeros(nv), u)),
                        method=self.method, dense_output=True, events=events or None, rtol=self.rtol,
                        atol=self.atol, max_step=self._max_step(q, u, C, low))
        if sol.status < 0:
            raise SimulationError(f"solve_ivp failed: {sol.message}")
        tau_stop, end = float(sol.t[-1]), sol.status == 0
        y_stop = sol.y[:, -1]
        if not end:  # a gap that dipped below 0 within one ODE step: stop where it crossed
            tau_cross = self._crossing(sol, qb, 0.0, tau_stop, [i for i in free if i not in low])
            if tau_cross is not None:
                tau_stop, y_stop = tau_cross, sol.sol(tau_cross)
        t_stop = self.t_end if end else t + tau_stop

        def dense(tg: float):
            y = sol.sol(min(tg - t, tau_stop))
            return self.q_of(qb, y[:nv]), y[nv:]
        batch = None
        if self.figures is not None:  # the samples' states one by one, what they record at once (the same floats)
            def batch(tgs):
                Q, U = zip(*(dense(tg) for tg in tgs.tolist()))
                Q, U = np.array(Q), np.array(U)
                return (Q, U, *self.figures(Q, U))
        samples = (Segment(dense, t_stop, end, len(C), batch),)
        if end:
            self.s.state = State(t_stop, self.q_of(qb, y_stop[:nv]), y_stop[nv:].copy())
            return Report(Status.FINISHED, t_stop, self.s.state, records, work, segments=samples)
        self.s.t = t_stop
        self.s.events += 1
        if self.s.events > self.max_events:
            raise SimulationError(f"more than {self.max_events} events")
        self.s.stuck = self.s.stuck + 1 if tau_stop < 1e-13 else 0
        if self.s.stuck > 100:
            raise SimulationError("100 events without time advancing")
        self.s.state = State(t_stop, self.q_of(qb, y_stop[:nv]), y_stop[nv:].copy())
        stopped = [(kind, i) for (kind, i), te in zip(tags, sol.t_events)
                   if len(te) and abs(te[-1] - tau_stop) <= 1e-12]
        self.s.released = frozenset(i for kind, i in stopped if kind in ("release", "open"))
        self.s.opened = frozenset(i for kind, i in stopped if kind == "open")
        return Report(Status.RUNNING, t_stop, self.s.state, records, work, segments=samples)

    def position(self) -> tuple[int, float]:
        return self.s.events + 1, self.s.t

    def progress(self) -> tuple[float, float, str]:
        return self.s.state.t - self.t0, self.t_end - self.t0, "s"

    def state_dict(self) -> dict:
        return self.s.to_json()

    def load_state_dict(self, d: dict) -> None:
        self.s = Carried.from_json(d)

    def meta(self, status: str, wall: float, points: int) -> dict:
        reference = {"method": self.method, "rtol": self.rtol, "atol": self.atol, "max_step": self.max_step,
                     "gap_tol": self.gap_tol, "v_tol": V_TOL, "g_res": G_RES, "g_zeno": G_ZENO, "v_zeno": V_ZENO,
                     "dt_zeno": DT_ZENO, "lam_eps": LAM_EPS, "idle_tol": IDLE_TOL, "lie_group_chart": self.lie}
        run = {"steps": None, "events": self.s.events, "impacts": self.s.ev.impacts, "nfev": self.s.ev.nfev,
               "nfev_constrained": self.s.ev.constrained,
               "wall_seconds": wall}
        return run_metadata(self.model, status, run, integrator="event-driven", reference=reference,
                            zeno=self.s.ev.zeno)


def simulate_event_driven(model: Model, *, state: State | None = None, t_end: float | None = None,
                          rtol: float = 1e-12, atol: float = 1e-12, method: str = "DOP853",
                          t_eval=None, max_step: float = 1e-2, max_events: int = 100_000,
                          data: Data | None = None, progress: bool = False, checkpoint: Checkpoint | None = None,
                          spill: str | Path | None = None, check: Check | None = None) -> Trajectory:
    """Integrate `model` event by event (module doc) from `state` (default: the scene's initial
    state) to `t_end` [s] (default: state.t + the scene's duration), restitution = the scene's e.

    rtol, atol: solve_ivp tolerances of the smooth phases; method: "DOP853" (default) or another
    explicit solve_ivp method; max_step [s]: bound on an ODE step (no gap dips below 0 and back
    unseen within one step); t_eval: sample instants [s] in [t0, t_end] (default: every
    save_every * dt of the scene's options, the instants ms.simulate records);
    max_events: give up beyond this many events; progress, checkpoint, spill, check: as
    ms.simulate (driver.drive).

    Returns a :class:`Trajectory` with ms.simulate's arrays: samples at t_eval (a sample at an
    impact instant is the post-impact state, one at t0 the initial state); one log row per
    contact percussion with log_t the exact impact time, log_step the index of the next
    sample, log_impact True; contact_work = -(energy lost in impacts) since the previous
    sample; a branch row per corner impact with several admissible outcomes. meta:
    "integrator": "event-driven", "status", "zeno" (the
    accumulation points declared: t, t_accumulation, speed, pairs), "reference" (tolerances and
    thresholds), "run" (events, impacts, nfev, wall_seconds). Raises UnsupportedModel for a pair
    without an analytic gap, SimulationError (with .trajectory up to the failure) otherwise."""
    refuse_driven(model, "event-driven")
    refuse_drives(model, "event-driven")
    with run_data(model, data) as data:
        state = state or initial_state(model, data)
        t_end, t_grid = sample_grid(model, state, t_end, t_eval)
        integ = EventDrivenRun(model, data, model.options.restitution, rtol, atol, method, max_step, max_events,
                               state=state, t_end=t_end)
        return drive(integ, model, data, grid=t_grid, progress=progress, checkpoint=checkpoint, spill=spill,
                     check=check, capacity=len(t_grid))
