"""The one QP projection of the package (piqp), serving the impact law and the corner law.

primal (velocity space):  v = argmin 1/2 (v - v0)' M (v - v0)  s.t.  W' v >= b
dual   (contact space):   lam = argmin 1/2 lam' G lam + lam' (W' v0 - b),  lam >= 0,
                          G = W' M^-1 W (Delassus),  v = v0 + M^-1 W lam
Both return (v, lam) with M (v - v0) = W lam (docs/theory.md §1; b = 0 there, the per-contact
restitution rules shift b, docs/theory.md §2.7). After piqp the solution is
polished on its active set A = {lam_i > 0}: G_AA lam_A = b_A - W_A' v0 is solved directly and
kept when it satisfies the KKT conditions to round-off, which makes single impacts and the
cradle exact to round-off instead of to piqp's tolerance.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np
import piqp
import scipy.linalg.lapack
import scipy.optimize

from .options import QPForm


@dataclass(frozen=True, slots=True)
class QPResult:
    """status: piqp's status name ("PIQP_SOLVED", ...), or "ADMISSIBLE" when v0 already satisfies
    every constraint (no QP to solve); ok: solved and usable; iterations: piqp's interior-point
    iterations; polished: the active-set polish was accepted; v (nv,), lam (m,);
    residual (property): the KKT residual of (v, lam), computed when asked (it costs ~5 us)."""

    status: str
    ok: bool
    iterations: int
    polished: bool
    v: np.ndarray
    lam: np.ndarray
    problem: tuple = field(default=(), repr=False, compare=False)  # (M, W, v0, b), for the residual

    @property
    def residual(self) -> float:
        """max(|M(v - v0) - W lam|, max(0, b - W'v), max(0, -lam), |lam . (W'v - b)|)."""
        if not self.ok:
            return float("inf")
        if not self.problem:
            return 0.0
        return kkt_residual(*self.problem[:3], self.v, self.lam, self.problem[3])


_STATUS = {getattr(piqp, n): n for n in dir(piqp) if n.startswith("PIQP_")}
_gesv = scipy.linalg.lapack.dgesv


def kkt_residual(M, W, v0, v, lam, b=None) -> float:
    """max(|M(v - v0) - W lam|, max(0, b - W'v), max(0, -lam), |lam . (W'v - b)|) (inf-norms)."""
    slack = W.T @ v if b is None else W.T @ v - b
    r = np.abs(M @ (v - v0) - W @ lam).max(initial=0.0)
    return float(max(r, -slack.min(initial=0.0), -lam.min(initial=0.0), abs(lam @ slack)))


def _polish(W, v0, b, Minv, lam):
    """Re-solve exactly on the active set A = {lam_i > 0} of piqp's answer.

    On A: G_AA lam_A = b_A - W_A' v0, lam_A >= 0 (a direct solve, or NNLS when the rows are
    redundant, e.g. 4 corners of a face on a plane: rank 3); v = v0 + M^-1 W_A lam_A, then one step
    of iterative refinement on the rows that push. Kept only if it satisfies the KKT conditions to
    round-off (W' v >= b for every row): the exact solution."""
    if len(lam) == 1:  # one contact: the projection in closed form (same formula as below)
        w = W[:, 0]
        Miw = Minv @ w
        lam1 = max(0.0, float(b[0] - w @ v0) / float(w @ Miw)) if lam[0] > 0 else 0.0
        return v0 + lam1 * Miw, np.array([lam1])
    act = lam > 1e-7 * max(1.0, lam.max())
    if not act.any():
        vp, lp = v0.copy(), np.zeros_like(lam)
    else:
        full = act.all()
        WA = W if full else W[:, act]
        MiWA = Minv @ WA
        G, rhs = WA.T @ MiWA, (b if full else b[act]) - WA.T @ v0
        tol = 1e-12 * (1.0 + np.abs(rhs).max())
        lu, piv, lamA, info = _gesv(G, rhs)  # LAPACK directly: np.linalg.solve costs ~20 us here
        ok = info == 0 and lamA.min() >= 0 and np.abs(G @ lamA - rhs).max() <= tol  # False for NaN too
        if not ok:
            lamA, rnorm = scipy.optimize.nnls(G, rhs)
            if not rnorm <= tol:
                return None
        vp = v0 + MiWA @ lamA
        # one step of iterative refinement: lamA is as exact as its magnitude allows, but a light body
        # under a heavy one (lamA ~ R times its own weight impulse) then moves by ~R eps in the directions
        # the rows hold; the residual of W_A'v = b_A is computed where v ~ 0, so accurately, and solving
        # for it on the independent rows P = {lamA_i > 0} leaves W_A'v - b_A at ulp(v) (docs/theory.md §1.5)
        P = lamA > 0.0
        if P.any():
            rP = ((b if full else b[act]) - WA.T @ vp)[P]
            _, _, dP, info = _gesv(G[np.ix_(P, P)], rP)
            if info == 0 and np.abs(dP).max() <= 1e-8 * (1.0 + np.abs(lamA).max()):  # False for NaN too
                d = np.zeros_like(lamA)
                d[P] = dP
                lamA = np.maximum(lamA + d, 0.0)
                vp = vp + MiWA @ d
        if full:
            lp = lamA
        else:
            lp = np.zeros_like(lam)
            lp[act] = lamA
    if (W.T @ vp - b).min() < -1e-12 * (1.0 + np.abs(v0).max()):
        return None
    return vp, lp


class Polish(enum.Enum):
    """How piqp's answer is refined on its active set (docs/theory.md §1)."""

    ACTIVE_SET = "active-set"  # the law: exact KKT solve on A = {lam_i > 0} (LAPACK; NNLS if redundant)
    LEAST_SQUARES = "least-squares"  # the corner law: least squares on the strictly active rows
    NONE = "none"  # piqp's answer as it is


def solve(M: np.ndarray, W: np.ndarray, v0: np.ndarray, *, b: np.ndarray | None = None,
          Minv: np.ndarray | None = None, form: QPForm = QPForm.PRIMAL, eps: float = 1e-10,
          max_iter: int = 250, polish: Polish = Polish.ACTIVE_SET, screen: bool = True,
          polish_tol: float = 1e-9) -> QPResult:
    """Project v0 onto {v : W' v >= b} (b = 0 by default) in the metric M with piqp.

    Minv: M^-1 if the caller has it (Pinocchio's computeMinverse), else it is computed.
    screen: return v0 itself when it is already admissible to round-off (no QP).
    polish_tol: the acceptance tolerance of Polish.LEAST_SQUARES (rows with multipliers above
    sqrt(polish_tol) are active; the polished v must satisfy W'v >= -polish_tol)."""
    m = W.shape[1]
    b = np.zeros(m) if b is None else np.asarray(b, float)
    if polish is Polish.ACTIVE_SET and Minv is None:
        Minv = np.linalg.inv(M)
    if not np.isfinite(v0).all():  # an overflow upstream: no projection of it is meaningful
        return QPResult("NON_FINITE_INPUT", False, 0, False, v0.copy(), np.zeros(m))
    if screen and (W.T @ v0 - b).min() >= -1e-13 * (1.0 + np.abs(v0).max()):
        # v0 already admissible (up to round-off): the projection is v0 itself, nothing to solve
        return QPResult("ADMISSIBLE", True, 0, False, v0.copy(), np.zeros(m), (M, W, v0, b))
    s = piqp.DenseSolver()
    st = s.settings
    st.verbose = False
    st.eps_abs = st.eps_rel = eps
    st.eps_duality_gap_abs = st.eps_duality_gap_rel = eps  # default 1e-8 would bound the accuracy
    st.max_iter = max_iter
    if form is QPForm.PRIMAL:
        s.setup(M, -(M @ v0), None, None, W.T, b, None)
        status = s.solve()
        v, lam = s.result.x.copy(), s.result.z_l.copy()
    else:
        if Minv is None:
            Minv = np.linalg.inv(M)
        MiW = Minv @ W
        s.setup(W.T @ MiW, W.T @ v0 - b, None, None, None, None, None, np.zeros(m), None)
        status = s.solve()
        lam = s.result.x.copy()
        v = v0 + MiW @ lam
    iters = s.result.info.iter
    if status != piqp.PIQP_SOLVED:
        return QPResult(_STATUS.get(status, str(status)), False, iters, False, v, lam)
    if not (np.isfinite(v).all() and np.isfinite(lam).all()):  # piqp has answered "solved" with NaN
        return QPResult("NON_FINITE_SOLUTION", False, iters, False, v, lam)
    p = None
    if polish is Polish.ACTIVE_SET:
        np.maximum(lam, 0.0, out=lam)
        p = _polish(W, v0, b, Minv, lam)
    elif polish is Polish.LEAST_SQUARES:
        p = _polish_least_squares(M, W, v0, lam, polish_tol)
    if p is not None:
        v, lam = p
    return QPResult("PIQP_SOLVED", True, iters, p is not None, v, lam, (M, W, v0, b))


def _polish_least_squares(M, W, v0, lam, tol):
    """Re-solve on the strictly active rows (lam_i > sqrt(tol) max(1, lam)): M (v - v0) = W_a lam_a,
    W_a' v = 0, by least squares; kept when lam_a >= 0 and W' v >= -tol (b = 0)."""
    act = lam > np.sqrt(tol) * max(1.0, float(np.max(lam)))
    if not np.any(act):
        return None
    Ga = W.T[act]
    MiG = np.linalg.solve(M, Ga.T)
    za = np.linalg.lstsq(Ga @ MiG, -Ga @ v0, rcond=None)[0]
    vp = v0 + MiG @ za
    if not (np.all(za >= 0.0) and np.all(W.T @ vp >= -tol)):
        return None
    z = np.zeros_like(lam)
    z[act] = za
    return vp, z
