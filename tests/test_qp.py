"""The one QP projection (moreau_sim.qp, docs/theory.md §1): v = argmin 1/2 |v - v0|_M^2 s.t. W'v >= b,
in both forms, with the active-set polish, the admissible screen, Polish.LEAST_SQUARES and failures."""

from pathlib import Path

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import nonzeros, qp, schur, sums
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
    solved = qp.solve(M, W, u_sep, screen=False, polish=qp.Polish.NONE)
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
    """A piqp solve that runs out of iterations: piqp's status, not ok, infinite residual, no polish."""
    M, W, u = random_problem(0, nv=7, m=5)
    res = qp.solve(M, W, u, max_iter=1, polish=qp.Polish.NONE)
    assert res.status == "PIQP_MAX_ITER_REACHED"
    assert not res.ok and not res.polished and res.residual == np.inf


@pytest.mark.parametrize("ratio", [1.0, 1e2, 1e3, 1e4])
@pytest.mark.parametrize("form", list(QPForm))
def test_heavy_on_light_stack_comes_to_rest_exactly(ratio, form):
    """A cube of `ratio` kg on a 1 kg cube on the ground, aligned, one step of gravity (v0 = -h g/1.5
    for both): 4 + 4 corner rows of rank 3 + 3. The exact projection is v = 0. Solving for multipliers
    of ~ratio times the light cube's weight impulse leaves its velocity at ~ratio * eps (1e-12 m/s at
    1:10,000, the round-off that tipped the 1:1000 stack over, docs/theory.md §1.5); the polish's
    refinement step computes the residual where v ~ 0 and brings v to round-off of v itself."""
    h, g = 1e-2, 9.81
    I1, I2 = 1.0 * 0.01 / 6, ratio * 0.01 / 6
    M = np.diag([1.0, 1.0, 1.0, I1, I1, I1, ratio, ratio, ratio, I2, I2, I2])
    n = np.array([0.0, 0.0, 1.0])
    cols = []
    for z in (-0.05, 0.05):  # the ground under the light cube, then the light-heavy face
        for sx in (-1, 1):
            for sy in (-1, 1):
                p = np.array([0.05 * sx, 0.05 * sy, z])
                w = np.zeros(12)
                w[:3], w[3:6] = n, np.cross(p, n)
                if z > 0:  # the row of the heavy cube (B = light, A = heavy): n'(v_heavy(p) - v_light(p))
                    w[:6] *= -1.0
                    w[6:9], w[9:12] = n, np.cross(p - np.array([0.0, 0.0, 0.1]), n)
                cols.append(w)
    W = np.array(cols).T
    v0 = np.zeros(12)
    v0[2] = v0[8] = -h * g / 1.5
    res = qp.solve(M, W, v0, form=form)
    assert res.ok and res.polished and res.residual <= 1e-13 * ratio
    assert np.abs(res.v).max() <= 1e-17, np.abs(res.v).max()


def test_kkt_residual_measures_each_condition():
    """Zero at the exact projection; each violated condition shows up by its size."""
    M, w, v0 = np.eye(2), np.array([[0.0], [1.0]]), np.array([1.0, -2.0])
    v, lam = np.array([1.0, 0.0]), np.array([2.0])
    assert qp.kkt_residual(M, w, v0, v, lam) == 0.0
    assert qp.kkt_residual(M, w, v0, v, np.array([1.5])) == pytest.approx(0.5)  # stationarity
    assert qp.kkt_residual(M, w, v0, np.array([1.0, -0.25]), lam) >= 0.25  # feasibility
    assert qp.kkt_residual(M, w, v0, v, lam, b=np.array([-0.5])) == pytest.approx(1.0)  # lam (w'v - b)


def _random_qp(seed, dependent=False, bounds=False):
    """A random projection with 1-12 rows in 1-12 velocities (W Fortran-ordered as the step's rows);
    `dependent`: row 3 = row 0 + row 1 - row 2 (a face on a plane); `bounds`: b != 0."""
    rng = np.random.default_rng(seed)
    nv, m = int(rng.integers(1, 13)), int(rng.integers(4 if dependent else 1, 13))
    A = rng.standard_normal((nv, nv))
    M = A @ A.T + nv * np.eye(nv)
    W = np.asfortranarray(rng.standard_normal((nv, m)))
    if dependent:
        W[:, 3] = W[:, 0] + W[:, 1] - W[:, 2]
    b = 0.1 * rng.standard_normal(m) if bounds else np.zeros(m)
    return M, W, rng.standard_normal(nv), b


