"""The active set's solves G_AA x = y on a large contact-space G by a factored base set and a Schur complement
(docs/theory.md §1.3, "Moves by a Schur complement"): where A is the base set B (its factor made by
nonzeros.lu_factor) with the rows P added and the rows D dropped, |P| + |D| <= SCHUR_ROWS, x comes from B's factor
and a dense (|P| + |D|)-square system; else A is factored and becomes the base. src/step.cpp schur_solve makes the
same operations in the same order (docs/theory.md §2.8)."""

from __future__ import annotations

import threading

import numpy as np

from . import nonzeros

SCHUR_MIN_ROWS = 32  # sets of more rows than this (qp.LU_CACHED_ROWS) are solved here, on a G ...
SCHUR_G_ROWS = 200  # ... of more rows than this (qp.NONZERO_ROWS; src/step.cpp kWideRows) ...
WIDE_ROW = 64  # ... with at most this many nonzeros a row on average (src/step.cpp kWideRow: its sparse G)
SCHUR_ROWS = 40  # at most this many rows added to the base set and dropped from it; more: A becomes the base

_held = threading.local()  # the base of this thread: (G, its rows B ascending, pos: a row's place in B or -1, B's
# factor, the columns z = G_BB^-1 c of the rows added and dropped so far, by (row, added)); one G at a time, as
# src/step.cpp's thread_local SchurCache


def applies(G: nonzeros.Contact, k: int) -> bool:
    """Whether a solve of k rows of G goes here (G: qp._by_nonzeros's, above qp.NONZERO_ROWS rows; not in retried's
    second try)."""
    m = G.shape[0]
    wide = G.rows.val.size > WIDE_ROW * m
    return k > SCHUR_MIN_ROWS and m > SCHUR_G_ROWS and not wide and not getattr(_held, "off", False)


def retried(polish, *args):
    """polish(*args) (qp._polish: None where it has no answer), and where it has none after solves here, once more
    with direct factors alone: the complement's moves carry the base's conditioning, and on near-dependent rows
    (a settled pile's face corners) they can end on a set that the final solve rejects, where the direct moves
    find the answer (src/step.cpp project: the same retry)."""
    _held.used = False
    p = polish(*args)
    if p is None and _held.used:
        _held.off = True
        try:
            p = polish(*args)
        finally:
            _held.off = False
    return p


def solve(G: nonzeros.Contact, idx: np.ndarray, rhs: np.ndarray, dense_solve, fresh: bool = False) -> np.ndarray | None:
    """x = G_AA^-1 rhs (A = idx, ascending), or None where a factor or the complement is singular or x not finite.
    dense_solve: qp._lu_solve (the complement's solve); fresh: A becomes the base (the final solve of a projection:
    its multipliers on A's own factor, as accurate as G_AA allows, where the complement's carry G_BB's conditioning)."""
    _held.used = True
    base = getattr(_held, "base", None)
    if base is not None and (base[0] is not G or (fresh and not np.array_equal(base[1], idx))):
        base = None  # (fresh: A's own factor; the base's where A is it)
    if base is not None:
        pos = base[2]
        inB = pos[idx] >= 0
        P = idx[~inB]
        kept = np.zeros(G.shape[0], bool)
        kept[idx] = True
        D = base[1][~kept[base[1]]]
        if P.size + D.size > SCHUR_ROWS:
            base = None
    if base is None:  # A becomes the base: factored
        pos = np.full(G.shape[0], -1)
        pos[idx] = np.arange(idx.size)
        rows, cols, vals = G.rows.sub(idx, pos)
        f = nonzeros.lu_factor(idx.size, rows, cols, vals)
        _held.base = None if f is None else (G, idx.copy(), pos, f, {})
        return None if f is None else nonzeros.lu_apply(f, rhs)
    _, B, pos, f, cols = base
    if not P.size and not D.size:
        return nonzeros.lu_apply(f, rhs)
    yB = np.zeros(B.size)
    yB[pos[idx[inB]]] = rhs[inB]
    w = nonzeros.lu_apply(f, yB)
    if w is None:
        return None
    extra = [(int(p), True) for p in P] + [(int(d), False) for d in D]
    Z = []
    for key in extra:  # z = G_BB^-1 G_Bp (added p) or G_BB^-1 e_d (dropped d), made once per base
        z = cols.get(key)
        if z is None:
            if key[1]:
                c = G.column(key[0])[B]
            else:
                c = np.zeros(B.size)
                c[pos[key[0]]] = 1.0
            z = nonzeros.lu_apply(f, c)
            if z is None:
                return None
            cols[key] = z
        Z.append(z)
    n, nP = len(extra), P.size
    S, t = np.empty((n, n)), np.empty(n)
    y = rhs[~inB]
    for i, (a, added) in enumerate(extra):
        if added:  # row a: G_aB x_B + G_aP x_P = y_a
            for j, z in enumerate(Z):
                d = G.rows.row_dot(a, z, pos)
                S[i, j] = _entry(G, a, extra[j][0]) - d if j < nP else -d
            t[i] = y[i] - G.rows.row_dot(a, w, pos)
        else:  # row a held at 0
            pa = pos[a]
            for j, z in enumerate(Z):
                S[i, j] = -z[pa]
            t[i] = -w[pa]
    s = dense_solve(S, t)
    if s is None:
        return None
    xB = w
    for j, z in enumerate(Z):
        xB = xB - z * s[j]
    x = np.empty(idx.size)
    x[inB] = xB[pos[idx[inB]]]
    x[~inB] = s[:nP]
    return x if np.isfinite(x).all() else None


def _entry(G: nonzeros.Contact, a: int, b: int) -> float:
    """G_ab (+0.0 where not stored)."""
    lo, hi = G.rows.ptr[a], G.rows.ptr[a + 1]
    k = lo + int(np.searchsorted(G.rows.col[lo:hi], b))
    return float(G.rows.val[k]) if k < hi and G.rows.col[k] == b else 0.0
