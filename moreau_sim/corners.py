"""The set-valued Newton impact law at re-entrant corners (docs/theory.md §3; Glocker 2000, §3.4):
every Clarke-stationary point of 1/2 |v - v0|_M^2 over a union of polyhedral cones, the selection
among them, and corner_law, the law as a step (v0 = v_free) and an impact at one instant
(v0 = u-) apply it. The exposed-facet normal cone, the algorithm (one projection per non-empty
subset of pieces) and the scaling and tolerances (tol = 1e-9, tau = sqrt(tol)) are derived in
docs/corner-law.md. Units: velocities in generalized units, M in kg and kg m^2, distances in J;
M (v - v0) = [A_j; ...; W']' lam, the percussion P = (1 + e) lam.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from . import qp
from .law import outcome
from .options import Selection, check_restitution

MAX_PIECES = 6  # 2^6 - 1 = 63 QPs; more pieces means the contact model is wrong, not big.

__all__ = ["MAX_PIECES", "Candidate", "CornerLaw", "CornerSolution", "corner_law", "impact_outcomes", "select",
           "stationary_points"]


@dataclass(frozen=True, eq=False)
class Candidate:
    """One stationary point v [velocity] of Phi, distance = 1/2 |v - v0|_M^2 [J].

    pieces: every piece containing v; v is the projection of v0 onto their intersection (∩ S),
    and no other candidate has the same pieces. kind: "projection" if v is also the projection onto
    one piece alone, else "corner". multipliers lam [N s]: M (v - v0) = [A_p0; A_p1; ...; W']' lam,
    rows stacked in the order of `pieces`, then W's columns."""

    v: np.ndarray
    distance: float
    pieces: tuple[int, ...]
    kind: str
    global_min: bool
    multipliers: np.ndarray


@dataclass(frozen=True, eq=False)
class CornerSolution:
    """All stationary points, global minimizers first (ties ordered by `pieces`, lexicographic),
    then by increasing distance. candidates[0] is the GLOBAL_MIN choice."""

    candidates: tuple[Candidate, ...]
    unique: bool
    qp_solves: int  # projections actually solved (<= 2^p - 1; subsets containing v0 are free)
    lp_solves: int  # small LPs of the stationarity checks


def stationary_points(M, v0, pieces, W=None, *, tol: float = 1e-9) -> CornerSolution:
    """Clarke-stationary points of 1/2 |v - v0|_M^2 + I_K(v), K = ∪_j {A_j v >= 0, W' v >= 0}.

    M: (n, n) SPD kinetic metric; v0: (n,); pieces: 1..MAX_PIECES arrays (k_j, n), one row per
    face (constraint gradient); W: (n, m) smooth contacts common to all pieces, or None."""
    M, v0, pieces, W, tol = _validate(M, v0, pieces, W, tol, "v0")
    p, tau = len(pieces), float(np.sqrt(tol))
    m_s = float(np.max(np.diag(M)))
    s = float(np.linalg.norm(v0)) or 1.0
    Mn, v0n = M / m_s, v0 / s
    nA = [np.linalg.norm(A, axis=1) for A in pieces]                 # unit rows: tolerances in one scale
    nW = np.linalg.norm(W, axis=0)
    An = [A / nr[:, None] for A, nr in zip(pieces, nA)]
    Wn = W.T / nW[:, None]
    rows = [np.vstack([A, Wn]) for A in An]                           # rows of K_j = T_j ∩ S

    # 1. project v0 onto the intersection of each subset (size, then lexicographic order)
    groups: list[dict] = []  # one per distinct v: {"vn", "subsets": [...], "res": {subset: (v, lam)}}
    qp_solves = 0
    for size in range(1, p + 1):
        for sub in itertools.combinations(range(p), size):
            G = np.vstack([An[j] for j in sub] + [Wn])
            scale = np.concatenate([nA[j] for j in sub] + [nW])
            if np.all(G @ v0n >= 0.0):          # v0 already in this intersection: v = v0 exactly
                vn, v, lam = v0n, v0.copy(), np.zeros(G.shape[0])
            else:
                vn, z = _project(Mn, v0n, G, tol)
                qp_solves += 1
                v, lam = s * vn, (m_s * s) * z / scale
            for g in groups:
                if np.max(np.abs(g["vn"] - vn)) <= tau:
                    break
            else:
                g = {"vn": vn, "subsets": [], "res": {}}
                groups.append(g)
            g["subsets"].append(sub)
            g["res"][sub] = (v, lam)

    # 2. distances; global minimizers are stationary by definition, the others are checked
    half_energy = 0.5 * float(v0 @ M @ v0)
    tie = tau * half_energy
    for g in groups:
        sub = max(g["subsets"], key=len)  # = J(v) for a stationary v (docstring), unique size
        g["pieces"] = sub
        g["v"], g["lam"] = g["res"][sub]
        dv = g["v"] - v0
        g["distance"] = 0.5 * float(dv @ M @ dv)
    d_min = min(g["distance"] for g in groups)
    lp = [0]
    kept = []
    for g in groups:
        if g["distance"] <= d_min + tie or _clarke_stationary(g["vn"], Mn @ (v0n - g["vn"]), rows, tau,
                                                               lp):
            kept.append(g)

    # 3. order: tie classes of distance, then pieces tuple (deterministic)
    kept.sort(key=lambda g: (g["distance"], g["pieces"]))
    cls, start, keyed = 0, kept[0]["distance"], []
    for g in kept:
        if g["distance"] - start > tie:
            cls, start = cls + 1, g["distance"]
        keyed.append((cls, g["pieces"], g))
    keyed.sort(key=lambda t: (t[0], t[1]))
    cands = tuple(
        Candidate(v=_frozen(g["v"]), distance=g["distance"], pieces=g["pieces"],
                  kind="projection" if any(len(u) == 1 for u in g["subsets"]) else "corner",
                  global_min=c == 0, multipliers=_frozen(g["lam"]))
        for c, _, g in keyed)
    return CornerSolution(candidates=cands, unique=len(cands) == 1, qp_solves=qp_solves, lp_solves=lp[0])


def impact_outcomes(M, u_minus, e, pieces, W=None, *,
                    tol: float = 1e-9) -> list[tuple[Candidate, np.ndarray]]:
    """Every post-impact velocity u+ = (1 + e) v - e u- [velocity], one per stationary point v,
    in the order of stationary_points(M, u_minus, ...). e: the global restitution in [0, 1]."""
    e = check_restitution(e)
    M, u_minus, pieces, W, tol = _validate(M, u_minus, pieces, W, tol, "u_minus")
    sol = stationary_points(M, u_minus, pieces, W, tol=tol)
    return [(c, outcome(np.asarray(c.v), u_minus, e)) for c in sol.candidates]


def select(solution: CornerSolution, policy: Selection | str = Selection.GLOBAL_MIN) -> int:
    """Index into solution.candidates of the candidate the stepper continues with.

    GLOBAL_MIN: least distance; among tied minimizers the lowest `pieces` tuple (lexicographic) -
      the caller's piece order decides, as symmetry cannot. Always index 0.
    SYMMETRIC: the unique global minimizer; if several tie, the first candidate (in the solution's
      order) whose pieces contain all the tied minimizers' pieces - for symmetric data this is the
      projection onto the tied pieces' intersection, mapped to itself by the symmetry (note §3:
      u- = (1, 1) gives v = (0, 0), u+ = (-e, -e)); if there is none, as GLOBAL_MIN.
    FIRST: the lowest `pieces` tuple whatever the distance: the piece order is a priority list
      (e.g. put the previous step's piece first to keep the choice persistent)."""
    policy = Selection(policy)
    cands = solution.candidates
    if policy is Selection.FIRST:
        return min(range(len(cands)), key=lambda i: cands[i].pieces)
    tied = [c for c in cands if c.global_min]
    if policy is Selection.SYMMETRIC and len(tied) > 1:
        union = set().union(*(c.pieces for c in tied))
        for i, c in enumerate(cands):
            if union <= set(c.pieces):
                return i
    return 0


@dataclass(frozen=True, eq=False)
class CornerLaw:
    """The set-valued law applied (docs/theory.md §3): v the chosen stationary point; W (nv, m + k)
    the smooth rows then the rows of the chosen piece(s)' faces, `faces` [(corner, face)] (k);
    lam their multipliers in that order (M (v - v0) = W lam); solution, chosen: all stationary
    points and the index of the one taken; u_plus: each candidate's outcome when there are
    several (a branch), else None."""

    v: np.ndarray
    W: np.ndarray
    faces: list
    lam: np.ndarray
    solution: CornerSolution
    chosen: int
    u_plus: tuple | None


def corner_law(M, v0, u_minus, e, W, pieces, rows, choice, *, selection: Selection | str = Selection.GLOBAL_MIN,
               pick: int | None = None) -> CornerLaw | None:
    """The corner law of a step (v0 = v_free) or of an impact at one instant (v0 = u_minus): the
    stationary points over the union of `pieces` with the smooth rows W (nv, m), the one
    `selection` picks (or candidate `pick`); rows[c]: corner c's face rows (k_c, nv); choice[j]:
    the face per corner of piece j. None when there are more than MAX_PIECES pieces."""
    if len(pieces) > MAX_PIECES:
        return None
    sol = stationary_points(M, v0, list(pieces), W if W.shape[1] else None)
    k = select(sol, selection) if pick is None else min(pick, len(sol.candidates) - 1)
    cand = sol.candidates[k]
    faces = [(c, choice[j][c]) for j in cand.pieces for c in range(len(rows))]
    face_rows = np.array([rows[c][f] for c, f in faces]).reshape(len(faces), -1).T
    lam = np.asarray(cand.multipliers, float)
    u_plus = None if sol.unique else tuple(outcome(np.asarray(c.v), u_minus, e) for c in sol.candidates)
    return CornerLaw(np.array(cand.v), np.concatenate((W, face_rows), axis=1), faces,
                     np.concatenate((lam[len(faces):], lam[:len(faces)])), sol, k, u_plus)


# --- internals ---------------------------------------------------------------------------------

def _project(Mn, v0n, G, tol):
    """argmin 1/2 (v - v0)' M (v - v0) s.t. G v >= 0 (docs/theory.md §1), and its multipliers:
    the package's one projection (qp.solve), exact on its active set as the smooth law's (§1.3); where
    that finds none, piqp's to eps = tol/10 polished by least squares (to ~1e-7 of |v0| only: a corner
    step of the slope scene then booked D - L = -9.4e-10 J of an impact's 1.9e-4 J, docs/theory.md §3.3)."""
    eps = max(tol / 10.0, 1e-14)   # the duality-gap test defaults to 1e-8: set it too (else ~1e-7 in v)
    res = qp.solve(Mn, G.T, v0n, eps=eps, polish=qp.Polish.ACTIVE_SET, screen=False, polish_tol=tol)
    if not (res.ok and res.polished):
        res = qp.solve(Mn, G.T, v0n, eps=eps, polish=qp.Polish.LEAST_SQUARES, screen=False, polish_tol=tol)
    if not res.ok:
        raise RuntimeError(f"corner projection QP failed: {res.status}")
    return res.v, res.lam


def _clarke_stationary(vn, g, rows, tau, lp) -> bool:
    """g = M (v0 - v) ∈ N^C_K(v)? (module docstring). rows: unit rows of each piece (∩ S)."""
    J = [j for j, R in enumerate(rows) if np.min(R @ vn) >= -tau]
    act = [rows[j][np.abs(rows[j] @ vn) <= tau] for j in J]
    if any(a.shape[0] == 0 for a in act):             # v interior to K: N^C = {0}
        return float(np.linalg.norm(g)) <= tau
    bases = [_null_basis(a[_implicit_equalities(a, lp)], tau) for a in act]
    Q = bases[0]
    same = all(B.shape == Q.shape and np.max(np.abs(B @ B.T - Q @ Q.T)) <= tau for B in bases)
    if not same:   # pieces of different spans: outer bound, the sum of the pieces' normal cones
        return _in_cone(-g, np.vstack(act), tau)
    if Q.shape[1] == 0:                                # L = {0}: N^C is everything
        return True
    L = [_restrict(a, Q, tau) for a in act]            # local cones in coordinates of V
    exposed = [b for j, Lj in enumerate(L) for b in Lj if _exposed(j, b, L, tau, lp)]
    gens = np.array(exposed).reshape(len(exposed), Q.shape[1])
    return _in_cone(-(Q.T @ g), gens, tau)          # g ∈ cone{-b}


def _exposed(j, b, L, tau, lp) -> bool:
    """Is the facet L_j ∩ b⊥ (n-1 dimensional) not covered by the pieces that reach across b⊥?"""
    H = np.linalg.svd(b[None, :])[2][1:].T                    # orthonormal basis of b⊥
    across = [_restrict(Lk, H, tau) for k, Lk in enumerate(L) if k != j and not _in_cone(b, Lk, tau)]
    return _uncovered(_restrict(L[j], H, tau), across, tau, lp)


def _uncovered(F, covers, tau, lp) -> bool:
    """{F z >= 0} minus ∪ {C z >= 0} has an interior point (all rows unit, one linear space)."""
    if not _has_interior(F, tau, lp):
        return False
    if not covers:
        return True
    C, rest = covers[0], covers[1:]
    return any(_uncovered(np.vstack([F, -r]), rest, tau, lp) for r in C)   # C's complement, by row


def _has_interior(R, tau, lp) -> bool:
    """max s s.t. R z >= s, |z| <= 1: does the cone {R z >= 0} have an interior point?"""
    if R.shape[0] == 0:
        return True
    from scipy.optimize import linprog  # here: corners only (~40 MB of RSS a run without corners never loads)

    k = R.shape[1]
    lp[0] += 1
    res = linprog(np.r_[np.zeros(k), -1.0], A_ub=np.hstack([-R, np.ones((R.shape[0], 1))]),
                  b_ub=np.zeros(R.shape[0]), bounds=[(-1.0, 1.0)] * k + [(0.0, 1.0)], method="highs")
    return res.status == 0 and -res.fun > tau


def _implicit_equalities(A, lp) -> np.ndarray:
    """Rows of {A x >= 0} that vanish on the whole cone: max sum t, A x >= t, 0 <= t <= 1."""
    from scipy.optimize import linprog

    k, n = A.shape
    lp[0] += 1
    res = linprog(np.r_[np.zeros(n), -np.ones(k)], A_ub=np.hstack([-A, np.eye(k)]), b_ub=np.zeros(k),
                  bounds=[(None, None)] * n + [(0.0, 1.0)] * k, method="highs")
    if res.status != 0:
        raise RuntimeError(f"corner LP failed: {res.message}")
    return res.x[n:] < 0.5


def _null_basis(E, tau) -> np.ndarray:
    """Orthonormal basis (columns) of {x : E x = 0}."""
    n = E.shape[1]
    if E.shape[0] == 0:
        return np.eye(n)
    _, sv, Vt = np.linalg.svd(E)
    return Vt[int(np.sum(sv > tau)):].T


def _restrict(R, B, tau) -> np.ndarray:
    """Rows of R in the coordinates of the subspace with basis B, unit; rows vanishing there dropped."""
    RB = R @ B
    nr = np.linalg.norm(RB, axis=1)
    keep = nr > tau
    return RB[keep] / nr[keep, None]


def _in_cone(x, gens, tau) -> bool:
    """x ∈ cone{rows of gens} (NNLS residual <= tau |x|); b ∈ cone{rows of L_k} iff L_k ⊆ {b x >= 0}."""
    if gens.shape[0] == 0:
        return float(np.linalg.norm(x)) <= tau
    from scipy.optimize import nnls

    _, res = nnls(gens.T, x)
    return res <= tau * max(1.0, float(np.linalg.norm(x)))


def _frozen(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


def _validate(M, v0, pieces, W, tol, v_name):
    try:
        tol = float(tol)
    except (TypeError, ValueError):
        raise ValueError(f"tol must be a small positive number, got {tol!r}") from None
    if not 0.0 < tol <= 1e-4:
        raise ValueError(f"tol must lie in (0, 1e-4], got {tol!r}")
    v0 = np.array(v0, dtype=float)
    if v0.ndim != 1 or v0.size == 0 or not np.all(np.isfinite(v0)):
        raise ValueError(f"{v_name} must be a finite 1-D array, got shape {v0.shape}")
    n = v0.size
    M = np.array(M, dtype=float)
    if M.shape != (n, n) or not np.all(np.isfinite(M)):
        raise ValueError(f"M must be a finite ({n}, {n}) array to match {v_name}, got shape {M.shape}")
    if np.max(np.abs(M - M.T)) > 1e-10 * np.max(np.abs(M)):
        raise ValueError("M must be symmetric")
    try:
        np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        raise ValueError("M must be positive definite") from None
    if isinstance(pieces, np.ndarray) or not isinstance(pieces, (list, tuple)):
        raise ValueError("pieces must be a list or tuple of (k_j, n) arrays")
    if not 1 <= len(pieces) <= MAX_PIECES:
        raise ValueError(f"pieces must hold 1 to {MAX_PIECES} pieces, got {len(pieces)}")
    out = []
    for j, A in enumerate(pieces):
        A = np.array(A, dtype=float)
        if A.ndim != 2 or A.shape[0] == 0 or A.shape[1] != n or not np.all(np.isfinite(A)):
            raise ValueError(f"pieces[{j}] must be a finite (k, {n}) array with k >= 1, got shape {A.shape}")
        if np.any(np.linalg.norm(A, axis=1) == 0.0):
            raise ValueError(f"pieces[{j}] has a zero row (no constraint gradient)")
        out.append(A)
    W = np.zeros((n, 0)) if W is None else np.array(W, dtype=float)
    if W.ndim != 2 or W.shape[0] != n or not np.all(np.isfinite(W)):
        raise ValueError(f"W must be a finite ({n}, m) array or None, got shape {W.shape}")
    if np.any(np.linalg.norm(W, axis=0) == 0.0):
        raise ValueError("W has a zero column (no constraint gradient)")
    return M, v0, out, W, tol
