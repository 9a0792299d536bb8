"""The one QP projection of the package: v = argmin 1/2 (v - v0)'M(v - v0) s.t. W'v >= b, by a dual active
set (from nothing up to COLD_START_ROWS rows; above, warm-started from the caller's `start`, the previous step's
final active set, with piqp's answer on sparse matrices as its fallback), re-solved on its final active set
(docs/theory.md §1.3, §1.5); its floating-point order, shared with src/step.cpp: §2.8."""

from __future__ import annotations

import enum
import math
import sys
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import piqp

if TYPE_CHECKING:
    import scipy.sparse

from . import nonzeros, schur
from .islands import islands
from .options import QPForm
from .sums import ordered


@dataclass(frozen=True, slots=True)
class QPResult:
    """status: piqp's status name ("PIQP_SOLVED", ...), "ACTIVE_SET" when the active set solved it
    without piqp, or "ADMISSIBLE" when v0 already satisfies every constraint (no QP to solve); ok:
    solved and usable; iterations: piqp's interior-point iterations, or the active set's moves;
    polished: the answer is the active set's exact one (Polish.ACTIVE_SET) or the least-squares one; v (nv,), lam (m,);
    active (status ACTIVE_SET): the first pass's final active set (bool (m,): independent rows, the next step's start);
    the problem it solved, where it solved one: M, W (nv, m), v0 (nv,), b (m,) (None otherwise);
    residual (property): the KKT residual of (v, lam), computed when asked (it costs ~5 us)."""

    status: str
    ok: bool
    iterations: int
    polished: bool
    v: np.ndarray
    lam: np.ndarray
    M: np.ndarray | None = field(default=None, repr=False, compare=False)
    W: np.ndarray | None = field(default=None, repr=False, compare=False)
    v0: np.ndarray | None = field(default=None, repr=False, compare=False)
    b: np.ndarray | None = field(default=None, repr=False, compare=False)
    active: np.ndarray | None = field(default=None, repr=False, compare=False)  # ACTIVE_SET: the first pass's final set

    @property
    def residual(self) -> float:
        """max(|M(v - v0) - W lam|, max(0, b - W'v), max(0, -lam), |lam . (W'v - b)|)."""
        if not self.ok:
            return float("inf")
        if self.M is None:
            return 0.0
        return kkt_residual(self.M, self.W, self.v0, self.v, self.lam, self.b)


_STATUS = {getattr(piqp, n): n for n in dir(piqp) if n.startswith("PIQP_")}
_EMPTY = np.zeros(0)


def kkt_residual(M, W, v0, v, lam, b=None) -> float:
    """max(|M(v - v0) - W lam|, max(0, b - W'v), max(0, -lam), |lam . (W'v - b)|) (inf-norms)."""
    slack = W.T @ v if b is None else W.T @ v - b
    r = np.abs(M @ (v - v0) - W @ lam).max(initial=0.0)
    return float(max(r, -slack.min(initial=0.0), -lam.min(initial=0.0), abs(lam @ slack)))


COLD_START_ROWS = 200  # up to this many rows (= SPARSE_ROWS) the active set starts from nothing, and piqp is only its
# fallback; the compiled step runs this method, not piqp (docs/theory.md §1.3)
# 200, not 100, since the paid position lift is compiled (measured 2026-11-28, CPU, medians of 3 interleaved rounds,
# load 3.5-5.6): the 27-cube pile 41.8 -> 3.3 ms a step (mean; every step compiled, none handed back), columns of 150
# and 199 beads 6.4 -> 1.7 and 8.3 -> 2.9 ms, 100 beads 0.73 -> 0.74 ms and box_stack_10 resting 401 -> 400 us unchanged
SPARSE_ROWS = 200  # above this many rows the active set starts from `start` (solve), the rows the caller takes as
# active (the stepper: the previous step's final set, matched by the contacts' identities), and where it fails the
# sparse path (_solve_sparse: piqp's start, SuperLU) solves; the compiled step runs the same warm start (§1.3)
# The active set's tolerances (src/step.cpp receives them from compiled.CONSTANTS):
SCREEN = 1e-13  # v0 is admissible, and a row of the active set met, when W'v - b >= -SCREEN (1 + max|v0|)
DEPENDENT = 1e-12  # row p depends on the active rows when z = G_pp + G_pA d <= DEPENDENT G_pp
MET = 1e-14  # a dependent row is met within MET m max|G| max(lam) (the round-off of G lam)
ACCEPT = 1e-12  # the answer is kept when lam_A >= -ACCEPT max(1, lam_A) and W'v - b >= -ACCEPT (1 + max|v0|)
REFINE = 1e-8  # the refinement step is taken when it moves lam_A by at most REFINE (1 + max(lam_A))
SECOND_PASS = 1e-15  # the second pass's tolerance, relative to max|b| + max|W| max|v|
MOVES_PER_ROW, MOVES_EXTRA = 5, 10  # the active set gives up after MOVES_PER_ROW m + MOVES_EXTRA moves
WARM_ROWS = 1000  # above this many rows a projection without a start takes the sparse path alone: there the cold
# start's moves cost too much (a 1500-bead column's first step 3.3 s in Python against 0.36 s by the sparse path,
# measured 2026-11-28); the compiled step hands such a step back. With a start (the previous step's final set) the
# warm-started active set is the first path at any size, in both steps (docs/theory.md §1.3)
NONZERO_ROWS = SPARSE_ROWS  # above this many rows _polish forms its products and solves by their nonzeros
# (nonzeros.py; the same bits; docs/theory.md §2.8). The Python step, measured 2026-11-28 (CPU, one BLAS thread,
# medians of interleaved runs, load 1.2-3.3): a column of 300 beads 21.6 -> 12.6 ms a step, of 1000 beads
# 172 -> 58 ms (its cold first step ~10 s -> ~1.5 s), the pile of 64 boxes 459 -> 235 ms (its active set's solves)
START_PASSES = 4  # a warm start's rows with negative multipliers are dropped and the rest solved again, at most
# this many solves; a start still negative (or singular) then: from nothing (_active_set)


