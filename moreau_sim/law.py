"""Glocker's Newtonian impact law with one global restitution e (impact-law.md §1).

    v  = prox_{T_C}(v0) = argmin_{W' v >= 0} 1/2 (v - v0)' M (v - v0)     (project)
    u+ = (1 + e) v - e u-                                                 (outcome)

For a single impact v0 = u-; in the midpoint step v0 = v_free (impact-law.md §2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import qp
from .scene import QPForm


def _check_e(e: float) -> None:
    if not (0.0 <= e <= 1.0):
        raise ValueError(f"restitution e must lie in [0, 1], got {e!r}")


def project(M: np.ndarray, W: np.ndarray, v0: np.ndarray, *, b: np.ndarray | None = None,
            Minv: np.ndarray | None = None, form: QPForm = QPForm.PRIMAL, eps: float = 1e-10) -> qp.QPResult:
    """The proximal point of v0 on the tangent cone {v : W' v >= 0} in the kinetic metric M
    (with b: on {W' v >= b}, the stepper's rule for closed contacts that separate).

    Returns the QP result: v, the multipliers lam with M (v - v0) = W lam, status and residual."""
    if W.shape[1] == 0:
        return qp.QPResult("NO_CONTACT", True, 0, False, np.array(v0, float), np.zeros(0))
    return qp.solve(M, W, v0, b=b, Minv=Minv, form=form, eps=eps)


def outcome(v: np.ndarray, u_minus: np.ndarray, e: float) -> np.ndarray:
    """u+ = (1 + e) v - e u- = v - e (u- - v): the normal part u- - v reversed and scaled by e.

    Written in the second form so that u+ = u- exactly when nothing happens (v = u-)."""
    return v - e * (u_minus - v)


@dataclass(frozen=True, slots=True)
class Impact:
    """One impact: u_plus, the percussions P = (1 + e) lam [N s] per contact, the QP result,
    and the energy lost (1 - e^2)/2 ||u- - v||_M^2 [J]."""

    u_plus: np.ndarray
    P: np.ndarray
    qp: qp.QPResult
    energy_loss: float


def impact(M: np.ndarray, W: np.ndarray, u_minus: np.ndarray, e: float, *, form: QPForm = QPForm.PRIMAL,
           eps: float = 1e-10) -> Impact:
    """The impact law at one instant, no forces: u- -> u+ through the closed contacts W."""
    _check_e(e)
    res = project(M, W, u_minus, form=form, eps=eps)
    if not res.ok:
        raise RuntimeError(f"impact QP failed: {res.status}")
    v_perp = u_minus - res.v
    return Impact(outcome(res.v, u_minus, e), (1.0 + e) * res.lam, res,
                  0.5 * (1.0 - e * e) * float(v_perp @ M @ v_perp))
