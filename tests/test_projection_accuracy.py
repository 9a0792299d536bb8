"""The projection's accuracy under heavy loads (docs/theory.md §2.11, "The projection's round-off"): the velocity
projections of a resting stack of cubes with mass ratios up to 1e5 against the same QPs solved exactly (rational
arithmetic, Goldfarb and Idnani's dual active set on the float data as given), and the stacks' rest over long runs
(every cube within 1e-6 m of its start, T + V never above its start by more than 1e-9 E0), over e and h: the
projections of the Python step, the rest of the compiled one (the two steps give the same bits,
tests/test_compiled*.py)."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from test_stack_family import stack

import moreau_sim as ms
from moreau_sim import qp

HEAVY = [1.0, 1e3, 1.0, 1e5]  # the traced draw of §2.11: a 1 kg cube under a 1e5 kg one, on a 1e3 kg one
FIVE = [1e4, 1.0, 100.0, 1e5, 1e4]  # the family's draw that crept 2.3e-6 m in 6 s (§2.11)


def _exact(W, v0, b, Minv):
    """argmin 1/2 (v - v0)'M(v - v0) s.t. W'v >= b with M^-1 = Minv, in exact arithmetic on the given floats:
    the dual active set from nothing (every step exact, so no tolerance), v = v0 + M^-1 W lam as floats. On integers
    (the floats' exact values times powers of two), G_AA's solves by Bareiss's fraction-free elimination."""
    nv, m = W.shape
    # on integers: each array as n 2^-e (e common to its entries); G and r scaled by one power of two 2^K, which
    # leaves the QP's lam unchanged (its every condition is homogeneous in (G, r))
    (Wi, a), (Mii, c), (v0i, d), (bi, f) = (_integers(x) for x in (W, Minv, v0, b))
    MiWi = [[sum(Mii[i][k] * Wi[k][j] for k in range(nv) if Mii[i][k] and Wi[k][j]) for j in range(m)]
            for i in range(nv)]  # M^-1 W 2^(a + c)
    K = max(2 * a + c, a + d, f)
    G = [[sum(Wi[k][i] * MiWi[k][j] for k in range(nv)) << (K - 2 * a - c) for j in range(m)] for i in range(m)]
    r = [Fraction((bi[i] << (K - f)) - (sum(Wi[k][i] * v0i[k] for k in range(nv)) << (K - a - d))) for i in range(m)]
    MiW = [[Fraction(x, 1 << (a + c)) for x in row] for row in MiWi]
    v0f = [Fraction(x, 1 << d) for x in v0i]
    lam, act = [Fraction(0)] * m, []

    def solve(A, y):  # A x = y on integers: Bareiss's fraction-free elimination, then back-substitution
        n = len(A)
        a = [[int(x) for x in row] + [int(y[i])] for i, row in enumerate(A)]
        prev = 1
        for j in range(n):
            p = next((i for i in range(j, n) if a[i][j]), None)
            if p is None:
                return None
            a[j], a[p] = a[p], a[j]
            for i in range(j + 1, n):
                a[i] = [0] * (j + 1) + [(a[i][k] * a[j][j] - a[i][j] * a[j][k]) // prev for k in range(j + 1, n + 1)]
            prev = a[j][j]
        x = [Fraction(0)] * n
        for j in range(n - 1, -1, -1):
            x[j] = (Fraction(a[j][n]) - sum(a[j][k] * x[k] for k in range(j + 1, n))) / a[j][j]
        return x

    for _ in range(10 * m + 10):
        s = [sum(G[i][j] * lam[j] for j in range(m) if lam[j]) - r[i] for i in range(m)]
        viol = [(s[i], i) for i in range(m) if i not in act and s[i] < 0]
        if not viol:
            v = [v0f[i] + sum(MiW[i][j] * lam[j] for j in act) for i in range(nv)]
            return np.array([float(x) for x in v])
        p = min(viol)[1]
        while True:  # add p, dropping the rows whose multipliers reach zero first
            d = solve([[G[i][j] for j in act] for i in act], [-G[i][p] for i in act]) if act else []
            assert d is not None, "G_AA is singular"
            z = G[p][p] + sum(G[p][j] * dj for j, dj in zip(act, d))
            sp = sum(G[p][j] * lam[j] for j in range(m) if lam[j]) - r[p]
            t1 = -sp / z if z > 0 else None
            drops = [(lam[j] / -dj, j) for j, dj in zip(act, d) if dj < 0]
            t2, k = min(drops) if drops else (None, None)
            t = t1 if t2 is None or (t1 is not None and t1 <= t2) else t2
            assert t is not None, "the rows cannot all be met"
            for j, dj in zip(act, d):
                lam[j] += t * dj
            lam[p] += t
            if t is t1:
                act = sorted(act + [p])
                break
            lam[k] = Fraction(0)
            act.remove(k)
    raise AssertionError("the exact active set did not settle")


def _integers(x) -> tuple[list, int]:
    """A float array's entries exactly as integers n times a common 2^-e: (the integers, nested as x is; e >= 0)."""
    x = np.asarray(x, float)
    ratios = [v.as_integer_ratio() for v in x.ravel().tolist()]  # (n, 2^k)
    e = max(den.bit_length() - 1 for _, den in ratios) if ratios else 0
    ints = [num << (e - den.bit_length() + 1) for num, den in ratios]
    return (np.array(ints, dtype=object).reshape(x.shape).tolist(), e)


def _projections(monkeypatch, masses, h, e, duration):
    """The step's velocity projections (W, v0, b, M^-1, v) solved by the active set in a run of the Python step."""
    seen = []
    solve = qp.solve

    def recording(M, W, v0, **kw):
        res = solve(M, W, v0, **kw)
        if res.status == "ACTIVE_SET" and W.shape[1] > 1 and np.any(v0):
            seen.append((W, v0, np.zeros(W.shape[1]) if kw.get("b") is None else kw["b"], kw["Minv"], res.v))
        return res

    monkeypatch.setattr(qp, "solve", recording)  # records qp.solve's inputs and answers; piqp and all run as ever
    ms.run(stack(masses, h, e, "time-stepping"), duration=duration, step_impl="python")
    return seen


@pytest.mark.slow
@pytest.mark.parametrize("h", [1e-3, 1e-2])
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_the_projection_of_a_heavy_stack_is_the_exact_one(monkeypatch, e, h):
    """Each projection of the first 0.1 s within 1e-12 m/s (rad/s) of the exact one: the light cube carries
    2.5e3 N s, so a multiplier's round-off (~1e-6 N s) alone would move it by 1e-6 m/s."""
    seen = _projections(monkeypatch, HEAVY, h, e, 0.1)
    assert seen
    for W, v0, b, Minv, v in seen[:: max(1, len(seen) // 12)]:
        assert np.abs(v - _exact(W, v0, b, Minv)).max() <= 1e-12


@pytest.mark.slow
@pytest.mark.parametrize("h", [1e-3, 1e-2])
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_a_heavy_stack_rests_to_round_off(e, h):
    """2 s of rest of five cubes (1e4, 1, 100, 1e5, 1e4 kg, bottom to top; 2.65 m at 4 s before the normals' fixes
    of §6.2; at (e, h) = (0.5, 1e-2) and (1, 1e-3) it crept 1.3e-6 m in 2 s before the one-face vertex normal):
    every cube within the family's 1e-6 m of its start, T + V never above its start by more than 1e-9 E0.
    (The heavier draw HEAVY is left out: at h = 1e-2 which of its orders holds is decided at round-off, §2.11.)"""
    tr = ms.run(stack(FIVE, h, e, "time-stepping"), duration=2.0)
    q = tr.q.reshape(len(tr.t), len(FIVE), 7)
    assert float(np.abs(q[:, :, :3] - q[0, :, :3]).max()) <= 1e-6
    E = tr.total_energy
    assert float((E - E[0]).max()) <= 1e-9 * abs(E[0])