LU_SCALAR = 12  # up to this many unknowns _lu_factor works on Python floats (fewer calls than numpy's row operations)
LU_CACHE = 128  # factors kept (the active set solves with the same G_AA again: 2 of 3 solves in box_stack_5)
LU_CACHED_ROWS = 32  # of matrices up to this many rows (at most ~4 MB of Python floats)
LU_SPARSE_NONZEROS = 8  # above LU_CACHED_ROWS rows, a clean matrix with at most this many nonzeros a row:
# _lu_solve_sparse (the same bits at the cost of its nonzeros)
_factors: dict = {}


def _clean(A: np.ndarray) -> bool:
    """A finite, without a -0.0 entry (a contact-space G and its submatrices: every entry a sum ending + 0.0)."""
    return bool(np.isfinite(A).all()) and not bool(np.signbit(A[A == 0.0]).any())


def _lu_solve_sparse(A: np.ndarray, rhs):
    """_lu_solve's bits for a clean A (_clean) at a cost of its nonzeros and their fill, not n^3 (a column of
    beads: G_AA tridiagonal): nonzeros.lu_factor on A's nonzero entries, nonzeros.lu_apply on rhs (src/step.cpp
    sparse_lu_solve is the same algorithm; docs/theory.md §2.8)."""
    rows, cols = np.nonzero(A)
    return nonzeros.lu_apply(nonzeros.lu_factor(A.shape[0], rows, cols, A[rows, cols]), rhs)


def _lu_solve(A, rhs):
    """x = A^-1 rhs by Gaussian elimination with partial pivoting, written out so that every entry gets the same
    operations in the same order on any CPU, with any BLAS (docs/theory.md §2.8; src/step.cpp lu_solve makes the
    same ones): at column j the pivot is the first largest |a_ij| (i >= j), rows j and p swap, then for each
    i > j: l = a_ij / a_jj, a_ik = a_ik - l a_jk (k > j), x_i = x_i - l x_j; back substitution by columns,
    j = n-1 .. 0: x_j = x_j / a_jj, x_i = x_i - a_ij x_j (i < j). None at a zero or non-finite pivot (a NaN in
    the column included) or a non-finite x. The factors of a matrix are kept (by its bytes) and applied to the
    next right-hand side: the same operations on x as eliminating them together. Tested bit for bit against the
    elimination on Python floats (tests/test_qp.py) and against src/step.cpp (tests/test_compiled.py)."""
    A = np.ascontiguousarray(A, float)
    if A.shape[0] > LU_CACHED_ROWS:
        if np.count_nonzero(A) <= LU_SPARSE_NONZEROS * A.shape[0] and _clean(A):
            return _lu_solve_sparse(A, rhs)
        f = _lu_factor(A)
    else:
        key = A.tobytes()
        f = _factors.get(key, _factors)
        if f is _factors:
            if len(_factors) >= LU_CACHE:
                _factors.clear()
            f = _factors[key] = _lu_factor(A)
    return _lu_apply(f, rhs)


def _lu_apply(f, rhs):
    """x = A^-1 rhs by _lu_factor's factors f of A (None: None): the elimination's operations on rhs."""
    if f is None:
        return None
    swaps, lower, upper, diag = f
    x = np.asarray(rhs, float).tolist()
    for j, p in enumerate(swaps):  # P rhs (the multipliers below moved with their rows)
        if p != j:
            x[j], x[p] = x[p], x[j]
    for j, col in enumerate(lower):  # L y = P rhs by columns: each entry as the rhs column of the elimination gets it
        xj = x[j]
        x[j + 1:] = [s - lo * xj for s, lo in zip(x[j + 1:], col)]
    for j in range(len(x) - 1, -1, -1):  # U x = y by columns
        xj = x[j] = x[j] / diag[j]
        x[:j] = [s - a * xj for s, a in zip(x[:j], upper[j])]
    return np.array(x) if all(map(math.isfinite, x)) else None