@pytest.mark.parametrize("bounds", [False, True])
@pytest.mark.parametrize("dependent", [False, True])
def test_active_set_is_the_exact_projection(dependent, bounds):
    """The dual active set alone (no piqp) solves random problems, dependent rows and shifted bounds
    included, to round-off: the KKT residual is <= 1e-13 of the problem's scale, and piqp agrees
    to its own tolerance. An infeasible problem (a dependent row with an inconsistent bound) is
    left to piqp, which says so."""
    solved = 0
    for seed in range(60):
        M, W, v0, b = _random_qp(seed, dependent, bounds)
        res = qp.solve(M, W, v0, b=b)
        raw = qp.solve(M, W, v0, b=b, polish=qp.Polish.NONE)
        if res.status != "ACTIVE_SET":
            assert res.status == "ADMISSIBLE" or not raw.ok, (seed, res.status, raw.status)
            continue
        solved += 1
        assert res.polished and res.iterations >= 1
        scale = 1.0 + np.abs(v0).max() + np.abs(res.lam).max() * np.abs(W).max()
        assert res.residual <= 1e-13 * scale, (seed, res.residual)
        assert (res.lam >= 0).all()
        if raw.ok:
            np.testing.assert_allclose(res.v, raw.v, atol=1e-6)
    assert solved >= 40


def test_active_set_drops_a_row_on_the_way():
    """Row 1 is the most violated and is taken first; row 0, then violated, cannot join it (row 1's
    multiplier would turn negative): row 1 leaves on the way and row 0 alone is active. One guess of
    the active set ({1} or {0, 1}) would have been rejected."""
    W = np.asfortranarray(np.array([[-1.0, 2.0], [1.0, 4.0], [3.0, -3.0]]).T)
    v0 = np.array([3.0, -4.0])  # W'v0 = (-11, -13, 21)
    res = qp.solve(np.eye(2), W, v0)
    assert res.status == "ACTIVE_SET" and res.polished
    assert res.iterations == 3  # add 1; add 0 (row 1 leaves first); add 0
    lam0 = 11.0 / 5.0  # -(w0'v0) / (w0'w0)
    np.testing.assert_allclose(res.lam, [lam0, 0.0, 0.0], rtol=1e-15, atol=0)
    np.testing.assert_allclose(res.v, v0 + lam0 * W[:, 0], rtol=0, atol=1e-15)
    assert (W.T @ res.v)[1:].min() > 1.0 and res.residual <= 1e-14


def test_infeasible_rows_go_to_piqp():
    """w'v >= 1 and -w'v >= 1 cannot both hold: the active set gives up and piqp reports it."""
    M, w = np.eye(3), np.array([1.0, 2.0, 0.0])
    res = qp.solve(M, np.column_stack([w, -w]), np.zeros(3), b=np.ones(2))
    assert not res.ok and res.status == "PIQP_PRIMAL_INFEASIBLE"


def test_column_of_beads_correction_at_step_1292_is_exact():
    """The full-length column_of_beads run parted between the two steps at step 1292 (t = 0.646 s): its
    position-correction QP (2 rows) was left at piqp's ~1e-11 answer by the one-guess polish. Every QP of
    that step is now solved exactly by the active set."""
    from moreau_sim import stepper
    from moreau_sim.data import make_data
    from moreau_sim.simulate import initial_state

    sc = ms.load_scene(Path(__file__).resolve().parent.parent / "scenes" / "column_of_beads.toml")
    sc = sc.with_options(step_impl="python")
    model = ms.build_model(sc)
    data = make_data(model)
    state, h, e = initial_state(model), sc.options.dt, sc.options.restitution
    seen = []
    solve = qp.solve

    def spy(M, W, v0, **kw):
        r = solve(M, W, v0, **kw)
        seen.append((M, W, v0, kw.get("b"), r))
        return r

    for k in range(1292):
        if k == 1291:
            qp.solve = spy
        try:
            state = stepper.step(model, data, state, h=h, e=e, t_next=(k + 1) * h).state
        finally:
            qp.solve = solve
    corr = [s for s in seen if not s[2].any()]
    assert corr, "no position correction at step 1292"
    for *_, r in seen:
        assert r.status in ("ACTIVE_SET", "ADMISSIBLE"), r.status
        assert r.residual <= 1e-15
    M, W, v0, b, r = corr[0]
    raw = qp.solve(M, W, v0, b=b, polish=qp.Polish.NONE)
    assert raw.residual > 1e-12 > r.residual  # piqp alone is not exact here


def _column_problem(n):
    """A resting column of n unit beads on prismatic joints (M = I, rows e_0 and e_k - e_{k-1}: the
    Delassus matrix tridiagonal), every bead at v0 = -g h: the exact projection is v = 0 with the
    multiplier of contact k (under bead k) carrying the n - k beads above it, lam_k = (n - k) g h."""
    W = np.zeros((n, n))
    W[0, 0] = 1.0
    for k in range(1, n):
        W[k, k], W[k - 1, k] = 1.0, -1.0
    gh = 9.81 * 5e-4
    return np.eye(n), W, np.full(n, -gh), gh


