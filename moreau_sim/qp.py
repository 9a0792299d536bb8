"""Thin piqp wrappers for the impact QP, one result type for both forms.

primal (velocity space):  v = argmin 1/2 (v - v0)' M (v - v0)  s.t.  W' v >= 0
dual   (contact space):   lam = argmin 1/2 lam' G lam + lam' W' v0,  lam >= 0,  G = W' M^-1 W,
                          v = v0 + M^-1 W lam
Both return (v, lam) with M (v - v0) = W lam (impact-law.md §1). After piqp, the solution is
polished on its active set A = {lam_i > 0}: the equality-constrained projection
G_AA lam_A = -W_A' v0 is solved directly and kept when it is feasible (lam_A >= 0,
W' v >= 0) and its KKT residual is smaller, which makes single impacts and the cradle exact
to round-off instead of to piqp's tolerance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import piqp
import scipy.optimize

from .scene import QPForm


@dataclass(frozen=True, slots=True)
class QPResult:
    """status: piqp's status name ("PIQP_SOLVED", ...); ok: solved (and usable);
    iterations: piqp's interior-point iterations; residual: the KKT residual of (v, lam)
    (max of stationarity, primal and dual infeasibility, complementarity, in the units of
    velocity x metric); polished: the active-set polish was accepted; v (nv,), lam (m,)."""

    status: str
    ok: bool
    iterations: int
    residual: float
    polished: bool
    v: np.ndarray
    lam: np.ndarray


def kkt_residual(M: np.ndarray, W: np.ndarray, v0: np.ndarray, v: np.ndarray, lam: np.ndarray) -> float:
    """max(|M(v - v0) - W lam|, max(0, -W'v), max(0, -lam), |lam . W'v|) (inf-norms)."""
    gamma = W.T @ v
    r = np.abs(M @ (v - v0) - W @ lam).max(initial=0.0)
    return float(max(r, (-gamma).max(initial=0.0), (-lam).max(initial=0.0), abs(float(lam @ gamma))))


def _settings(s, eps: float) -> None:
    s.settings.verbose = False
    s.settings.eps_abs = eps
    s.settings.eps_rel = eps


def _status(st) -> str:
    return str(st).rsplit(".", 1)[-1]


def _polish(W, v0, Minv, lam):
    """Re-solve exactly on the active set A = {lam_i > 0} of piqp's answer.

    On A: G_AA lam_A = -W_A' v0, lam_A >= 0 (a direct solve, or NNLS when the rows are
    redundant, e.g. 4 corners of a face on a plane: rank 3); v = v0 + M^-1 W_A lam_A. The result
    is kept only if it satisfies the KKT conditions of the QP to round-off (W_A' v = 0 up to
    the solve's residual, W' v >= 0 for every row), i.e. it is the exact solution."""
    scale = max(1.0, float(np.abs(lam).max(initial=0.0)))
    act = np.flatnonzero(lam > 1e-7 * scale)
    lp = np.zeros_like(lam)
    vp = np.array(v0, float)
    if len(act):
        WA = W[:, act]
        MiWA = Minv @ WA
        G, b = WA.T @ MiWA, -(WA.T @ v0)
        tol_b = 1e-12 * (1.0 + float(np.abs(b).max()))
        lamA = None
        try:
            lamA = np.linalg.solve(G, b)
            if not (np.all(np.isfinite(lamA)) and lamA.min() >= 0 and np.abs(G @ lamA - b).max() <= tol_b):
                lamA = None
        except np.linalg.LinAlgError:
            pass
        if lamA is None:
            lamA, rnorm = scipy.optimize.nnls(G, b)
            if not rnorm <= tol_b:
                return None
        vp += MiWA @ lamA
        lp[act] = lamA
    if (W.T @ vp).min() < -1e-12 * (1.0 + float(np.abs(v0).max())):
        return None
    return vp, lp


def solve(M: np.ndarray, W: np.ndarray, v0: np.ndarray, *, Minv: np.ndarray | None = None,
          form: QPForm = QPForm.PRIMAL, eps: float = 1e-10, max_iter: int = 250, polish: bool = True) -> QPResult:
    """Project v0 onto {v : W' v >= 0} in the metric M with piqp (see module doc).

    Minv: M^-1 if the caller has it (Pinocchio's computeMinverse), else it is computed."""
    nv, m = W.shape
    if Minv is None:
        Minv = np.linalg.inv(M)
    gamma0 = W.T @ v0
    if gamma0.min() >= -1e-13 * (1.0 + float(np.abs(v0).max())):
        # v0 already admissible (up to round-off): the projection is v0 itself, nothing to solve
        return QPResult("ADMISSIBLE", True, 0, 0.0, False, np.array(v0, float), np.zeros(m))
    s = piqp.DenseSolver()
    _settings(s, eps)
    s.settings.max_iter = max_iter
    if form is QPForm.PRIMAL:
        s.setup(M, -(M @ v0), None, None, W.T, np.zeros(m), None)
        st = s.solve()
        v, lam = s.result.x.copy(), s.result.z_l.copy()
    else:
        MiW = Minv @ W
        G = W.T @ MiW
        s.setup(G, W.T @ v0, None, None, None, None, None, np.zeros(m), None)
        st = s.solve()
        lam = s.result.x.copy()
        v = v0 + MiW @ lam
    status = _status(st)
    ok = st == piqp.PIQP_SOLVED and np.all(np.isfinite(v)) and np.all(np.isfinite(lam))
    iters = int(s.result.info.iter)
    if not ok:
        return QPResult(status, False, iters, float("inf"), False, v, lam)
    lam = np.maximum(lam, 0.0)
    p = _polish(W, v0, Minv, lam) if polish else None
    if p is not None:
        v, lam = p
    return QPResult(status, True, iters, kkt_residual(M, W, v0, v, lam), p is not None, v, lam)