def _lu_factor(A: np.ndarray):
    """(the pivot row of each column, the columns of L below the diagonal, of U above it, U's diagonal) as
    Python floats, or None at a zero or non-finite pivot: small matrices on Python floats, larger ones by
    numpy row operations (elementwise, one rounding each), the same operations either way."""
    n = A.shape[0]
    swaps = []
    if n <= LU_SCALAR:
        a = A.tolist()
        for j in range(n):
            p, best = j, abs(a[j][j])
            if best == best:
                for i in range(j + 1, n):
                    v = abs(a[i][j])
                    if v != v:  # a NaN: the pivot is no number
                        p, best = i, v
                        break
                    if v > best:
                        p, best = i, v
            piv = a[p][j]
            if not (piv != 0.0 and math.isfinite(piv)):
                return None
            swaps.append(p)
            if p != j:
                a[j], a[p] = a[p], a[j]
            rj = a[j][j + 1:]
            for i in range(j + 1, n):
                ri = a[i]
                lo = ri[j] = ri[j] / piv
                ri[j + 1:] = [s - lo * t for s, t in zip(ri[j + 1:], rj)]
        return _columns(a, swaps)
    a = A.copy()
    for j in range(n):
        p = j + int(np.abs(a[j:, j]).argmax())  # the first NaN, else the first largest
        piv = float(a[p, j])
        if not (piv != 0.0 and math.isfinite(piv)):
            return None
        swaps.append(p)
        if p != j:
            row = a[j].copy()
            a[j] = a[p]
            a[p] = row
        if j + 1 < n:
            lo = a[j + 1:, j] = a[j + 1:, j] / piv
            S = a[j + 1:, j + 1:]
            np.subtract(S, np.multiply.outer(lo, a[j, j + 1:]), out=S)
    return _columns(a.tolist(), swaps)


def _columns(a: list, swaps: list):
    """_lu_factor's result from the rows a of the factored matrix (L below the diagonal, U on and above)."""
    cols = list(zip(*a)) if a else []
    return swaps, [c[j + 1:] for j, c in enumerate(cols)], [c[:j] for j, c in enumerate(cols)], \
        [a[j][j] for j in range(len(a))]


def _issparse(A) -> bool:
    """scipy.sparse.issparse, without importing scipy.sparse: a run on dense matrices (every compiled run) never
    loads it (~23 MiB of RSS); nothing is a sparse matrix before scipy.sparse is imported."""
    sp = sys.modules.get("scipy.sparse")
    return sp is not None and sp.issparse(A)


def _solve(A, rhs):
    """x = A^-1 rhs: _lu_solve for a dense A, SuperLU (scipy's splu, sequential: the same bits run to
    run) for a sparse one; None when singular or not finite."""
    if not _issparse(A):
        return _lu_solve(A, rhs)
    if A.shape[0] == 0:
        return np.zeros(0)
    from scipy.sparse.linalg import splu  # here: the sparse path only (issue 14: no RSS a small run never uses)

    try:
        x = splu(A.tocsc()).solve(np.asarray(rhs, float))
    except RuntimeError:  # "Factor is exactly singular"
        return None
    return x if np.isfinite(x).all() else None


def _sub(G, idx):
    """G[idx][:, idx]; for a CSC G (sorted indices, idx increasing) by gathering its columns idx and renumbering
    their rows, O(their nonzeros) (scipy's fancy indexing costs ~50 us a call)."""
    if not _issparse(G):
        return G[idx][:, idx]
    k = len(idx)
    if k == G.shape[0]:
        return G
    pos = np.full(G.shape[0], -1)
    pos[idx] = np.arange(k)
    start, cnt = G.indptr[idx], G.indptr[idx + 1] - G.indptr[idx]
    sel = np.repeat(start - np.cumsum(cnt) + cnt, cnt) + np.arange(int(cnt.sum()))
    rows = pos[G.indices[sel]]
    keep = rows >= 0
    col = np.repeat(np.arange(k), cnt)[keep]
    import scipy.sparse  # here and in _csc, _solve_sparse: the sparse path only (_issparse)

    return scipy.sparse.csc_matrix((G.data[sel][keep], rows[keep], np.searchsorted(col, np.arange(k + 1))),
                                   shape=(k, k))


def _line(A, p, m):
    """Column p of a CSC A (or row p of a CSR A) as a dense vector of length m."""
    out = np.zeros(m)
    a, b = A.indptr[p], A.indptr[p + 1]
    out[A.indices[a:b]] = A.data[a:b]
    return out


def _sparse_mul(A, x):
    """A @ x for a scipy.sparse A (the products of the sparse path: sums over the nonzeros only)."""
    return A @ x