@pytest.mark.parametrize("form", list(QPForm))
@pytest.mark.parametrize("n", [13, 50, 101, 400, 600])
def test_sparse_path_solves_a_resting_column_exactly(n, form):
    """The active set (from nothing: no start given) and, above SPARSE_ROWS rows, its fallback the sparse path
    (piqp's SparseSolver, the active set on CSC matrices) give the closed form to round-off, polished, with a KKT
    residual at round-off."""
    M, W, v0, gh = _column_problem(n)
    res = qp.solve(M, W, v0, Minv=M, form=form)
    assert res.ok and res.polished and res.status == "ACTIVE_SET"  # either form: no piqp
    answers = [res]
    if n > qp.SPARSE_ROWS:
        sp = qp._solve_sparse(M, W, v0, np.zeros(n), M, form, 1e-10, 250, True)
        assert sp.ok and sp.polished and sp.status == "PIQP_SOLVED"
        answers.append(sp)
    for res in answers:
        np.testing.assert_allclose(res.v, 0.0, rtol=0, atol=1e-15 * n)
        np.testing.assert_allclose(res.lam, gh * (n - np.arange(n)), rtol=1e-13, atol=0)
        assert res.residual <= 1e-15 * n


@pytest.mark.parametrize("bounds", [False, True])
@pytest.mark.parametrize("seed", range(6))
def test_sparse_path_is_the_projection_the_cold_active_set_gives(seed, bounds, monkeypatch):
    """Random block-diagonal problems (bodies on separate root joints) of 13 to nv rows, on the sparse path
    (its threshold lowered to 12 rows): the answer equals the dense cold active set's (qp._polish on
    the dense matrices, the small-problem method) to round-off, and is repeatable bit for bit."""
    monkeypatch.setattr(qp, "SPARSE_ROWS", 12)
    polish = qp._polish  # the dense cold active set, the reference
    _sparse_path_only(monkeypatch)
    rng = np.random.default_rng(seed)
    blocks = [rng.standard_normal((k, k)) for k in rng.integers(1, 4, 12)]
    M = np.zeros((sum(len(B) for B in blocks),) * 2)
    a = 0
    for B in blocks:
        M[a:a + len(B), a:a + len(B)] = B @ B.T + len(B) * np.eye(len(B))
        a += len(B)
    nv = M.shape[0]
    m = int(rng.integers(13, nv + 1))  # independent rows (generically): dependent ones are the dense polish's
    W = np.zeros((nv, m))
    for j in range(m):  # each row touches two bodies' velocities, like a contact between two bodies
        cols = rng.choice(nv, 2, replace=False)
        W[cols, j] = rng.standard_normal(2)
    v0 = rng.standard_normal(nv) - 2.0 * np.linalg.solve(M, W @ np.ones(m))
    b = 0.1 * rng.standard_normal(m) if bounds else np.zeros(m)
    Minv = np.linalg.inv(M)
    res = qp.solve(M, W, v0, b=b, Minv=Minv)
    again = qp.solve(M, W, v0, b=b, Minv=Minv)
    ref = polish(W, v0, b, Minv)
    assert res.ok and res.polished and res.status == "PIQP_SOLVED" and ref is not None
    scale = 1.0 + np.abs(v0).max() + np.abs(res.lam).max() * np.abs(W).max()
    assert res.residual <= 1e-13 * scale
    np.testing.assert_allclose(res.v, ref[0], rtol=0, atol=1e-12 * scale)
    np.testing.assert_array_equal(res.v, again.v)
    np.testing.assert_array_equal(res.lam, again.lam)


def _sparse_path_only(monkeypatch):
    """Above SPARSE_ROWS rows, the warm-started active set (qp._polish on the dense matrices) made to fail: the
    sparse path, its fallback, answers (its own qp._polish on CSC matrices left as it is)."""
    polish = qp._polish
    monkeypatch.setattr(qp, "_polish", lambda W, *a: polish(W, *a) if qp._issparse(W) else None)


