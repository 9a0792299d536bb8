"""The active set's solves by a factored base set and a Schur complement (moreau_sim/schur.py, src/step.cpp
schur_solve; docs/theory.md §1.3, "Moves by a Schur complement"): the solve against the direct one on G_AA, the base
kept while at most SCHUR_ROWS rows are added to it and dropped from it and made again past that, and the compiled
projection bit for bit with qp.solve where its moves go through it."""

import numpy as np
import pytest

from moreau_sim import compiled, qp, schur

from helpers import pile_projection


def _contact(seed: int, m: int = 300):
    """A pile-like G = W'M^-1 W of m rows by its nonzeros (qp._by_nonzeros), and W of full column rank."""
    M, W, v0, b, Minv = pile_projection(seed, m // 2, m)
    return qp._by_nonzeros(W, Minv)[2]


def _base():
    held = getattr(schur._held, "base", None)
    return None if held is None else held[1]


@pytest.mark.parametrize("seed", range(4))
def test_a_solve_on_the_base_and_its_complement_is_the_direct_solve(seed):
    """From a base B of 120 rows: sets with 1 to SCHUR_ROWS rows added and dropped solve G_AA x = y to 1e-10 of the
    direct solve (numpy's, relative to max|x|), B kept; one row more makes that set the base; a fresh solve (a
    projection's final one) makes its set the base and gives the dense elimination's bits (qp._lu_solve), on the base's
    own factor where its set is the base."""
    rng = np.random.default_rng(seed)
    G = _contact(seed)
    Gd = G.rows.dense()
    m = G.shape[0]
    schur._held.base = None
    B = np.sort(rng.choice(m, 120, replace=False))
    rhs = rng.standard_normal(B.size)
    x = schur.solve(G, B, rhs, qp._lu_solve)
    assert np.abs(x - np.linalg.solve(Gd[np.ix_(B, B)], rhs)).max() <= 1e-10 * np.abs(x).max()
    outside = np.setdiff1d(np.arange(m), B)
    for n in (1, 2, 7, 20, schur.SCHUR_ROWS, schur.SCHUR_ROWS + 1):
        added = int(rng.integers(0, n + 1))
        A = np.sort(np.concatenate([np.setdiff1d(B, rng.choice(B, n - added, replace=False)),
                                    rng.choice(outside, added, replace=False)]))
        y = rng.standard_normal(A.size)
        x = schur.solve(G, A, y, qp._lu_solve)
        ref = np.linalg.solve(Gd[np.ix_(A, A)], y)
        assert np.abs(x - ref).max() <= 1e-10 * np.abs(ref).max(), n
        assert np.array_equal(_base(), B if n <= schur.SCHUR_ROWS else A), n
        B = _base()
    A = np.sort(np.concatenate([B[1:], np.setdiff1d(np.arange(m), B)[:1]]))  # fresh: A's own factor, the base
    y = rng.standard_normal(A.size)
    x = schur.solve(G, A, y, qp._lu_solve, fresh=True)
    assert np.array_equal(_base(), A)
    assert x.view(np.int64).tolist() == qp._lu_solve(Gd[np.ix_(A, A)], y).view(np.int64).tolist()  # its bits
    held = schur._held.base
    x2 = schur.solve(G, A, y, qp._lu_solve, fresh=True)  # A is the base: its factor, not made again
    assert schur._held.base is held and x2.view(np.int64).tolist() == x.view(np.int64).tolist()
    schur._held.base = None


def test_another_g_makes_its_own_base():
    schur._held.base = None
    G1, G2 = _contact(0), _contact(1)
    A = np.arange(40, 80)
    rhs = np.ones(A.size)
    schur.solve(G1, A, rhs, qp._lu_solve)
    assert schur._held.base[0] is G1
    x = schur.solve(G2, A, rhs, qp._lu_solve)
    assert schur._held.base[0] is G2
    assert np.abs(x - np.linalg.solve(G2.rows.dense()[np.ix_(A, A)], rhs)).max() <= 1e-10 * np.abs(x).max()
    schur._held.base = None


def test_applies_above_schur_min_rows_only():
    G = _contact(0)
    assert not schur.applies(G, schur.SCHUR_MIN_ROWS) and schur.applies(G, schur.SCHUR_MIN_ROWS + 1)


@pytest.mark.parametrize("m", [240, 480, 800])
def test_the_compiled_projection_through_the_complement_is_qp_solve_bit_for_bit(m, monkeypatch):
    """Pile-like projections of 240-800 rows from nothing: their active sets grow past SCHUR_MIN_ROWS rows, move
    through the complement and make new bases. The compiled projection gives qp.solve's v and multipliers bit for bit,
    and the answer meets the law (KKT) to round-off."""
    assert compiled.available(), compiled.unavailable_reason()
    calls = {"complement": 0, "base": 0}
    solve = schur.solve

    def counted(G, idx, rhs, dense_solve, fresh=False):
        before = _base()
        x = solve(G, idx, rhs, dense_solve, fresh)
        after = _base()
        made = after is not None and (before is None or after is not before)
        calls["base" if made else "complement"] += 1
        return x

    monkeypatch.setattr(schur, "solve", counted)
    for seed in range(2):
        M, W, v0, b, Minv = pile_projection(seed, m // 4, m)
        schur._held.base = None
        ref = qp.solve(M, W, v0, b=b, Minv=Minv)
        status, v, lam = compiled._module.project(W, v0, b, Minv, compiled.CONSTANTS)
        assert status is not None and ref.status == status.name == "ACTIVE_SET", (seed, ref.status)
        assert v.view(np.int64).tolist() == ref.v.view(np.int64).tolist(), seed
        assert lam.view(np.int64).tolist() == ref.lam.view(np.int64).tolist(), seed
        assert ref.residual <= 1e-10 * (1.0 + np.abs(v0).max()) * max(1.0, np.abs(ref.lam).max())
    assert calls["complement"] > 10 * calls["base"] > 0, calls


def test_a_polish_without_an_answer_after_the_complement_is_tried_once_more_with_direct_factors(monkeypatch):
    """schur.retried: where the moves through the complement end without an answer (here every complement's solve
    made to fail), the projection is the one by direct factors alone, bit for bit; with an answer, one try only."""
    M, W, v0, b, Minv = pile_projection(0, 120, 480)
    with monkeypatch.context() as mp:
        mp.setattr(schur, "SCHUR_MIN_ROWS", 10**9)
        direct = qp.solve(M, W, v0, b=b, Minv=Minv)
    tries = []
    polish = qp._polish
    monkeypatch.setattr(qp, "_polish", lambda *a: tries.append(1) or polish(*a))
    qp.solve(M, W, v0, b=b, Minv=Minv)
    assert len(tries) == 1
    solve = schur.solve
    monkeypatch.setattr(schur, "solve", lambda G, idx, rhs, dense, fresh=False: None if fresh else solve(
        G, idx, rhs, dense, fresh))
    tries.clear()
    got = qp.solve(M, W, v0, b=b, Minv=Minv)
    assert len(tries) == 2 and got.status == direct.status == "ACTIVE_SET"
    assert got.v.view(np.int64).tolist() == direct.v.view(np.int64).tolist()
    assert got.lam.view(np.int64).tolist() == direct.lam.view(np.int64).tolist()
    assert not getattr(schur._held, "off", False)