def _active_set(G, r, tol, act=None, mul=np.matmul):
    """The contact-space QP  min 1/2 lam'G lam - r'lam, lam >= 0  (G = W'M^-1 W, r = b - W'v0) by
    Goldfarb and Idnani's dual active-set method (docs/theory.md §1). From lam = 0 (or the warm start
    `act`, the rows taken as active: lam_A = G_AA^-1 r_A with its negative rows dropped, START_PASSES solves at
    most, else from nothing) it adds the most violated inactive row p (slack s = G lam - r below
    -tol; the first such row on ties): lam_A moves along G_AA d = -G_Ap and lam_p by t until row p is
    tight (t = -s_p/z, z = G_pp + G_pA d), or until a multiplier of A reaches zero first (that row leaves
    A, and the same p is tried again). A row dependent on A (z <= 1e-12 G_pp: four corners of a face on
    a plane) moves only the multipliers; if none can shrink, p counts as met when its violation is within
    the round-off of G lam, else the rows cannot all be met. Returns (act, lam, moves) with every row of
    act tight, or None when the rows are infeasible, a solve is singular or it takes more than 5 m + 10
    moves. mul: the products (ordered on dense matrices, which src/step.cpp mirrors operation for
    operation with the same LU (_lu_solve), so both steps decide alike; _sparse_mul on the sparse path)."""
    m = r.shape[0]
    lam = np.zeros(m)
    sparse, nz = _issparse(G), isinstance(G, nonzeros.Contact)
    solve = _solve_nonzeros if nz else lambda G, idx, rhs: _solve(_sub(G, idx), rhs)
    if sparse:  # the sparse path (solve): G in CSC and CSR for its columns and rows, each O(its nonzeros)
        G = G.tocsc()
        G.sort_indices()
        Gr, diag = G.tocsr(), G.diagonal()
    start, act = act, np.zeros(m, bool)
    if start is not None:  # lam_A = G_AA^-1 r_A, its negative rows dropped (START_PASSES solves at most)
        cur = start.copy()
        for _ in range(START_PASSES):
            idx = np.flatnonzero(cur)
            x = solve(G, idx, r[idx]) if idx.size else None
            if x is None:  # singular, or nothing left: from nothing
                break
            neg = x < 0.0
            if not neg.any():
                act, lam[idx] = cur, x
                break
            cur[idx[neg]] = False
    moves, gmax = 0, (np.abs(G.data).max(initial=0.0) if sparse else G.gmax if nz else np.abs(G).max())
    while True:
        s = (G.rows.dot(lam) if nz else mul(G, lam)) - r
        s[act] = np.inf
        p = int(np.argmin(s))
        if s[p] >= -tol:
            return act, lam, moves
        if sparse:
            col, row, gpp = _line(G, p, m), _line(Gr, p, m), diag[p]
        elif nz:  # G's column p; its row p by G.rows (row_dot)
            col, row, gpp = G.column(p), None, float(G.diag[p])
        else:
            col, row, gpp = G[:, p], G[p], G[p, p]
        while True:  # add p, dropping the rows whose multipliers reach zero on the way
            moves += 1
            if moves > MOVES_PER_ROW * m + MOVES_EXTRA:
                return None
            idx = np.flatnonzero(act)
            if idx.size:
                d = solve(G, idx, -col[idx])
                if d is None:
                    return None
                if nz:  # ordered(G[p, idx], d) over row p's nonzero terms (d finite: _lu_solve's answer)
                    pos = np.full(m, -1)
                    pos[idx] = np.arange(idx.size)
                    z = gpp + G.rows.row_dot(p, d, pos)
                else:
                    z = gpp + (row[idx] @ d if sparse else mul(G[p, idx], d))
            else:
                d, z = _EMPTY, gpp
            if nz:  # row p's slack now: ordered(G[p], lam) over its nonzero terms where lam is finite
                sp = (G.rows.row_dot(p, lam) if np.isfinite(lam).all() else ordered(G.rows.dense()[p], lam)) - r[p]
            else:
                sp = (row @ lam if sparse else mul(G[p], lam)) - r[p]  # row p's slack now
            t1 = -sp / z if z > DEPENDENT * gpp else np.inf  # row p tight (inf: p depends on A)
            neg = d < 0.0
            t2, k = np.inf, -1
            if neg.any():
                ratio = lam[idx[neg]] / -d[neg]
                j = int(np.argmin(ratio))
                t2, k = ratio[j], int(idx[neg][j])
            if t1 == np.inf and t2 == np.inf:  # p depends on A and no multiplier of A can shrink
                if lam[p] == 0.0 and sp >= -(tol + MET * m * gmax * lam.max()):
                    return act, lam, moves  # p is met to the round-off of G lam (lam large): as met as it can be
                return None  # the rows cannot all be met (or z is NaN)
            if not t1 <= t2 and k < 0:  # t1 NaN and no row to drop: no answer (k = -1 would drop the last row)
                return None
            t = t1 if t1 <= t2 else t2
            lam[idx] = lam[idx] + t * d
            lam[p] = lam[p] + t
            np.maximum(lam, 0.0, out=lam)
            if t1 <= t2:
                act[p] = True
                break
            lam[k] = 0.0
            act[k] = False


