"""Energies of a state (the ledger, docs/theory.md §5). Units: J."""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from .data import Data
from .model import Model


def kinetic(model: Model, data: Data, q: np.ndarray, u: np.ndarray) -> float:
    """T = 1/2 u' M(q) u."""
    return float(pin.computeKineticEnergy(model.pin, data.pin, q, u))


def potential(model: Model, data: Data, q: np.ndarray) -> float:
    """V = -sum_b m_b gravity . c_b (zero at the world origin)."""
    return float(pin.computePotentialEnergy(model.pin, data.pin, q))


def total(model: Model, data: Data, q: np.ndarray, u: np.ndarray) -> float:
    return kinetic(model, data, q, u) + potential(model, data, q)
