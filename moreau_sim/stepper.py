"""The midpoint Moreau step (impact-law.md §2), nothing else.

    q_m     = q_k (+) h/2 u_k                 (pinocchio.integrate: Lie group)
    H       = {i : g_i(q_m) <= tol},  W = [w_i], M = M(q_m), f = -h(q_m, u_k)
    u_free  = u_k + h M^-1 f
    v_free  = (u_free + e u_k) / (1 + e)
    v       = argmin_{W' v >= 0} 1/2 (v - v_free)' M (v - v_free)     (law.project, piqp)
    u_{k+1} = (1 + e) v - e u_k,    P = (1 + e) lam
    q_{k+1} = q_m (+) h/2 u_{k+1}
With no closed contact u_{k+1} = u_free exactly (ABA, no QP). The scene's rules (scene.py,
each an option with its measured reason in README/docs) refine the plain step:
  Separating.ELASTIC   e_i = 1 for a closed contact separating at the start of the step;
  SlowImpacts.PLASTIC  e_i = 0 for an impact slower than one step of the smooth forces
                       (both enter the QP as the bound w_i'v >= (e - e_i) gamma_i^k / (1 + e));
  Bias.MIDPOINT        h(q_m, u) at the midpoint velocity (u_k + u_free)/2 (free_velocity);
  PositionCorrection   q_{k+1} projected onto g >= 0 within the step's dissipated energy;
  Tunnelling.SWEPT     contacts also looked for along the motion of a fast body;
and a corner contact (impact-law.md §3) takes the set-valued law (_corner_law).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from . import qp
from .contacts import (CORNER, NO_CONTACTS, Contacts, CornerPieces, contact_rows, corner_pieces, detect, distinct,
                       pair_distances)
from .corners import MAX_PIECES, select, stationary_points
from .energy import kinetic, potential
from .law import outcome, project
from .model import Data, Model
from .qp import QPResult
from .scene import Bias, PositionCorrection, QPForm, Separating, SlowImpacts, Tunnelling
from .state import State
from .tunnelling import swept_detect

_EMPTY = np.zeros(0)


@dataclass(frozen=True, slots=True)
class StepResult:
    """One step: the new state; the closed contacts H at q_m; percussions P [N s] (m,);
    gamma_minus = W' u_k and gamma_plus = W' u_{k+1} [m/s]; contact_work
    W_c = sum_i P_i (gamma_plus_i + gamma_minus_i) / 2 [J] (impact-law.md §2, energy ledger);
    qp: the QP result (None when no contact was closed); branch: at a corner impact with
    several admissible outcomes (impact-law.md §3), (solution, chosen index, u_plus of each
    candidate), else None. At a corner, `contacts` lists the smooth contacts and then one entry
    per face of the chosen piece(s) (feature CORNER + face), aligned with P. correction_energy:
    the change of T + V made by the position correction [J] (0 without; never more than the
    step dissipated), so that E_{k+1} - E_k = W_c + correction_energy where the smooth motion is exact."""

    state: State
    contacts: Contacts
    P: np.ndarray
    gamma_minus: np.ndarray
    gamma_plus: np.ndarray
    contact_work: float
    qp: QPResult | None
    branch: tuple | None = None
    correction_energy: float = 0.0


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
    # how far a vertex can move in the step (|u| times the largest lever arm): a corner struck within
    # the step may have crossed one face plane by up to this; a thinner pair may be passed through
    travel = h * float(np.abs(u).max(initial=0.0)) * model.reach
    contacts = detect(model, data, q_m, corner_margin=travel)
    opts = model.scene.options
    if opts.tunnelling is Tunnelling.SWEPT and travel > model.thinnest_pair:
        contacts = swept_detect(model, data, q, u, h, q_m, contacts)  # a thin obstacle crossed in the step
    if contacts.m == 0 and not contacts.corners:
        u_next = free_velocity(model, data, q_m, u, h, opts.bias)
        q_next = pin.integrate(pm, q_m, 0.5 * h * u_next)
        return StepResult(State(t1, q_next, u_next), NO_CONTACTS, _EMPTY, _EMPTY, _EMPTY, 0.0, None)
    M = pin.crba(pm, pd, q_m, pin.Convention.WORLD)  # also fills data.J (WORLD) for the rows
    contacts, W = distinct(contacts, contact_rows(model, data, contacts))
    pieces = None
    if contacts.corners:
        contacts, W, pieces = corner_pieces(model, data, contacts, W)
    Minv = pin.computeMinverse(pm, pd, q_m)
    u_free = free_velocity(model, data, q_m, u, h, opts.bias)
    v_free = (u_free + e * u) / (1.0 + e)
    branch = None
    if pieces is not None:  # the set-valued law at a corner (impact-law.md §3)
        res, contacts, W, branch = _corner_law(M, W, v_free, u, e, contacts, pieces, opts, corner_choice)
        gamma_minus = W.T @ u
    else:
        gamma_minus = W.T @ u
        b = _bound_shift(W, u, u_free, gamma_minus, e, opts)
        res = project(M, W, v_free, b=b, Minv=Minv, form=form or opts.qp_form, eps=eps or opts.qp_tolerance)
    u_next = outcome(res.v, u, e)
    P = (1.0 + e) * res.lam
    gamma_plus = W.T @ u_next
    work = float(P @ (gamma_plus + gamma_minus)) * 0.5
    q_next = pin.integrate(pm, q_m, 0.5 * h * u_next)
    corr = 0.0
    if opts.position_correction is PositionCorrection.PROJECTION:
        q_next, corr = _project_positions(model, data, q, u, q_next, u_next, contacts.g + 0.5 * h * gamma_plus,
                                          M, W, Minv)
    return StepResult(State(t1, q_next, u_next), contacts, P, gamma_minus, gamma_plus, work, res, branch, corr)


def _bound_shift(W, u, u_free, gamma_minus, e, opts):
    """Per-contact restitution e_i where the rules of the scene depart from e, as the QP's bound:
    w_i'(u_{k+1} + e_i u_k) >= 0  <=>  w_i'v >= (e - e_i) gamma_i^k / (1 + e). None if e_i = e for all.
    Separating.ELASTIC: e_i = 1 where gamma_i^k > 0 (closed but separating: no positive work).
    SlowImpacts.PLASTIC: e_i = 0 where 0 < -gamma_i^k <= -w_i'(u_free - u_k) (slower than a step
    of the smooth forces: the bounce is below the step's resolution)."""
    e_i = None
    if opts.separating is Separating.ELASTIC and e < 1.0 and gamma_minus.max(initial=0.0) > 0.0:
        e_i = np.where(gamma_minus > 0.0, 1.0, e)
    if opts.slow_impacts is SlowImpacts.PLASTIC and e > 0.0 and gamma_minus.min(initial=0.0) < 0.0:
        slow = (gamma_minus < 0.0) & (gamma_minus >= W.T @ (u_free - u))
        if slow.any():
            e_i = np.where(slow, 0.0, e if e_i is None else e_i)
    return None if e_i is None else (e - e_i) * gamma_minus / (1.0 + e)


