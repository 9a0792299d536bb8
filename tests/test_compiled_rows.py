"""The projection above the former row limit of 100 (issue 24): the cold dual active set up to qp.COLD_START_ROWS
(200) rows in both steps, its solves on the nonzeros of G_AA (src/step.cpp sparse_lu_solve,
qp._lu_solve_sparse) with the dense elimination's bits, signed zeros included (docs/theory.md §1.3, §2.8). A column
of N touching beads (benchmarks.scaling.column, N rows, 100 < N < 200) is stepped by the compiled step on
every step and gives the Python step's bits, with the law's closed forms: at rest the percussion under bead k
carries the N - k beads above it; a top bead hitting the resting column leaves with e times its speed while the
column stays at rest (the projection of u- onto the column's cone is 0: the ground takes the blow)."""

from __future__ import annotations

import numpy as np
import pytest

import moreau_sim as ms
import moreau_sim.compiled as compiled
from moreau_sim import qp
from moreau_sim.data import make_data

# rows: above the former limit of 100, and 199, the largest column whose pairs are listed (model.LAZY_PAIRS = 20,000;
# a column of 200 beads is handed back for its unlisted pairs, not its rows)
SIZES = (150, 199)


@pytest.fixture(scope="module", autouse=True)
def _compiled():
    assert compiled.available(), compiled.unavailable_reason()


def _column(n: int, **options) -> ms.Scene:
    from benchmarks.scaling import column

    return column(n).with_options(**options)


def _steps(sc: ms.Scene, k: int):
    """k steps of `sc` from its initial state with each step: ([python StepResults], [compiled ...], counts)."""
    out = {}
    for impl in ("python", "compiled"):
        model = ms.build_model(sc.with_options(step_impl=impl))
        data = make_data(model)
        st, rs = ms.initial_state(model, data), []
        for _ in range(k):
            r = ms.step(model, data, st)
            rs.append(r)
            st = r.state
        out[impl] = (rs, compiled.counts(data), model)
    return out


def _bits(x) -> list:
    return np.ascontiguousarray(x, float).view(np.int64).tolist()


@pytest.mark.parametrize("N", SIZES)
@pytest.mark.parametrize("e", [0.0, 0.9])
def test_a_resting_column_above_100_rows_is_compiled_exact_and_bit_identical(e, N):
    """N touching 1 kg beads from rest: every step's N-row QP taken by the compiled step (the cold active set,
    no hand-back), the same bits as the Python step, the column at rest and P_k = (N - k) m g h."""
    got = _steps(_column(N, restitution=e), 3)
    (ref, _, model), (new, counts, _) = got["python"], got["compiled"]
    assert N <= qp.COLD_START_ROWS and set(counts) == {"contact"} and counts["contact"] == 3
    h, g = model.options.dt, 9.81
    for a, b in zip(ref, new):
        assert a.contacts.m == b.contacts.m == N and a.qp.status == b.qp.status == "ACTIVE_SET"
        for x, y in ((a.state.q, b.state.q), (a.state.u, b.state.u), (a.P, b.P)):
            assert _bits(x) == _bits(y)
        order = np.argsort(b.contacts.joint_a)  # contact k: under bead k
        np.testing.assert_allclose(b.P[order], (N - np.arange(N)) * g * h, rtol=1e-12, atol=0)
        assert np.abs(b.state.u).max() <= 1e-15


def _hit(n: int, V: float, e: float) -> ms.Scene:
    """benchmarks.scaling.column's n touching beads, the top one moving down at V [m/s]."""
    from benchmarks.scaling import REPO

    b = ms.SceneBuilder(f"column_hit_{n}", folder=REPO / "scenes", restitution=e, dt=5e-4, duration=0.01)
    for k in range(n):
        b.add_body(f"bead{k}", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1), q0=[0.1 + 0.2 * k],
                   u0=[-V if k == n - 1 else 0.0])
    b.add_halfspace("ground")
    return b.build()


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_a_bead_hitting_a_resting_column_leaves_with_e_times_its_speed(e):
    """The top bead of N = 150 touching beads moving down at V onto the resting column: the projection of u- onto
    {u_0 >= 0, u_k >= u_(k-1)} (M diagonal, equal masses) is 0, so the column keeps u = 0 and the top bead leaves
    at e times its approach; kinetic energy e^2 T-; both steps bit for bit, all compiled."""
    N, V = SIZES[0], 1.0
    got = _steps(_hit(N, V, e), 1)
    (ref, _, _), (new, counts, _) = got["python"], got["compiled"]
    assert set(counts) == {"contact"}
    a, b = ref[0], new[0]
    assert b.contacts.m == N
    for x, y in ((a.state.q, b.state.q), (a.state.u, b.state.u), (a.P, b.P)):
        assert _bits(x) == _bits(y)
    u = b.state.u
    assert abs(u[-1] - e * V) <= 1e-12 * V and np.abs(u[:-1]).max() <= 1e-15
    assert 0.5 * u @ u <= 0.5 * V ** 2 * (e ** 2 + 1e-12)
