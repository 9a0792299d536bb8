"""The state of a simulation: time, configuration and velocity, nothing else."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class State:
    """t [s]; q generalized coordinates (nq, Pinocchio's convention); u generalized velocities (nv)."""

    t: float
    q: np.ndarray
    u: np.ndarray
