"""The one QP projection (moreau_sim.qp, docs/theory.md §1): v = argmin 1/2 |v - v0|_M^2 s.t. W'v >= b,
in both forms, with the active-set polish, the admissible screen, Polish.LEAST_SQUARES and failures."""

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import qp
from moreau_sim.options import QPForm

from helpers import random_problem


def one_row_projection(M, w, v0, b):
    """The exact projection on one half-space w'v >= b in the metric M."""
    Miw = np.linalg.solve(M, w)
    lam = max(0.0, (b - w @ v0) / (w @ Miw))
    return v0 + lam * Miw, lam


def test_primal_and_dual_forms_agree():
    for seed in range(5):
        M, W, u = random_problem(seed, nv=7, m=5)
        a = qp.solve(M, W, u, form=ms.QPForm.PRIMAL)
        b = qp.solve(M, W, u, form=ms.QPForm.DUAL)
        assert a.ok and b.ok
        np.testing.assert_allclose(a.v, b.v, atol=1e-12)
        assert a.residual <= 1e-12 and b.residual <= 1e-12


@pytest.mark.parametrize("form", list(ms.QPForm))
@pytest.mark.parametrize("b", [0.0, 0.3, -0.2])
def test_one_row_with_a_bound_is_the_closed_form(form, b):
    """W'v >= b (the restitution bounds shift b): the KKT point of one row in closed form, to round-off."""
    M, W, u = random_problem(3, nv=5, m=1)
    v, lam = one_row_projection(M, W[:, 0], u, b)
    res = qp.solve(M, W, u, b=np.array([b]), form=form)
    assert res.ok and res.polished
    np.testing.assert_allclose(res.v, v, rtol=0, atol=1e-13)
    np.testing.assert_allclose(res.lam, [lam], rtol=1e-12)
    np.testing.assert_allclose(M @ (res.v - u), W @ res.lam, atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_active_set_polish_makes_the_solution_exact(seed):
    """piqp alone meets its tolerance (KKT residual ~1e-10); the polish makes it round-off (<= 1e-13)."""
    M, W, u = random_problem(seed)
    raw = qp.solve(M, W, u, polish=qp.Polish.NONE)
    exact = qp.solve(M, W, u)
    assert raw.ok and not raw.polished and exact.polished
    assert exact.residual <= 1e-13
    assert raw.residual > exact.residual
    np.testing.assert_allclose(raw.v, exact.v, atol=1e-8)  # the same point, to piqp's tolerance


@pytest.mark.parametrize("seed", range(5))
def test_least_squares_polish_agrees_with_the_active_set_polish(seed):
    """Polish.LEAST_SQUARES (the corner law's) reaches the same exact point on a smooth problem (b = 0)."""
    M, W, u = random_problem(seed)
    ls = qp.solve(M, W, u, polish=qp.Polish.LEAST_SQUARES)
    act = qp.solve(M, W, u)
    assert ls.ok and ls.polished
    np.testing.assert_allclose(ls.v, act.v, atol=1e-12)
    np.testing.assert_allclose(ls.lam, act.lam, atol=1e-11)
    assert ls.residual <= 1e-12


def test_admissible_velocity_is_screened_without_a_qp():
    """W'v0 >= b already: v = v0 bit for bit, no multiplier, no piqp iteration; without the screen
    piqp finds the same point."""
    M, W, u = random_problem(1)
    u_sep = u + 10.0 * np.linalg.solve(M, W @ np.ones(W.shape[1]))
    assert (W.T @ u_sep).min() > 0
    res = qp.solve(M, W, u_sep)
    assert res.status == "ADMISSIBLE" and res.ok and res.iterations == 0
    np.testing.assert_array_equal(res.v, u_sep)
    np.testing.assert_array_equal(res.lam, 0.0)
    solved = qp.solve(M, W, u_sep, screen=False)
    assert solved.status == "PIQP_SOLVED" and solved.iterations > 0
    np.testing.assert_allclose(solved.v, u_sep, atol=1e-12)


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


def test_failure_is_reported_not_polished():
    """A solve that runs out of iterations, without the exact fallback: piqp's status, not ok,
    infinite residual, no polish."""
    M, W, u = random_problem(0, nv=7, m=5)
    res = qp.solve(M, W, u, max_iter=1, polish=qp.Polish.NONE)
    assert res.status == "PIQP_MAX_ITER_REACHED"
    assert not res.ok and not res.polished and res.residual == np.inf


def test_unconverged_piqp_is_rescued_by_the_least_distance_program():
    """With the default polish, a piqp that runs out of iterations hands over to the exact
    least-distance program (NNLS): the same projection as a converged solve, to round-off."""
    M, W, u = random_problem(0, nv=7, m=5)
    ref = qp.solve(M, W, u)
    res = qp.solve(M, W, u, max_iter=1)
    assert res.status == "LEAST_DISTANCE" and res.ok and res.polished and res.residual <= 1e-12
    np.testing.assert_allclose(res.v, ref.v, atol=1e-13)


@pytest.mark.parametrize("ratio", [1e2, 1e3, 1e4])
@pytest.mark.parametrize("form", list(QPForm))
def test_redundant_stack_with_a_large_mass_ratio_is_exact(ratio, form):
    """A heavy cube on a light one on the ground, both at rest, aligned: 4 + 4 corner rows of rank 3
    + 3, per-contact bounds b of a few 1e-14 (round-off velocities under the restitution rules). The
    active set is redundant (G_AA singular): the answer must still satisfy the KKT conditions to
    round-off and leave the light cube at rest to ~ulp(heavy weight impulse), not piqp's tolerance."""
    h, g = 1e-2, 9.81
    I1, I2 = 1.0 * 0.01 / 6, ratio * 0.01 / 6
    M = np.diag([1.0, 1.0, 1.0, I1, I1, I1, ratio, ratio, ratio, I2, I2, I2])
    n = np.array([0.0, 0.0, 1.0])
    cols = []
    for z, two in ((-0.05, False), (0.05, True)):  # ground under the light cube, then light-heavy
        for sx in (-1, 1):
            for sy in (-1, 1):
                p = np.array([0.05 * sx, 0.05 * sy, z])
                w = np.zeros(12)
                w[:3], w[3:6] = -n if two else n, -np.cross(p, n) if two else np.cross(p, n)
                if two:
                    w[6:9], w[9:12] = n, np.cross(p - np.array([0, 0, 0.1]), n)
                cols.append(w)
    W = np.array(cols).T
    rng = np.random.default_rng(1)
    v0 = np.zeros(12)
    v0[2] = v0[8] = -h * g / 1.5
    b = -1e-14 * rng.random(8)
    res = qp.solve(M, W, v0, b=b, form=form)
    assert res.ok and res.polished and res.residual <= 1e-12 * ratio
    # the light cube stays at rest to the round-off of the heavy cube's weight impulse (~ratio * 1e-16
    # in its velocity, times the lever over the inertia for its rotation); piqp alone: ~1e-5
    assert np.abs(res.v[:6]).max() <= 1e-15 * ratio


def test_kkt_residual_measures_each_condition():
    """Zero at the exact projection; each violated condition shows up by its size."""
    M, w, v0 = np.eye(2), np.array([[0.0], [1.0]]), np.array([1.0, -2.0])
    v, lam = np.array([1.0, 0.0]), np.array([2.0])
    assert qp.kkt_residual(M, w, v0, v, lam) == 0.0
    assert qp.kkt_residual(M, w, v0, v, np.array([1.5])) == pytest.approx(0.5)  # stationarity
    assert qp.kkt_residual(M, w, v0, np.array([1.0, -0.25]), lam) >= 0.25  # feasibility
    assert qp.kkt_residual(M, w, v0, v, lam, b=np.array([-0.5])) == pytest.approx(1.0)  # lam (w'v - b)