def _by_nonzeros(W, Minv):
    """(W' as nonzeros.Rows, M^-1 W and G = W'M^-1 W by their nonzeros: `ordered`'s bits) where W and M^-1 are
    finite and G is too (a clean G: its entries sums ending + 0.0), else None (the dense products)."""
    if not (np.isfinite(W).all() and np.isfinite(Minv).all()):
        return None
    WT = nonzeros.Rows.of(W.T)
    MiW = nonzeros.product(nonzeros.Rows.of(Minv), nonzeros.Rows.of(W))
    G = nonzeros.product(WT, MiW)
    if not np.isfinite(G.val).all():
        return None
    return WT, MiW, nonzeros.Contact(G)


def _solve_nonzeros(G, idx, rhs, fresh: bool = False):
    """_solve(_sub(G, idx), rhs) for a nonzeros.Contact G: G_AA from G's rows, solved by _lu_solve's elimination
    on its nonzeros (nonzeros.lu_factor; above LU_CACHED_ROWS rows with at most LU_SPARSE_NONZEROS a row, as
    _lu_solve chooses) or on the dense G_AA. The factor is kept: applied to the next right-hand side on the same
    rows (the start's, the final and the refinement's solves), and its first steps taken where the next rows differ
    by one added or dropped at sorted place c (the active set's moves; nonzeros.lu_factor's prefix rule, src/step.cpp
    band_lu_solve's): the same operations either way (docs/theory.md §2.8). Above schur.SCHUR_MIN_ROWS: schur.solve."""
    if schur.applies(G, idx.size):  # the active set's moves on a large G (docs/theory.md §1.3)
        return schur.solve(G, idx, rhs, _lu_solve, fresh)
    key = idx.tobytes()
    last = G.factor
    if last is not None and last[0] == key:
        return last[1](last[2], rhs)
    k = idx.size
    pos = np.full(G.shape[0], -1)
    pos[idx] = np.arange(k)
    rows, cols, vals = G.rows.sub(idx, pos)
    if k > LU_CACHED_ROWS and rows.size <= LU_SPARSE_NONZEROS * k:
        prefix = None, 0, 0
        if last is not None and last[1] is nonzeros.lu_apply and last[2] is not None:
            c, change = nonzeros.one_apart(last[3], idx)
            if change and c:
                prefix = last[2], c, change
        G.factor = key, nonzeros.lu_apply, nonzeros.lu_factor(k, rows, cols, vals, *prefix), idx.copy()
    else:
        A = np.zeros((k, k))
        A[rows, cols] = vals
        if k <= LU_CACHED_ROWS:
            return _lu_solve(A, rhs)
        G.factor = key, _lu_apply, _lu_factor(A), idx.copy()
    return G.factor[1](G.factor[2], rhs)


