"""Joint limits as unilateral constraints of the same law (docs/theory.md §1, §2.1, §7): a 1-dof
revolute or prismatic joint with finite position limits (the Pinocchio model's
lowerPositionLimit / upperPositionLimit: URDF <limit>, MJCF range) has two gaps,
g = q_i - q_lower >= 0 and g = q_upper - q_i >= 0 [rad or m], whose rows are the constant unit
vectors +-e_i of velocity space. They enter a step's contacts (constraints.closed_limits) as
contacts.FeatureKind.JOINT_LIMIT, with collision-pair index len(model.pairs) + the limit's index
(so the percussion log and the plots tell them apart) and feature = the Pinocchio joint id.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin


UNLIMITED = 1e300  # a limit at least this large (Pinocchio's default +-DBL_MAX, or inf) is no limit


@dataclass(frozen=True, slots=True)
class JointLimit:
    """One side of one joint's range: g(q) = sign (q[idx_q] - bound) >= 0, row sign e_{idx_v}.

    index: its place in Model.limits; pair: its pair index in contacts (len(model.pairs) + index);
    joint: the Pinocchio joint id; name: "<joint> lower" or "<joint> upper"; sign: +1 (lower) or
    -1 (upper); bound [rad or m]."""

    index: int
    pair: int
    joint: int
    name: str
    sign: float
    bound: float
    idx_q: int
    idx_v: int

    def gap(self, q: np.ndarray) -> float:
        """g(q) [rad or m] (>= 0 inside the range)."""
        return self.sign * (float(q[self.idx_q]) - self.bound)


_ONE_DOF = ("JointModelR", "JointModelP")  # RX, RY, RZ, RevoluteUnaligned, PX, ..., PrismaticUnaligned


def joint_limits(pm: pin.Model, joints, npairs: int) -> tuple[JointLimit, ...]:
    """The limits of the 1-dof revolute and prismatic joints among `joints` (Pinocchio ids) whose
    lower / upper position limit is finite (below UNLIMITED in size). Continuous joints
    (JointModelRUB*, nq = 2), spherical, free-flyer, planar and composite joints have none."""
    out: list[JointLimit] = []
    for j in joints:
        jm = pm.joints[j]
        kind = jm.shortname()
        if not (jm.nq == 1 and jm.nv == 1 and kind.startswith(_ONE_DOF) and not kind.startswith("JointModelRUB")):
            continue
        lo, hi = float(pm.lowerPositionLimit[jm.idx_q]), float(pm.upperPositionLimit[jm.idx_q])
        for sign, bound, side in ((1.0, lo, "lower"), (-1.0, hi, "upper")):
            if abs(bound) < UNLIMITED:
                k = len(out)
                out.append(JointLimit(k, npairs + k, j, f"{pm.names[j]} {side}", sign, bound, jm.idx_q, jm.idx_v))
    return tuple(out)


def limit_gaps(limits: tuple[JointLimit, ...], q: np.ndarray) -> np.ndarray:
    """g of every limit at q (k,) [rad or m]."""
    return np.array([lim.gap(q) for lim in limits])


def limit_rows(limits: tuple[JointLimit, ...], pairs: np.ndarray, nv: int) -> np.ndarray:
    """Rows (nv, k) of the limits with the given pair indices: sign e_{idx_v}."""
    W = np.zeros((nv, len(pairs)))
    first = limits[0].pair if limits else 0
    for col, p in enumerate(pairs.tolist()):
        lim = limits[p - first]
        W[lim.idx_v, col] = lim.sign
    return W
