"""Glocker's Newtonian impact law with one global restitution e (docs/theory.md §1, §2.7).

    v  = prox_{T_C}(v0) = argmin_{W' v >= b} 1/2 (v - v0)' M (v - v0)     (project)
    u+ = (1 + e) v - e u-                                                 (outcome)
    P  = (1 + e) lam                                                      (percussion)

For a single impact v0 = u- and b = 0; in the midpoint step v0 = v_free, and b carries the
per-contact restitution rules (restitution_bounds). The set-valued law at re-entrant corners
(corners.py) uses the same outcome and percussion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import qp
from .sums import ordered
from .options import QPForm, Separating, SlowImpacts, check_restitution

# The round-off an energy identity of the step holds to: a step's T + V is "not above" a level E* when
# E <= E* + ENERGY_ROUNDOFF (T_k + |V_k| + T_{k+1} + |V_{k+1}|) (docs/theory.md §2.10)
ENERGY_ROUNDOFF = 1e-14


def project(M: np.ndarray, W: np.ndarray, v0: np.ndarray, *, b: np.ndarray | None = None,
            Minv: np.ndarray | None = None, form: QPForm = QPForm.PRIMAL, eps: float = 1e-10,
            start: np.ndarray | None = None, blocks=None) -> qp.QPResult:
    """The proximal point of v0 on the tangent cone {v : W' v >= 0} in the kinetic metric M
    (with b: on {W' v >= b}, the per-contact restitution rules, restitution_bounds). start: the rows the
    active set starts from above qp.SPARSE_ROWS rows (qp.solve; the stepper's previous final set). blocks: M's
    diagonal blocks by tree, for qp.solve's islands (docs/theory.md §1.3, islands; None: one problem).

    Returns the QP result: v, the multipliers lam with M (v - v0) = W lam, status and residual."""
    if W.shape[1] == 0:
        return qp.QPResult("NO_CONTACT", True, 0, False, np.array(v0, float), np.zeros(0))
    return qp.solve(M, W, v0, b=b, Minv=Minv, form=form, eps=eps, start=start, blocks=blocks)


def outcome(v: np.ndarray, u_minus: np.ndarray, e: float) -> np.ndarray:
    """u+ = (1 + e) v - e u- = v - e (u- - v): the normal part u- - v reversed and scaled by e.

    Written in the second form so that u+ = u- exactly when nothing happens (v = u-)."""
    return v - e * (u_minus - v)


def percussion(lam: np.ndarray, e: float) -> np.ndarray:
    """P = (1 + e) lam [N s]: the percussions of an impact (or a step) from the multipliers of
    the projection, M (v - v0) = W lam."""
    return (1.0 + e) * lam


def restitution_bounds(W: np.ndarray, u: np.ndarray, u_free: np.ndarray, gamma_minus: np.ndarray, e: float, *,
                       separating: Separating, slow_impacts: SlowImpacts) -> np.ndarray | None:
    """Per-contact restitution e_i where the rules depart from e, as the QP's bound (docs/theory.md §2.7):
    w_i'(u_{k+1} + e_i u_k) >= 0  <=>  w_i'v >= (e - e_i) gamma_i^k / (1 + e). None if e_i = e for all.

    Separating.ELASTIC: e_i = 1 where gamma_i^k > 0 (closed but separating: no positive work, §2.2).
    SlowImpacts.PLASTIC: e_i = 0 where 0 < -gamma_i^k <= -w_i'(u_free - u_k) (slower than a step
    of the smooth forces: the bounce is below the step's resolution, §2.3)."""
    e_i = None
    if separating is Separating.ELASTIC and e < 1.0 and gamma_minus.max(initial=0.0) > 0.0:
        e_i = np.where(gamma_minus > 0.0, 1.0, e)
    if slow_impacts is SlowImpacts.PLASTIC and e > 0.0 and gamma_minus.min(initial=0.0) < 0.0:
        slow = (gamma_minus < 0.0) & (gamma_minus >= ordered(W.T, u_free - u))
        if slow.any():
            e_i = np.where(slow, 0.0, e if e_i is None else e_i)
    return None if e_i is None else (e - e_i) * gamma_minus / (1.0 + e)


@dataclass(frozen=True, slots=True)
class Impact:
    """One impact: u_plus, the percussions P = (1 + e) lam [N s] per contact, the QP result,
    and the energy lost (1 - e^2)/2 ||u- - v||_M^2 [J]."""

    u_plus: np.ndarray
    P: np.ndarray
    qp: qp.QPResult
    energy_loss: float


def impact(M: np.ndarray, W: np.ndarray, u_minus: np.ndarray, e: float, *, form: QPForm = QPForm.PRIMAL,
           eps: float = 1e-10, Minv: np.ndarray | None = None) -> Impact:
    """The impact law at one instant, no forces: u- -> u+ through the closed contacts W (Minv: M^-1 if the
    caller has it, as project takes it)."""
    check_restitution(e)
    res = project(M, W, u_minus, Minv=Minv, form=form, eps=eps)
    if not res.ok:
        raise RuntimeError(f"impact QP failed: {res.status}")
    v_perp = u_minus - res.v
    return Impact(outcome(res.v, u_minus, e), percussion(res.lam, e), res,
                  0.5 * (1.0 - e * e) * float(ordered(ordered(v_perp, M), v_perp)))  # (v'M) v, §2.8