@pytest.mark.parametrize("e", [0.0, 0.9])
def test_a_resting_column_of_120_beads_takes_the_sparse_path_exactly(e, monkeypatch):
    """A column of 120 touching 1 kg beads (benchmarks.scaling.column) stepped from rest with the Python step, the
    sparse path's threshold lowered to 100 rows: every step's QP (120 rows) goes the sparse way, polished, and the
    column stays at rest with the closed-form percussions: contact k (under bead k) carries the 120 - k beads
    above it, P_k = (120 - k) m g h."""
    from benchmarks.scaling import column

    monkeypatch.setattr(qp, "SPARSE_ROWS", 100)
    monkeypatch.setattr(qp, "COLD_START_ROWS", 100)
    _sparse_path_only(monkeypatch)

    n = 120
    model = ms.build_model(column(n, step_impl="python").with_options(restitution=e))
    data = ms.make_data(model)
    h, g = model.options.dt, 9.81
    st = ms.initial_state(model)
    for _ in range(3):
        r = ms.step(model, data, st)
        assert r.qp.status == "PIQP_SOLVED" and r.qp.polished and r.contacts.m == n > qp.SPARSE_ROWS
        order = np.argsort(r.contacts.joint_a)  # contact k: bead k's joint (k + 1) over bead k - 1 or the ground
        np.testing.assert_allclose(r.P[order], (n - np.arange(n)) * g * h, rtol=1e-12, atol=0)
        assert np.abs(r.state.u).max() <= 1e-15 and np.abs(r.state.q - st.q).max() <= 1e-15
        st = r.state