def free_velocity(model: Model, data: Data, q_m: np.ndarray, u: np.ndarray, h: float, bias: Bias) -> np.ndarray:
    """u_free = u_k + h M(q_m)^-1 (-h(q_m, u_bar)) [velocity]: u_bar = u_k (EXPLICIT) or the fixed
    point u_bar = (u_k + u_free)/2 (MIDPOINT; a few ABA calls; exact for models whose bias does not
    depend on u, where it stops after one)."""
    pm, pd = model.pin, data.pin
    zero = np.zeros(pm.nv)
    u_free = u + h * pin.aba(pm, pd, q_m, u, zero)
    if bias is Bias.EXPLICIT or not model.velocity_bias:
        return u_free
    scale = 1e-15 * (1.0 + float(np.abs(u).max()))
    for _ in range(MIDPOINT_ITERATIONS):
        nxt = u + h * pin.aba(pm, pd, q_m, 0.5 * (u + u_free), zero)
        done = float(np.abs(nxt - u_free).max()) <= scale
        u_free = nxt
        if done:
            break
    return u_free


MIDPOINT_ITERATIONS = 8  # fixed-point sweeps of Bias.MIDPOINT (contraction factor ~ h |omega|)


def _project_positions(model, data, q, u, q_next, u_next, g_next, M, W, Minv) -> tuple[np.ndarray, float]:
    """PositionCorrection.PROJECTION: dq = argmin 1/2 dq'M dq s.t. g_i + w_i'dq >= 0 on the closed
    contacts (g_i: gaps at q_{k+1} linearized from q_m), applied as q_{k+1} (+) alpha dq with
    alpha <= 1 the largest step for which T + V at the end does not exceed T + V at the start
    of the step: the correction may give back energy the step dissipated, never more.
    Returns (q, the change of T + V it made [J])."""
    tol = model.scene.options.contact_tolerance
    if not len(g_next) or g_next.min() >= -tol:
        return q_next, 0.0
    E0 = kinetic(model, data, q, u) + potential(model, data, q)
    E1 = kinetic(model, data, q_next, u_next) + potential(model, data, q_next)
    budget = E0 - E1
    if budget <= 0.0:
        return q_next, 0.0
    res = qp.solve(M, W, np.zeros(model.nv), b=-g_next, Minv=Minv)
    if not res.ok:
        return q_next, 0.0
    q_c = pin.integrate(model.pin, q_next, res.v)
    dE = kinetic(model, data, q_c, u_next) + potential(model, data, q_c) - E1
    if dE > budget:
        q_c = pin.integrate(model.pin, q_next, (budget / dE) * res.v)  # E is ~linear in dq here
        dE = kinetic(model, data, q_c, u_next) + potential(model, data, q_c) - E1
        if dE > budget:  # not linear after all: keep the uncorrected step rather than gain energy
            return q_next, 0.0
    # the displacement only knows the closed contacts: it must not push another pair into contact
    # (a column of beads: pushing 2 off 1 pushes 1 into 0). Otherwise the step stays uncorrected.
    before, after = pair_distances(model, data, q_next), pair_distances(model, data, q_c)
    if (after < np.minimum(before, 0.0) - tol).any():
        return q_next, 0.0
    return q_c, dE


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
