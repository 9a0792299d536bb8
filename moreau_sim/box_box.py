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
    return e0 @ R.T + oMi.translation, ed @ R.T, el, ef @ R.T


def overlap(box_a: tuple, box_b: tuple) -> float:
    """The boxes' penetration depth [m] (box_a, box_b: (R, c, half) in the world): the least overlap of their
    projections over the 15 separating axes (the 6 face normals and the 9 cross products of their
    directions); negative where an axis separates them (then not the distance, only a lower bound of it)."""
    (Ra, ca, ha), (Rb, cb, hb) = box_a, box_b
    c = cross_rows(Ra.T[:, None, :], Rb.T[None, :, :]).reshape(9, 3)
    s = np.sqrt((c * c).sum(axis=1))
    axes = np.concatenate((Ra.T, Rb.T, c[s > PARALLEL] / s[s > PARALLEL, None]))
    return float((np.abs(axes @ Ra) @ ha + np.abs(axes @ Rb) @ hb - np.abs(axes @ (ca - cb))).min())


def edge_crossings(A: tuple, B: tuple, box_a: tuple, box_b: tuple, tol: float) -> list[tuple]:
    """The edge pairs of boxes A and B (world(): edges of each; box_a, box_b: (R, c, half) of each box in the
    world) that touch or cross: each a tuple (g [m], p_A (3,), p_B (3,), n (3,), k, l) for A's edge k and B's
    edge l, in the order of 12 k + l.

    With edges a0 + s e_A (0 <= s <= L_A) and b0 + t e_B: n = +-(e_A x e_B)/|e_A x e_B| oriented out of
    B's edge (n in the cone of B's two face normals there, -n in A's, both to CONE), p_A, p_B the two
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
    s = np.sqrt(np.einsum("klx,klx->kl", c, c))
    ok = s > PARALLEL
    n = c / np.where(ok, s, 1.0)[:, :, None]
    nb = np.einsum("klx,lfx->klf", n, fb)  # n against B's two face normals at edge l
    flip = nb.sum(axis=2) < 0.0
    n[flip] *= -1.0
    nb[flip] *= -1.0
    na = np.einsum("klx,kfx->klf", n, fa)
    ok &= (nb.min(axis=2) >= -CONE) & (na.max(axis=2) <= CONE)
    w = a0[:, None, :] - b0[None, :, :]
    g = np.einsum("klx,klx->kl", n, w)
    ok &= g <= tol
    if not ok.any():
        return []
    bb = ea @ eb.T
    d = np.einsum("kx,klx->kl", ea, w)
    e = np.einsum("lx,klx->kl", eb, w)
    den = np.where(ok, s * s, 1.0)  # 1 - (e_A.e_B)^2
    sa = (bb * e - d) / den
    tb = (e - bb * d) / den
    ok &= (sa >= EDGE_END * la[:, None]) & (sa <= (1.0 - EDGE_END) * la[:, None])
    ok &= (tb >= EDGE_END * lb[None, :]) & (tb <= (1.0 - EDGE_END) * lb[None, :])
    if (g[ok] < 0.0).any():
        ok &= g >= -(DEPTH_RATIO * max(overlap(box_a, box_b), 0.0) + tol)
    return [(float(g[k, j]), a0[k] + sa[k, j] * ea[k], b0[j] + tb[k, j] * eb[j], n[k, j], int(k), int(j))
            for k, j in zip(*np.nonzero(ok))]
