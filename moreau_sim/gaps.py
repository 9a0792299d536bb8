"""The contact layer's per-feature gaps (docs/theory.md §7, §7.1, §7.2): each feature of a collision
pair (and each joint limit, limits.py) with its gap g, row w, drift Wdot' u and gamma = w' u, from (q, u):
:meth:`Gaps.features` returns everything it computes (FeatureState) and keeps nothing between calls.
The decisions at events that use them are in event_rules.py."""

from __future__ import annotations

from dataclasses import dataclass, field

import coal
import numpy as np
import pinocchio as pin

from .data import Data
from .errors import MoreauSimError, SimulationError
from .limits import JointLimit
from .model import Model

G_RES = 1e-13  # [m] smallest gap whose sign is trusted (~3000x the rounding of positions ~ 1 m)


class UnsupportedModel(MoreauSimError, ValueError):
    """The reference cannot integrate this model (a pair type it has no analytic gap for)."""


@dataclass(frozen=True, slots=True)
class Feature:
    """One gap function. kind "point_plane": point `p` (joint frame of joint_a) above the plane
    n' x = d (world); "sphere_sphere": centres p (joint_a) and p_b (joint_b), radii r, r_b;
    "sphere_box": centre p (joint_a), radius r, static box (rotation R, centre p_b, half sides h);
    "rim_plane", "rim_box", "side_edge": a cylinder on joint_a (centre p, axis a, radius r, half
    length hl) with cap `feature` (0: +hl, 1: -hl) against the plane (n, d) or the static box (R,
    p_b, h), or with the box's edge `feature`; "sphere_cylinder": the sphere (p on joint_a, r)
    against the cylinder (p_b, a on joint_b, r_b, hl); "vertex_box", "edge_edge": feature
    `feature` of the box pair `box` (:class:`BoxPair`); "joint_limit": the joint limit `limit`."""

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
    a: np.ndarray = field(default_factory=lambda: np.zeros(3))  # cylinder kinds: unit axis (its joint's frame)
    hl: float = 0.0  # cylinder kinds: half length [m]
    limit: "JointLimit | None" = None  # "joint_limit": g = sign (q_i - bound), row sign e_i, no drift (limits.py)


