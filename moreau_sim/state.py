"""The state of a simulation: time, configuration and velocity, nothing else."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class State:
    """t [s]; q generalized coordinates (nq, Pinocchio's convention); u generalized velocities (nv)."""

    t: float
    q: np.ndarray
    u: np.ndarray

    def finite(self) -> bool:
        """Whether every entry of q and u is finite (no NaN, no inf)."""
        # Python floats: ~4x cheaper than np.isfinite(...).all() at the sizes of a step
        return all(map(math.isfinite, self.q.tolist())) and all(map(math.isfinite, self.u.tolist()))
