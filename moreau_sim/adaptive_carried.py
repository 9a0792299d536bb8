"""What an adaptive run carries from one accepted point to the next (adaptive.AdaptiveRun, docs/theory.md §8): a
step end (End), where the run is (Mode), and the whole of it (Carried), which is its checkpoint."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from .event_rules import EventState
from .state import State

BACK_STEPS = 8  # consecutive quiet fixed steps before returning to extrapolated steps

NO_ROWS = np.zeros(0)
NO_ROWS.flags.writeable = False  # an End's multipliers and margins without C (read-only, shared)


class End:
    """A step end: (t, q, u), the accelerations a, the multipliers of C, and of the watched
    features (watch + low) the gaps g, rates gamma and second derivatives gdd = W'a + drift."""

    __slots__ = ("t", "q", "u", "a", "lam", "g", "gamma", "gdd", "margin", "near")

    def __init__(self, t, q, u, a, lam, g, gamma, gdd, margin, near):
        self.t, self.q, self.u, self.a, self.lam, self.g, self.gamma, self.gdd = t, q, u, a, lam, g, gamma, gdd
        self.margin = margin  # C's distances to the ends of their regions [m] (docs/theory.md §7.1)
        self.near = near  # the watched box features whose pair's bounding spheres overlap


class Mode(Enum):
    """Where an adaptive run is: at an event (the decisions are next), in a phase, in fixed steps."""

    EVENT = "event"
    PHASE = "phase"
    FIXED = "fixed"


@dataclass(eq=False)
class Carried:
    """What the adaptive integrator carries from one accepted point to the next (its checkpoint,
    passed to the event rules): the state there; t [s] (the step under way); mode; H [s] (the
    next extrapolated step); the event rules' EventState; the phase's sets (C persistent, shadow
    its duplicate rows, watch by their gaps, low within G_RES by their rise and return) and its
    step end e0 (not saved: a function of the state and the sets); released (at the current
    event: not re-admitted there); the fixed-step bookkeeping (t_back: the last return, back_steps
    quiet steps to return, quiet ones in a row, previous_fresh: the next is a stretch's first,
    burst: the event times within the last dt, fallbacks); counters."""

    state: State
    t: float
    mode: Mode = Mode.EVENT
    H: float = 0.0
    ev: EventState = field(default_factory=EventState)
    C: tuple = ()
    shadow: tuple = ()
    watch: list = field(default_factory=list)
    low: list = field(default_factory=list)
    e0: End | None = None
    released: frozenset = frozenset()
    t_back: float = -np.inf
    back_steps: int = BACK_STEPS
    quiet: int = 0
    previous_fresh: bool = False
    burst: list = field(default_factory=list)
    fallbacks: list = field(default_factory=list)
    stuck: int = 0
    events: int = 0
    accepted: int = 0
    rejected: int = 0
    fixed: int = 0
    landings: int = 0

    def to_json(self) -> dict:
        s = self.state
        return {"t": s.t, "q": s.q.tolist(), "u": s.u.tolist(), "t_now": self.t, "rules": self.ev.to_json(),
                "mode": self.mode.value, "H": self.H, "t_back": None if self.t_back == -np.inf else self.t_back,
                "stuck": self.stuck, "released": sorted(self.released), "burst": self.burst,
                "back_steps": self.back_steps, "fallbacks": self.fallbacks, "previous_fresh": self.previous_fresh,
                "quiet": self.quiet, "counts": [self.events, self.accepted, self.rejected, self.fixed, self.landings],
                "C": list(self.C), "shadow": list(self.shadow), "low": list(self.low), "watch": list(self.watch)}

    @classmethod
    def from_json(cls, d: dict) -> "Carried":
        events, accepted, rejected, fixed, landings = d["counts"]
        return cls(State(float(d["t"]), np.array(d["q"], float), np.array(d["u"], float)), float(d["t_now"]),
                   Mode(d["mode"]), float(d["H"]), EventState.from_json(d["rules"]), tuple(d["C"]),
                   tuple(d["shadow"]), list(d["watch"]), list(d["low"]), None, frozenset(d["released"]),
                   -np.inf if d["t_back"] is None else float(d["t_back"]), int(d["back_steps"]), int(d["quiet"]),
                   bool(d["previous_fresh"]), list(d["burst"]), list(d["fallbacks"]), int(d["stuck"]), events,
                   accepted, rejected, fixed, landings)
