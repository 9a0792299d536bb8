"""The constraints of the closed contacts: their rows w_i (the gradients of the gaps mapped to
velocity space, W = [w_1 ... w_m]), duplicate rows merged, and the pieces of the admissible cone
at corners (docs/theory.md §1, §3, §6).

    assemble_constraints(model, data, q, contacts) -> Constraints(contacts, M, W, pieces)

is the one assembly every caller uses (the stepper, the outcome analysis, the event-driven
integrator, the benchmarks): M(q) by CRBA tree by tree (trees.py; which also fills the WORLD joint
Jacobians the rows need), the rows (joint limits' among them, limits.py), distinct rows, then the corner pieces.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from .contacts import NO_CONTACTS, Contacts, Corner, FeatureKind
from .data import Data
from .limits import limit_rows
from .model import Model
from .sums import ordered


def contact_rows(model: Model, data: Data, contacts: Contacts) -> np.ndarray:
    """W = [w_1 ... w_m] (nv, m), the gradients of the gaps mapped to velocity space.

    Needs data.kinematics.J = the WORLD joint Jacobians at the same q as `contacts`
    (the forest's mass_matrix fills it: trees.py).
    w_i = n_i' (J_A(p_A) - J_B(p_B)) = n' J_lin + (p x n)' J_ang: the unit wrench [n; p x n] at the
    world origin applied to the WORLD Jacobian, masked to the joints that move each body (+0.0 elsewhere)."""
    m = contacts.m
    if m == 0:
        return np.zeros((model.nv, 0))
    J = data.kinematics.J
    n = contacts.normal
    nn = np.concatenate((n, n))
    p = np.concatenate((contacts.point_a, contacts.point_b))
    c = np.stack((p[:, 1] * nn[:, 2] - p[:, 2] * nn[:, 1], p[:, 2] * nn[:, 0] - p[:, 0] * nn[:, 2],
                  p[:, 0] * nn[:, 1] - p[:, 1] * nn[:, 0]), axis=1)  # p x n
    R = ordered(nn, J[:3]) + ordered(c, J[3:])  # (2m, nv): A, then B (src/step.cpp contact_rows: the same sums)
    mask = model.support_mask
    A, B = mask[contacts.joint_a], mask[contacts.joint_b]
    W = (R[:m] * A - R[m:] * B).T
    W[((A == 0.0) & (B == 0.0)).T] = 0.0  # +0.0 on the velocities that move neither body (src/step.cpp: not computed)
    lim = contacts.kind == FeatureKind.JOINT_LIMIT
    if lim.any():  # a joint limit's row is the constant +-e_i (its zero normal gave a zero row above)
        W[:, lim] = limit_rows(model.limits, contacts.pair[lim], model.nv)
    return W


def closed_limits(model: Model, q: np.ndarray, tol: float) -> Contacts:
    """The joint limits with g(q) <= tol [rad or m] as contacts (kind JOINT_LIMIT, pair
    len(model.pairs) + the limit's index, feature = its joint id; no points, zero normals: their rows
    +-e_i are set by contact_rows). docs/theory.md §2.1."""
    if not model.limits:
        return NO_CONTACTS
    on = [lim for lim in model.limits if lim.gap(q) <= tol]
    if not on:
        return NO_CONTACTS
    k = len(on)
    z3 = np.zeros((k, 3))
    return Contacts(np.array([lim.gap(q) for lim in on]), z3, z3, z3, np.array([lim.pair for lim in on], np.int64),
                    np.full(k, int(FeatureKind.JOINT_LIMIT), np.int64), np.array([lim.joint for lim in on], np.int64),
                    np.array([lim.joint for lim in on], np.int64), np.zeros(k, np.int64))


_UPPER: dict[int, np.ndarray] = {}
_WEIGHTS: dict[int, np.ndarray] = {}
DISTINCT = 1e-12  # two rows are the same contact when they differ by at most this, relative to 1 + max|W|
SCREEN_ROWS = 12  # above this many rows distinct screens the pairs by a sort (O(m log m)) instead of comparing all


def _duplicates_screened(W: np.ndarray, tol: float) -> np.ndarray:
    """The mask of distinct's all-pairs test (row j repeats an earlier row i: max_k |W_kj - W_ki| <= tol), found
    by a screen: two such rows have keys k = c'w (c a fixed weight vector, c_k in [1, 2]) within
    |c|_1 tol plus the keys' round-off, so after sorting the keys only neighbours within that window are
    compared, exactly as the all-pairs test does. O(m log m) plus the candidates (docs/theory.md §6.4)."""
    nv, m = W.shape
    c = _WEIGHTS.get(nv)
    if c is None:  # fixed (seeded) and irregular: the rows e_j - e_i of a column must not share a key
        c = _WEIGHTS[nv] = np.random.default_rng(0).uniform(1.0, 2.0, nv)
    key = c @ W
    scale = float(np.abs(c).sum())
    window = scale * tol + 4.0 * np.finfo(float).eps * nv * scale * (float(np.abs(W).max()) + tol)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    hi = np.searchsorted(ks, ks + window, side="right")  # candidates of sorted position a: a+1 .. hi[a]-1
    dup = np.zeros(m, bool)
    for a in np.flatnonzero(hi > np.arange(m) + 1):
        i, js = order[a], order[a + 1:hi[a]]  # (a's candidates at once: a blown-up robot had 31 million of them)
        same = js[np.abs(W[:, js] - W[:, i:i + 1]).max(axis=0) <= tol]
        dup[np.maximum(same, i)] = True  # the later of the two repeats the earlier
    return dup


def distinct(contacts: Contacts, W: np.ndarray) -> tuple[Contacts, np.ndarray]:
    """Drop contacts whose row w_i repeats an earlier one (to 1e-12 relative): the same
    constraint twice, e.g. the front and back corners of a planar block. Keeps the first."""
    m = W.shape[1]
    if m < 2:
        return contacts, W
    tol = DISTINCT * (1.0 + np.abs(W).max())
    if m > SCREEN_ROWS:
        dup = _duplicates_screened(W, tol)
    else:
        upper = _UPPER.get(m)
        if upper is None:
            upper = _UPPER[m] = np.triu(np.ones((m, m), bool), 1)
        same = np.abs(W[:, :, None] - W[:, None, :]).max(axis=0) <= tol
        dup = (same & upper).any(axis=0)
    if not dup.any():
        return contacts, W
    keep = ~dup
    return contacts.select(keep), W[:, keep]


@dataclass(frozen=True, slots=True)
class CornerPieces:
    """The pieces of the admissible cone of one step (docs/theory.md §3).

    rows[c]: (k_c, nv) rows of corner c's faces (distinct, non-zero), corners[c] its Corner;
    pieces: one (n_corners, nv) array per choice of one face per corner (itertools.product
    order); choice[j]: the face index per corner of piece j."""

    corners: tuple
    rows: tuple
    pieces: tuple
    choice: tuple


def corner_pieces(model: Model, data: Data, contacts: Contacts, W: np.ndarray):
    """Rows of every corner's faces; a corner left with one distinct non-zero row becomes a
    smooth contact (appended to contacts and W); corners whose rows repeat another's (the front
    and back of a planar block) are dropped. Returns (contacts, W, CornerPieces or None)."""
    keep_c, keep_r = [], []
    extra = []
    for c in contacts.corners:
        k = len(c.normals)
        one = corner_faces(c, np.arange(k))
        R = contact_rows(model, data, one).T  # (k, nv)
        scale = 1e-12 * (1.0 + np.abs(R).max())
        idx = [i for i in range(k) if np.abs(R[i]).max() > scale
               and not any(np.abs(R[i] - R[j]).max() <= scale for j in range(i))]
        if not idx:
            continue
        if len(idx) == 1:
            extra.append((one.select(np.isin(np.arange(k), idx)), R[idx].T))
            continue
        Rk = R[idx]
        if any(len(r) == len(Rk) and all(np.abs(r - x).max(axis=1).min() <= scale for x in Rk) for r in keep_r):
            continue
        keep_c.append(Corner(c.g, c.point_a, c.point_b, c.normals[idx], c.pair, c.joint_a, c.joint_b, c.features))
        keep_r.append(Rk)
    for one, col in extra:
        contacts = contacts.concat(one)
        W = np.concatenate((W, col), axis=1)
    if not keep_c:
        return contacts.concat(corners=()), W, None
    choice = tuple(itertools.product(*(range(len(r)) for r in keep_r)))
    pieces = tuple(np.array([keep_r[c][f] for c, f in enumerate(ch)]) for ch in choice)
    return contacts, W, CornerPieces(tuple(keep_c), tuple(keep_r), pieces, choice)


def corner_faces(c: Corner, faces: np.ndarray) -> Contacts:
    """Contacts for faces `faces` of corner c: one per face, at the corner's point, with the face's
    normal (kind CORNER, feature = the face index)."""
    k = len(faces)
    return Contacts(np.full(k, c.g), np.tile(c.point_a, (k, 1)), np.tile(c.point_b, (k, 1)), c.normals[faces],
                    np.full(k, c.pair), np.full(k, int(FeatureKind.CORNER)), np.asarray(faces), np.full(k, c.joint_a),
                    np.full(k, c.joint_b))


@dataclass(frozen=True, slots=True)
class Constraints:
    """The closed contacts at q as constraints: contacts (smooth, distinct rows; single-face
    corners appended as smooth contacts), M = M(q) (nv, nv) [kg, kg m^2], W (nv, m) their rows,
    pieces the corners' admissible pieces (None without a corner)."""

    contacts: Contacts
    M: np.ndarray
    W: np.ndarray
    pieces: CornerPieces | None


def assemble_constraints(model: Model, data: Data, q: np.ndarray, contacts: Contacts) -> Constraints:
    """M(q), the rows of `contacts` (detected at q) and of the joint limits closed at q (added unless
    `contacts` has them already), distinct rows, corner pieces."""
    M = model.forest.mass_matrix(data.kinematics, q)  # also fills the WORLD Jacobians for the rows
    if model.limits and not (contacts.kind == FeatureKind.JOINT_LIMIT).any():
        contacts = contacts.concat(closed_limits(model, q, model.options.contact_tolerance))
    contacts, W = distinct(contacts, contact_rows(model, data, contacts))
    pieces = None
    if contacts.corners:
        contacts, W, pieces = corner_pieces(model, data, contacts, W)
    return Constraints(contacts, M, W, pieces)