def _polish(W, v0, b, Minv, act=None):
    """The exact projection by the active set (_active_set from nothing, or warm-started from `act`; dense
    products by `ordered`), re-solved on its final set A: G_AA lam_A = b_A - W_A'v0 (_solve),
    v = v0 + M^-1 W_A lam_A. Kept only if lam_A >= 0 and W'v >= b to round-off (the KKT conditions;
    M (v - v0) = W lam holds by construction); else None. Returns (v, lam, moves, the first pass's final set A)."""
    m = W.shape[1]
    sparse = _issparse(W)
    mul = _sparse_mul if sparse else ordered
    if m == 1:  # one contact: the projection in closed form
        w = W[:, 0]
        Miw = mul(Minv, w)
        lam1 = max(0.0, float(b[0] - mul(w, v0)) / float(mul(w, Miw)))
        return v0 + lam1 * Miw, np.array([lam1]), 1, np.array([lam1 > 0.0])
    scale = 1.0 + np.abs(v0).max(initial=0.0)
    nz = _by_nonzeros(W, Minv) if not sparse and m > NONZERO_ROWS else None
    if nz is not None:  # W'v, M^-1 W_A x and the solves of G_AA by the nonzeros (nonzeros.py): the same bits
        WT, MiW, G = nz

        def wt(v, rows=None):
            return WT.dot(v) if rows is None else WT.dot(v)[rows]

        def miw(idx, x):
            full = np.zeros(m)
            full[idx] = x
            return MiW.dot(full)
        solve, wabs = _solve_nonzeros, WT.val
    else:
        MiW = mul(Minv, W)
        G = mul(W.T, MiW)
        if sparse:
            MiW, G = MiW.tocsc(), G.tocsc()
            G.sort_indices()

        def wt(v, rows=None):
            return mul(W.T, v) if rows is None else mul(W[:, rows].T, v)

        def miw(idx, x):
            return mul(MiW[:, idx], x)

        def solve(G, idx, rhs, fresh=False):
            return _solve(_sub(G, idx), rhs)
        wabs = W.data if sparse else W
    r = b - wt(v0)
    sol = _active_set(G, r, SCREEN * scale, act, mul)
    if sol is None:
        return None
    act, lam, moves = sol
    first = act.copy()  # returned: the next step's start (stepper.keep_active), independent rows by construction
    idx = np.flatnonzero(act)
    lp = np.zeros(m)
    if not idx.size:
        vp = v0.copy()
    else:
        lamA = solve(G, idx, r[idx], True)  # (fresh: A's own factor, not a complement's: schur.solve)
        if lamA is None or lamA.min() < -ACCEPT * max(1.0, lamA.max()):
            return None
        np.maximum(lamA, 0.0, out=lamA)
        vp = v0 + miw(idx, lamA)
        # one step of iterative refinement: lamA is as exact as its magnitude allows, but a light body
        # under a heavy one (lamA ~ R times its own weight impulse) then moves by ~R eps in the directions
        # the rows hold; the residual of W_P'v = b_P is computed where v ~ 0, so accurately, and solving
        # for it on the rows that push, P = {lamA_i > 0}, leaves W_P'v - b_P at ulp(v) (docs/theory.md §1.5)
        P = lamA > 0.0
        if P.any():
            iP = idx[P]
            dP = solve(G, iP, b[iP] - wt(vp, iP))
            if dP is not None and np.abs(dP).max() <= REFINE * (1.0 + lamA.max()):
                lamA[P] = np.maximum(lamA[P] + dP, 0.0)
                vp = vp + miw(iP, dP)
        lp[idx] = lamA
        # and the answer projected once more: its residual W'v - b is accurate where v ~ 0, so the rows the
        # first pass left violated at the round-off of lam (a resting 1:10,000 stack's other corners) are
        # met to that accuracy (tol2); kept when it violates no row more than before
        r2 = b - wt(vp)
        tol2 = SECOND_PASS * (np.abs(b).max() + np.abs(wabs).max(initial=0.0) * np.abs(vp).max())
        sol = _active_set(G, r2, tol2, None, mul)
        if sol is not None and sol[0].any():
            i2 = np.flatnonzero(sol[0])
            v2 = vp + miw(i2, sol[1][i2])
            if (wt(v2) - b).min() >= -r2.max():
                vp = v2
                lp[i2] += sol[1][i2]
                moves += sol[2]
    if (wt(vp) - b).min() < -ACCEPT * scale:
        return None
    return vp, lp, moves, first


class Polish(enum.Enum):
    """How piqp's answer is refined on its active set (docs/theory.md §1)."""

    ACTIVE_SET = "active-set"  # the law: exact, by the dual active set (_active_set), piqp its fallback
    LEAST_SQUARES = "least-squares"  # the corner law: least squares on the strictly active rows
    NONE = "none"  # piqp's answer as it is


def _piqp(kind, eps: float, max_iter: int):
    """piqp's DenseSolver or SparseSolver (`kind`), quiet, with eps on the residuals and the duality gap."""
    s = kind()
    st = s.settings
    st.verbose = False
    st.eps_abs = st.eps_rel = eps
    st.eps_duality_gap_abs = st.eps_duality_gap_rel = eps  # default 1e-8 would bound the accuracy
    st.max_iter = max_iter
    return s


def _no_answer(status, iters: int, v: np.ndarray, lam: np.ndarray) -> QPResult | None:
    """The failed QPResult when piqp did not solve, or answered "solved" with NaN; None for an answer."""
    if status != piqp.PIQP_SOLVED:
        return QPResult(_STATUS.get(status, str(status)), False, iters, False, v, lam)
    if not (np.isfinite(v).all() and np.isfinite(lam).all()):
        return QPResult("NON_FINITE_SOLUTION", False, iters, False, v, lam)
    return None


