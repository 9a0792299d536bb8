"""The step protocol every integrator follows (docs/theory.md §9), modelled on scipy's OdeSolver:
``step()`` advances to the next accepted point (a fixed step, an event, a phase's step) and
returns a :class:`Report` of what happened there; the driver (driver.py) does everything else.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Protocol

import numpy as np

from .contacts import Contacts
from .state import State


class Status(Enum):
    """Where an integrator is after a step (scipy's OdeSolver.status as an enum)."""

    RUNNING = "running"
    FINISHED = "finished"
    FAILED = "failed"


class RunStatus(Enum):
    """How a run ended, meta["status"] of its trajectory (docs/output.md): complete when it ran to
    its end and every invariant held (invariants.py), flagged when it ran to its end but broke one
    (listed in meta["invariants"]), failed when it stopped ("failed: " and the reason)."""

    COMPLETE = "complete"
    FLAGGED = "flagged"
    FAILED = "failed"


@dataclass(slots=True)
class FixedStep:
    """A midpoint Moreau step to record (docs/theory.md §2, §5): its percussions, its ledger
    (Recorder.account_step) and its branch. index: the log's step number (None: the index of the
    next sample); t [s]: the step's midpoint; before: the state it started from; result: the
    stepper's StepResult; h [s], e; fresh: the first step of a stretch (no previous contacts)."""

    index: int | None
    t: float
    before: State
    result: object
    h: float
    e: float
    fresh: bool = False


@dataclass(slots=True)
class Impact:
    """An impact located in time (docs/theory.md §1, §3, §7) to record: at t [s] and q, u- -> u+;
    M = M(q), v the law's projection, restitution e; per contact P [N s], gamma- and gamma+ [m/s];
    branch: (solution, chosen, u_plus of each candidate) at a corner with several outcomes, or None."""

    t: float
    q: np.ndarray
    u_minus: np.ndarray
    u_plus: np.ndarray
    M: np.ndarray
    v: np.ndarray
    e: float
    contacts: Contacts
    P: np.ndarray
    gamma_minus: np.ndarray
    gamma_plus: np.ndarray
    branch: tuple | None = None


@dataclass(slots=True)
class Segment:
    """Samples of the output grid that fall in a step: the grid instants t < until (<= if closed)
    are sampled at dense(t) -> (q, u), with n_contacts closed contacts; batch (where not None) gives all of
    them in one call, batch(instants) -> (q rows, u rows, kinetic, potential, pair gaps) as dense(t) and the
    recorder's sample would (compiled_events.sampler)."""

    dense: Callable[[float], tuple[np.ndarray, np.ndarray]]
    until: float
    closed: bool
    n_contacts: int
    batch: Callable | None = None


@dataclass(slots=True)
class Report:
    """What one step() did. status, message (FAILED: naming the step); t [s] and state: the accepted
    point; records: FixedStep / Impact to record, in order, before the samples; work, corr [J]: the
    contact work and correction energy since the previous accepted point; an integrator with an
    output grid gives its samples as segments (dense output), one without marks an accepted point
    that is a sample with due (n_contacts: its closed contacts)."""

    status: Status
    t: float
    state: State | None = None
    records: tuple = ()
    work: float = 0.0
    corr: float = 0.0
    segments: tuple[Segment, ...] = ()
    due: bool = False
    n_contacts: int = 0
    message: str = ""


class Integrator(Protocol):
    """An integrator the driver runs. unit: what position() counts in error messages ("step",
    "phase"); state: the current accepted state (its own arrays: the ledger recognizes a state it
    has seen by identity); t0, t_end [s]: the run's span; grid: True when it samples an output
    grid through Report.segments (else Report.due)."""

    unit: str
    state: State
    t0: float
    t_end: float
    grid: bool

    def step(self, t_sample: float = np.inf) -> Report:
        """Advance to the next accepted point; raise SimulationError (named by the driver) or report
        FAILED. t_sample [s]: the next output instant not yet sampled (a fixed step may land on it)."""

    def position(self) -> tuple[int, float]:
        """(the number of the step or phase under way, its time [s])."""

    def progress(self) -> tuple[float, float, str]:
        """(done, total, unit) for the progress bar."""

    def state_dict(self) -> dict:
        """The integrator's state at its current accepted point, as JSON (plain lists and floats)."""

    def load_state_dict(self, d: dict) -> None:
        """Continue from state_dict()'s output, bit for bit."""

    def meta(self, status: str, wall: float, points: int) -> dict:
        """The trajectory's meta (recording.run_metadata) with `status` after `wall` [s] and `points`
        accepted points recorded (an error while recording one names the step that produced it)."""
