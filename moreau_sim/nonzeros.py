"""The projection's matrices by their nonzero entries (qp._polish above qp.NONZERO_ROWS rows; docs/theory.md §2.8):
W, M^-1, M^-1 W and G = W'M^-1 W as `Rows`, their products with `sums.ordered`'s bits over the nonzero terms only,
G_AA's entries without a dense copy, and qp._lu_solve's elimination on a clean matrix's nonzeros, its factor kept
apart from the right-hand side (the active set's start, its final solve and the refinement solve the same G_AA).

Why the bits are `ordered`'s: each entry is summed over its terms in index order from the first, one rounding per
product and per sum, then + 0.0; a term with a zero factor (the other factor finite) is +-0, and adding a signed
zero changes at most the sign of a zero sum, which the final + 0.0 settles, so leaving such terms out (or adding
+-0 terms at the end of a sum) changes no bit (sums.ordered's docstring). src/step.cpp sums the same way
(contact_space, GInfo, row_dot)."""

from __future__ import annotations

import math

import numpy as np

from .sums import nonzero, ordered, padded, rows_dot


class Rows:
    """A matrix of `shape` by the nonzero entries of its rows: ptr (n + 1,), col and val (each row's columns
    ascending). dot(x) is sums.ordered(A, x) bit for bit (x finite: over the nonzero terms; else on the dense A)."""

    __slots__ = ("shape", "ptr", "col", "val", "_layout")

    def __init__(self, shape, ptr, col, val):
        self.shape, self.ptr, self.col, self.val = (int(shape[0]), int(shape[1])), ptr, col, val
        self._layout = None

    @classmethod
    def of(cls, A: np.ndarray) -> Rows:
        """A dense matrix's nonzero entries (a NaN counts as nonzero)."""
        r, c = nonzero(A)
        return cls(A.shape, np.searchsorted(r, np.arange(A.shape[0] + 1)), c, A[r, c])

    def row_of(self) -> np.ndarray:
        """The row of each stored entry."""
        return np.repeat(np.arange(self.shape[0]), np.diff(self.ptr))

    def dense(self) -> np.ndarray:
        out = np.zeros(self.shape)
        out[self.row_of(), self.col] = self.val
        return out

    def dot(self, x: np.ndarray) -> np.ndarray:
        """ordered(A, x): sums.rows_dot for a finite x, else on the dense A."""
        if not np.isfinite(x).all():
            return ordered(self.dense(), x)
        if self._layout is None:
            self._layout = padded(self.shape[0], self.row_of(), self.col, self.val)
        return rows_dot(self.shape[0], None, None, None, x, self._layout)

    def row_dot(self, p: int, x: np.ndarray, pos: np.ndarray | None = None) -> float:
        """ordered(A[p], x) (x finite), or with pos: ordered(A[p, idx], x) where pos[c] is column c's place in idx
        (-1: not in it; idx ascending)."""
        a, b = self.ptr[p], self.ptr[p + 1]
        c = self.col[a:b]
        if pos is None:
            t = self.val[a:b] * x[c]
        else:
            at = pos[c]
            keep = at >= 0
            t = self.val[a:b][keep] * x[at[keep]]
        return float(np.add.accumulate(t)[-1]) + 0.0 if t.size else 0.0

    def sub(self, idx: np.ndarray, pos: np.ndarray):
        """A[idx][:, idx]'s nonzero entries (row, column, value; by rows, columns ascending), pos as in row_dot."""
        a, cnt = self.ptr[idx], np.diff(self.ptr)[idx]
        sel = np.repeat(a - np.cumsum(cnt) + cnt, cnt) + np.arange(int(cnt.sum()))
        at = pos[self.col[sel]]
        keep = at >= 0
        return np.repeat(np.arange(len(idx)), cnt)[keep], at[keep], self.val[sel][keep]


