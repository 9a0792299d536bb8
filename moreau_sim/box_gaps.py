"""The box-box features of the per-feature gaps (docs/theory.md §7.1): a box pair's vertices in
the other box and its edge pairs, all BOX_FEATURES of a pair at once (box_pair); gaps.py calls it.
Products are sums in index order (sums.py, docs/theory.md §2.8)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import box_box
from .kinematics import G_RES, Kinematics, cross_rows
from .model import Model
from .sums import dot3, dots

ARC_TOL = 1e-9  # an edge pair's normal may leave the edges' normal cones by this (face on face: at their ends)
EDGE_END = 1e-6  # an edge pair is active only where both closest points are this far (relative) from the ends
PARALLEL = 1e-9  # |e_A x e_B| below this: parallel edges, no edge-edge gap (the vertices cover faces on faces)
BOX_FEATURES = 16 + 144  # per box pair: 8 + 8 vertices in the other box, 12 x 12 edge pairs
EDGE_K = np.arange(12)  # a box's edges as in box_geometry: along axis k // 4, at the signs of the other two axes
BOX_EDGES = (EDGE_K // 4, (EDGE_K // 4 + 1) % 3, (EDGE_K // 4 + 2) % 3,
          np.where((EDGE_K % 4) // 2, 1.0, -1.0), np.where(EDGE_K % 2, 1.0, -1.0))


@dataclass(frozen=True, slots=True, eq=False)
class _Box:
    """One box of a pair, in its joint frame: vertices v (8, 3), the edges leaving each vertex
    ve (8, 3, 3), face planes (normals fn (6, 3), offsets fd (6,)), edges (starts e0 (12, 3),
    unit directions ed (12, 3), lengths el (12,), the two adjacent faces' normals ef (12, 2, 3)),
    bounding sphere (centre c, radius r)."""

    joint: int
    v: np.ndarray
    ve: np.ndarray
    fn: np.ndarray
    fd: np.ndarray
    e0: np.ndarray
    ed: np.ndarray
    el: np.ndarray
    ef: np.ndarray
    c: np.ndarray
    r: float
    half: float  # [m] smallest half side


def box_geometry(model: Model, g: int, joint: int) -> _Box:
    go = model.geometries[g]
    h = np.asarray(go.geometry.halfSide, float)
    tg = go.placement.translation
    e0, ed, el, ef = box_box.box_edges(go.geometry, go.placement)  # the 12 edges in the joint frame
    fn, fd = model.face_planes[g]
    return _Box(joint, np.asarray(model.vertices[g]), np.asarray(model.vertex_edges[g]), np.asarray(fn),
                np.asarray(fd), e0, ed, el, ef, tg.copy(),
                float(np.linalg.norm(h)), float(h.min()))


@dataclass(frozen=True, slots=True, eq=False)
class BoxPair:
    """A pair of two boxes A (coal's first shape) and B (second), either moving or static: the
    geometry of its BOX_FEATURES features (docs/theory.md §7.1): feature i < 8 is A's vertex i in
    B, 8 <= i < 16 B's vertex i - 8 in A, 16 + 12 k + l the edge pair (A's edge k, B's edge l)."""

    pair: int
    a: _Box
    b: _Box


@dataclass(frozen=True, slots=True)
class BoxGaps:
    """What box_pair computes for the features `which` of one pair: g [m], W (nv, k) and drift
    [m/s^2] (None without rows), margin [m] and smooth (as FeatureState's); faces: (vertex
    features, their faces) if it has vertices; edges: (edge features, active) if it has edge
    pairs; points: (which, points on A, on B, normals) with rows and the bounding spheres
    overlapping (else None)."""

    g: np.ndarray
    W: np.ndarray | None
    drift: np.ndarray | None
    margin: np.ndarray
    smooth: np.ndarray
    faces: tuple | None
    edges: tuple | None
    points: tuple | None


def box_pair(kin: Kinematics, bp: BoxPair, which: np.ndarray, rows: bool, faces: dict) -> BoxGaps:
    """The gaps of box pair bp's features `which` (indices in the pair; docs/theory.md §7.1); faces:
    (pair, vertex feature) -> the face a persistent vertex keeps."""
    A, B = bp.a, bp.b
    RA, tA = kin.frame(A.joint)[:2] if A.joint else (np.eye(3), np.zeros(3))
    RB, tB = kin.frame(B.joint)[:2] if B.joint else (np.eye(3), np.zeros(3))
    cA, cB = dots(RA, A.c) + tA, dots(RB, B.c) + tB
    dc = cA - cB
    dist = float(np.sqrt(dot3(dc, dc)))
    k = len(which)
    margin = np.full(k, np.inf)
    smooth = np.ones(k, bool)
    if dist > A.r + B.r:  # bounding spheres apart: every feature is open; their gap stands in
        g = np.full(k, dist - A.r - B.r)
        if not rows:
            return BoxGaps(g, None, None, margin, smooth, None, None, None)
        n = dc / dist
        vA, aA, _, JA = kin.motion(A.joint, cA[None], True)
        vB, aB, _, JB = kin.motion(B.joint, cB[None], True)
        dv = (vA - vB)[0]
        drift = dot3(n, (aA - aB)[0]) + (dot3(dv, dv) - dot3(n, dv) ** 2) / dist  # as sphere_sphere
        w = kin.rows(JA, JB, cA[None], cB[None], n[None])
        return BoxGaps(g, np.repeat(w, k, axis=1), np.full(k, drift), margin, smooth, None, None, None)
    g = np.empty(k)
    v_faces = e_active = None
    P_a, P_b, nn = np.empty((k, 3)), np.empty((k, 3)), np.empty((k, 3))
    extra = np.zeros(k)  # drift terms of the turning normal, per feature
    v_sel = which < 16
    e_sel = ~v_sel
    if v_sel.any():
        # vertices in the other box: s(p) = max_f (n_f' p - d_f) over the faces that count (below: a
        # vertex sliding exactly along an aligned box's edge line keeps seeing the face it meets)
        NA, NB = dots(A.fn[:, None], RA), dots(B.fn[:, None], RB)  # the rows of fn @ R.T
        P = np.concatenate((dots(A.v[:, None], RA) + tA, dots(B.v[:, None], RB) + tB))
        E = np.concatenate((dots(A.ve[..., None, :], RA), dots(B.ve[..., None, :], RB)))
        wv = which[v_sel]
        P, E = P[wv], E[wv]
        ina = wv < 8  # A's vertex in B (else B's in A)
        N = np.where(ina[:, None, None], NB[None], NA[None])  # (kv, 6, 3) the other box's faces
        D = np.where(ina[:, None], (B.fd + dots(NB, tB))[None], (A.fd + dots(NA, tA))[None])
        S = dots(N, P[:, None]) - D
        # a face counts if its plane leaves the vertex's own cone outside (the vertex can touch it
        # first), or if the vertex is outside it (S > G_RES: then g > 0 whatever the cone, so a
        # block pivoting on one bottom corner keeps the other's gap over the face it comes down on)
        valid = dots(E[:, :, None], N[:, None]).min(axis=1) >= -ARC_TOL
        count = valid | (S > G_RES)
        count[~count.any(axis=1)] = True
        f = np.where(count, S, -np.inf).argmax(axis=1)
        if faces:  # persistent vertices: the face chosen at the phase's start
            f = np.array([faces.get((bp.pair, k), fk) for k, fk in zip(wv.tolist(), f.tolist())])
        v_faces = (wv, f)
        g[v_sel] = S[np.arange(len(wv)), f]
        # the vertex's distance to its face's edges: -max of the other faces' S (region, §7.1)
        margin[v_sel] = -np.where(np.arange(6)[None] == f[:, None], -np.inf, S).max(axis=1)
        if rows:
            n = N[np.arange(len(wv)), f] * np.where(ina, 1.0, -1.0)[:, None]  # from B to A
            P_a[v_sel] = P_b[v_sel] = P
            nn[v_sel] = n
    if e_sel.any():
        # edge pairs: d = n'(a0 - b0) along n = +-(e_A x e_B)/|.| (outward of B's edge)
        ka, kb = np.divmod(which[e_sel] - 16, 12)
        a0, ea, fa = dots(A.e0[ka][:, None], RA) + tA, dots(A.ed[ka][:, None], RA), dots(A.ef[ka][..., None, :], RA)
        b0, eb, fb = dots(B.e0[kb][:, None], RB) + tB, dots(B.ed[kb][:, None], RB), dots(B.ef[kb][..., None, :], RB)
        c = cross_rows(ea, eb)
        cn = np.sqrt(dots(c, c))
        ok = cn > PARALLEL
        cn = np.where(ok, cn, 1.0)
        n = c / cn[:, None]
        sigma = np.where(dots(n, fb[:, 0] + fb[:, 1]) < 0.0, -1.0, 1.0)
        n = n * sigma[:, None]
        arcs = ((dots(n[:, None], fb) >= -ARC_TOL).all(axis=1) & (dots(n[:, None], fa) <= ARC_TOL).all(axis=1))
        r = a0 - b0
        d = dots(n, r)
        bb = dots(ea, eb)
        ra, rb = dots(r, ea), dots(r, eb)
        s = (bb * rb - ra) / cn ** 2  # the lines' closest points a0 + s e_A, b0 + t e_B
        t = (rb - bb * ra) / cn ** 2
        # within both edges, EDGE_END (relative) from their ends: a crossing at an end is a vertex's
        # contact (vertex_box); there the stand-in is >= EDGE_END * length, never closed
        la, lb = A.el[ka], B.el[kb]
        ex_s = np.maximum(np.maximum(EDGE_END * la - s, s - (1.0 - EDGE_END) * la), 0.0)
        ex_t = np.maximum(np.maximum(EDGE_END * lb - t, t - (1.0 - EDGE_END) * lb), 0.0)
        active = ok & arcs & (ex_s == 0.0) & (ex_t == 0.0) & (d >= -min(A.half, B.half))
        # the closest points' distance to the ends of the region where the pair counts (§7.1)
        margin[e_sel] = np.where(ok, np.minimum.reduce(
            [s - EDGE_END * la, (1.0 - EDGE_END) * la - s, t - EDGE_END * lb, (1.0 - EDGE_END) * lb - t]), np.inf)
        e_active = (which[e_sel], active)
        smooth[e_sel] = active
        g[e_sel] = np.where(active, d, np.where(ok, np.sqrt(d * d + ex_s * ex_s + ex_t * ex_t), A.r + B.r))
        if rows:
            P_a[e_sel] = a0 + s[:, None] * ea
            P_b[e_sel] = b0 + t[:, None] * eb
            nn[e_sel] = np.where(ok[:, None], n, 0.0)
    if not rows:
        return BoxGaps(g, None, None, margin, smooth, v_faces, e_active, None)
    vA, aA, wA, JA = kin.motion(A.joint, P_a, True)
    vB, aB, wB, JB = kin.motion(B.joint, P_b, True)
    dv, da = vA - vB, aA - aB
    if v_sel.any():  # a vertex in a face that turns with its box: + 2 (w_face x n)' dv
        w_face = np.where(ina[:, None], wB, wA)
        extra[v_sel] = 2.0 * dots(cross_rows(w_face, nn[v_sel]), dv[v_sel])
    if e_sel.any():  # an edge pair: + 2 n' dv - d |n'|^2, n' the rate of the normal of e_A x e_B
        cdot = (cross_rows(cross_rows(wA[None], ea), eb) + cross_rows(ea, cross_rows(wB[None], eb))) * sigma[:, None]
        ndot = (cdot - n * dots(n, cdot)[:, None]) / cn[:, None]
        ndot = np.where(ok[:, None], ndot, 0.0)
        extra[e_sel] = 2.0 * dots(ndot, dv[e_sel]) - np.where(ok, d, 0.0) * dots(ndot, ndot)
    return BoxGaps(g, kin.rows(JA, JB, P_a, P_b, nn), dots(nn, da) + extra, margin, smooth, v_faces, e_active,
                   (which, P_a, P_b, nn))
