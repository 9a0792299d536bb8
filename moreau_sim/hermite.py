"""The adaptive integrator's dense output (docs/theory.md §8): the quintic Hermite interpolant of a step's ends
(values, slopes and curvatures at both ends) in powers of tau in [0, 1], and the instants of a step where the
gaps' interpolants are checked for a crossing. Shared by the Python run (adaptive.py) and the compiled sampler
and locator it hands the basis to (compiled_events.py)."""

from __future__ import annotations

import numpy as np

from .sums import ordered

CHECK_POINTS = 16  # interior instants of a step where the gaps' interpolants are checked

# The quintic Hermite basis on [0, 1] in powers of tau: row k holds the coefficients of tau^0..tau^5
# of the basis function of value 0, slope 0, curvature 0, value 1, slope 1, curvature 1.
QUINTIC = np.array([[1, 0, 0, -10, 15, -6], [0, 1, 0, -6, 8, -3], [0, 0, 0.5, -1.5, 1.5, -0.5],
                    [0, 0, 0, 10, -15, 6], [0, 0, 0, -4, 7, -3], [0, 0, 0, 0.5, -1, 0.5]])
POWERS = np.arange(6)
CHECK = np.linspace(0.0, 1.0, CHECK_POINTS + 1)
CHECK_BASIS = ordered(CHECK[:, None] ** POWERS, QUINTIC.T)  # (points, 6)
CHECK_FLOATS = CHECK.tolist()


def poly(coef: np.ndarray) -> np.ndarray:
    """Power coefficients (6, ...) of the quintic Hermite interpolant of Hermite data coef (6, ...)."""
    return ordered(QUINTIC.T, coef)


def polyval(p: np.ndarray, x: float):
    """p[0] + p[1] x + ... + p[5] x^5 (Horner), p (6, ...)."""
    y = p[5]
    for k in range(4, -1, -1):
        y = y * x + p[k]
    return y


def polyslope(p: np.ndarray, x: float):
    """d/dx of polyval(p, x)."""
    y = 5.0 * p[5]
    for k in range(4, 0, -1):
        y = y * x + k * p[k]
    return y