def solve(M: np.ndarray, W: np.ndarray, v0: np.ndarray, *, b: np.ndarray | None = None,
          Minv: np.ndarray | None = None, form: QPForm = QPForm.PRIMAL, eps: float = 1e-10,
          max_iter: int = 250, polish: Polish = Polish.ACTIVE_SET, screen: bool = True,
          polish_tol: float = 1e-9, start: np.ndarray | None = None, blocks=None, start_any: bool = False) -> QPResult:
    """Project v0 onto {v : W' v >= b} (b = 0 by default) in the metric M with piqp.

    Minv: M^-1 if the caller has it (Pinocchio's computeMinverse), else it is computed.
    screen: return v0 itself when it is already admissible to round-off (no QP).
    polish_tol: the acceptance tolerance of Polish.LEAST_SQUARES (rows with multipliers above
    sqrt(polish_tol) are active; the polished v must satisfy W'v >= -polish_tol).
    start: above SPARSE_ROWS rows (Polish.ACTIVE_SET), the rows the active set starts from (bool (m,); None or
    none set: from nothing); at or below, it is not read (the cold start, docs/theory.md §1.3).
    blocks: (first velocity, nv) of each kinematic tree, M's diagonal blocks (Forest.blocks): above SPARSE_ROWS
    rows (Polish.ACTIVE_SET) a problem whose rows fall into independent islands is solved island by island
    (_by_islands, docs/theory.md §1.3, islands); None: as one. start_any: `start` is read at any size (an island's)."""
    m = W.shape[1]
    b = np.zeros(m) if b is None else np.asarray(b, float)
    if polish is Polish.ACTIVE_SET and Minv is None:
        Minv = np.linalg.inv(M)
    if not np.isfinite(v0).all():  # an overflow upstream: no projection of it is meaningful
        return QPResult("NON_FINITE_INPUT", False, 0, False, v0.copy(), np.zeros(m))
    cold = polish is Polish.ACTIVE_SET and m <= COLD_START_ROWS
    warm = polish is Polish.ACTIVE_SET and m > SPARSE_ROWS
    if screen and (ordered(W.T, v0) - b).min() >= -SCREEN * (1.0 + np.abs(v0).max()):
        # v0 already admissible (up to round-off): the projection is v0 itself, nothing to solve
        return QPResult("ADMISSIBLE", True, 0, False, v0.copy(), np.zeros(m), M, W, v0, b)
    if warm and blocks is not None:
        got = _by_islands(M, W, v0, b, Minv, blocks, start, form=form, eps=eps, max_iter=max_iter, screen=screen,
                          polish_tol=polish_tol)
        if got is not None:
            return got
    if warm and m > WARM_ROWS and (start is None or not np.any(start)):  # the sparse path alone (WARM_ROWS)
        return _solve_sparse(M, W, v0, b, Minv, form, eps, max_iter, screen)
    if cold or warm:  # above SPARSE_ROWS warm-started from `start` (its moves grow with the rows that change)
        act = None if not (warm or start_any) or start is None or not np.any(start) else np.asarray(start, bool)
        p = schur.retried(_polish, W, v0, b, Minv, act)
        if p is not None:
            return QPResult("ACTIVE_SET", True, p[2], True, p[0], p[1], M, W, v0, b, p[3])
    if warm:  # the active set failed (its move limit, a singular or rejected solve): piqp + SuperLU, as before
        return _solve_sparse(M, W, v0, b, Minv, form, eps, max_iter, screen)
    s = _piqp(piqp.DenseSolver, eps, max_iter)
    if form is QPForm.PRIMAL:
        s.setup(M, -ordered(M, v0), None, None, W.T, b, None)
        status = s.solve()
        v, lam = s.result.x.copy(), s.result.z_l.copy()
    else:
        if Minv is None:
            Minv = np.linalg.inv(M)
        MiW = ordered(Minv, W)
        s.setup(ordered(W.T, MiW), ordered(W.T, v0) - b, None, None, None, None, None, np.zeros(m), None)
        status = s.solve()
        lam = s.result.x.copy()
        v = v0 + ordered(MiW, lam)
    iters = s.result.info.iter
    if status == piqp.PIQP_MAX_ITER_REACHED and form is QPForm.PRIMAL:
        # the primal form's interior point can stall on rows dependent to round-off (a symmetric resting stack:
        # primal residual 5e-11 after 250, 1000 or 5000 iterations) where the dual form converges (45 iterations):
        # that one (docs/theory.md §2.11)
        return solve(M, W, v0, b=b, Minv=Minv, form=QPForm.DUAL, eps=eps, max_iter=max_iter, polish=polish,
                     screen=screen, polish_tol=polish_tol)
    failed = _no_answer(status, iters, v, lam)
    if failed is not None:
        return failed
    p = None
    if polish is Polish.ACTIVE_SET and not cold:  # warm-started from piqp's active set
        np.maximum(lam, 0.0, out=lam)
        p = _polish(W, v0, b, Minv, lam > 1e-7 * max(1.0, lam.max()))
    elif polish is Polish.LEAST_SQUARES:
        p = _polish_least_squares(M, W, v0, lam, polish_tol)
    if p is not None:
        v, lam = p[:2]
    return QPResult("PIQP_SOLVED", True, iters, p is not None, v, lam, M, W, v0, b)


def _by_islands(M, W, v0, b, Minv, blocks, start, **opts) -> QPResult | None:
    """solve island by island (islands.islands; docs/theory.md §1.3, islands): each island's rows projected on its
    own trees' velocities, with its own screen, tolerances and size rules, warm-started from its rows of `start` at
    any size (start_any: the stepper keeps the whole problem's set; from nothing where none is kept); the other
    velocities keep v0. None where there is one island, or where an island has no answer (then solve takes the
    whole)."""
    parts = islands(W, blocks)
    if parts is None:
        return None
    m = W.shape[1]
    v, lam, act = v0.copy(), np.zeros(m), np.zeros(m, bool)
    moves, status, polished = 0, "ADMISSIBLE", True
    for dofs, rows in parts:
        ix = np.ix_(dofs, dofs)
        res = solve(M[ix], W[np.ix_(dofs, rows)], v0[dofs], b=b[rows], Minv=Minv[ix],
                    start=None if start is None else start[rows], start_any=True, **opts)
        if not res.ok:
            return None
        v[dofs], lam[rows] = res.v, res.lam
        act[rows] = res.lam > 0.0 if res.active is None else res.active  # keep_active's rule, island by island
        moves += res.iterations
        if res.status != "ADMISSIBLE":
            polished = polished and res.polished
            status = res.status if status != "PIQP_SOLVED" else status
    return QPResult(status, True, moves, polished, v, lam, M, W, v0, b, act)


