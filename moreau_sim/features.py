"""Per-feature gaps of the contact layer, and what an integrator that locates events does with them.

A *feature* is one gap function of a collision pair, with its row w, the drift term Wdot' u
(from Pinocchio's bias accelerations) and gamma = w' u: every vertex of a polytope against a
half-space, a sphere against a half-space, a sphere against a sphere, a sphere against a static
box; and for two boxes (either moving, docs/theory.md §7.1), computed per pair in numpy:
  - "vertex_box": each box's vertices p in the other, g = max_f (n_f' p - d_f) over the other's
    face planes (at a tie within contact_tolerance, the faces the vertex's own cone can touch
    first), n the arg-max face's normal (kept through a phase while persistent), drift
    n'(abar_A(p) - abar_B(p)) + 2 (w_face x n)' dv; its region ends at its face's edges;
  - "edge_edge": each of the 12 x 12 edge pairs, g = d = n'(a0 - b0) along n = +-(e_A x e_B)/|.|
    (outward of B's edge) while active (n in both edges' normal cones, the lines' closest points
    inside both edges, d >= -smallest half side), else a positive stand-in; rows at the closest
    points, drift n'(abar_A - abar_B) + 2 n_dot' dv - d |n_dot|^2; its region ends where the
    closest points leave the edges (`margin`: the distance to a region's end, an event in a phase);
  - while the pair's bounding spheres are apart, all its features report the spheres' gap.
Per-vertex gaps (not coal's pair distance, which is the minimum over corners and stays 0
while a block pivots) make each corner of a rocking block its own event. Other pair types
(cylinders, meshes) raise :class:`UnsupportedModel` naming the pair.

:class:`FeatureContacts` holds what the event-driven integrator (event_driven.py, docs/theory.md
§7) and the adaptive one (adaptive.py, §8) share: the features' kinematics, the constrained
accelerations of a persistent set C (a = ABA + M^-1 W_C lam, W_C' a + Wdot_C' u = 0), and
:meth:`FeatureContacts.resolve` at an event: the impact (law.impact on the contacts
contacts.detect closes, or at a corner the fixed step's set-valued law, docs/theory.md §3, §7;
with the Zeno rule), then the acceleration-level contact problem that
decides which touching contacts persist (event_driven.py's module doc states the rules).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import coal
import numpy as np
import pinocchio as pin

from .constraints import assemble_constraints
from .contacts import FeatureKind, detect, from_rows
from .data import Data
from .errors import MoreauSimError, SimulationError, named_stops
from .law import impact, project
from .model import Model
from .recording import LOG_RELATIVE, PercussionRow, Recorder
from .state import State
from .stepper import ContactProblem, solve_impact
from .trajectory import Trajectory

V_TOL = 1e-9  # [m/s] |gamma| <= this on a closed feature: touching, not impacting
G_RES = 1e-13  # [m] smallest gap whose sign is trusted (~3000x the rounding of positions ~ 1 m)
G_ZENO = 1e-12  # [m] a rebound whose apex would stay below this is not resolved (Zeno rule)
V_ZENO = 1e-8  # [m/s] nor an impact slower than this
DT_ZENO = 1e-12  # [s] nor an impact this soon after the previous one
LAM_EPS = 1e-9  # [N] a persistent contact is released when its multiplier falls below -LAM_EPS
G_REGION = 1e-6  # [m] ... or a persistent box feature when it passes its region's end by this (§7.1)
ACC_TOL = 1e-8  # [m/s^2] relative acceleration below this (scaled): a touching contact persists


class UnsupportedModel(MoreauSimError, ValueError):
    """The reference cannot integrate this model (a pair type it has no analytic gap for)."""


@dataclass(frozen=True, slots=True)
class Feature:
    """One gap function. kind "point_plane": point `p` (joint frame of joint_a) above the plane
    n' x = d (world); "sphere_sphere": centres p (joint_a) and p_b (joint_b), radii r, r_b;
    "sphere_box": centre p (joint_a), radius r, static box (rotation R, centre c, half sides h);
    "vertex_box", "edge_edge": feature `feature` of the box pair `box` (:class:`BoxPair`)."""

    kind: str
    pair: int
    feature: int
    joint_a: int
    joint_b: int
    p: np.ndarray
    n: np.ndarray = field(default_factory=lambda: np.zeros(3))
    d: float = 0.0
    r: float = 0.0
    p_b: np.ndarray = field(default_factory=lambda: np.zeros(3))
    r_b: float = 0.0
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    h: np.ndarray = field(default_factory=lambda: np.zeros(3))
    box: "BoxPair | None" = None  # "vertex_box" / "edge_edge": the pair's geometry (vectorized kinds)


ARC_TOL = 1e-9  # an edge pair's normal may leave the edges' normal cones by this (face on face: at their ends)
EDGE_END = 1e-6  # an edge pair is active only where both closest points are this far (relative) from the ends
PARALLEL = 1e-9  # |e_A x e_B| below this: parallel edges, no edge-edge gap (the vertices cover faces on faces)
BOX_FEATURES = 16 + 144  # per box pair: 8 + 8 vertices in the other box, 12 x 12 edge pairs


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


def _box(model: Model, g: int, joint: int) -> _Box:
    go = model.geom.geometryObjects[g]
    h = np.asarray(go.geometry.halfSide, float)
    Rg, tg = go.placement.rotation, go.placement.translation
    e0, ed, el, ef = [], [], [], []
    for a in range(3):  # the 4 edges along axis a, at the signs (sb, sc) of the other two axes
        b, c = (a + 1) % 3, (a + 2) % 3
        for sb in (-1.0, 1.0):
            for sc in (-1.0, 1.0):
                x = np.zeros(3)
                x[a], x[b], x[c] = -h[a], sb * h[b], sc * h[c]
                e0.append(Rg @ x + tg)
                ed.append(Rg[:, a].copy())
                el.append(2.0 * h[a])
                ef.append([sb * Rg[:, b], sc * Rg[:, c]])
    fn, fd = model.face_planes[g]
    return _Box(joint, np.asarray(model.vertices[g]), np.asarray(model.vertex_edges[g]), np.asarray(fn),
                np.asarray(fd), np.array(e0), np.array(ed), np.array(el), np.array(ef), tg.copy(),
                float(np.linalg.norm(h)), float(h.min()))


@dataclass(frozen=True, slots=True, eq=False)
class BoxPair:
    """A pair of two boxes A (coal's first shape) and B (second), either moving or static: the
    geometry of its BOX_FEATURES features (docs/theory.md §7.1): feature i < 8 is A's vertex i in
    B, 8 <= i < 16 B's vertex i - 8 in A, 16 + 12 k + l the edge pair (A's edge k, B's edge l)."""

    pair: int
    a: _Box
    b: _Box


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b of (k, 3) arrays (broadcasting; np.cross's axis handling costs ~30 us a call)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), axis=-1)


def _skew(w: np.ndarray) -> np.ndarray:
    """The matrix of w x . (3, 3)."""
    w0, w1, w2 = w.tolist()
    return np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for 3-vectors (in Python floats: the same IEEE operations, without numpy's per-element cost)."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def feature_list(model: Model) -> tuple[Feature, ...]:
    """The gap functions of every collision pair (UnsupportedModel for other pair types)."""
    out = []
    gobs = model.geom.geometryObjects
    for pair in model.pairs:
        ga, gb = gobs[pair.first], gobs[pair.second]
        sa, sb = ga.geometry, gb.geometry
        ja, jb = pair.joint_first, pair.joint_second
        if isinstance(sb, coal.Halfspace) and jb == 0:
            _, n, d = model.bounds[pair.second]
            if isinstance(sa, coal.Sphere) and sa.radius > 0:
                centre = ga.placement.translation.copy()
                out.append(Feature("point_plane", pair.index, -1, ja, 0, centre, n, d + sa.radius))
                continue
            if len(model.vertices[pair.first]):
                out += [Feature("point_plane", pair.index, i, ja, 0, v.copy(), n, d)
                        for i, v in enumerate(model.vertices[pair.first])]
                continue
        if isinstance(sa, coal.Sphere) and isinstance(sb, coal.Sphere):
            out.append(Feature("sphere_sphere", pair.index, -1, ja, jb, ga.placement.translation.copy(),
                                r=sa.radius, p_b=gb.placement.translation.copy(), r_b=sb.radius))
            continue
        if isinstance(sa, coal.Sphere) and isinstance(sb, coal.Box) and jb == 0:
            out.append(Feature("sphere_box", pair.index, -1, ja, 0, ga.placement.translation.copy(), r=sa.radius,
                                R=gb.placement.rotation.copy(), p_b=gb.placement.translation.copy(),
                                h=np.asarray(sb.halfSide, float).copy()))
            continue
        if isinstance(sa, coal.Box) and isinstance(sb, coal.Box):
            bp = BoxPair(pair.index, _box(model, pair.first, ja), _box(model, pair.second, jb))
            out += [Feature("vertex_box" if i < 16 else "edge_edge", pair.index, i, ja, jb,
                            (bp.a.v[i] if i < 8 else bp.b.v[i - 8]) if i < 16 else np.zeros(3), box=bp)
                    for i in range(BOX_FEATURES)]
            continue
        raise UnsupportedModel(f"{model.scene.name}: pair '{pair.name}' ({type(sa).__name__} vs "
                               f"{type(sb).__name__}): the feature integrators have gaps for polytope or "
                               "sphere vs half-space, sphere vs sphere, sphere vs static box and box vs box only")
    return tuple(out)


@dataclass(frozen=True, slots=True)
class FeatureState:
    """Gaps g [m], rows W (nv, k), drift Wdot' u [m/s^2] and gamma = W' u [m/s] of features."""

    g: np.ndarray
    W: np.ndarray
    drift: np.ndarray
    gamma: np.ndarray


class FeatureContacts:
    """The features of a model and the contact decisions at events (module doc). Mutable
    bookkeeping shared by the event-driven and the adaptive runs: the Recorder `rec` (set by the
    caller), the Zeno declarations, the contact work since the last sample, counters."""

    def __init__(self, model: Model, data: Data, e: float, feats: tuple[Feature, ...] | None = None):
        self.model, self.data, self.e = model, data, e
        # a feature is closed when its gap is <= this [m]: the tolerance contacts.detect uses
        self.gap_tol = max(model.options.contact_tolerance, G_RES)
        self.pm, self.pd = model.pin, data.pin
        self.nv = model.nv
        self.feats = feature_list(model) if feats is None else feats
        self.zero = np.zeros(self.nv)
        self.rec: Recorder | None = None
        self.zeno: list[dict] = []
        self.work = 0.0  # contact work since the last sample [J] (= -energy lost in impacts)
        self.last_impact = -np.inf
        self.impacts = self.nfev = 0
        self.t = float("nan")  # [s] where the run is (errors name it): a step's or phase's start, an event
        self.box_faces: dict = {}  # pair -> (vertex features, their faces) at the last call
        self.faces: dict = {}  # (pair, vertex feature) -> its face, for the persistent vertices of a phase
        self.box_points: dict = {}  # pair -> (features, points on A, on B, normals) at the last call with rows
        # pair -> the column of its feature 0 in feats (box pairs' features are consecutive)
        self.box_index = {f.pair: i for i, f in reversed(list(enumerate(self.feats))) if f.box is not None}
        self._redundant: dict = {}  # persistent set C -> its rows are linearly dependent
        self.edge_active: dict = {}  # pair -> (edge features, gap was d: not a stand-in) at the last call

    # ---- kinematics of the features -------------------------------------------------------
    def _point(self, j: int, p_local: np.ndarray, rows: bool):
        """World position, velocity, bias acceleration (q'' = 0) and Jacobian (3, nv) of a
        point fixed in joint j's frame (needs forwardKinematics(q, u, 0) and, for rows, J)."""
        if j == 0:
            return p_local, np.zeros(3), np.zeros(3), (np.zeros((3, self.nv)) if rows else None)
        frame = self._frames.get(j)
        if frame is None:  # the joint's placement, twist and bias acceleration, read once per call
            M, v, a = self.pd.oMi[j], self.pd.v[j], self.pd.a[j]
            frame = self._frames[j] = (M.rotation, M.translation, v.angular, v.linear, a.angular, a.linear)
        R, t, w, v_lin, a_ang, a_lin = frame
        vl = v_lin + cross(w, p_local)
        p = R @ p_local + t
        vel = R @ vl
        acc = R @ (a_lin + cross(a_ang, p_local) + cross(w, vl))
        Jp = None
        if rows:
            if self._J is None:
                self._J = self.pd.J.reshape(6, -1)
            J = self._J
            Jp = (J[:3] - pin.skew(p) @ J[3:]) * self.model.support_mask[j]
        return p, vel, acc, Jp

    def features(self, q: np.ndarray, u: np.ndarray, idx=None, rows: bool = True) -> FeatureState:
        """Gaps (and rows, drift, gamma if `rows`) of the features `idx` (default all) at (q, u)."""
        pm, pd = self.pm, self.pd
        if rows:
            pin.computeJointJacobians(pm, pd, q)
        pin.forwardKinematics(pm, pd, q, u, self.zero)
        self._frames, self._J = {}, None
        self.box_points.clear()
        self.box_faces.clear()
        self.edge_active.clear()
        idx = range(len(self.feats)) if idx is None else idx
        k = len(idx)
        g, drift, W = np.empty(k), np.zeros(k), np.zeros((self.nv, k))
        self.margin = np.full(k, np.inf)  # [m] each feature's distance to the end of its region (below)
        self.smooth = np.ones(k, bool)  # False: an edge pair's stand-in (its rows and drift are the lines')
        boxes: dict = {}
        for col, i in enumerate(idx):
            f = self.feats[i]
            if f.box is not None:  # box-box kinds: vectorized per pair, below
                entry = boxes.get(f.pair)
                if entry is None:
                    entry = boxes[f.pair] = (f.box, [], [])
                entry[1].append(col)
                entry[2].append(f.feature)
                continue
            pa, va, aa, Ja = self._point(f.joint_a, f.p, rows)
            if f.kind == "point_plane":
                n, curv = f.n, 0.0
                g[col] = n @ pa - f.d
                vrel, arel, Jrel = va, aa, Ja
            elif f.kind == "sphere_sphere":
                pb, vb, ab, Jb = self._point(f.joint_b, f.p_b, rows)
                dv = pa - pb
                dist = float(np.sqrt(dv @ dv))
                n = dv / dist
                g[col] = dist - f.r - f.r_b
                vrel, arel = va - vb, aa - ab
                Jrel = Ja - Jb if rows else None
                curv = (vrel @ vrel - (n @ vrel) ** 2) / dist
            else:  # sphere_box: distance from the centre to a static box (face, edge or vertex region)
                cl = f.R.T @ (pa - f.p_b)
                clamp = np.clip(cl, -f.h, f.h)
                out = np.abs(cl) > f.h
                vl = f.R.T @ va
                if out.any():
                    diff = cl - clamp
                    dist = float(np.sqrt(diff @ diff))
                    nl = diff / dist
                    g[col] = dist - f.r
                    # curvature of the distance: the velocity across the closest edge/vertex
                    vp = np.where(out, vl, 0.0)
                    curv = (vp @ vp - (nl @ vl) ** 2) / dist if out.sum() > 1 else 0.0
                else:  # centre inside the box: the nearest face
                    s = f.h - np.abs(cl)
                    ax = int(np.argmin(s))
                    nl = np.zeros(3)
                    nl[ax] = np.sign(cl[ax]) or 1.0
                    g[col] = -s[ax] - f.r
                    curv = 0.0
                n = f.R @ nl
                vrel, arel, Jrel = va, aa, Ja
            if rows:
                drift[col] = n @ arel + curv
                W[:, col] = n @ Jrel
        for bp, cols, which in boxes.values():
            g[cols], Wb, db = self._box_pair(bp, np.array(which), rows)
            self.margin[cols] = self._box_margin
            self.smooth[cols] = self._box_smooth
            if rows:
                W[:, cols] = Wb
                drift[cols] = db
        gamma = W.T @ u if rows else np.zeros(k)
        return FeatureState(g, W, drift, gamma)

    # ---- box-box kinds (docs/theory.md §7.1), all BOX_FEATURES of a pair at once ----------------
    def _frame(self, j: int):
        """(R, t, w, v, a_ang, a_lin) of joint j (placement; twist and bias acceleration in its frame)."""
        frame = self._frames.get(j)
        if frame is None:
            M, v, a = self.pd.oMi[j], self.pd.v[j], self.pd.a[j]
            frame = self._frames[j] = (M.rotation, M.translation, v.angular, v.linear, a.angular, a.linear)
        return frame

    def _motion(self, j: int, P: np.ndarray, rows: bool):
        """Velocities and bias accelerations (q'' = 0) (k, 3) of joint j's material points at the
        world points P (k, 3), its angular velocity (world) and its masked (J_lin, J_ang) if rows."""
        if j == 0:
            z = np.zeros_like(P)
            return z, z, np.zeros(3), None
        R, t, w, v_lin, a_ang, a_lin = self._frame(j)
        Pl = (P - t) @ R
        Sw = _skew(w)  # w x p = p @ Sw.T for the rows p of Pl
        vl = v_lin + Pl @ Sw.T
        vel = vl @ R.T
        acc = (a_lin + Pl @ _skew(a_ang).T + vl @ Sw.T) @ R.T
        J = None
        if rows:
            if self._J is None:
                self._J = self.pd.J.reshape(6, -1)
            mask = self.model.support_mask[j]
            J = (self._J[:3] * mask, self._J[3:] * mask)
        return vel, acc, R @ w, J

    def _rows(self, JA, JB, PA: np.ndarray, PB: np.ndarray, n: np.ndarray) -> np.ndarray:
        """w = J_A(p_A)' n - J_B(p_B)' n (nv, k) for contact points PA, PB and normals n (k, 3)."""
        W = np.zeros((self.nv, len(n)))
        for J, P, sign in ((JA, PA, 1.0), (JB, PB, -1.0)):
            if J is not None:  # n' J_p = n' J_lin + (p x n)' J_ang
                W += sign * (J[0].T @ n.T + J[1].T @ _cross(P, n).T)
        return W

    def _box_pair(self, bp: BoxPair, which: np.ndarray, rows: bool):
        """(g, W, drift) of box pair bp's features `which` (indices in the pair; docs/theory.md §7.1)."""
        A, B = bp.a, bp.b
        RA, tA = self._frame(A.joint)[:2] if A.joint else (np.eye(3), np.zeros(3))
        RB, tB = self._frame(B.joint)[:2] if B.joint else (np.eye(3), np.zeros(3))
        cA, cB = RA @ A.c + tA, RB @ B.c + tB
        dc = cA - cB
        dist = float(np.sqrt(dc @ dc))
        k = len(which)
        self._box_margin = np.full(k, np.inf)
        self._box_smooth = np.ones(k, bool)
        if dist > A.r + B.r:  # bounding spheres apart: every feature is open; their gap stands in
            g = np.full(k, dist - A.r - B.r)
            if not rows:
                return g, None, None
            n = dc / dist
            vA, aA, _, JA = self._motion(A.joint, cA[None], True)
            vB, aB, _, JB = self._motion(B.joint, cB[None], True)
            dv = (vA - vB)[0]
            drift = n @ (aA - aB)[0] + (dv @ dv - (n @ dv) ** 2) / dist  # as sphere_sphere
            w = self._rows(JA, JB, cA[None], cB[None], n[None])
            return g, np.repeat(w, k, axis=1), np.full(k, drift)
        g = np.empty(k)
        P_a, P_b, nn = np.empty((k, 3)), np.empty((k, 3)), np.empty((k, 3))
        extra = np.zeros(k)  # drift terms of the turning normal, per feature
        v_sel = which < 16
        e_sel = ~v_sel
        if v_sel.any():
            # vertices in the other box: s(p) = max_f (n_f' p - d_f) over the faces that count (below: a
            # vertex sliding exactly along an aligned box's edge line keeps seeing the face it meets)
            NA, NB = A.fn @ RA.T, B.fn @ RB.T
            P = np.concatenate((A.v @ RA.T + tA, B.v @ RB.T + tB))
            E = np.concatenate((A.ve @ RA.T, B.ve @ RB.T))
            wv = which[v_sel]
            P, E = P[wv], E[wv]
            ina = wv < 8  # A's vertex in B (else B's in A)
            N = np.where(ina[:, None, None], NB[None], NA[None])  # (kv, 6, 3) the other box's faces
            D = np.where(ina[:, None], (B.fd + NB @ tB)[None], (A.fd + NA @ tA)[None])
            S = np.einsum("vfe,ve->vf", N, P) - D
            # a face counts if its plane leaves the vertex's own cone outside (the vertex can touch it
            # first), or if the vertex is outside it (S > G_RES: then g > 0 whatever the cone, so a
            # block pivoting on one bottom corner keeps the other's gap over the face it comes down on)
            valid = np.einsum("vke,vfe->vkf", E, N).min(axis=1) >= -ARC_TOL
            count = valid | (S > G_RES)
            count[~count.any(axis=1)] = True
            f = np.where(count, S, -np.inf).argmax(axis=1)
            if self.faces:  # persistent vertices: the face chosen at the phase's start
                f = np.array([self.faces.get((bp.pair, k), fk) for k, fk in zip(wv.tolist(), f.tolist())])
            self.box_faces[bp.pair] = (wv, f)
            g[v_sel] = S[np.arange(len(wv)), f]
            # the vertex's distance to its face's edges: -max of the other faces' S (region, §7.1)
            self._box_margin[v_sel] = -np.where(np.arange(6)[None] == f[:, None], -np.inf, S).max(axis=1)
            if rows:
                n = N[np.arange(len(wv)), f] * np.where(ina, 1.0, -1.0)[:, None]  # from B to A
                P_a[v_sel] = P_b[v_sel] = P
                nn[v_sel] = n
        if e_sel.any():
            # edge pairs: d = n'(a0 - b0) along n = +-(e_A x e_B)/|.| (outward of B's edge)
            ka, kb = np.divmod(which[e_sel] - 16, 12)
            a0, ea, fa = A.e0[ka] @ RA.T + tA, A.ed[ka] @ RA.T, A.ef[ka] @ RA.T
            b0, eb, fb = B.e0[kb] @ RB.T + tB, B.ed[kb] @ RB.T, B.ef[kb] @ RB.T
            c = _cross(ea, eb)
            cn = np.sqrt((c * c).sum(axis=1))
            ok = cn > PARALLEL
            cn = np.where(ok, cn, 1.0)
            n = c / cn[:, None]
            sigma = np.where((n * fb.sum(axis=1)).sum(axis=1) < 0.0, -1.0, 1.0)
            n = n * sigma[:, None]
            arcs = ((np.einsum("ke,kje->kj", n, fb) >= -ARC_TOL).all(axis=1)
                    & (np.einsum("ke,kje->kj", n, fa) <= ARC_TOL).all(axis=1))
            r = a0 - b0
            d = (n * r).sum(axis=1)
            bb = (ea * eb).sum(axis=1)
            ra, rb = (r * ea).sum(axis=1), (r * eb).sum(axis=1)
            s = (bb * rb - ra) / cn ** 2  # the lines' closest points a0 + s e_A, b0 + t e_B
            t = (rb - bb * ra) / cn ** 2
            # within both edges, EDGE_END (relative) from their ends: a crossing at an end is a vertex's
            # contact (vertex_box); there the stand-in is >= EDGE_END * length, never closed
            la, lb = A.el[ka], B.el[kb]
            ex_s = np.maximum(np.maximum(EDGE_END * la - s, s - (1.0 - EDGE_END) * la), 0.0)
            ex_t = np.maximum(np.maximum(EDGE_END * lb - t, t - (1.0 - EDGE_END) * lb), 0.0)
            active = ok & arcs & (ex_s == 0.0) & (ex_t == 0.0) & (d >= -min(A.half, B.half))
            # the closest points' distance to the ends of the region where the pair counts (§7.1)
            self._box_margin[e_sel] = np.where(ok, np.minimum.reduce(
                [s - EDGE_END * la, (1.0 - EDGE_END) * la - s, t - EDGE_END * lb, (1.0 - EDGE_END) * lb - t]), np.inf)
            self.edge_active[bp.pair] = (which[e_sel], active)  # for tests
            self._box_smooth[e_sel] = active
            g[e_sel] = np.where(active, d, np.where(ok, np.sqrt(d * d + ex_s * ex_s + ex_t * ex_t), A.r + B.r))
            if rows:
                P_a[e_sel] = a0 + s[:, None] * ea
                P_b[e_sel] = b0 + t[:, None] * eb
                nn[e_sel] = np.where(ok[:, None], n, 0.0)
        if not rows:
            return g, None, None
        vA, aA, wA, JA = self._motion(A.joint, P_a, True)
        vB, aB, wB, JB = self._motion(B.joint, P_b, True)
        dv, da = vA - vB, aA - aB
        if v_sel.any():  # a vertex in a face that turns with its box: + 2 (w_face x n)' dv
            w_face = np.where(ina[:, None], wB, wA)
            extra[v_sel] = 2.0 * (_cross(w_face, nn[v_sel]) * dv[v_sel]).sum(axis=1)
        if e_sel.any():  # an edge pair: + 2 n' dv - d |n'|^2, n' the rate of the normal of e_A x e_B
            cdot = (_cross(_cross(wA[None], ea), eb) + _cross(ea, _cross(wB[None], eb))) * sigma[:, None]
            ndot = (cdot - n * (n * cdot).sum(axis=1)[:, None]) / cn[:, None]
            ndot = np.where(ok[:, None], ndot, 0.0)
            extra[e_sel] = 2.0 * (ndot * dv[e_sel]).sum(axis=1) - np.where(ok, d, 0.0) * (ndot * ndot).sum(axis=1)
        self.box_points[bp.pair] = (which, P_a, P_b, nn)  # contact points and normals (_missed_features)
        return g, self._rows(JA, JB, P_a, P_b, nn), (nn * da).sum(axis=1) + extra


    def thin_limit(self, u: np.ndarray, a: np.ndarray, h: float) -> float:
        """The longest step [s] over which no point can travel half the thinnest pair's extent
        (Model.thinnest_pair) from velocities u at accelerations a (those of the phase's persistent
        set) over a step of up to h: a gap cannot then go from one side of a thin obstacle to the
        other between two checks."""
        thin = self.model.thinnest_pair
        if not np.isfinite(thin):
            return np.inf
        v = (float(np.abs(u).max()) + float(np.abs(a).max()) * h) * self.model.reach
        return 0.5 * thin / v if v > 0.0 else np.inf

    # ---- dynamics --------------------------------------------------------------------------
    def dynamics(self, q, u, C):
        """(a, lam): free accelerations (ABA) plus the bilateral forces of the persistent set C."""
        self.nfev += 1
        a = pin.aba(self.pm, self.pd, q, u, self.zero).copy()
        if not C:
            return a, np.zeros(0)
        fs = self.features(q, u, C)
        Minv = pin.computeMinverse(self.pm, self.pd, q)
        MiW = Minv @ fs.W
        G = fs.W.T @ MiW
        rhs = -(fs.W.T @ a + fs.drift)
        redundant = self._redundant.get(C)
        if redundant is None:  # rows of C dependent (4 corners of a face on a face): decided once per set
            redundant = self._redundant[C] = bool(np.linalg.matrix_rank(fs.W) < len(C))
        if redundant:
            return a + MiW @ (lam := np.linalg.lstsq(G, rhs, rcond=1e-12)[0]), lam  # minimum-norm forces
        try:
            lam = np.linalg.solve(G, rhs)
        except np.linalg.LinAlgError:
            lam = np.linalg.lstsq(G, rhs, rcond=1e-12)[0]  # redundant rows: minimum-norm forces
        return a + MiW @ lam, lam

    # ---- events ----------------------------------------------------------------------------
    def resolve(self, t: float, q: np.ndarray, u: np.ndarray, released: frozenset):
        """Impact (with the Zeno rule), then the persistent set C at (t, q, u) (module doc).
        Returns (u, C, shadow): C persistent features, shadow: duplicates of C's rows."""
        self.t = t
        self.faces = {}  # chosen afresh at an event
        fs = self.features(q, u)
        closed = (fs.g <= self.gap_tol) & self.smooth  # an edge pair's stand-in is never a contact (§7.1)
        if (closed & (fs.gamma < -V_TOL)).any():
            u = self._impact(t, q, u, fs)
            fs = self.features(q, u)
        # a box feature past the end of its region (margin < -G_REGION/2: a phase ends at -G_REGION, docs/theory.md
        # §7.1) does not persist; a corner resting exactly on an edge (margin 0 to rounding and drift) does
        inside = self.margin > -0.5 * G_REGION
        touching = [i for i in np.flatnonzero(closed & (np.abs(fs.gamma) <= V_TOL) & inside) if i not in released]
        if not touching:
            return u, (), ()
        # distinct rows only (the front and back corners of a planar block repeat each other)
        keep, shadow = [], []
        scale = 1e-12 * (1.0 + np.abs(fs.W).max())
        for i in touching:
            (shadow if any(np.abs(fs.W[:, i] - fs.W[:, j]).max() <= scale for j in keep) else keep).append(i)
        a_free = pin.aba(self.pm, self.pd, q, u, self.zero).copy()
        M = pin.crba(self.pm, self.pd, q)
        Wk, dk = fs.W[:, keep], fs.drift[keep]
        res = project(M, Wk, a_free, b=-dk)
        if not res.ok:
            raise SimulationError(f"the contact-force QP failed ({res.status}) at t = {t:.12g} s")
        rel = Wk.T @ res.v + dk
        tol = ACC_TOL * (1.0 + np.abs(dk).max() + np.abs(Wk.T @ a_free).max())
        C = tuple(int(i) for i, r in zip(keep, rel) if r <= tol)
        for i in C:  # a persistent vertex keeps its face through the phase (its row may not flip at a tie)
            f = self.feats[i]
            if f.kind == "vertex_box":
                wv, faces = self.box_faces[f.pair]
                self.faces[(f.pair, f.feature)] = int(faces[np.searchsorted(wv, f.feature)])
        if C:  # remove the residual normal velocity of the persistent contacts (~1e-16)
            Minv = pin.computeMinverse(self.pm, self.pd, q)
            W = fs.W[:, list(C)]
            MiW = Minv @ W
            u = u - MiW @ np.linalg.lstsq(W.T @ MiW, W.T @ u, rcond=1e-12)[0]
        shadow = tuple(int(i) for i in shadow if any(np.abs(fs.W[:, i] - fs.W[:, j]).max() <= scale for j in C))
        return u, C, shadow

    def _missed_features(self, fs: FeatureState, W: np.ndarray) -> list:
        """Contact rows (as contacts.from_rows takes them) of the closed box-box vertices and of the
        closed, approaching active edge pairs whose row is not in the span of coal's rows W: an edge lying
        across a face meets the face's edges at points coal's one witness of that segment contact
        does not stand for, and coal's point query gives a vertex exactly on a face (|g| ~ 1e-17 m)
        an arbitrary normal (docs/theory.md §7.1). Needs fs = self.features(q, u) of all features."""
        out = []
        for pair, (which, P_a, P_b, nn) in self.box_points.items():
            e_which, active = self.edge_active.get(pair, (np.zeros(0, int), np.zeros(0, bool)))
            for i, k in enumerate(which.tolist()):
                if k >= 16 and not active[np.searchsorted(e_which, k)]:
                    continue
                col = self.box_index[pair] + k
                if fs.g[col] > self.gap_tol or (k >= 16 and fs.gamma[col] >= -V_TOL):
                    continue
                w = fs.W[:, col]
                if k >= 16 and W.shape[1]:  # a closed vertex's own row always replaces coal's
                    r = w - W @ np.linalg.lstsq(W, w, rcond=1e-12)[0]
                    if np.abs(r).max() <= 1e-9 * np.abs(w).max():
                        continue
                out.append((float(fs.g[col]), P_a[i], P_b[i], nn[i], pair,
                            FeatureKind.VERTEX if k < 16 else FeatureKind.WITNESS, k))
                W = np.column_stack((W, w))
        return out

    def _impact(self, t, q, u, fs: FeatureState) -> np.ndarray:
        """The impact law on the contacts detect() closes at q: law.impact (docs/theory.md §1), or at
        a corner the set-valued law with the scene's selection policy (§3, §7.2)."""
        pm, pd, model = self.pm, self.pd, self.model
        # the pairs whose features are closed are in contact: detect examines two polytopes' vertices
        # then whatever coal's narrow phase says (it can report exactly touching boxes, -7e-12 m, as apart)
        self.data.warm_start_pairs = set(self.data.warm_start_pairs) | {
            self.feats[i].pair for i in np.flatnonzero(fs.g <= self.gap_tol)}
        c = detect(model, self.data, q)
        cs = assemble_constraints(model, self.data, q, c)
        # (at a corner the struck vertex is the corner's: its faces are the pieces, not a feature row)
        missed = self._missed_features(fs, cs.W) if cs.pieces is None else []
        if missed:  # they replace coal's contacts of the same vertices
            keys = {(m[4], int(m[5]), m[6]) for m in missed}
            keep = np.array([k not in keys for k in zip(c.pair.tolist(), c.kind.tolist(), c.feature.tolist())], bool)
            cs = assemble_constraints(model, self.data, q, c.select(keep).concat(from_rows(model, missed)))
        c, M, W = cs.contacts, cs.M, cs.W
        if c.m == 0 and cs.pieces is None:
            raise SimulationError(f"a gap event at t = {t:.12g} s but coal finds no closed contact")
        if cs.pieces is None and not (W.T @ u < -V_TOL).any():
            raise SimulationError(f"a feature approaches at t = {t:.12g} s (gamma = {fs.gamma.min():.3g} m/s) but "
                                  "none of coal's closed contacts does")
        # the Zeno rule (module doc) on the approaching features: their free normal accelerations a_n
        appr = np.flatnonzero((fs.g <= self.gap_tol) & (fs.gamma < -V_TOL))
        a_n = fs.W[:, appr].T @ pin.aba(pm, pd, q, u, self.zero) + fs.drift[appr]
        speed = -fs.gamma[appr]
        low = ((self.e * speed) ** 2 < -2.0 * a_n * G_ZENO) | (speed < V_ZENO)
        zeno = bool(low.all()) or t - self.last_impact < DT_ZENO
        e = 0.0 if zeno else self.e
        if cs.pieces is None:
            imp = impact(M, W, u, e)
            P, res, u_plus, gm, gp, loss = imp.P, imp.qp, imp.u_plus, W.T @ u, W.T @ imp.u_plus, imp.energy_loss
        else:  # the fixed step's corner law on a step of zero length (v_free = u-): one home for it
            pb = ContactProblem(0.0, e, q, u, q, c, u, u, M, pin.computeMinverse(pm, pd, q), W, cs.pieces)
            sol = solve_impact(pb, model.options)
            if not sol.qp.ok:
                raise SimulationError(f"the corner law failed ({sol.qp.status}) at t = {t:.12g} s")
            c, P, res, u_plus, gm, gp = sol.contacts, sol.P, sol.qp, sol.u_next, sol.gamma_minus, sol.gamma_plus
            dv = u - res.v  # the impact's energy identity holds at every stationary point (§3)
            loss = 0.5 * (1.0 - e * e) * float(dv @ M @ dv)
            if sol.branch is not None:
                cand, chosen, ups = sol.branch
                self.rec.branch(self.rec.n, t, chosen, [(up, k.distance, k.global_min)
                                                        for up, k in zip(ups, cand.candidates)])
        if zeno and self.e < 1.0 and len(speed):
            k = int(np.argmax(speed))
            dt = 2.0 * self.e * speed[k] / ((1.0 - self.e) * -a_n[k]) if a_n[k] < 0 else 0.0
            self.zeno.append({"t": t, "t_accumulation": float(t + dt), "speed": float(speed[k]),
                              "pairs": sorted(set(c.pair.tolist()))})
        cut = LOG_RELATIVE * float(P.max(initial=0.0))
        for i in np.flatnonzero((P > cut) & (P > 0)):  # step: the index of the next sample
            self.rec.log(PercussionRow(self.rec.n, t, int(c.pair[i]), int(c.kind[i]), int(c.feature[i]), float(c.g[i]),
                                       float(P[i]), float(gm[i]), float(gp[i]), c.point_a[i], c.normal[i], True))
        self.rec.account_impact(t, q, u, u_plus, M, res.v, e, P)
        self.work -= loss
        self.last_impact = t
        self.impacts += 1
        return u_plus



    unit = "phase"  # what position() counts, in error messages

    def position(self) -> tuple[int, float]:
        """(the number of the step or phase under way, its time [s]): what an error names."""
        return self.events + 1, self.t

    def sample(self, t: float, q: np.ndarray, u: np.ndarray, n_contacts: int, corr: float = 0.0) -> None:
        """Record a sample with the contact work (and correction energy) since the previous one;
        a non-finite one stops the run (nothing non-finite is ever complete)."""
        state = State(t, q, u)
        if not state.finite():
            raise SimulationError(f"the state at t = {t:.6g} s became non-finite (NaN or inf)")
        self.rec.sample(state, self.work, corr, n_contacts)
        self.work = 0.0
        if not self.rec.finite():
            raise SimulationError(f"the energies or gaps at t = {t:.6g} s became non-finite (an overflow: check "
                                  "gravity, masses and initial velocities)")


def sample_grid(model: Model, state: State, t_end: float | None, t_eval) -> tuple[float, np.ndarray]:
    """t_end [s] (default: state.t + the scene's duration) and the sample instants of a run that
    locates events: t_eval, checked to increase strictly within [t0, t_end], or by default every
    save_every * dt of the scene's options (the instants ms.simulate records)."""
    opts = model.options
    t_end = state.t + opts.duration if t_end is None else float(t_end)
    if not t_end > state.t:
        raise ValueError(f"t_end = {t_end} s must be after the initial time {state.t} s")
    if t_eval is None:
        n = max(1, int(round((t_end - state.t) / (opts.dt * opts.save_every))))
        return t_end, state.t + (t_end - state.t) * np.arange(n + 1) / n
    t_grid = np.asarray(t_eval, float)
    if t_grid.ndim != 1 or np.any(np.diff(t_grid) <= 0) or t_grid[0] < state.t or t_grid[-1] > t_end:
        raise ValueError(f"t_eval must increase strictly within [{state.t}, {t_end}] s")
    return t_end, t_grid


def run_recorded(integ: FeatureContacts, state: State, t_end: float, t_grid: np.ndarray, meta) -> Trajectory:
    """integ.run(state, t_end, t_grid) into a new Recorder; the Trajectory with meta(model, integ,
    status, wall0), or (errors.named_stops) SimulationError naming integ.position() with
    .trajectory up to the failure, SimulationInterrupted on Ctrl-C."""
    integ.rec = Recorder(integ.model, integ.data, len(t_grid))
    integ.t = float(state.t)
    wall0 = time.perf_counter()

    def partial(status: str) -> Trajectory:
        return integ.rec.trajectory(meta(integ.model, integ, status, wall0))

    with named_stops(integ.position, partial, unit=integ.unit):
        integ.run(state, t_end, t_grid)
    return integ.rec.trajectory(meta(integ.model, integ, "complete", wall0))
