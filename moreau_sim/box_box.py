"""Edge-on-edge contacts of two boxes for the fixed step's detection (docs/theory.md §2.5, §6.2): the
crossings of an edge of one box with an edge of the other, which no vertex of either sees (a box tipping
over the end of a slope: the slope's end edge crosses the box's bottom face). Plain functions on arrays,
so that src/step.cpp can mirror them one for one. coal has no query for a pair's edge crossings (its
narrow phase reports one witness point per pair), so they are computed here in closed form.
"""

from __future__ import annotations

import coal
import numpy as np
import pinocchio as pin

from .kinematics import cross_rows

CONE = 1e-9  # an edge pair's normal may leave the edges' normal cones by this (face on face: at their ends)
EDGE_END = 1e-6  # a crossing this close (relative to the edge's length) to an edge's end is a vertex's contact
PARALLEL = 1e-9  # |e_A x e_B| below this: parallel edges, no crossing (vertices and patches cover them)
_AXIS = np.arange(12) // 4  # the axis each of a box's 12 edges runs along (box_edges)
DEPTH_RATIO = 4.0  # a crossing deeper than this times the boxes' penetration depth is no contact (edge_crossings)
FACE_ANGLE = np.pi / 4  # [rad] faces this close to anti-parallel: their clipped overlap's corners count (face_patch)