def _csc(A) -> scipy.sparse.csc_matrix:
    """A dense matrix as CSC, its exact zeros dropped (the tree's pattern of M and M^-1: bodies on separate root
    joints give block-diagonal ones; the rows W touch the joints that move their two bodies)."""
    import scipy.sparse

    if _issparse(A):
        return A.tocsc()
    A = np.asarray(A, float)
    n, k = A.shape
    if A.flags.f_contiguous:  # CSC from column-major memory: one pass for the nonzeros (scipy's path takes ~4)
        flat = A.ravel(order="F")
        nz = np.flatnonzero(flat != 0.0)  # on a bool mask: ~30x faster than on the floats
        indptr = np.searchsorted(nz, np.arange(0, n * k + 1, n) if n else np.zeros(k + 1, int))
        return scipy.sparse.csc_matrix((flat[nz], nz % max(n, 1), indptr), shape=(n, k))
    flat = np.ascontiguousarray(A).ravel()
    nz = np.flatnonzero(flat != 0.0)
    indptr = np.searchsorted(nz, np.arange(0, n * k + 1, k) if k else np.zeros(n + 1, int))
    return scipy.sparse.csr_matrix((flat[nz], nz % max(k, 1), indptr), shape=(n, k)).tocsc()


def _solve_sparse(M, W, v0, b, Minv, form, eps, max_iter, screen) -> QPResult:
    """The large-problem path of solve (Polish.ACTIVE_SET above SPARSE_ROWS rows; docs/theory.md §1.3): the
    same method as the dense one on sparse matrices - piqp's SparseSolver gives the start, _polish's active set
    on G = W'M^-1 W in CSC (SuperLU for its solves) re-solves it and accepts it by the same KKT test - so the
    cost follows the nonzeros (a column of N beads: M diagonal, G tridiagonal, O(N)) instead of m^2 or m^3."""
    import scipy.sparse

    m = W.shape[1]
    Ms, Ws, Mis = _csc(M), _csc(W), _csc(Minv)
    problem = (M, W, v0, b)  # as given, as the dense path keeps them (the residual, the recorder)
    if screen and (Ws.T @ v0 - b).min() >= -SCREEN * (1.0 + np.abs(v0).max()):
        return QPResult("ADMISSIBLE", True, 0, False, v0.copy(), np.zeros(m), *problem)
    s = _piqp(piqp.SparseSolver, eps, max_iter)
    if form is QPForm.PRIMAL:
        s.setup(scipy.sparse.triu(Ms, format="csc"), -(Ms @ v0), None, None, Ws.T.tocsc(), b, None)
        status = s.solve()
        v, lam = s.result.x.copy(), s.result.z_l.copy()
    else:
        MiW = (Mis @ Ws).tocsc()
        s.setup(scipy.sparse.triu(Ws.T @ MiW, format="csc"), Ws.T @ v0 - b, None, None, None, None, None,
                np.zeros(m), None)
        status = s.solve()
        lam = s.result.x.copy()
        v = v0 + MiW @ lam
    iters = s.result.info.iter
    failed = _no_answer(status, iters, v, lam)
    if failed is not None:
        return failed
    np.maximum(lam, 0.0, out=lam)
    act = lam > 1e-7 * max(1.0, lam.max())
    p = _polish(Ws, v0, b, Mis, act)
    if p is None:  # degenerate rows (dependent ones the sparse round-off took in): the dense polish, as before
        dense = [A.toarray() if _issparse(A) else A for A in (W, Minv)]
        p = _polish(dense[0], v0, b, dense[1], act)
    if p is not None:
        v, lam = p[:2]
    return QPResult("PIQP_SOLVED", True, iters, p is not None, v, lam, *problem)


def _polish_least_squares(M, W, v0, lam, tol):
    """Re-solve on the strictly active rows (lam_i > sqrt(tol) max(1, lam)): M (v - v0) = W_a lam_a,
    W_a' v = 0, by least squares; kept when lam_a >= 0 and W' v >= -tol (b = 0)."""
    act = lam > np.sqrt(tol) * max(1.0, float(np.max(lam)))
    if not np.any(act):
        return None
    Ga = W.T[act]
    MiG = np.linalg.solve(M, Ga.T)
    za = np.linalg.lstsq(Ga @ MiG, -Ga @ v0, rcond=None)[0]
    vp = v0 + MiG @ za
    if not (np.all(za >= 0.0) and np.all(W.T @ vp >= -tol)):
        return None
    z = np.zeros_like(lam)
    z[act] = za
    return vp, z
