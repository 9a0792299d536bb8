"""Sums in a fixed order (docs/theory.md §2.8): each entry of a product summed in index order from its first
term, one rounding per product and per sum, then + 0.0, on every CPU and with any BLAS, as src/step.cpp sums
them. `ordered` is the product of matrices and vectors; `dot3` and `dots` are the same sums
of 3-vectors (the gaps' geometry), on Python floats and along the last axis of arrays."""

from __future__ import annotations

import numpy as np

SPARSE_SIZE = 1 << 16  # ordered(A, x) of an A with at least this many entries, at most 1 / SPARSE_FILL of them nonzero
SPARSE_FILL = 4  # (W'u of a few hundred contacts), and x finite: over A's nonzero terms only (rows_dot)


def nonzero(A: np.ndarray):
    """np.nonzero(A) of a 2-d A (rows, then columns ascending; a NaN counts), from a mask of A in its memory order
    (np.nonzero on the floats costs ~15x more; a transposed A: its columns' entries sorted by rows)."""
    if A.flags.c_contiguous:
        return np.divmod(np.flatnonzero(A != 0.0), max(A.shape[1], 1))
    if A.flags.f_contiguous:
        c, r = np.divmod(np.flatnonzero(A.T != 0.0), max(A.shape[0], 1))
        order = np.argsort(r, kind="stable")
        return r[order], c[order]
    return np.nonzero(A)


def padded(n: int, r: np.ndarray, c: np.ndarray, v: np.ndarray):
    """The (n, k) matrix with entries v at (r, c) (by rows, columns ascending) as (K, n) arrays of its rows' t-th
    entries' columns and values, padded with column 0 and value 0.0 (rows_dot's layout)."""
    cnt = np.bincount(r, minlength=n)
    t = np.arange(r.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    k = int(cnt.max(initial=0))
    cols, vals = np.zeros((k, n), np.intp), np.zeros((k, n))
    cols[t, r], vals[t, r] = c, v
    return cols, vals


def rows_dot(n: int, r: np.ndarray, c: np.ndarray, v: np.ndarray, x: np.ndarray, layout=None) -> np.ndarray:
    """ordered(A, x) for a finite x and the (n, k) matrix A with entries v at (r, c) (by rows, columns ascending) and
    +-0 elsewhere: each row's terms in column order, as padded passes of the rows' t-th terms (a padding term
    0 * x_0 = +-0 after a row's last one; the + 0.0 settles a zero sum's sign, ordered's docstring). layout:
    padded(n, r, c, v) where the caller keeps it."""
    cols, vals = padded(n, r, c, v) if layout is None else layout
    if not len(cols):
        return np.zeros(n)
    out = vals[0] * x[cols[0]]
    for t in range(1, len(cols)):
        out += vals[t] * x[cols[t]]
    return out + 0.0


def dot3(a: np.ndarray, b: np.ndarray) -> float:
    """a'b of two 3-vectors as `ordered` sums it, ((a0 b0 + a1 b1) + a2 b2) + 0.0, on Python floats (cheaper
    than numpy's per-call cost on 3 entries)."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return a0 * b0 + a1 * b1 + a2 * b2 + 0.0


def dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """sum_e a[..., e] b[..., e] over a last axis of 3 entries (broadcasting) as `ordered` sums it: row-wise
    dot products, R @ x as dots(R, x), the rows of X @ R.T as dots(X[:, None], R)."""
    if b.ndim == 1 and a.shape == (3, 3):  # R x: on Python floats (the same operations, cheaper)
        (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = a.tolist()
        b0, b1, b2 = b.tolist()
        return np.array([a00 * b0 + a01 * b1 + a02 * b2 + 0.0, a10 * b0 + a11 * b1 + a12 * b2 + 0.0,
                         a20 * b0 + a21 * b1 + a22 * b2 + 0.0])
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2] + 0.0


def ordered(A, x):
    """A @ x (A 1-d or 2-d, x 1-d or 2-d) summed over the inner index in order from its first product, one
    rounding per product and per sum (no BLAS kernel, no FMA), then + 0.0: the same bits on every CPU, at
    every size and memory alignment, and the same as src/step.cpp's odot / omatmul. The one product of the
    step's stages (stepper, law, constraints, qp), of the ledger (ledger.impact_terms) and of the event rules
    and their gaps (event_rules, gaps, box_gaps, kinematics): numpy's
    own products follow OpenBLAS's kernels, whose order changes with the size, the machine and the arrays'
    alignment (docs/theory.md §2.8).
    np.add.accumulate adds in index order by definition (reductions need not). The final + 0.0 turns a -0.0
    into +0.0 and changes nothing else; after it, leaving out products that are exact zeros (A finite, x_k = 0)
    cannot change a bit, as adding a signed zero changes at most the sign of a zero sum: the large 2-d
    products use that, summing over the nonzero entries of each column of x (the sparse rows W)."""
    n = A.shape[-1]
    if n == 0 or n != x.shape[0]:
        return np.matmul(A, x) + 0.0  # empty sums are zeros (mismatched shapes: numpy's error)
    if n <= 4 and (A.ndim == 2 or x.ndim == 2):  # a few terms (3-vectors): one elementwise pass per term
        cols = [A[:, t, None] for t in range(n)] if A.ndim == 2 and x.ndim == 2 else [A[..., t] for t in range(n)]
        out = cols[0] * x[0]
        for t in range(1, n):
            out = out + cols[t] * x[t]
        return out + 0.0
    if A.ndim == 1:
        return np.add.accumulate(A * x)[-1] + 0.0 if x.ndim == 1 else ordered(A[None], x)[0]
    if x.ndim == 1:
        if A.size >= SPARSE_SIZE and np.isfinite(x).all():  # a large A: its rows' nonzero terms (W'u) where few
            r, c = nonzero(A)
            if SPARSE_FILL * r.size <= A.size:
                return rows_dot(A.shape[0], r, c, A[r, c], x)
        if A.shape[0] >= 16 * n and A.size > 4096:  # many short sums (the features' gamma = W'u): a pass per term
            out = A[:, 0] * x[0]
            for t in range(1, n):
                out += A[:, t] * x[t]
            return out + 0.0
        return np.add.accumulate(A * x, axis=1)[:, -1] + 0.0
    if A.shape[0] * n * x.shape[1] <= 4096:
        return np.add.accumulate(A[:, :, None] * x[None, :, :], axis=1)[:, -1, :] + 0.0
    nz = x != 0.0
    k = int(nz.sum(axis=0).max())
    if 2 * k <= n and np.isfinite(A).all():  # sparse columns: their nonzero rows in order, then zeros
        rows = np.argsort(~nz, axis=0, kind="stable")[:max(k, 1)]  # (k, cols): a stable sort keeps the order
        vals = np.take_along_axis(x, rows, axis=0)
        out = A[:, rows[0]] * vals[0]
        for t in range(1, k):
            out += A[:, rows[t]] * vals[t]
        return out + 0.0
    out = A[:, 0, None] * x[0]  # dense and large: one pass per inner index (no (rows, n, cols) temporary)
    for t in range(1, n):
        out += A[:, t, None] * x[t]
    return out + 0.0
