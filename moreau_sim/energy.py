"""Energies of a state (the ledger, docs/theory.md §5), on the forest (§2.12). Units: J."""

from __future__ import annotations

import numpy as np

from .data import Data
from .model import Model


def kinetic(model: Model, data: Data, q: np.ndarray, u: np.ndarray) -> float:
    """T = 1/2 u' M(q) u (on the forest, trees.py)."""
    return float(model.forest.kinetic(data.kinematics, q, u))


def potential(model: Model, data: Data, q: np.ndarray) -> float:
    """V = -sum_b m_b gravity . c_b (zero at the world origin)."""
    return float(model.forest.potential(data.kinematics, q))


def total(model: Model, data: Data, q: np.ndarray, u: np.ndarray) -> float:
    return kinetic(model, data, q, u) + potential(model, data, q)
