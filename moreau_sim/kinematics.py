"""One evaluation's joint kinematics for the per-feature gaps (docs/theory.md §7): placements,
twists, bias accelerations (q'' = 0) and Jacobians of material points, read from pinocchio's
data once per joint. gaps.Gaps.features builds one per call and drops it when it returns. Its products
are sums in index order (sums.py, docs/theory.md §2.8)."""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from .model import Model
from .sums import dots, ordered

G_RES = 1e-13  # [m] smallest gap whose sign is trusted (~3000x the rounding of positions ~ 1 m)


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b of (k, 3) arrays (broadcasting; np.cross's axis handling costs ~30 us a call)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), axis=-1)


def skew(w: np.ndarray) -> np.ndarray:
    """The matrix of w x . (3, 3)."""
    w0, w1, w2 = w.tolist()
    return np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for 3-vectors (in Python floats: the same IEEE operations, without numpy's per-element cost)."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


class Kinematics:
    """The joints' kinematics at one (q, u) (after forwardKinematics(q, u, 0) and, for rows,
    computeJointJacobians): each joint's frame and the Jacobian are read on first use and kept
    for this evaluation only."""

    __slots__ = ("pd", "mask", "nv", "frames", "J")

    def __init__(self, model: Model, pd):
        self.pd, self.mask, self.nv = pd, model.support_mask, model.nv
        self.frames: dict = {}
        self.J = None

    def jacobian(self) -> np.ndarray:
        if self.J is None:
            self.J = self.pd.J.reshape(6, -1)
        return self.J

    def frame(self, j: int):
        """(R, t, w, v, a_ang, a_lin) of joint j (placement; twist and bias acceleration in its frame)."""
        frame = self.frames.get(j)
        if frame is None:
            M, v, a = self.pd.oMi[j], self.pd.v[j], self.pd.a[j]
            frame = self.frames[j] = (M.rotation, M.translation, v.angular, v.linear, a.angular, a.linear)
        return frame

    def frame0(self, j: int):
        """frame(j), or the world's (at rest) for j = 0."""
        return (np.eye(3),) + (np.zeros(3),) * 5 if j == 0 else self.frame(j)

    def point(self, j: int, p_local: np.ndarray, rows: bool):
        """World position, velocity, bias acceleration (q'' = 0) and Jacobian (3, nv) (if rows) of
        a point fixed in joint j's frame."""
        if j == 0:
            return p_local, np.zeros(3), np.zeros(3), (np.zeros((3, self.nv)) if rows else None)
        R, t, w, v_lin, a_ang, a_lin = self.frame(j)
        vl = v_lin + cross(w, p_local)
        p = dots(R, p_local) + t
        vel = dots(R, vl)
        acc = dots(R, a_lin + cross(a_ang, p_local) + cross(w, vl))
        Jp = None
        if rows:
            J = self.jacobian()
            Jp = (J[:3] - ordered(pin.skew(p), J[3:])) * self.mask[j]
        return p, vel, acc, Jp

    def motion(self, j: int, P: np.ndarray, rows: bool):
        """Velocities and bias accelerations (q'' = 0) (k, 3) of joint j's material points at the
        world points P (k, 3), its angular velocity (world) and its masked (J_lin, J_ang) if rows."""
        if j == 0:
            z = np.zeros_like(P)
            return z, z, np.zeros(3), None
        R, t, w, v_lin, a_ang, a_lin = self.frame(j)
        Pl = dots((P - t)[:, None], R.T)  # (P - t) @ R
        Sw = skew(w)  # w x p = p @ Sw.T for the rows p of Pl
        vl = v_lin + dots(Pl[:, None], Sw)
        vel = dots(vl[:, None], R)  # vl @ R.T
        acc = dots((a_lin + dots(Pl[:, None], skew(a_ang)) + dots(vl[:, None], Sw))[:, None], R)
        J = None
        if rows:
            Jf = self.jacobian()
            mask = self.mask[j]
            J = (Jf[:3] * mask, Jf[3:] * mask)
        return vel, acc, dots(R, w), J

    def rows(self, JA, JB, PA: np.ndarray, PB: np.ndarray, n: np.ndarray) -> np.ndarray:
        """w = J_A(p_A)' n - J_B(p_B)' n (nv, k) for contact points PA, PB and normals n (k, 3)."""
        W = np.zeros((self.nv, len(n)))
        for J, P, sign in ((JA, PA, 1.0), (JB, PB, -1.0)):
            if J is not None:  # n' J_p = n' J_lin + (p x n)' J_ang
                W += sign * (ordered(J[0].T, n.T) + ordered(J[1].T, cross_rows(P, n).T))
        return W