def box_edges(geometry: coal.Box, placement: pin.SE3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The 12 edges of a box in its joint frame: starts (12, 3) [m], unit directions (12, 3), lengths (12,)
    [m] and the outward normals of the two faces that meet there (12, 2, 3). Edge k runs along the box's
    axis a = k // 4 from -h_a, at the signs of the next two axes ((k % 4) // 2, k % 2: 0 is -, 1 is +)."""
    h = np.asarray(geometry.halfSide, float)
    R, t = placement.rotation, placement.translation
    e0, ed, el, ef = [], [], [], []
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        for sb in (-1.0, 1.0):
            for sc in (-1.0, 1.0):
                x = np.zeros(3)
                x[a], x[b], x[c] = -h[a], sb * h[b], sc * h[c]
                e0.append(R @ x + t)
                ed.append(R[:, a])
                el.append(2.0 * h[a])
                ef.append([sb * R[:, b], sc * R[:, c]])
    return np.array(e0), np.array(ed), np.array(el), np.array(ef)


def world(edges: tuple, oMi: pin.SE3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """box_edges' arrays placed by the joint placement oMi (world frame)."""
    e0, ed, el, ef = edges
    R = oMi.rotation
    return _rt(e0, R) + oMi.translation, _rt(ed, R), el, _rt(ef, R)


def _dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a.b along a last axis of 3 entries (broadcasting) summed in index order, as _dot and src/box_box.hpp dot3."""
    return (a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]) + a[..., 2] * b[..., 2]


def _rt(F: np.ndarray, R: np.ndarray) -> np.ndarray:
    """F @ R.T for rows F (..., 3) summed in index order (src/box_box.hpp row_rt: the same bits; no BLAS)."""
    return _dots(F[..., None, :], R)


def overlap(box_a: tuple, box_b: tuple) -> float:
    """The boxes' penetration depth [m] (box_a, box_b: (R, c, half) in the world): the least overlap of their
    projections over the 15 separating axes (the 6 face normals and the 9 cross products of their
    directions); negative where an axis separates them (then not the distance, only a lower bound of it)."""
    (Ra, ca, ha), (Rb, cb, hb) = box_a, box_b
    c = cross_rows(Ra.T[:, None, :], Rb.T[None, :, :]).reshape(9, 3)
    s = np.sqrt(_dots(c, c))
    axes = np.concatenate((Ra.T, Rb.T, c[s > PARALLEL] / s[s > PARALLEL, None]))
    pa = ((0.0 + np.abs(_dots(axes, Ra[:, 0])) * ha[0]) + np.abs(_dots(axes, Ra[:, 1])) * ha[1]) \
        + np.abs(_dots(axes, Ra[:, 2])) * ha[2]
    pb = ((0.0 + np.abs(_dots(axes, Rb[:, 0])) * hb[0]) + np.abs(_dots(axes, Rb[:, 1])) * hb[1]) \
        + np.abs(_dots(axes, Rb[:, 2])) * hb[2]
    return float(((pa + pb) - np.abs(_dots(axes, ca - cb))).min())  # in index order: src/box_box.hpp overlap


def depth_floor(box_a: tuple, box_b: tuple, tol: float) -> float:
    """The deepest gap [m] a contact of two crossed boxes may have: -(DEPTH_RATIO overlap() + tol). An edge
    crossing or face corner below it is the two lines or planes meeting far from where the boxes overlap;
    coal's pair contact below it is its EPA failing (contacts.detect)."""
    return -(DEPTH_RATIO * max(overlap(box_a, box_b), 0.0) + tol)


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """a.b of two 3-vectors summed in index order (src/box_box.hpp dot3: the same decisions, bit for bit)."""
    return (float(a[0]) * float(b[0]) + float(a[1]) * float(b[1])) + float(a[2]) * float(b[2])


def face_patch(A: tuple, B: tuple, box_a: tuple, box_b: tuple, tol: float) -> list[tuple]:
    """The corners of the overlap of two nearly parallel faces of boxes A and B (world(): their edges; box_a,
    box_b: (R, c, half) of each in the world, for the depth test), each with its own gap (docs/theory.md §6.2):
    [(g [m], p_A (3,), p_B (3,), n (3,), i) for corner i], [] unless the faces are within FACE_ANGLE of
    anti-parallel and overlap. contacts.detect takes them where coal's patch has no polygon.
    The corners are those with g <= tol, as every contact's (a corner still open is no row: a row holds its
    corner where it is, and the law has no gap to let it close; a tilted box comes down on it in a later step).

    A box's axes a_i are its edges 0, 4, 8, its half sides half their lengths, its centre edge 0's start
    + sum_i h_i a_i. The reference face is the face of least interpenetration: among A's outward normals
    negated and B's (n oriented from B to A; A's first, -a_i then +a_i, then B's), the first of largest
    s(n) = n.(c_A - c_B) - sum_i |n.a_i| h_A,i - sum_j |n.b_j| h_B,j (contacts._face_axis in closed form).
    The incident face is the other box's face whose outward normal is most opposite to the reference face's
    outward normal o; the pair counts when |cos| between them >= cos(FACE_ANGLE). The incident face's 4
    corners are clipped (Sutherland-Hodgman) to the reference face's 4 side planes; each clipped corner p
    gets its own gap to the reference plane, g = o.p - o.x_ref (> 0 apart), with p_B = p_A - g n (B's face
    the reference, p_A = p) or p_A = p_B + g n (A's, p_B = p). Where any corner is crossed (g < 0) the corners
    deeper than DEPTH_RATIO times the boxes' penetration depth (+ tol) are dropped, as edge_crossings does.
    src/box_box.hpp face_patch is this function, operation for operation."""
    boxes = []
    for e0, ed, el, _ in (A, B):
        U = (ed[0], ed[4], ed[8])
        h = (0.5 * float(el[0]), 0.5 * float(el[4]), 0.5 * float(el[8]))
        boxes.append((U, ((e0[0] + h[0] * U[0]) + h[1] * U[1]) + h[2] * U[2], h))
    (Ua, ca, ha), (Ub, cb, hb) = boxes
    d = ca - cb
    best, s_best, n = 0, -np.inf, None
    for f in range(12):
        nf = (Ua[f % 3] if f < 3 else -Ua[f % 3]) if f < 6 else (-Ub[f % 3] if f < 9 else Ub[f % 3])
        pa = (abs(_dot(nf, Ua[0])) * ha[0] + abs(_dot(nf, Ua[1])) * ha[1]) + abs(_dot(nf, Ua[2])) * ha[2]
        pb = (abs(_dot(nf, Ub[0])) * hb[0] + abs(_dot(nf, Ub[1])) * hb[1]) + abs(_dot(nf, Ub[2])) * hb[2]
        s = (_dot(nf, d) - pa) - pb
        if f == 0 or s > s_best:
            best, s_best, n = f, s, nf
    ref_a = best < 6
    i = best % 3
    Ur, cr, hr, Ui, ci, hi = (Ua, ca, ha, Ub, cb, hb) if ref_a else (Ub, cb, hb, Ua, ca, ha)
    o = -n if ref_a else n  # the reference face's outward normal
    c = [_dot(o, Ui[k]) for k in range(3)]
    j = 0
    for k in (1, 2):
        if abs(c[k]) > abs(c[j]):
            j = k
    if not abs(c[j]) >= np.cos(FACE_ANGLE):
        return []
    j1, j2 = (j + 1) % 3, (j + 2) % 3
    fc = ci - (hi[j] if c[j] > 0.0 else -hi[j]) * Ui[j]  # the incident face's centre: its normal opposes o
    poly = [(fc + (s1 * hi[j1]) * Ui[j1]) + (s2 * hi[j2]) * Ui[j2]
            for s1, s2 in ((-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0))]
    for k in ((i + 1) % 3, (i + 2) % 3):  # the reference face's side planes: |u_k.(x - c_r)| <= h_r,k
        for sign in (1.0, -1.0):
            axis = sign * Ur[k]
            lim = hr[k] + _dot(axis, cr)
            clipped = []
            for m in range(len(poly)):
                p, q = poly[m], poly[(m + 1) % len(poly)]
                dp, dq = _dot(axis, p) - lim, _dot(axis, q) - lim
                if dp <= 0.0:
                    clipped.append(p)
                if (dp < 0.0 < dq) or (dq < 0.0 < dp):
                    clipped.append(p + (dp / (dp - dq)) * (q - p))
            poly = clipped
            if not poly:
                return []
    plane = _dot(o, cr + hr[i] * o)
    gaps = [_dot(o, p) - plane for p in poly]
    hits = [(g, m, p) for m, (g, p) in enumerate(zip(gaps, poly)) if g <= tol]
    if any(g < 0.0 for g, _, _ in hits):
        floor = depth_floor(box_a, box_b, tol)
        hits = [x for x in hits if x[0] >= floor]
    return [(g, p + g * n, p, n, m) if ref_a else (g, p, p - g * n, n, m) for g, m, p in hits]


def edge_crossings(A: tuple, B: tuple, box_a: tuple, box_b: tuple, tol: float) -> list[tuple]:
    """The edge pairs of boxes A and B (world(): edges of each; box_a, box_b: (R, c, half) of each box in the
    world) that touch or cross: each a tuple (g [m], p_A (3,), p_B (3,), n (3,), k, l) for A's edge k and B's
    edge l, in the order of 12 k + l.

    With edges a0 + s e_A (0 <= s <= L_A) and b0 + t e_B: n = +-(e_A x e_B)/|e_A x e_B| oriented out of
    B's edge (n in the cone of B's two face normals there, -n in A's, both to CONE; outside one by less than
    CONE: that cone's nearest direction, the face normal at its other end, docs/theory.md §6.2), p_A, p_B the two
    lines' closest points, g = n.(p_A - p_B) = n.(a0 - b0) the signed distance between the lines (> 0
    apart, < 0 crossed). A pair counts when both closest points are inside their edges (EDGE_END of the
    length from either end: a crossing at an end is a vertex's contact), g <= tol, and where they cross
    (g < 0) -g <= DEPTH_RATIO overlap(box_a, box_b) + tol. With n in both cones, -g is the overlap of the
    boxes' projections on n, so -g >= overlap(): a crossing much deeper than the boxes' penetration depth is
    the two lines meeting far from where the boxes overlap (a box's side edge standing 3 um into a slab's top
    face, 5 cm behind the slab's end edge, gave g = -5 cm). Parallel edges (|e_A x e_B| < PARALLEL) never
    count."""
    a0, ea, la, fa = A
    b0, eb, lb, fb = B
    # a box's edges run along its 3 axes (edge k along axis k // 4): the 144 cross products are 9
    c = cross_rows(ea[::4, None, :], eb[None, ::4, :])[_AXIS[:, None], _AXIS[None, :]]  # (12, 12, 3)
    s = np.sqrt(_dots(c, c))  # index-order sums: src/box_box.hpp edge_candidates
    ok = s > PARALLEL
    n = c / np.where(ok, s, 1.0)[:, :, None]
    nb = _dots(n[:, :, None, :], fb[None, :, :, :])  # n against B's two face normals at edge l
    flip = nb.sum(axis=2) < 0.0
    n[flip] *= -1.0
    nb[flip] *= -1.0
    na = _dots(n[:, :, None, :], fa[:, None, :, :])
    ok &= (nb.min(axis=2) >= -CONE) & (na.max(axis=2) <= CONE)
    # a normal outside a cone by less than CONE (nearly parallel edges of faces on faces: e_A x e_B is then the
    # faces' relative tilt over their relative yaw, ill-conditioned) is the cone's nearest direction: the face
    # normal at the cone's other end (A's first, then B's)
    k_a, l_a = np.nonzero(ok & (na.max(axis=2) > 0.0))
    n[k_a, l_a] = -fa[k_a, 1 - na[k_a, l_a].argmax(axis=1)]
    k_b, l_b = np.nonzero(ok & (na.max(axis=2) <= 0.0) & (nb.min(axis=2) < 0.0))
    n[k_b, l_b] = fb[l_b, 1 - nb[k_b, l_b].argmin(axis=1)]
    w = a0[:, None, :] - b0[None, :, :]
    g = _dots(n, w)
    ok &= g <= tol
    if not ok.any():
        return []
    bb = _dots(ea[:, None, :], eb[None, :, :])
    d = _dots(ea[:, None, :], w)
    e = _dots(eb[None, :, :], w)
    den = np.where(ok, s * s, 1.0)  # 1 - (e_A.e_B)^2
    sa = (bb * e - d) / den
    tb = (e - bb * d) / den
    ok &= (sa >= EDGE_END * la[:, None]) & (sa <= (1.0 - EDGE_END) * la[:, None])
    ok &= (tb >= EDGE_END * lb[None, :]) & (tb <= (1.0 - EDGE_END) * lb[None, :])
    if (g[ok] < 0.0).any():
        ok &= g >= depth_floor(box_a, box_b, tol)
    return [(float(g[k, j]), a0[k] + sa[k, j] * ea[k], b0[j] + tb[k, j] * eb[j], n[k, j], int(k), int(j))
            for k, j in zip(*np.nonzero(ok))]
