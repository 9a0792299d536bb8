"""The impact law at one instant (impact-law.md §1) and the QP that computes it."""

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import qp


def random_problem(seed, nv=6, m=3):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((nv, nv))
    M = A @ A.T + nv * np.eye(nv)
    W = rng.standard_normal((nv, m))
    u = rng.standard_normal(nv)
    u -= W @ np.linalg.lstsq(W, u, rcond=None)[0] * 0  # keep u generic
    u -= 2.0 * np.linalg.solve(M, W @ np.ones(m))  # make the contacts approach
    return M, W, u


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


def test_primal_and_dual_forms_agree():
    for seed in range(5):
        M, W, u = random_problem(seed, nv=7, m=5)
        a = qp.solve(M, W, u, form=ms.QPForm.PRIMAL)
        b = qp.solve(M, W, u, form=ms.QPForm.DUAL)
        assert a.ok and b.ok
        np.testing.assert_allclose(a.v, b.v, atol=1e-12)
        assert a.residual <= 1e-12 and b.residual <= 1e-12


def test_redundant_rows_are_solved_exactly():
    """Four corners of a box face resting on a plane give rank-3 rows: the projection is still exact."""
    M = np.diag([1.0, 1.0, 1.0, 0.02, 0.03, 0.01])
    pts = [np.array([sx * 0.1, sy * 0.2, -0.1]) for sx in (-1, 1) for sy in (-1, 1)]
    n = np.array([0.0, 0.0, 1.0])
    W = np.array([np.concatenate([n, np.cross(p, n)]) for p in pts]).T
    u = np.array([0.3, -0.2, -1.0, 0.5, -0.4, 0.7])
    res = qp.solve(M, W, u)
    assert res.ok and res.polished and res.residual <= 1e-13
    np.testing.assert_allclose(res.v[[2, 3, 4]], 0.0, atol=1e-14)  # normal motion stopped
    np.testing.assert_allclose(res.v[[0, 1, 5]], u[[0, 1, 5]], atol=1e-14)  # tangential kept


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
