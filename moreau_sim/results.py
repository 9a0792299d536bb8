"""What a midpoint Moreau step returns (StepResult), and the constants its two implementations share: the
Python step (stepper.py) and the compiled one (src/step.cpp, which receives them through
compiled.CONSTANTS). The step: docs/theory.md §2; the ledger's terms it carries: §5."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .contacts import Contacts
from .qp import QPResult
from .state import State

RESTING = 1e-9  # bodies end a step at rest when their speeds are below this fraction of one step's (stepper._resting)
HOLD = 0.5  # a lift at rest along the normals leaves each closed contact of its bodies within HOLD contact tolerances
MIDPOINT_ITERATIONS = 8  # fixed-point sweeps of Bias.MIDPOINT (contraction factor ~ h |omega|; §2.4)
MIDPOINT_TOLERANCE = 1e-15  # the sweeps stop when u_free moves by at most this times 1 + max|u_k|


@dataclass(frozen=True, slots=True)
class StepResult:
    """One step: the new state; the closed contacts H at q_m; percussions P [N s] (m,);
    gamma_minus = W' u_k and gamma_plus = W' u_{k+1} [m/s]; contact_work
    W_c = sum_i P_i (gamma_plus_i + gamma_minus_i) / 2 [J] (docs/theory.md §5);
    qp: the QP result (None when no contact was closed; its M, W, v0 = v_free, b: the projection's problem);
    branch: at a corner impact with several admissible outcomes (docs/theory.md §3), (solution, chosen
    index, u_plus of each candidate), else None. At a corner, `contacts` lists the smooth contacts and then
    one entry per face of the chosen piece(s) (kind CORNER, feature = face), aligned with P.
    correction_energy: the change of T + V made by the position correction [J] (0 without; never more than
    the step dissipated), so that E_{k+1} - E_k = W_c + correction_energy where the smooth motion is exact.
    u_free: the velocity the smooth forces alone give, u_k + h M(q_m)^-1 f [velocity] (the ledger's smooth
    motion, §5.3; u_{k+1} itself on a step without contact).
    tau: the joint torques of the step [N or N m] (actuation.py, evaluated at t_m, q_m, u_k; None: none);
    obstacle_work: the work of prescribed motion, -sum_i P_i dg_i/dt [J] of moving statics and driven joints plus
    the driven joints' work W_p (§2.9, §2.13, §5.5); drive_work_free: W_p of the step without its contacts [J].
    u_law: the law's u_{k+1} where the position correction paid a lift with the velocities (§2.5), which the
    ledger measures the impact on (§5.2); None where state.u is the law's (or the cap's, §2.10)."""

    state: State
    contacts: Contacts
    P: np.ndarray
    gamma_minus: np.ndarray
    gamma_plus: np.ndarray
    contact_work: float
    qp: QPResult | None
    branch: tuple | None = None
    correction_energy: float = 0.0
    u_free: np.ndarray | None = None
    tau: np.ndarray | None = None
    obstacle_work: float = 0.0
    u_law: np.ndarray | None = None
    drive_work_free: float = 0.0
