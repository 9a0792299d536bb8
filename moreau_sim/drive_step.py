"""A step with driven joints (docs/theory.md §2.13; the joints: drive.py, Model.drive): the velocity rows split
into free (r) and driven (d) ones, u_d taken from xdot(t_k) to xdot(t_{k+1}), the impact law solved in r-space with
the driven rows' contribution as a constraint rate (§2.9), and the drive's work booked (§5.5). Its products and
solves follow §2.8 (sums.ordered, qp._lu_solve), as the compiled step (src/step.cpp drive_start) makes them."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .drive import Drive
from .errors import SimulationError
from .options import Bias
from .qp import _lu_solve
from .sums import ordered
from .results import MIDPOINT_ITERATIONS, MIDPOINT_TOLERANCE


@dataclass(frozen=True)
class DriveStep:
    """What a driven step knows (stepper.assemble): the driven rows d (indices) and free rows r, the
    driven velocity at the step's end xdot = xdot(t_{k+1}) [m/s or rad/s], M = M(q_m), the unconstrained free
    velocity u_f, the driven one u_c (u_c,d = xdot), u_k; work_free: the drive's work in the contact-free step [J]."""

    r: np.ndarray
    d: np.ndarray
    xdot: np.ndarray
    M: np.ndarray
    u_f: np.ndarray
    u_c: np.ndarray
    u_k: np.ndarray
    work_free: float

    def work(self, u_next: np.ndarray) -> float:
        """W_p = ubar_d' [M (u_{k+1} - u_f)]_d, ubar_d = (u_d^k + xdot)/2: the work of the drive's reaction
        (and of the percussions on the driven rows beyond their rate's share, booked in W_o) [J] (§5.5)."""
        ubar = 0.5 * (self.u_k[self.d] + self.xdot)
        return float(ordered(ubar, ordered(self.M[self.d], u_next - self.u_f)))

    def reduced(self, pb):
        """The problem in r-space: M_rr, W_r, u_r, u_free_r, v_free_r, and the rate W_d' (xdot + e u_d^k)/(1 + e)
        added (§2.9, §2.13).
        A contact that only driven rows move (W_r = 0) is left out where it opens or holds (rate >= 0); where
        the drive closes it (rate < 0) nothing can stop it: SimulationError naming the pair."""
        if pb.pieces is not None:
            raise SimulationError("a corner impact (docs/theory.md §3) with a driven joint: not supported")
        r, d = self.r, self.d
        Mrr = pb.M[np.ix_(r, r)]
        rate = ordered(pb.W[d].T, (self.xdot + pb.e * self.u_k[d]) / (1.0 + pb.e))  # (gamma^{k+1} + e gamma^k)/(1 + e)
        rate = rate if pb.rate is None else pb.rate + rate
        W, contacts = pb.W[r], pb.contacts
        rigid = ~(W != 0.0).any(axis=0)
        if rigid.any():
            if (rate[rigid] < 0.0).any():
                i = int(np.flatnonzero(rigid & (rate < 0.0))[0])
                raise SimulationError(f"a driven joint drives collision pair {int(contacts.pair[i])} (contact gap "
                                      f"{contacts.g[i]:.3g} m) into an obstacle that nothing else can move: a "
                                      "prescribed motion cannot be stopped (change the trajectory or the scene)")
            keep = ~rigid
            W, contacts, rate = W[:, keep], contacts.select(keep), rate[keep]
        return replace(pb, u=pb.u[r], u_free=pb.u_free[r], v_free=pb.v_free[r], M=Mrr, Minv=_inverse(Mrr),
                       W=W, rate=rate, contacts=contacts)

    def expanded(self, pb, imp):
        """The r-space solution made whole: u_{k+1} = (u_r^{k+1}, xdot), W with its driven rows zeroed (the
        position correction moves the free rows only), the QP's problem embedded (M with a zero d block: the
        ledger's D and L of the free rows), obstacle_work + W_p."""
        r, d, nv = self.r, self.d, len(self.u_k)
        u = np.empty(nv)
        u[r], u[d] = imp.u_next, self.xdot
        W = np.zeros((nv, imp.W.shape[1]))
        W[r] = imp.W
        q = imp.qp
        if q.M is not None:
            M = np.zeros((nv, nv))
            M[np.ix_(r, r)] = q.M
            q = replace(q, M=M, W=W, v=self._embed(q.v), v0=self._embed(q.v0))
        else:
            q = replace(q, v=self._embed(q.v))
        return replace(imp, u_next=u, W=W, qp=q, obstacle_work=imp.obstacle_work + self.work(u))

    def for_correction(self, pb):
        """The position correction's problem (§2.5, free rows only): M block-diagonal (M_rr, M_dd), so that
        with the driven rows of W zero the displacement leaves the driven joints where they are."""
        r, d = self.r, self.d
        M = np.zeros_like(self.M)
        M[np.ix_(r, r)] = self.M[np.ix_(r, r)]
        M[np.ix_(d, d)] = self.M[np.ix_(d, d)]
        return replace(pb, M=M, Minv=_inverse(M))

    def _embed(self, v: np.ndarray) -> np.ndarray:
        out = np.empty(len(self.u_k))
        out[self.r], out[self.d] = v, self.xdot
        return out


