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

from .contacts import CORNER, NO_CONTACTS, Contacts, CornerPieces, contact_rows, corner_pieces, detect, distinct
from .corners import MAX_PIECES, select, stationary_points
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
    qp: the QP result (None when no contact was closed); branch: at a corner impact with
    several admissible outcomes (impact-law.md §3), (solution, chosen index, u_plus of each
    candidate), else None. At a corner, `contacts` lists the smooth contacts and then one entry
    per face of the chosen piece(s) (feature CORNER + face), aligned with P."""

    state: State
    contacts: Contacts
    P: np.ndarray
    gamma_minus: np.ndarray
    gamma_plus: np.ndarray
    contact_work: float
    qp: QPResult | None
    branch: tuple | None = None


def step(model: Model, data: Data, state: State, h: float, e: float, *, t_next: float | None = None,
         form: QPForm | None = None, eps: float | None = None, corner_choice: int | None = None) -> StepResult:
    """Advance `state` by one midpoint Moreau step of size h [s] with restitution e.

    t_next: the new time (default state.t + h; the loop passes k h to avoid round-off drift).
    form / eps: the impact QP's form and tolerance (default: the scene's options).
    corner_choice: at a corner with several admissible outcomes, continue with candidate number
    corner_choice (in the order of corners.stationary_points) instead of the scene's policy.
    A failed QP is returned in the result (qp.ok False); :func:`simulate` turns it into an error."""
    pm, pd = model.pin, data.pin
    q, u = state.q, state.u
    t1 = state.t + h if t_next is None else t_next
    q_m = pin.integrate(pm, q, 0.5 * h * u)
    # a corner struck within the step: the vertex may have crossed one face plane by up to the
    # distance it travels in the step (|u| times the largest lever arm, model.reach)
    contacts = detect(model, data, q_m, corner_margin=h * float(np.abs(u).max(initial=0.0)) * model.reach)
    if contacts.m == 0 and not contacts.corners:
        u_next = u + h * pin.aba(pm, pd, q_m, u, np.zeros(pm.nv))
        q_next = pin.integrate(pm, q_m, 0.5 * h * u_next)
        return StepResult(State(t1, q_next, u_next), NO_CONTACTS, _EMPTY, _EMPTY, _EMPTY, 0.0, None)
    opts = model.scene.options
    M = pin.crba(pm, pd, q_m, pin.Convention.WORLD)  # also fills data.J (WORLD) for the rows
    contacts, W = distinct(contacts, contact_rows(model, data, contacts))
    pieces = None
    if contacts.corners:
        contacts, W, pieces = corner_pieces(model, data, contacts, W)
    Minv = pin.computeMinverse(pm, pd, q_m)
    u_free = u - h * (Minv @ pin.nonLinearEffects(pm, pd, q_m, u))
    v_free = (u_free + e * u) / (1.0 + e)
    branch = None
    if pieces is not None:  # the set-valued law at a corner (impact-law.md §3)
        res, contacts, W, branch = _corner_law(M, W, v_free, u, e, contacts, pieces, opts, corner_choice)
        gamma_minus = W.T @ u
    else:
        gamma_minus = W.T @ u
        b = None
        if opts.separating is Separating.ELASTIC and e < 1.0 and gamma_minus.max(initial=0.0) > 0.0:
            # e_i = 1 where gamma_i^k > 0: w_i'(u_{k+1} + e_i u_k) >= 0 <=> w_i'v >= (e - e_i) gamma_i^k / (1+e)
            b = np.where(gamma_minus > 0.0, (e - 1.0) * gamma_minus / (1.0 + e), 0.0)
        res = project(M, W, v_free, b=b, Minv=Minv, form=form or opts.qp_form, eps=eps or opts.qp_tolerance)
    u_next = outcome(res.v, u, e)
    P = (1.0 + e) * res.lam
    gamma_plus = W.T @ u_next
    work = float(P @ (gamma_plus + gamma_minus)) * 0.5
    q_next = pin.integrate(pm, q_m, 0.5 * h * u_next)
    return StepResult(State(t1, q_next, u_next), contacts, P, gamma_minus, gamma_plus, work, res, branch)


def _corner_law(M, W, v_free, u, e, contacts: Contacts, cp: CornerPieces, opts, choice=None):
    """All stationary points over the union of pieces (corners.stationary_points), the one the
    scene's selection policy picks, and the contacts/rows/multipliers of the chosen piece(s).

    With corners the Separating rule is not applied (the set-valued law takes no bound shift)."""
    if len(cp.pieces) > MAX_PIECES:
        res = QPResult(f"TOO_MANY_CORNER_PIECES ({len(cp.pieces)} > {MAX_PIECES})", False, 0, False, v_free,
                       np.zeros(W.shape[1]))
        return res, contacts, W, None
    sol = stationary_points(M, v_free, list(cp.pieces), W if W.shape[1] else None)
    k = select(sol, opts.corner_selection) if choice is None else min(choice, len(sol.candidates) - 1)
    cand = sol.candidates[k]
    # the chosen candidate's active rows: the faces of its pieces, then the smooth contacts
    faces = [(c, cp.choice[j][c]) for j in cand.pieces for c in range(len(cp.corners))]
    ext = [Contacts(np.array([cp.corners[c].g]), cp.corners[c].point_a[None], cp.corners[c].point_b[None],
                    cp.corners[c].normals[f][None], np.array([cp.corners[c].pair]), np.array([CORNER + f]),
                    np.array([cp.corners[c].joint_a]), np.array([cp.corners[c].joint_b])) for c, f in faces]
    rows = np.array([cp.rows[c][f] for c, f in faces]).reshape(len(faces), -1).T
    lam = np.asarray(cand.multipliers, float)
    W_all = np.concatenate((W, rows), axis=1)
    lam_all = np.concatenate((lam[len(faces):], lam[:len(faces)]))
    fields = Contacts.__slots__[:-1]
    merged = Contacts(*(np.concatenate([getattr(contacts, f)] + [getattr(x, f) for x in ext]) for f in fields))
    res = QPResult("CORNER_LAW", True, sol.qp_solves, False, np.array(cand.v), lam_all,
                   (M, W_all, v_free, np.zeros(W_all.shape[1])))
    branch = None if sol.unique else (sol, k, tuple(outcome(np.asarray(c.v), u, e) for c in sol.candidates))
    return res, merged, W_all, branch