ARC_TOL = 1e-9  # an edge pair's normal may leave the edges' normal cones by this (face on face: at their ends)
EDGE_END = 1e-6  # an edge pair is active only where both closest points are this far (relative) from the ends
PARALLEL = 1e-9  # |e_A x e_B| below this: parallel edges, no edge-edge gap (the vertices cover faces on faces)
BOX_FEATURES = 16 + 144  # per box pair: 8 + 8 vertices in the other box, 12 x 12 edge pairs
_K = np.arange(12)  # a box's edges as in _box: along axis k // 4, at the signs of the other two axes
_EDGES = (_K // 4, (_K // 4 + 1) % 3, (_K // 4 + 2) % 3,
          np.where((_K % 4) // 2, 1.0, -1.0), np.where(_K % 2, 1.0, -1.0))
CYL_SCREEN = 0.01  # [m] a cylinder's bounding sphere this far from a box: its features report the sphere's gap
SIN_FLAT = 1e-6  # a closed cylinder rim whose cap is within this (sine) of parallel to the plane: refused (§7.2)


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
        cyl = _cylinder_features(model, pair) if coal.Cylinder in (type(sa), type(sb)) else None
        if cyl is not None:
            out += cyl
            continue
        if isinstance(sa, coal.Box) and isinstance(sb, coal.Box):
            bp = BoxPair(pair.index, _box(model, pair.first, ja), _box(model, pair.second, jb))
            out += [Feature("vertex_box" if i < 16 else "edge_edge", pair.index, i, ja, jb,
                            (bp.a.v[i] if i < 8 else bp.b.v[i - 8]) if i < 16 else np.zeros(3), box=bp)
                    for i in range(BOX_FEATURES)]
            continue
        raise UnsupportedModel(f"{model.scene.name}: pair '{pair.name}' ({type(sa).__name__} vs "
                               f"{type(sb).__name__}): the feature integrators have gaps for polytope, sphere or "
                               "cylinder vs half-space, sphere vs sphere, sphere or cylinder vs static box, sphere "
                               "vs cylinder and box vs box only")
    return tuple(out) + tuple(Feature("joint_limit", lim.pair, lim.joint, lim.joint, 0, np.zeros(3), limit=lim)
                              for lim in model.limits)


CYLINDER_KINDS = ("rim_plane", "rim_box", "side_edge", "sphere_cylinder")


def _cylinder_features(model: Model, pair) -> list[Feature] | None:
    """The features of a pair with a cylinder (docs/theory.md §7.2), or None for a pair type
    without them: a moving cylinder's two cap rims (feature 0: the cap at +halfLength along its
    axis, 1: at -halfLength) against a static half-space or box (and its side against the box's
    edges); a sphere against a cylinder (either moving). Gaps and rows do not depend on which shape coal lists first."""
    gobs = model.geom.geometryObjects
    ends = [(pair.first, pair.joint_first), (pair.second, pair.joint_second)]
    if not isinstance(gobs[ends[0][0]].geometry, coal.Cylinder):
        ends.reverse()
    (gc, jc), (gx, jx) = ends
    go, other = gobs[gc], gobs[gx]
    cyl, shape = go.geometry, other.geometry
    centre, axis = go.placement.translation.copy(), go.placement.rotation[:, 2].copy()
    r, hl = float(cyl.radius), float(cyl.halfLength)
    if isinstance(shape, coal.Halfspace) and jx == 0 and jc != 0:
        _, n, d = model.bounds[gx]
        return [Feature("rim_plane", pair.index, k, jc, 0, centre, n, d, r=r, a=axis, hl=hl) for k in (0, 1)]
    if isinstance(shape, coal.Box) and jx == 0 and jc != 0:
        box = dict(r=r, R=other.placement.rotation.copy(), p_b=other.placement.translation.copy(),
                   h=np.asarray(shape.halfSide, float).copy(), a=axis, hl=hl)
        return ([Feature("rim_box", pair.index, k, jc, 0, centre, **box) for k in (0, 1)]
                + [Feature("side_edge", pair.index, k, jc, 0, centre, **box) for k in range(12)])
    if isinstance(shape, coal.Sphere) and shape.radius > 0 and (jc != 0 or jx != 0):
        return [Feature("sphere_cylinder", pair.index, -1, jx, jc, other.placement.translation.copy(),
                        r=float(shape.radius), p_b=centre, r_b=r, a=axis, hl=hl)]
    return None


def _point_box(cl: np.ndarray, vl: np.ndarray, h: np.ndarray) -> tuple[float, np.ndarray, float]:
    """(signed distance [m], unit normal, curvature term [m/s^2]) of a point at cl moving with vl
    (the box's frame) from the box |x_i| <= h_i: face, edge or vertex region outside, the nearest
    face inside. The curvature term (the velocity across the closest edge/vertex) completes the
    distance's second derivative: n'(relative acceleration) + curv."""
    clamp = np.clip(cl, -h, h)
    out = np.abs(cl) > h
    if out.any():
        diff = cl - clamp
        dist = float(np.sqrt(diff @ diff))
        nl = diff / dist
        vp = np.where(out, vl, 0.0)
        return dist, nl, ((vp @ vp - (nl @ vl) ** 2) / dist if out.sum() > 1 else 0.0)
    s = h - np.abs(cl)
    ax = int(np.argmin(s))
    nl = np.zeros(3)
    nl[ax] = np.sign(cl[ax]) or 1.0
    return -float(s[ax]), nl, 0.0


def _perp(a: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to the unit vector a."""
    b = np.eye(3)[int(np.argmin(np.abs(a)))]
    b = b - (b @ a) * a
    return b / np.sqrt(b @ b)


@dataclass(frozen=True, slots=True)
class FeatureState:
    """Gaps g [m], rows W (nv, k), drift Wdot' u [m/s^2] and gamma = W' u [m/s] of features; margin
    [m]: each one's distance to the end of its region (inf: none, docs/theory.md §7.1); smooth:
    False for an edge pair's stand-in; of the box pairs and cylinder features computed: faces
    (pair -> (vertex features, their faces)), points (pair -> (features, points on A, on B,
    normals), with rows), edges (pair -> (edge features, active: the gap is d, not a stand-in)),
    exact (cylinder feature -> its gap is the distance), witness (cylinder feature -> (point on
    A, on B, normal B to A), with rows)."""

    g: np.ndarray
    W: np.ndarray
    drift: np.ndarray
    gamma: np.ndarray
    margin: np.ndarray
    smooth: np.ndarray
    faces: dict
    points: dict
    edges: dict
    exact: dict
    witness: dict


class Gaps:
    """The features of a model (feature_list) and their kinematics at any (q, u); gap_tol [m]: a
    feature at most this far is closed (its rim refusals and side stand-ins use it)."""

    def __init__(self, model: Model, data: Data, feats: tuple[Feature, ...], gap_tol: float):
        self.model, self.data, self.feats, self.gap_tol = model, data, feats, gap_tol
        self.pm, self.pd = model.pin, data.pin
        self.nv, self.zero = model.nv, np.zeros(model.nv)
        self._pair_names = {p.index: p.name for p in model.pairs}

    # ---- kinematics of the features -------------------------------------------------------
    def _point(self, j: int, p_local: np.ndarray, rows: bool):
        """World position, velocity, bias acceleration (q'' = 0) and Jacobian (3, nv) of a
        point fixed in joint j's frame (needs forwardKinematics(q, u, 0) and, for rows, J)."""
        if j == 0:
            return p_local, np.zeros(3), np.zeros(3), (np.zeros((3, self.nv)) if rows else None)
        R, t, w, v_lin, a_ang, a_lin = self._frame(j)  # read once per call
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

    def features(self, q: np.ndarray, u: np.ndarray, idx=None, rows: bool = True, faces: dict | None = None
                 ) -> FeatureState:
        """Gaps (and rows, drift, gamma if `rows`) of the features `idx` (default all) at (q, u);
        faces: (pair, vertex feature) -> the face a persistent vertex keeps (docs/theory.md §7.1)."""
        pm, pd = self.pm, self.pd
        if rows:
            pin.computeJointJacobians(pm, pd, q)
        pin.forwardKinematics(pm, pd, q, u, self.zero)
        self._frames, self._J, self._faces = {}, None, faces or {}
        # this call's scratch (FeatureState's dicts), filled by the kinds' helpers
        self.box_points, self.box_faces, self.edge_active, self.cyl_exact, self.cyl_points = {}, {}, {}, {}, {}
        self._screens, self._sides = {}, {}
        idx = range(len(self.feats)) if idx is None else idx
        k = len(idx)
        g, drift, W = np.empty(k), np.zeros(k), np.zeros((self.nv, k))
        margin = np.full(k, np.inf)  # [m] each feature's distance to the end of its region (below)
        smooth = np.ones(k, bool)  # False: an edge pair's stand-in (its rows and drift are the lines')
        boxes: dict = {}
        for col, i in enumerate(idx):
            f = self.feats[i]
            if f.limit is not None:  # a joint limit: constant row, no curvature term (drift 0)
                g[col], W[f.limit.idx_v, col] = f.limit.gap(q), f.limit.sign
                continue
            if f.box is not None:  # box-box kinds: vectorized per pair, below
                entry = boxes.get(f.pair)
                if entry is None:
                    entry = boxes[f.pair] = (f.box, [], [])
                entry[1].append(col)
                entry[2].append(f.feature)
                continue
            if f.kind in CYLINDER_KINDS:
                g[col], w, drift[col] = self._cylinder(f, rows)
                self.cyl_exact[i] = self._exact
                if rows:
                    self.cyl_points[i] = self._witness
                    W[:, col] = w
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
                dist, nl, curv = _point_box(f.R.T @ (pa - f.p_b), f.R.T @ va, f.h)
                g[col] = dist - f.r
                n = f.R @ nl
                vrel, arel, Jrel = va, aa, Ja
            if rows:
                drift[col] = n @ arel + curv
                W[:, col] = n @ Jrel
        for bp, cols, which in boxes.values():
            g[cols], Wb, db = self._box_pair(bp, np.array(which), rows)
            margin[cols] = self._box_margin
            smooth[cols] = self._box_smooth
            if rows:
                W[:, cols] = Wb
                drift[cols] = db
        gamma = W.T @ u if rows else np.zeros(k)
        return FeatureState(g, W, drift, gamma, margin, smooth, self.box_faces, self.box_points, self.edge_active,
                            self.cyl_exact, self.cyl_points)

    # ---- cylinder kinds (docs/theory.md §7.2) ---------------------------------------------------
    def _frame0(self, j: int):
        """_frame(j), or the world's (at rest) for j = 0."""
        return (np.eye(3),) + (np.zeros(3),) * 5 if j == 0 else self._frame(j)

    def _cylinder(self, f: Feature, rows: bool):
        """(g, w (nv,) or None, drift) of a cylinder feature (docs/theory.md §7.2); self._exact:
        whether g is the distance there (else a positive stand-in)."""
        self._exact = True
        if f.kind == "sphere_cylinder":
            return self._sphere_cylinder(f, rows)
        if f.kind in ("rim_box", "side_edge"):
            screen = self._screens.get(f.pair)
            if screen is None:
                screen = self._screens[f.pair] = self._screen(f, rows)
            if screen[0] > CYL_SCREEN:  # the cylinder's bounding sphere is clear of the box: its gap stands in
                self._exact = False
                self._witness = screen[3]
                return screen[:3]
        if f.kind == "side_edge":  # all 12 edges of the pair at once, kept for this call
            sides = self._sides.get(f.pair)
            if sides is None:
                sides = self._sides[f.pair] = self._side_edges(f, rows)
            g, W, drift, exact, witness = sides
            k = f.feature
            self._exact, self._witness = bool(exact[k]), (tuple(x[k] for x in witness) if rows else ())
            return float(g[k]), (W[:, k] if rows else None), float(drift[k]) if rows else 0.0
        if f.kind == "rim_plane":
            n, d, excess = f.n, f.d, 0.0
            g, w, drift, sig, p = self._rim(f, n, d, rows)
        else:  # rim_box: the largest of the rim's gaps to the box's 6 face planes
            RA, tA = self._frame0(f.joint_a)[:2]
            A, ck = RA @ f.a, RA @ (f.p + (f.hl if f.feature == 0 else -f.hl) * f.a) + tA
            N = np.concatenate((f.R.T, -f.R.T))  # the 6 outward face normals (rows) and offsets
            D = N @ f.p_b + np.tile(f.h, 2)
            best = int(np.argmax(N @ ck - f.r * np.sqrt(np.maximum(1.0 - (N @ A) ** 2, 0.0)) - D))
            n, d, ax = N[best], float(D[best]), best % 3
            g, w, drift, sig, p = self._rim(f, n, d, rows)
            pl = np.maximum(np.abs(f.R.T @ (p - f.p_b)) - f.h, 0.0)  # the support point beyond the face's sides
            pl[ax] = 0.0
            excess = float(np.sqrt(pl @ pl))
            if excess > 0.0:  # off the face: a positive stand-in, continuous with g on the face's sides
                self._exact = False
                g = float(np.sqrt(g * g + excess * excess)) if g >= 0.0 else g + excess
        if not rows:
            return g, None, 0.0
        self._witness = (p, p - g * n, n)
        if g <= self.gap_tol and (sig < SIN_FLAT or excess > self.gap_tol):
            name = self._pair_names[f.pair]
            where = ("a cap lies flat on the plane (|sin| = %.3g < %g): the rim's gap is not differentiable there"
                     % (sig, SIN_FLAT)) if sig < SIN_FLAT else (
                "the rim touches the box %.3g m beyond the sides of its face: at the box's edge the face-plane gap "
                "is a lower bound, not the distance" % excess)
            raise SimulationError(f"pair '{name}': {where} (docs/theory.md §7.2)")
        return g, w, drift

    def _screen(self, f: Feature, rows: bool):
        """(g, w, drift, witness) of the bounding sphere (the centre, radius sqrt(r^2 + hl^2)) of a
        cylinder against a static box, as sphere_box."""
        pc, va, aa, Ja = self._point(f.joint_a, f.p, rows)
        dist, nl, curv = _point_box(f.R.T @ (pc - f.p_b), f.R.T @ va, f.h)
        rb = float(np.hypot(f.r, f.hl))
        n = f.R @ nl
        if not rows:
            return dist - rb, None, 0.0, ()
        return dist - rb, n @ Ja, float(n @ aa + curv), (pc - rb * n, pc - dist * n, n)

    def _side_edges(self, f: Feature, rows: bool):
        """The cylinder's side against the 12 edges of a static box (numbered as _box's edges):
        (g, W (nv, 12), drift, exact, (points on the cylinder, on the edges, normals)). The axis
        segment a0 + s a (s in [0, 2 hl]) and an edge b0 + t e_B form edge_edge's pair (§7.1)
        with g = d - r, d = n'(a0 - b0), n = +-(a x e_B)/|.| outward of the edge; a positive
        stand-in where that is not the distance (n outside the edge's normal cone, a closest
        point beyond an end, d < 0, or parallel lines: the rims cover that segment's ends)."""
        j = f.joint_a
        RA, tA, w, _, _, _ = self._frame0(j)
        A = RA @ f.a
        a0 = RA @ f.p + tA - f.hl * A
        ax, b, c, sb, sc = _EDGES
        X = np.zeros((12, 3))
        X[_K, ax], X[_K, b], X[_K, c] = -f.h[ax], sb * f.h[b], sc * f.h[c]
        B0, EB = X @ f.R.T + f.p_b, f.R[:, ax].T
        F1, F2 = sb[:, None] * f.R[:, b].T, sc[:, None] * f.R[:, c].T
        CV = _cross(A[None], EB)
        cn = np.sqrt((CV * CV).sum(axis=1))
        ok = cn > PARALLEL
        cn = np.where(ok, cn, 1.0)
        sigma = np.where((CV * (F1 + F2)).sum(axis=1) < 0.0, -1.0, 1.0)
        N = CV * (sigma / cn)[:, None]
        r = a0 - B0
        d = (N * r).sum(axis=1)
        bb, ra, rb = EB @ A, r @ A, (r * EB).sum(axis=1)
        s = (bb * rb - ra) / cn ** 2  # the lines' closest points a0 + s a, b0 + t e_B
        t = (rb - bb * ra) / cn ** 2
        la, lb = 2.0 * f.hl, 2.0 * f.h[ax]
        ex_s = np.maximum(np.maximum(EDGE_END * la - s, s - (1.0 - EDGE_END) * la), 0.0)
        ex_t = np.maximum(np.maximum(EDGE_END * lb - t, t - (1.0 - EDGE_END) * lb), 0.0)
        active = (ok & ((N * F1).sum(axis=1) >= -ARC_TOL) & ((N * F2).sum(axis=1) >= -ARC_TOL)
                  & (ex_s == 0.0) & (ex_t == 0.0) & (d >= 0.0))
        # the stand-in stays above the closing tolerance: at the segment's ends the contact is the rim's
        # (or the end sphere's), and within EDGE_END of them sqrt(...) alone could close (panda's elbow did)
        g = np.where(active, d - f.r, np.where(ok, np.sqrt((d - f.r) ** 2 + ex_s ** 2 + ex_t ** 2) + 2.0 * self.gap_tol,
                                               f.r + float(np.sqrt(f.h @ f.h))))
        if not rows:
            return g, None, None, active, ()
        N = np.where(ok[:, None], N, 0.0)
        PA = a0 + s[:, None] * A
        vel, acc, om, J = self._motion(j, PA, True)
        cdot = _cross(_cross(om[None], A[None]), EB) * sigma[:, None]
        ndot = (cdot - N * (N * cdot).sum(axis=1)[:, None]) / cn[:, None]
        drift = np.where(ok, (N * acc).sum(axis=1) + 2.0 * (ndot * vel).sum(axis=1) - d * (ndot * ndot).sum(axis=1),
                         0.0)
        return g, self._rows(J, None, PA, PA, N), drift, active, (PA - f.r * N, B0 + t[:, None] * EB, N)

    def _rim(self, f: Feature, n: np.ndarray, d: float, rows: bool):
        """Cap f.feature's rim of a cylinder (joint_a) against the static plane n'x = d: its support
        point p = c - r s toward the plane, s = (n - (n'a) a)/|.|, g = n'c - r sqrt(1 - (n'a)^2) - d;
        returns (g, w, drift, sqrt(1 - (n'a)^2), p). The row is n'J(p) (the envelope theorem); the
        drift n'abar(c) + r (c_n c_n''/sigma + c_n'^2/sigma^3) (bias terms, c_n = n'a: §7.2)."""
        j = f.joint_a
        R, t, w, _, a_ang, _ = self._frame0(j)
        c_loc = f.p + (f.hl if f.feature == 0 else -f.hl) * f.a
        ck, _, ak, _ = self._point(j, c_loc, False)
        A = R @ f.a
        cn = float(n @ A)
        sig = float(np.sqrt(max(1.0 - cn * cn, 0.0)))
        s = (n - cn * A) / sig if sig > 0.0 else _perp(A)
        p = ck - f.r * s
        g = float(n @ ck) - f.r * sig - d
        if not rows:
            return g, None, 0.0, sig, p
        Jp = self._point(j, R.T @ (p - t), True)[3]
        om, al = R @ w, R @ a_ang
        oa = cross(om, A)
        c1 = float(n @ oa)  # (n'a)' and (n'a)'' at q'' = 0
        c2 = float(n @ (cross(al, A) + cross(om, oa)))
        curv = f.r * (cn * c2 / sig + c1 * c1 / sig ** 3) if sig > 0.0 else 0.0
        return g, n @ Jp, float(n @ ak) + curv, sig, p

    def _sphere_cylinder(self, f: Feature, rows: bool):
        """A sphere (centre p in joint_a, radius r) against a cylinder (centre p_b, axis a in joint_b,
        radius r_b, half length hl): g = dist(centre, cylinder) - r, the distance of the side (radial
        distance - r_b), a cap (axial - hl), or a rim, or inside minus the smaller depth. With
        dv = v_A(x) - v_B(x) at the centre x: gamma = n'dv, drift n'(abar_A - abar_B) + 2 (w_B x n)'dv
        + dv' K dv, K = dn/dx the normal's gradient (docs/theory.md §7.2)."""
        pc, va, aa, Ja = self._point(f.joint_a, f.p, rows)
        R, t, w, _, _, _ = self._frame0(f.joint_b)
        A = R @ f.a
        x = pc - (R @ f.p_b + t)
        z = float(x @ A)
        y = x - z * A
        rho = float(np.sqrt(y @ y))
        e = y / rho if rho > 0.0 else _perp(A)
        az, sz = abs(z), (1.0 if z >= 0.0 else -1.0)
        K = np.zeros((3, 3))
        tt = np.outer(tg := cross(A, e), tg)
        if az > f.hl and rho > f.r_b:  # rim region
            dx = x - (sz * f.hl * A + f.r_b * e)
            dist = float(np.sqrt(dx @ dx))
            n = dx / dist
            K = (np.eye(3) - np.outer(n, n) - (f.r_b / rho) * tt) / dist
        elif az > f.hl or (rho < f.r_b and f.hl - az < f.r_b - rho):  # cap region, or nearer a cap inside
            n, dist = sz * A, az - f.hl
        else:  # side region, or nearer the side inside
            n, dist = e, rho - f.r_b
            if rho > 0.0:
                K = tt / rho
        g = dist - f.r
        if not rows:
            return g, None, 0.0
        _, vb, ab, Jb = self._point(f.joint_b, R.T @ (pc - t), True)
        self._witness = (pc - f.r * n, pc - dist * n, n)
        dv = va - vb
        drift = float(n @ (aa - ab) + 2.0 * cross(R @ w, n) @ dv + dv @ K @ dv)
        return g, n @ (Ja - Jb), drift

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
            if self._faces:  # persistent vertices: the face chosen at the phase's start
                f = np.array([self._faces.get((bp.pair, k), fk) for k, fk in zip(wv.tolist(), f.tolist())])
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

    def thin_limit(self, u: np.ndarray, a: np.ndarray) -> float:
        """The longest step h [s] over which no point can travel the thinnest pair's extent
        (Model.thinnest_pair, the stepper's tunnelling bound) from velocities u at accelerations a
        (those of the phase's persistent set): reach (|u| h + |a| h^2 / 2) <= thinnest_pair, reach
        the model's largest lever arm. A gap then cannot go from one side of a thin obstacle to the
        other between two checks."""
        thin = self.model.thinnest_pair
        if not np.isfinite(thin):
            return np.inf
        v, acc, x = float(np.abs(u).max()), float(np.abs(a).max()), thin / self.model.reach
        s = v + np.sqrt(v * v + 2.0 * acc * x)  # the root of the quadratic, without cancellation
        return 2.0 * x / s if s > 0.0 else np.inf

    # ---- dynamics --------------------------------------------------------------------------