def start(drive: Drive, model, data, q_m: np.ndarray, u: np.ndarray, u_free: np.ndarray, t_m: float, h: float,
          M: np.ndarray | None = None, tau: np.ndarray | None = None) -> DriveStep:
    """The step of `drive`'s joints at (t_m, q_m, u_k) of size h [s] from the unconstrained free velocity u_free:
    u_c,r = u_f,r + M_rr^-1 M_rd (u_f,d - xdot), u_c,d = xdot = xdot(t_{k+1}) (M_rr (u_c,r - u_k,r) =
    h (tau_r - b_r) - M_rd (xdot - u_k,d)); with the midpoint bias b at the driven step's own mean velocity
    (a fixed point, as stepper.free_velocity's). tau: the step's torques (None: none)."""
    if M is None:
        M = model.forest.mass_matrix(data.kinematics, q_m)
    r, d = drive.r, drive.d
    xdot = drive.velocity(t_m + 0.5 * h)
    Mrr, Mrd = M[np.ix_(r, r)], M[np.ix_(r, d)]
    u_c = np.empty_like(u_free)
    u_c[d] = xdot
    u_c[r] = u_free[r] + _solve(Mrr, ordered(Mrd, u_free[d] - xdot))
    if model.velocity_bias and model.options.bias is Bias.MIDPOINT:  # b at the driven step's own mean (§2.4)
        zero = np.zeros(len(u)) if tau is None else tau
        scale = MIDPOINT_TOLERANCE * (1.0 + float(np.abs(u).max()))
        for _ in range(MIDPOINT_ITERATIONS):
            u_free = u + h * model.forest.acceleration(data.kinematics, q_m, 0.5 * (u + u_c), zero)
            nxt = u_free[r] + _solve(Mrr, ordered(Mrd, u_free[d] - xdot))
            done = float(np.abs(nxt - u_c[r]).max(initial=0.0)) <= scale
            u_c[r] = nxt
            if done:
                break
    ubar = 0.5 * (u[d] + xdot)
    work_free = float(ordered(ubar, ordered(M[d], u_c - u_free)))
    return DriveStep(r, d, xdot, M, u_free, u_c, u, work_free)


def _solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A^-1 b by qp._lu_solve (docs/theory.md §2.8: no LAPACK); SimulationError where A is singular."""
    x = _lu_solve(A, b)
    if x is None:
        raise SimulationError("a driven step's mass matrix is singular (the free joints' M_rr)")
    return x


def _inverse(A: np.ndarray) -> np.ndarray:
    """A^-1 column by column (_solve of the unit vectors; src/step.cpp inverse)."""
    return np.column_stack([_solve(A, e) for e in np.eye(len(A))]) if len(A) else np.zeros((0, 0))