def product(A: Rows, B: Rows) -> Rows:
    """ordered(A, B) of finite A and B as Rows: entry (i, j) summed over k ascending of A_ik B_kj, the terms
    with A_ik, B_kj != 0 only; the exact zero sums left out. The terms are made in the order of A's entries
    (i, then k ascending), a stable sort by (i, j) keeps k ascending in each entry, and the t-th terms of all
    entries are added in one pass (t = 0, 1, ...)."""
    nb = np.diff(B.ptr)
    cnt = nb[A.col]
    e = np.repeat(np.arange(A.col.size), cnt)
    pb = B.ptr[A.col][e] + np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    ncol = B.shape[1]
    key = A.row_of()[e] * ncol + B.col[pb]
    order = np.argsort(key, kind="stable")
    key, prod = key[order], A.val[e][order] * B.val[pb][order]
    first = np.flatnonzero(np.concatenate(([True], key[1:] != key[:-1]))) if key.size else np.zeros(0, np.intp)
    size = np.diff(np.append(first, key.size))
    out = prod[first]
    for t in range(1, int(size.max(initial=0))):
        g = np.flatnonzero(size > t)
        out[g] = out[g] + prod[first[g] + t]
    out = out + 0.0
    keep = out != 0.0
    key, out = key[first][keep], out[keep]
    rows = key // ncol
    return Rows((A.shape[0], ncol), np.searchsorted(rows, np.arange(A.shape[0] + 1)), key % ncol, out)


class Contact:
    """G = W'M^-1 W (m x m) by its nonzeros (rows: Rows), its columns' (cptr, cidx, cval), its diagonal and largest
    |entry|, for qp._active_set; every entry finite and a sum ending + 0.0 (clean: no -0.0). `factor`: the last
    factor of a G_AA (qp._solve_nonzeros), kept with its rows idx (bytes)."""

    __slots__ = ("rows", "shape", "cptr", "cidx", "cval", "diag", "gmax", "factor")

    def __init__(self, rows: Rows):
        self.rows, self.shape = rows, rows.shape
        m = rows.shape[0]
        r = rows.row_of()
        order = np.argsort(rows.col, kind="stable")  # by columns, rows ascending
        self.cptr = np.searchsorted(rows.col[order], np.arange(m + 1))
        self.cidx, self.cval = r[order], rows.val[order]
        self.diag = np.zeros(m)
        on = r == rows.col
        self.diag[r[on]] = rows.val[on]
        self.gmax = float(np.abs(rows.val).max(initial=0.0))
        self.factor = None

    def column(self, p: int) -> np.ndarray:
        out = np.zeros(self.shape[0])
        a, b = self.cptr[p], self.cptr[p + 1]
        out[self.cidx[a:b]] = self.cval[a:b]
        return out


def one_apart(old: np.ndarray, idx: np.ndarray) -> tuple[int, int]:
    """(c, +1) where the ascending rows idx are old with one added at place c, (c, -1) where one was dropped from
    old's place c, else (0, 0)."""
    n = min(old.size, idx.size)
    same = idx[:n] == old[:n]
    c = n if same.all() else int(np.argmin(same))
    if idx.size == old.size + 1 and np.array_equal(idx[c + 1:], old[c:]):
        return c, 1
    if idx.size + 1 == old.size and np.array_equal(idx[c:], old[c + 1:]):
        return c, -1
    return 0, 0