def test_a_run_of_a_resting_column_of_120_beads_keeps_its_energy(monkeypatch):
    """simulate() through the sparse path (its threshold lowered to 100 rows), recorder and ledger included: a
    resting column gains no energy and its energy budget closes (translations under gravity: exact to round-off)."""
    from moreau_sim.testing import assert_budget_closes, assert_no_energy_gain

    from benchmarks.scaling import column

    monkeypatch.setattr(qp, "SPARSE_ROWS", 100)
    monkeypatch.setattr(qp, "COLD_START_ROWS", 100)
    _sparse_path_only(monkeypatch)

    model = ms.build_model(column(120, step_impl="python").with_options(duration=4e-3))
    traj = ms.simulate(model, progress=False)
    assert_no_energy_gain(traj, rtol=1e-12)
    assert_budget_closes(traj, rtol=1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_ordered_sums_in_index_order_at_any_size_and_alignment(seed):
    """sums.ordered, the one product of the step's stages: every entry is sum_k a_k x_k added left to right from
    the first product, one rounding each, then + 0.0 (a Python float loop is the reference), bit for bit, signs
    of zero included, whatever the size (numpy's own products change their order with it), wherever the arrays
    start in memory (misaligned views), and for sparse columns (summed over their nonzero entries only)."""
    rng = np.random.default_rng(seed)

    def ref(a, x):
        s = a[0] * x[0]
        for k in range(1, len(a)):
            s = s + a[k] * x[k]
        return s + 0.0

    def bits(v):
        return np.asarray(v, float).view(np.int64).tolist()

    for n in (1, 2, 3, 5, 16, 17, 40, 101):
        r, c = (int(rng.integers(1, 9)), int(rng.integers(1, 5))) if n < 40 else (64, 4)  # both ways of 2-d @ 2-d
        buf = rng.standard_normal(r * n + 1) * 10.0 ** rng.integers(-8, 8, r * n + 1)
        A = buf[1:].reshape(r, n)  # 8 bytes off the buffer's start
        A[:, 0] = -0.0  # -0.0 products first: a sum of zeros must come out +0.0
        x = rng.standard_normal(n + 1)[1:]
        for X in (np.asfortranarray(rng.standard_normal((n, c))),
                  np.where(rng.random((n, c)) < 0.9, 0.0, rng.standard_normal((n, c)))):  # dense, then sparse
            X[:, -1] = 0.0  # one column of zeros
            assert bits(sums.ordered(A, X)) == bits([[ref(a, X[:, j]) for j in range(c)] for a in A])
        assert bits(sums.ordered(A[0], x)) == bits(ref(A[0], x))
        assert bits(sums.ordered(A[0], X)) == bits([ref(A[0], X[:, j]) for j in range(c)])
        assert bits(sums.ordered(A, x)) == bits([ref(a, x) for a in A])
        assert bits(sums.ordered(np.zeros((r, 0)), np.zeros(0))) == bits([0.0] * r)


def _lu_reference(A, rhs):
    """Gaussian elimination with partial pivoting as docs/theory.md §2.8 states it, on Python floats by index."""
    n = len(rhs)
    a = [[float(v) for v in row] for row in A]
    x = [float(v) for v in rhs]
    for j in range(n):
        col = [abs(a[i][j]) for i in range(j, n)]
        if any(v != v for v in col):
            return None
        p = j + col.index(max(col))  # the first largest
        if a[p][j] == 0.0 or abs(a[p][j]) == float("inf"):
            return None
        a[j], a[p], x[j], x[p] = a[p], a[j], x[p], x[j]
        for i in range(j + 1, n):
            lo = a[i][j] / a[j][j]
            for k in range(j + 1, n):
                a[i][k] = a[i][k] - lo * a[j][k]
            x[i] = x[i] - lo * x[j]
    for j in range(n - 1, -1, -1):
        x[j] = x[j] / a[j][j]
        for i in range(j):
            x[i] = x[i] - a[i][j] * x[j]
    return x if all(abs(v) < float("inf") for v in x) else None


def lu_systems(seed):
    """Random systems of 1-40 unknowns as the active set makes them (G_AA of W'M^-1 W, symmetric, some nearly
    singular) and general ones (pivoting), with ties of |a_ij| in a column, a singular one and a NaN."""
    rng = np.random.default_rng(seed)
    for n in (1, 2, 3, 4, 5, 8, 11, 12, 13, 17, 25, 40):
        B = rng.standard_normal((n + 2, n)) * 10.0 ** rng.integers(-3, 3, n)
        yield B.T @ B, rng.standard_normal(n)  # SPD
        A = rng.standard_normal((n, n))
        if n > 2:
            A[2, 0] = -A[0, 0]  # a tie in the first column: the first of the two is the pivot
        yield A, rng.standard_normal(n)
    yield np.array([[1.0, 2.0], [2.0, 4.0]]), np.ones(2)  # singular: a zero pivot
    yield np.array([[1.0, 0.0], [np.nan, 1.0]]), np.ones(2)
    yield from sparse_lu_systems(rng)


def sparse_lu_systems(rng):
    """Clean sparse systems above qp.LU_CACHED_ROWS rows (qp._lu_solve_sparse, src/step.cpp sparse_lu_solve): a
    column's tridiagonal G_AA, a banded non-symmetric one, a scattered one and a scaled permutation (a row swap at
    every column), each with right-hand sides of signed zeros (-G_Ap: most entries -0.0) and a singular one."""
    n = 40
    T = np.diag(2.0 + rng.random(n)) - np.diag(rng.random(n - 1), 1)
    B = np.where(np.abs(np.subtract.outer(np.arange(n), np.arange(n))) <= 2,
                 rng.standard_normal((n, n)) * 10.0 ** rng.integers(-3, 3, (n, n)), 0.0) + 0.1 * np.eye(n)
    S = np.where(rng.random((n, n)) < 3.0 / n, rng.standard_normal((n, n)), 0.0) + np.diag(rng.standard_normal(n))
    P = np.zeros((n, n))
    P[np.arange(n), rng.permutation(n)] = rng.standard_normal(n)
    for A in (T + T.T, B, S, P):
        A = A + 0.0  # no -0.0 entry
        yield A, -np.where(rng.random(n) < 0.8, 0.0, rng.standard_normal(n))
        yield A, np.where(rng.random(n) < 0.5, np.where(rng.random(n) < 0.5, -0.0, 0.0), rng.standard_normal(n))
    P[:, 0] = 0.0
    yield P + 0.0, np.ones(n)  # singular: no pivot in column 0


@pytest.mark.parametrize("scalar_rows", [0, qp.LU_SCALAR, 100])
@pytest.mark.parametrize("seed", range(3))
def test_lu_solve_is_the_stated_elimination_bit_for_bit(seed, scalar_rows, monkeypatch):
    """qp._lu_solve, the solve of the active set (no LAPACK: dgesv's bits change with the CPU OpenBLAS finds), is
    the elimination of docs/theory.md §2.8 written out on Python floats, bit for bit, on its Python-float and
    its numpy paths alike (scalar_rows moves the switch between them), for a fresh matrix and for one whose
    factors it kept, and None where a pivot is zero or no number; and it solves: A x = rhs to round-off."""
    monkeypatch.setattr(qp, "LU_SCALAR", scalar_rows)
    monkeypatch.setattr(qp, "_factors", {})
    rng = np.random.default_rng(seed)
    for A, rhs in lu_systems(seed):
        for b in (rhs, rng.standard_normal(len(rhs))):  # the second: the kept factors
            x, ref = qp._lu_solve(A, b), _lu_reference(A, b)
            if ref is None:
                assert x is None
                continue
            assert x is not None and x.view(np.int64).tolist() == np.asarray(ref).view(np.int64).tolist()
            assert np.abs(A @ x - b).max() <= 1e-8 * (np.abs(A).max() * np.abs(x).max() + np.abs(b).max())


def _bits(v):
    return np.asarray(v, float).view(np.int64).tolist()


def _ordered_ref(A, X):
    """sums.ordered's statement on Python floats: each entry summed over every term in index order from the first,
    then + 0.0 (A 2-d; X 1-d or 2-d)."""
    def one(a, x):
        s = a[0] * x[0]
        for k in range(1, len(a)):
            s = s + a[k] * x[k]
        return s + 0.0
    A, X = np.asarray(A).tolist(), np.asarray(X)
    if X.ndim == 1:
        return [one(a, X.tolist()) for a in A]
    cols = X.T.tolist()
    return [[one(a, x) for x in cols] for a in A]


def _sparse(rng, n, k, per_row):
    """An (n, k) matrix with about per_row nonzeros a row over six decades, some stored entries -0.0 (a zero term
    either way), row 1 empty and row 2's two terms cancelling exactly."""
    A = np.where(rng.random((n, k)) < per_row / k, rng.standard_normal((n, k)) * 10.0 ** rng.integers(-3, 3, (n, k)),
                 0.0)
    A[rng.random((n, k)) < 0.5 / k] = -0.0
    A[1] = 0.0
    A[2] = 0.0
    A[2, :2] = 1.0
    return A


@pytest.mark.parametrize("seed", range(3))
def test_products_by_nonzeros_are_ordered_bit_for_bit(seed):
    """The products of the projection by their nonzeros (docs/theory.md §2.8) give sums.ordered's statement bit for
    bit, signed zeros included: nonzeros.Rows.dot and sums.ordered of a large sparse A @ x (sums.rows_dot: each row's
    nonzero terms, C- and F-ordered A, -0.0 entries, an empty row, a row that cancels to 0), nonzeros.product of two
    sparse matrices (M^-1 W, W'M^-1 W), and with a non-finite x or a dense A the dense sum (NaN where it has one)."""
    rng = np.random.default_rng(seed)
    n, k = 300, 260  # 78,000 entries: above sums.SPARSE_SIZE
    assert n * k >= sums.SPARSE_SIZE
    A = _sparse(rng, n, k, 3.0)
    x = rng.standard_normal(k)
    x[rng.random(k) < 0.2] = -0.0
    x[:2] = 1.0, -1.0  # row 2: 1 - 1 = +0
    for a in (A, np.asfortranarray(A), np.ascontiguousarray(A.T).T):
        assert _bits(sums.ordered(a, x)) == _bits(_ordered_ref(A, x))
        assert _bits(nonzeros.Rows.of(a).dot(x)) == _bits(_ordered_ref(A, x))
    R = nonzeros.Rows.of(A)
    assert _bits(R.row_dot(0, x)) == _bits(_ordered_ref(A[:1], x)[0])
    idx = np.flatnonzero(rng.random(k) < 0.5)
    pos = np.full(k, -1)
    pos[idx] = np.arange(idx.size)
    assert _bits(R.row_dot(0, x[idx], pos)) == _bits(_ordered_ref(A[:1, idx], x[idx])[0])
    B = _sparse(rng, k, 120, 2.0)
    assert _bits(nonzeros.product(R, nonzeros.Rows.of(B)).dense()) == _bits(_ordered_ref(A, B))
    assert _bits(nonzeros.product(nonzeros.Rows.of(A.T), R).dense()) == _bits(_ordered_ref(A.T, A))
    for bad in (np.inf, np.nan):  # the dense sum: inf * 0 = NaN where the dense one has it
        y = x.copy()
        y[5] = bad
        with np.errstate(invalid="ignore"):
            np.testing.assert_array_equal(sums.ordered(A, y), _ordered_ref(A, y))
            np.testing.assert_array_equal(R.dot(y), _ordered_ref(A, y))
    D = rng.standard_normal((n, k))  # dense: the accumulate, as before
    assert _bits(sums.ordered(D, x)) == _bits(_ordered_ref(D, x))


def test_sparse_factor_is_kept_for_the_next_right_hand_side():
    """nonzeros.lu_factor once, nonzeros.lu_apply on several right-hand sides (the active set's start, final and
    refinement solves on the same G_AA): the stated elimination's bits each time (test_qp._lu_reference), signed
    zeros of the right-hand side included (-rhs: every zero's sign flipped), None where it is singular."""
    rng = np.random.default_rng(7)
    for A, rhs in sparse_lu_systems(rng):
        r, c = np.nonzero(A)
        f = nonzeros.lu_factor(len(A), r, c, A[r, c])
        for b in (rhs, -rhs, rng.standard_normal(len(rhs)), rhs):
            x, ref = nonzeros.lu_apply(f, b), _lu_reference(A, b)
            assert (x is None) == (ref is None)
            if ref is not None:
                assert _bits(x) == _bits(ref)


def _polish_both(monkeypatch, W, v0, b, Minv, act=None):
    """qp._polish on the dense products (NONZERO_ROWS above m) and by the nonzeros (NONZERO_ROWS 0), checked
    equal bit for bit (None alike): the answer, the multipliers, the moves and the first pass's final set."""
    monkeypatch.setattr(qp, "NONZERO_ROWS", 10**9)
    ref = qp._polish(W, v0, b, Minv, act)
    monkeypatch.setattr(qp, "NONZERO_ROWS", 0)
    got = qp._polish(W, v0, b, Minv, act)
    assert (got is None) == (ref is None)
    if ref is not None:
        assert _bits(got[0]) == _bits(ref[0]) and _bits(got[1]) == _bits(ref[1])
        assert got[2] == ref[2] and got[3].tolist() == ref[3].tolist()
    return ref


@pytest.mark.parametrize("bounds", [False, True])
@pytest.mark.parametrize("dependent", [False, True])
def test_polish_by_nonzeros_is_the_dense_polish_bit_for_bit(dependent, bounds, monkeypatch):
    """qp._polish above NONZERO_ROWS (W'v, M^-1 W_A x, G and its solves by the nonzeros) against the dense polish, bit
    for bit, on the random problems of test_active_set_is_the_exact_projection (dependent rows: a face on a plane;
    shifted bounds; W and v0 with -0.0 entries), cold and warm-started from a guess, and None alike where it fails."""
    solved = 0
    for seed in range(40):
        M, W, v0, b = _random_qp(seed, dependent, bounds)
        W[np.abs(W) < 0.3] = -0.0
        v0[::3] = -0.0
        Minv = np.linalg.inv(M)
        for act in (None, np.arange(W.shape[1]) % 2 == 0):
            solved += _polish_both(monkeypatch, W, v0, b, Minv, act) is not None
    assert solved >= 40


@pytest.mark.parametrize("seed", range(4))
def test_polish_by_nonzeros_on_large_problems_is_the_dense_polish(seed, monkeypatch):
    """Above LU_CACHED_ROWS active rows, both kinds of G_AA solve: block-diagonal M (bodies on separate root joints)
    with rows on two bodies each (G_AA sparse: nonzeros.lu_factor, kept between solves) and a dense W (G_AA dense: the
    numpy elimination, kept alike), 40-90 rows, cold and from a start; a column of 400 beads from its own answer (no
    move) and from every row; and a non-finite M^-1 (the dense products): the dense polish's bits."""
    rng = np.random.default_rng(seed)
    blocks = [rng.standard_normal((k, k)) for k in rng.integers(1, 4, 40)]
    nv = sum(len(B) for B in blocks)
    M = np.zeros((nv, nv))
    a = 0
    for B in blocks:
        M[a:a + len(B), a:a + len(B)] = B @ B.T + len(B) * np.eye(len(B))
        a += len(B)
    m = int(rng.integers(40, min(nv, 90) + 1))
    W = np.zeros((nv, m))
    for j in range(m):
        W[rng.choice(nv, 2, replace=False), j] = rng.standard_normal(2)
    Minv = np.linalg.inv(M)
    v0 = rng.standard_normal(nv) - 2.0 * Minv @ (W @ np.ones(m))
    b = 0.1 * rng.standard_normal(m)
    for act in (None, rng.random(m) < 0.7):
        assert _polish_both(monkeypatch, W, v0, b, Minv, act) is not None
    Wd = rng.standard_normal((60, 45))
    Md = np.eye(60) + 0.1 * np.diag(rng.random(60))
    vd = -Wd @ np.ones(45)
    _polish_both(monkeypatch, Wd, vd, np.zeros(45), np.linalg.inv(Md))
    Mi = Minv.copy()
    Mi[0, 0] = np.inf
    with np.errstate(invalid="ignore"):  # inf * 0 in the dense products
        _polish_both(monkeypatch, W, v0, b, Mi)
    Mc, Wc, vc, _ = _column_problem(400)
    with monkeypatch.context() as mp:  # the moves on the dense elimination's bits (no Schur complement: test_schur.py)
        mp.setattr(schur, "SCHUR_MIN_ROWS", 10**9)
        ref = _polish_both(mp, Wc, vc, np.zeros(400), Mc)
        _polish_both(mp, Wc, vc, np.zeros(400), Mc, ref[3])
        _polish_both(mp, Wc, vc, np.zeros(400), Mc, np.ones(400, bool))
    got = qp._polish(Wc, vc, np.zeros(400), Mc)  # through the complement: the same set, v to round-off
    assert got[3].tolist() == ref[3].tolist() and np.abs(got[0] - ref[0]).max() <= 1e-12 * np.abs(ref[0]).max()


def _prefix_after(A, before, sel, rhs):
    """nonzeros.lu_factor of A[sel][:, sel] from its factor of A[before][:, before] (the prefix rule): (x, the steps
    taken from the first factor), x checked bit for bit against the stated elimination (None alike)."""
    def entries(s):
        B = A[np.ix_(s, s)]
        r, c = np.nonzero(B)
        return len(s), r, c, B[r, c]

    before, sel = np.asarray(before), np.asarray(sel)
    first = nonzeros.lu_factor(*entries(before))
    c, change = nonzeros.one_apart(before, sel)
    f = nonzeros.lu_factor(*entries(sel), *((first, c, change) if first is not None and change and c else ()))
    x, ref = nonzeros.lu_apply(f, rhs), _lu_reference(A[np.ix_(sel, sel)], rhs)
    assert (x is None) == (ref is None), (before, sel)
    assert ref is None or _bits(x) == _bits(ref), (before, sel)
    return x, 0 if f is None else f[-1]


def test_sparse_factor_prefix_is_kept_bit_for_bit():
    """nonzeros.lu_factor's first c steps taken from the factor of the rows with one added or dropped at sorted place
    c (the active set's consecutive solves; src/step.cpp band_lu_solve's rule), bit for bit against the stated
    elimination: the clean systems of lu_systems with a row added, a row dropped, and the rule at its edge (as
    test_compiled.test_band_solve_prefix_kept_is_bit_identical_to_qp): an added row whose |a_cj| equals the pivot's
    below the pivot row (kept) or above it (the first largest: the whole elimination), one ulp below (kept) and above
    (not), a dropped row that was a pivot row (not kept) and one that was not (kept)."""
    check_prefix_rule(_prefix_after)


def check_prefix_rule(after, same_rows: bool = False):
    """The factor prefix's rule (docs/theory.md §2.8) for after(A, before, sel, rhs) -> (x, the steps taken from the
    last factor), checking x itself (nonzeros.lu_factor's and src/step.cpp band_lu_solve's): the clean systems of
    lu_systems with a row added and a row dropped (same_rows: and the same rows again), at least 40 of them keeping
    a prefix; then at its edges: an added row tied with a pivot above or below it, one ulp either side, and a
    dropped row that was or was not a pivot row."""
    rng = np.random.default_rng(12)
    kept = 0
    for seed in range(6):
        for A, rhs in lu_systems(seed):
            if not (np.isfinite(A).all() and not (np.signbit(A) & (A == 0.0)).any()):
                continue
            n = A.shape[0]
            for _ in range(3):
                sel = np.flatnonzero(rng.random(n) < 0.7)
                if sel.size < 2:
                    continue
                drop = np.delete(sel, rng.integers(sel.size))
                for before, now in ((drop, sel), (sel, drop)) + (((sel, sel),) if same_rows else ()):
                    kept += after(A, before, now, rhs[now].copy())[1] > 0
    assert kept >= 40

    def tie(a21, pivot_above):
        # step 0: row 0 the pivot (a_20 = 0: the added row 2 unchanged by it); step 1: |a_11| = 2 (pivot_above: row 1
        # the pivot, above the added row) or |a_31| = 2 (row 3 the pivot, below it); the added row's a_21
        A = np.array([[4.0, 0.0, 1.0, 1.0, 0.5],
                      [1.0, 2.0 if pivot_above else 1.0, 3.0, 0.0, 1.0],
                      [0.0, a21, 5.0, 1.0, 0.0],
                      [1.0, 1.0 if pivot_above else 2.0, 0.0, 6.0, 2.0],
                      [0.0, 0.5, 1.0, 2.0, 7.0]])
        return after(A, [0, 1, 3, 4], [0, 1, 2, 3, 4], np.array([1.0, -0.0, 2.0, -0.0, 3.0]))[1]

    assert tie(2.0, True) == 2 and tie(-2.0, True) == 2  # the first largest stays the pivot row above
    assert tie(2.0, False) == 0 and tie(-2.0, False) == 0  # the added row is the first largest: a new pivot row
    assert tie(np.nextafter(2.0, 0.0), False) == 2 and tie(np.nextafter(2.0, 3.0), True) == 0
    B = np.array([[1.0, 2.0, 0.0, 1.0], [3.0, 1.0, 1.0, 0.0], [5.0, 0.0, 4.0, 1.0], [0.0, 1.0, 1.0, 3.0]])
    rhs = np.array([-0.0, 1.0, 2.0])
    assert after(B, [0, 1, 2, 3], [0, 1, 3], rhs)[1] == 0  # row 2 was step 0's pivot row
    assert after(B, [0, 1, 2, 3], [0, 2, 3], rhs)[1] == 1  # row 1 was not (step 0: row 2; the drop at c = 1)
