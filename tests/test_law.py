"""The impact law at one instant (docs/theory.md §1): outcome, percussion, energy, restitution bounds.
The projection itself (both forms, the polish) is tested in test_qp.py."""

import numpy as np
import pytest

import moreau_sim as ms

from helpers import random_problem


def energy(M, x):
    return 0.5 * x @ M @ x


@pytest.mark.parametrize("e", [0.0, 0.3, 0.5, 0.8, 1.0])
@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("form", list(ms.QPForm))
def test_energy_identity_of_one_impact(e, seed, form):
    """2T+ = |v|_M^2 + e^2 |v_perp|_M^2, 2T- = |v|^2 + |v_perp|^2, v'M v_perp = 0 (to 1e-10)."""
    M, W, u = random_problem(seed)
    imp = ms.impact(M, W, u, e, form=form)
    v = imp.qp.v
    v_perp = u - v
    scale = energy(M, u)
    assert abs(v @ M @ v_perp) <= 1e-10 * scale
    assert abs(energy(M, imp.u_plus) - (energy(M, v) + e * e * energy(M, v_perp))) <= 1e-10 * scale
    assert abs(energy(M, u) - (energy(M, v) + energy(M, v_perp))) <= 1e-10 * scale
    assert abs((energy(M, u) - energy(M, imp.u_plus)) - imp.energy_loss) <= 1e-10 * scale
    assert energy(M, imp.u_plus) <= energy(M, u) * (1 + 1e-12)  # never a gain


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("seed", range(5))
def test_newton_law_complementarity(e, seed):
    """xi_i = (gamma+ + e gamma-)/(1+e) >= 0, P_i >= 0, xi_i P_i = 0, M(u+ - u-) = W P."""
    M, W, u = random_problem(seed, nv=5, m=4)
    imp = ms.impact(M, W, u, e)
    gm, gp = W.T @ u, W.T @ imp.u_plus
    xi = (gp + e * gm) / (1 + e)
    assert xi.min() >= -1e-12
    assert imp.P.min() >= 0
    assert np.abs(xi * imp.P).max() <= 1e-12
    np.testing.assert_allclose(M @ (imp.u_plus - u), W @ imp.P, atol=1e-12)


def test_admissible_velocity_is_unchanged():
    M, W, u = random_problem(1)
    u_sep = u + 10.0 * np.linalg.solve(M, W @ np.ones(W.shape[1]))  # now W'u > 0
    assert (W.T @ u_sep).min() > 0
    imp = ms.impact(M, W, u_sep, 0.5)
    np.testing.assert_array_equal(imp.u_plus, u_sep)
    np.testing.assert_array_equal(imp.P, 0.0)


def test_two_ball_head_on_momentum():
    """Two equal balls, one contact: momentum conserved, relative velocity reversed times e."""
    M = np.diag([2.0, 3.0])
    W = np.array([[-1.0], [1.0]])  # gap = x2 - x1 - d
    u = np.array([1.5, -0.5])
    for e in (0.0, 0.4, 1.0):
        up = ms.impact(M, W, u, e).u_plus
        assert abs((M @ up).sum() - (M @ u).sum()) <= 1e-14
        assert abs((up[1] - up[0]) - (-e * (u[1] - u[0]))) <= 1e-14


def test_restitution_out_of_range_is_refused():
    M, W, u = random_problem(0)
    with pytest.raises(ValueError, match="restitution"):
        ms.impact(M, W, u, 1.2)