def lu_factor(n: int, rows, cols, vals, last=None, c: int = 0, change: int = 0):
    """The elimination of qp._lu_solve on a clean n x n matrix given by its nonzero entries (rows, columns, values;
    by rows, columns ascending), at a cost of the nonzeros and their fill: each step's pivot row (the first largest
    |a_ij|; A clean: finite), the rows it updates with their multipliers (a_ij != 0), U's rows and columns above the
    diagonal and its diagonal; None at a zero or non-finite pivot. The factor gets only the operations
    a_ik - l a_jk with l, a_jk != 0: the others leave a_ik as it is, and no entry becomes -0.0 (docs/theory.md
    §2.8); src/step.cpp sparse_lu_solve is the same algorithm. lu_apply gives the right-hand side its operations.

    last, c, change: the factor of the same G's submatrix whose rows and columns were these but for one, added at
    sorted place c (change +1) or dropped from it (-1): its first c steps are taken where they pick the same pivot
    rows (src/step.cpp band_lu_solve's prefix rule: step j reads and writes column j and those right of it and
    leaves column j final, so the columns < c of L and U are the last factor's; an added row at c must not be the
    first largest |a_cj| of a step j < c, a dropped one must have been no pivot row), steps j < c are done again on
    the columns >= c (and on an added row, every column: its multipliers are new), the steps from c on as always:
    each entry gets the same operations in the same order; where the rule fails, the whole elimination."""
    if last is not None and change == -1 and c in last[0][:c]:
        last = None  # the dropped row was a pivot row
    if last is None:
        c, change = 0, 0
    add = c if change == 1 else -1
    a: list[dict] = [{} for _ in range(n)]
    colrows: list[list] = [[] for _ in range(n)]
    entries = rows, cols, vals
    if c:  # the columns < c of the rows but an added one: the last factor's L and U
        keep = (cols >= c) | (rows == add)
        entries = rows[keep], cols[keep], vals[keep]
    for r, k, v in zip(*(e.tolist() for e in entries)):
        a[r][k] = v
        colrows[k].append(r)
    at, pos = list(range(n)), list(range(n))
    swaps, pneg, steps, diag = [0] * n, [False] * n, [None] * n, [0.0] * n
    isfinite = math.isfinite

    def update(r, lo, prow):  # a_rk - lo a_jk over the pivot row's nonzero entries
        row = a[r]
        get = row.get
        for k, v in prow:
            x = get(k)
            if x is None:
                row[k] = 0.0 - lo * v
                colrows[k].append(r)
            else:
                row[k] = x - lo * v

    his: list = []  # steps j < c: the pivot row's nonzero entries in the columns >= c (U's, final)
    if c:
        o_swaps, _, o_steps, o_urows, o_diag, _, _ = last
        for j in range(c):  # the last factor's steps j < c, on the columns >= c and an added row
            p = o_swaps[j] if o_swaps[j] < c else o_swaps[j] + change
            piv = o_diag[j]
            if add >= 0:  # the added row (at c until step c) must not be step j's pivot row
                v = abs(a[add].get(j, 0.0))
                if not (v < abs(piv) or (v == abs(piv) and p < add)):
                    return lu_factor(n, rows, cols, vals)
            if p != j:
                at[j], at[p] = at[p], at[j]
                pos[at[j]], pos[at[p]] = j, p
            swaps[j], pneg[j], diag[j] = p, piv < 0.0, piv
            rowj = a[at[j]]
            hi = [(k, v) for k, v in rowj.items() if v != 0.0]  # its columns >= c, as steps < j left them
            his.append(hi)
            lo_part = []
            for k, v in o_urows[j].items():  # U's row j in the columns < c: the last factor's
                if k < c:
                    rowj[k] = v
                    if k > j and v != 0.0:
                        lo_part.append((k, v))
            upd = []
            for i, lo in o_steps[j]:
                if i == c and change == -1:
                    continue
                i = i if i < c else i + change
                if lo != 0.0 and hi:
                    update(at[i], lo, hi)
                upd.append((i, lo))
            if add >= 0 and j in a[add]:
                aij = a[add].pop(j)
                if aij != 0.0:
                    lo = aij / piv
                    if lo != 0.0:
                        update(add, lo, lo_part + hi)
                    upd.append((add, lo))
            steps[j] = upd
    for j in range(c, n):
        rowj = a[at[j]]
        p, best = j, abs(rowj.get(j, 0.0))  # the first largest |a_ij| below (A clean: no NaN)
        for r in colrows[j]:
            i = pos[r]
            if i > j:
                v = abs(a[r][j])
                if v > best or (v == best and i < p):
                    p, best = i, v
        piv = a[at[p]].get(j, 0.0)
        if not (piv != 0.0 and isfinite(piv)):
            return None
        if p != j:
            at[j], at[p] = at[p], at[j]
            pos[at[j]], pos[at[p]] = j, p
            rowj = a[at[j]]
        swaps[j], pneg[j], diag[j] = p, piv < 0.0, piv
        prow = [(k, v) for k, v in rowj.items() if k > j and v != 0.0]
        upd = []
        for r in colrows[j]:
            i = pos[r]
            if i <= j:
                continue
            aij = a[r].pop(j)
            if aij == 0.0:  # l = +-0 with the pivot's sign: lu_apply's flip of step j
                continue
            lo = aij / piv
            if lo != 0.0:
                update(r, lo, prow)
            upd.append((i, lo))
        steps[j] = upd
    urows = [a[at[i]] for i in range(n)]
    # back substitution by columns: U's column j from the rows above (the columns < c: the last factor's)
    ucol: list[list] = last[5][:c] + [[] for _ in range(n - c)] if c else [[] for _ in range(n)]
    for i, hi in enumerate(his):
        for k, v in hi:
            ucol[k].append((i, v))
    for i in range(c, n):
        for k, v in urows[i].items():
            if k > i and v != 0.0:
                ucol[k].append((i, v))
    return swaps, pneg, steps, urows, diag, ucol, c  # c: the steps taken from `last`


