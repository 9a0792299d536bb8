"""The midpoint Moreau step (impact-law.md §2), nothing else.

    q_m     = q_k (+) h/2 u_k                 (pinocchio.integrate: Lie group)
    H       = {i : g_i(q_m) <= tol},  W = [w_i], M = M(q_m), f = -h(q_m, u_k)
    u_free  = u_k + h M^-1 f
    v_free  = (u_free + e u_k) / (1 + e)
    v       = argmin_{W' v >= 0} 1/2 (v - v_free)' M (v - v_free)     (law.project, piqp)
    u_{k+1} = (1 + e) v - e u_k,    P = (1 + e) lam
    q_{k+1} = q_m (+) h/2 u_{k+1}
A closed contact that separates at the start of the step (gamma_i^k > 0) takes e_i = 1 under
the default rule Separating.ELASTIC (scene.py): the QP bound becomes
w_i' v >= (e - 1) gamma_i^k / (1 + e), and the step's contact work is never positive.
With no closed contact u_{k+1} = u_free exactly (computed by ABA, no QP).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from .contacts import NO_CONTACTS, Contacts, contact_rows, detect, distinct
from .law import outcome, project
from .model import Data, Model
from .qp import QPResult
from .scene import QPForm, Separating
from .state import State

_EMPTY = np.zeros(0)


@dataclass(frozen=True, slots=True)
class StepResult:
    """One step: the new state; the closed contacts H at q_m; percussions P [N s] (m,);
    gamma_minus = W' u_k and gamma_plus = W' u_{k+1} [m/s]; contact_work
    W_c = sum_i P_i (gamma_plus_i + gamma_minus_i) / 2 [J] (impact-law.md §2, energy ledger);
    qp: the QP result (None when no contact was closed)."""

    state: State
    contacts: Contacts
    P: np.ndarray
    gamma_minus: np.ndarray
    gamma_plus: np.ndarray
    contact_work: float
    qp: QPResult | None


def step(model: Model, data: Data, state: State, h: float, e: float, *, t_next: float | None = None,
         form: QPForm | None = None, eps: float | None = None) -> StepResult:
    """Advance `state` by one midpoint Moreau step of size h [s] with restitution e.

    t_next: the new time (default state.t + h; the loop passes k h to avoid round-off drift).
    form / eps: the impact QP's form and tolerance (default: the scene's options).
    A failed QP is returned in the result (qp.ok False); :func:`simulate` turns it into an error."""
    pm, pd = model.pin, data.pin
    q, u = state.q, state.u
    t1 = state.t + h if t_next is None else t_next
    q_m = pin.integrate(pm, q, 0.5 * h * u)
    contacts = detect(model, data, q_m)
    if contacts.m == 0:
        u_next = u + h * pin.aba(pm, pd, q_m, u, np.zeros(pm.nv))
        q_next = pin.integrate(pm, q_m, 0.5 * h * u_next)
        return StepResult(State(t1, q_next, u_next), NO_CONTACTS, _EMPTY, _EMPTY, _EMPTY, 0.0, None)
    opts = model.scene.options
    M = pin.crba(pm, pd, q_m, pin.Convention.WORLD)  # also fills data.J (WORLD) for the rows
    contacts, W = distinct(contacts, contact_rows(model, data, contacts))
    Minv = pin.computeMinverse(pm, pd, q_m)
    u_free = u - h * (Minv @ pin.nonLinearEffects(pm, pd, q_m, u))
    v_free = (u_free + e * u) / (1.0 + e)
    gamma_minus = W.T @ u
    b = None
    if opts.separating is Separating.ELASTIC and e < 1.0 and gamma_minus.max() > 0.0:
        # e_i = 1 where gamma_i^k > 0: w_i'(u_{k+1} + e_i u_k) >= 0 <=> w_i'v >= (e - e_i) gamma_i^k / (1+e)
        b = np.where(gamma_minus > 0.0, (e - 1.0) * gamma_minus / (1.0 + e), 0.0)
    res = project(M, W, v_free, b=b, Minv=Minv, form=form or opts.qp_form, eps=eps or opts.qp_tolerance)
    u_next = outcome(res.v, u, e)
    P = (1.0 + e) * res.lam
    gamma_plus = W.T @ u_next
    work = float(P @ (gamma_plus + gamma_minus)) * 0.5
    q_next = pin.integrate(pm, q_m, 0.5 * h * u_next)
    return StepResult(State(t1, q_next, u_next), contacts, P, gamma_minus, gamma_plus, work, res)