def lu_apply(f, rhs):
    """x = A^-1 rhs by lu_factor's factor f: every operation of the dense elimination on the right-hand side,
    x_i - (+-0) x_j included, which changes x_i only from -0.0 to +0.0 (when the product is -0.0: l = +-0 with the
    pivot's sign, back substitution's a_ij = +0): those steps are counted ("flips") and applied to x_i when it is
    next operated on or read (docs/theory.md §2.8). A non-finite x_j makes the dense answer non-finite: None."""
    if f is None:
        return None
    swaps, pneg, steps, _, diag, ucol, _ = f
    n = len(diag)
    x = np.asarray(rhs, float).tolist()
    stamp, flips = [-1] * n, [0] * (n + 1)  # flips[s]: the flipping steps among 0 .. s-1
    copysign, isfinite = math.copysign, math.isfinite
    for j in range(n):
        p = swaps[j]
        if p != j:
            x[j], x[p], stamp[j], stamp[p] = x[p], x[j], stamp[p], stamp[j]
        xj = x[j]
        if xj == 0.0 and flips[j] > flips[stamp[j] + 1] and copysign(1.0, xj) < 0.0:
            xj = x[j] = 0.0
        if not isfinite(xj):
            return None
        flips[j + 1] = flips[j] + (pneg[j] != (copysign(1.0, xj) < 0.0))
        fj = flips[j]
        for i, lo in steps[j]:
            xi = x[i]
            if xi == 0.0 and fj > flips[stamp[i] + 1] and copysign(1.0, xi) < 0.0:
                xi = 0.0
            x[i] = xi - lo * xj
            stamp[i] = j
    bflips, bstamp = [0] * (n + 1), [n] * n  # bflips[s]: the flipping steps among s .. n-1
    for j in range(n - 1, -1, -1):
        xj = x[j]
        if xj == 0.0 and bflips[j + 1] > bflips[bstamp[j]] and copysign(1.0, xj) < 0.0:
            xj = 0.0
        xj = x[j] = xj / diag[j]
        if not isfinite(xj):
            return None
        bflips[j] = bflips[j + 1] + (copysign(1.0, xj) < 0.0)
        bj = bflips[j + 1]
        for i, v in ucol[j]:
            xi = x[i]
            if xi == 0.0 and bj > bflips[bstamp[i]] and copysign(1.0, xi) < 0.0:
                xi = 0.0
            x[i] = xi - v * xj
            bstamp[i] = j
    return np.array(x)
