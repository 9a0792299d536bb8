"""The contact layer's per-feature gaps (docs/theory.md §7, §7.1, §7.2): each feature of a collision
pair (and each joint limit, limits.py) with its gap g, row w, drift Wdot' u and gamma = w' u, from (q, u):
:meth:`Gaps.features` returns everything it computes (FeatureState) and keeps nothing between calls.
The decisions at events that use them are in event_rules.py. Products are sums in index order (sums.py,
docs/theory.md §2.8)."""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType

import coal
import numpy as np
import pinocchio as pin

from .box_gaps import ARC_TOL, BOX_EDGES, BOX_FEATURES, EDGE_END, EDGE_K, PARALLEL, BoxPair, box_geometry, box_pair
from .data import Data
from .errors import MoreauSimError, SimulationError
from .kinematics import Kinematics, cross, cross_rows
from .limits import JointLimit
from .model import Model
from .sums import dot3, dots, ordered

CYL_SCREEN = 0.01  # [m] a cylinder's bounding sphere this far from a box: its features report the sphere's gap
SIN_FLAT = 1e-6  # a closed cylinder rim whose cap is within this (sine) of parallel to the plane: refused (§7.2)


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


def feature_list(model: Model) -> tuple[Feature, ...]:
    """The gap functions of every collision pair (UnsupportedModel for other pair types)."""
    out = []
    gobs = model.geometries
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
            bp = BoxPair(pair.index, box_geometry(model, pair.first, ja), box_geometry(model, pair.second, jb))
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
    gobs = model.geometries
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
        dist = float(np.sqrt(dot3(diff, diff)))
        nl = diff / dist
        vp = np.where(out, vl, 0.0)
        return dist, nl, ((dot3(vp, vp) - dot3(nl, vl) ** 2) / dist if out.sum() > 1 else 0.0)
    s = h - np.abs(cl)
    ax = int(np.argmin(s))
    nl = np.zeros(3)
    nl[ax] = np.sign(cl[ax]) or 1.0
    return -float(s[ax]), nl, 0.0


def _perp(a: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to the unit vector a."""
    b = np.eye(3)[int(np.argmin(np.abs(a)))]
    b = b - dot3(b, a) * a
    return b / np.sqrt(dot3(b, b))


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


_NONE = MappingProxyType({})  # a FeatureState's dict of what compiled features do not have (read-only, shared)


class Gaps:
    """The features of a model (feature_list) and their kinematics at any (q, u); gap_tol [m]: a
    feature at most this far is closed (its rim refusals and side stand-ins use it)."""

    def __init__(self, model: Model, data: Data, feats: tuple[Feature, ...], gap_tol: float):
        self.model, self.data, self.feats, self.gap_tol = model, data, feats, gap_tol
        self.pm, self.pd = model.pin, data.pin
        self.nv, self.zero = model.nv, np.zeros(model.nv)
        # the same features compiled (compiled_events.feature_gaps; None: these below); set by event_rules.make_rules
        self.compiled = None
        self._all = list(range(len(feats)))  # idx None: every feature
        self._flats: dict = {}  # k -> the compiled features' margin (inf) and smooth (True), read-only (_flat)

    def _flat(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(margin, smooth) of k compiled features (no regions, no stand-ins: inf and True), made once per k and
        read-only: a FeatureState is never written to, and these are the same at every call."""
        got = self._flats.get(k)
        if got is None:
            margin, smooth = np.full(k, np.inf), np.ones(k, bool)
            margin.flags.writeable = smooth.flags.writeable = False
            got = self._flats[k] = (margin, smooth)
        return got

    def features(self, q: np.ndarray, u: np.ndarray, idx=None, rows: bool = True, faces: dict | None = None
                 ) -> FeatureState:
        """Gaps (and rows, drift, gamma if `rows`) of the features `idx` (default all) at (q, u);
        faces: (pair, vertex feature) -> the face a persistent vertex keeps (docs/theory.md §7.1)."""
        if self.compiled is not None:  # points on static planes, sphere pairs: the same floats compiled
            g, W, drift, gamma = self.compiled.features(q, u, self._all if idx is None else [int(i) for i in idx],
                                                        rows)
            margin, smooth = self._flat(len(g))
            return FeatureState(g, W, drift, gamma, margin, smooth, _NONE, _NONE, _NONE, _NONE, _NONE)
        pm, pd = self.pm, self.pd
        if rows:
            pin.computeJointJacobians(pm, pd, q)
        pin.forwardKinematics(pm, pd, q, u, self.zero)
        kin = Kinematics(self.model, pd)  # this call's joint frames, read once per joint
        faces = faces or {}
        box_points, box_faces, edge_active, cyl_exact, cyl_points = {}, {}, {}, {}, {}  # FeatureState's dicts
        screens, sides = {}, {}  # per cylinder-box pair: its bounding sphere's gap, its side's 12 edge gaps
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
                g[col], w, drift[col], cyl_exact[i], witness = self._cylinder(kin, f, rows, screens, sides)
                if rows:
                    cyl_points[i] = witness
                    W[:, col] = w
                continue
            pa, va, aa, Ja = kin.point(f.joint_a, f.p, rows)
            if f.kind == "point_plane":
                n, curv = f.n, 0.0
                g[col] = dot3(n, pa) - f.d
                vrel, arel, Jrel = va, aa, Ja
            elif f.kind == "sphere_sphere":
                pb, vb, ab, Jb = kin.point(f.joint_b, f.p_b, rows)
                dv = pa - pb
                dist = float(np.sqrt(dot3(dv, dv)))
                n = dv / dist
                g[col] = dist - f.r - f.r_b
                vrel, arel = va - vb, aa - ab
                Jrel = Ja - Jb if rows else None
                curv = (dot3(vrel, vrel) - dot3(n, vrel) ** 2) / dist
            else:  # sphere_box: distance from the centre to a static box (face, edge or vertex region)
                dist, nl, curv = _point_box(dots(f.R.T, pa - f.p_b), dots(f.R.T, va), f.h)
                g[col] = dist - f.r
                n = dots(f.R, nl)
                vrel, arel, Jrel = va, aa, Ja
            if rows:
                drift[col] = dot3(n, arel) + curv
                W[:, col] = ordered(n, Jrel)
        for bp, cols, which in boxes.values():
            bg = box_pair(kin, bp, np.array(which), rows, faces)
            g[cols] = bg.g
            margin[cols] = bg.margin
            smooth[cols] = bg.smooth
            if bg.faces is not None:
                box_faces[bp.pair] = bg.faces
            if bg.edges is not None:
                edge_active[bp.pair] = bg.edges
            if rows:
                W[:, cols] = bg.W
                drift[cols] = bg.drift
            if bg.points is not None:
                box_points[bp.pair] = bg.points
        gamma = ordered(W.T, u) if rows else np.zeros(k)
        return FeatureState(g, W, drift, gamma, margin, smooth, box_faces, box_points, edge_active,
                            cyl_exact, cyl_points)

    # ---- cylinder kinds (docs/theory.md §7.2) ---------------------------------------------------
    def _cylinder(self, kin: Kinematics, f: Feature, rows: bool, screens: dict, sides: dict):
        """(g, w (nv,) or None, drift, exact, witness) of a cylinder feature (docs/theory.md §7.2):
        exact: whether g is the distance there (else a positive stand-in); witness (with rows):
        (point on A, on B, normal B to A). screens, sides: this call's per-pair results, filled here."""
        if f.kind == "sphere_cylinder":
            return self._sphere_cylinder(kin, f, rows)
        if f.kind in ("rim_box", "side_edge"):
            screen = screens.get(f.pair)
            if screen is None:
                screen = screens[f.pair] = self._screen(kin, f, rows)
            if screen[0] > CYL_SCREEN:  # the cylinder's bounding sphere is clear of the box: its gap stands in
                return screen[:3] + (False, screen[3])
        if f.kind == "side_edge":  # all 12 edges of the pair at once, kept for this call
            edges = sides.get(f.pair)
            if edges is None:
                edges = sides[f.pair] = self._side_edges(kin, f, rows)
            g, W, drift, exact, witness = edges
            k = f.feature
            return (float(g[k]), (W[:, k] if rows else None), float(drift[k]) if rows else 0.0, bool(exact[k]),
                    tuple(x[k] for x in witness) if rows else ())
        exact = True
        if f.kind == "rim_plane":
            n, d, excess = f.n, f.d, 0.0
            g, w, drift, sig, p = self._rim(kin, f, n, d, rows)
        else:  # rim_box: the largest of the rim's gaps to the box's 6 face planes
            RA, tA = kin.frame0(f.joint_a)[:2]
            A, ck = dots(RA, f.a), dots(RA, f.p + (f.hl if f.feature == 0 else -f.hl) * f.a) + tA
            N = np.concatenate((f.R.T, -f.R.T))  # the 6 outward face normals (rows) and offsets
            D = dots(N, f.p_b) + np.tile(f.h, 2)
            best = int(np.argmax(dots(N, ck) - f.r * np.sqrt(np.maximum(1.0 - dots(N, A) ** 2, 0.0)) - D))
            n, d, ax = N[best], float(D[best]), best % 3
            g, w, drift, sig, p = self._rim(kin, f, n, d, rows)
            pl = np.maximum(np.abs(dots(f.R.T, p - f.p_b)) - f.h, 0.0)  # the support point beyond the face's sides
            pl[ax] = 0.0
            excess = float(np.sqrt(dot3(pl, pl)))
            if excess > 0.0:  # off the face: a positive stand-in, continuous with g on the face's sides
                exact = False
                g = float(np.sqrt(g * g + excess * excess)) if g >= 0.0 else g + excess
        if not rows:
            return g, None, 0.0, exact, None
        if g <= self.gap_tol and (sig < SIN_FLAT or excess > self.gap_tol):
            name = next(p.name for p in self.model.pairs if p.index == f.pair)
            where = ("a cap lies flat on the plane (|sin| = %.3g < %g): the rim's gap is not differentiable there"
                     % (sig, SIN_FLAT)) if sig < SIN_FLAT else (
                "the rim touches the box %.3g m beyond the sides of its face: at the box's edge the face-plane gap "
                "is a lower bound, not the distance" % excess)
            raise SimulationError(f"pair '{name}': {where} (docs/theory.md §7.2)")
        return g, w, drift, exact, (p, p - g * n, n)

    def _screen(self, kin: Kinematics, f: Feature, rows: bool):
        """(g, w, drift, witness) of the bounding sphere (the centre, radius sqrt(r^2 + hl^2)) of a
        cylinder against a static box, as sphere_box."""
        pc, va, aa, Ja = kin.point(f.joint_a, f.p, rows)
        dist, nl, curv = _point_box(dots(f.R.T, pc - f.p_b), dots(f.R.T, va), f.h)
        rb = float(np.hypot(f.r, f.hl))
        n = dots(f.R, nl)
        if not rows:
            return dist - rb, None, 0.0, ()
        return dist - rb, ordered(n, Ja), dot3(n, aa) + curv, (pc - rb * n, pc - dist * n, n)

    def _side_edges(self, kin: Kinematics, f: Feature, rows: bool):
        """The cylinder's side against the 12 edges of a static box (numbered as box_geometry's edges):
        (g, W (nv, 12), drift, exact, (points on the cylinder, on the edges, normals)). The axis
        segment a0 + s a (s in [0, 2 hl]) and an edge b0 + t e_B form edge_edge's pair (§7.1)
        with g = d - r, d = n'(a0 - b0), n = +-(a x e_B)/|.| outward of the edge; a positive
        stand-in where that is not the distance (n outside the edge's normal cone, a closest
        point beyond an end, d < 0, or parallel lines: the rims cover that segment's ends)."""
        j = f.joint_a
        RA, tA, w, _, _, _ = kin.frame0(j)
        A = dots(RA, f.a)
        a0 = dots(RA, f.p) + tA - f.hl * A
        ax, b, c, sb, sc = BOX_EDGES
        X = np.zeros((12, 3))
        X[EDGE_K, ax], X[EDGE_K, b], X[EDGE_K, c] = -f.h[ax], sb * f.h[b], sc * f.h[c]
        B0, EB = dots(X[:, None], f.R) + f.p_b, f.R[:, ax].T
        F1, F2 = sb[:, None] * f.R[:, b].T, sc[:, None] * f.R[:, c].T
        CV = cross_rows(A[None], EB)
        cn = np.sqrt(dots(CV, CV))
        ok = cn > PARALLEL
        cn = np.where(ok, cn, 1.0)
        sigma = np.where(dots(CV, F1 + F2) < 0.0, -1.0, 1.0)
        N = CV * (sigma / cn)[:, None]
        r = a0 - B0
        d = dots(N, r)
        bb, ra, rb = dots(EB, A), dots(r, A), dots(r, EB)
        s = (bb * rb - ra) / cn ** 2  # the lines' closest points a0 + s a, b0 + t e_B
        t = (rb - bb * ra) / cn ** 2
        la, lb = 2.0 * f.hl, 2.0 * f.h[ax]
        ex_s = np.maximum(np.maximum(EDGE_END * la - s, s - (1.0 - EDGE_END) * la), 0.0)
        ex_t = np.maximum(np.maximum(EDGE_END * lb - t, t - (1.0 - EDGE_END) * lb), 0.0)
        active = (ok & (dots(N, F1) >= -ARC_TOL) & (dots(N, F2) >= -ARC_TOL)
                  & (ex_s == 0.0) & (ex_t == 0.0) & (d >= 0.0))
        # the stand-in stays above the closing tolerance: at the segment's ends the contact is the rim's
        # (or the end sphere's), and within EDGE_END of them sqrt(...) alone could close (panda's elbow did)
        g = np.where(active, d - f.r, np.where(ok, np.sqrt((d - f.r) ** 2 + ex_s ** 2 + ex_t ** 2) + 2.0 * self.gap_tol,
                                               f.r + float(np.sqrt(dot3(f.h, f.h)))))
        if not rows:
            return g, None, None, active, ()
        N = np.where(ok[:, None], N, 0.0)
        PA = a0 + s[:, None] * A
        vel, acc, om, J = kin.motion(j, PA, True)
        cdot = cross_rows(cross_rows(om[None], A[None]), EB) * sigma[:, None]
        ndot = (cdot - N * dots(N, cdot)[:, None]) / cn[:, None]
        drift = np.where(ok, dots(N, acc) + 2.0 * dots(ndot, vel) - d * dots(ndot, ndot), 0.0)
        return g, kin.rows(J, None, PA, PA, N), drift, active, (PA - f.r * N, B0 + t[:, None] * EB, N)

    def _rim(self, kin: Kinematics, f: Feature, n: np.ndarray, d: float, rows: bool):
        """Cap f.feature's rim of a cylinder (joint_a) against the static plane n'x = d: its support
        point p = c - r s toward the plane, s = (n - (n'a) a)/|.|, g = n'c - r sqrt(1 - (n'a)^2) - d;
        returns (g, w, drift, sqrt(1 - (n'a)^2), p). The row is n'J(p) (the envelope theorem); the
        drift n'abar(c) + r (c_n c_n''/sigma + c_n'^2/sigma^3) (bias terms, c_n = n'a: §7.2)."""
        j = f.joint_a
        R, t, w, _, a_ang, _ = kin.frame0(j)
        c_loc = f.p + (f.hl if f.feature == 0 else -f.hl) * f.a
        ck, _, ak, _ = kin.point(j, c_loc, False)
        A = dots(R, f.a)
        cn = dot3(n, A)
        sig = float(np.sqrt(max(1.0 - cn * cn, 0.0)))
        s = (n - cn * A) / sig if sig > 0.0 else _perp(A)
        p = ck - f.r * s
        g = dot3(n, ck) - f.r * sig - d
        if not rows:
            return g, None, 0.0, sig, p
        Jp = kin.point(j, dots(R.T, p - t), True)[3]
        om, al = dots(R, w), dots(R, a_ang)
        oa = cross(om, A)
        c1 = dot3(n, oa)  # (n'a)' and (n'a)'' at q'' = 0
        c2 = dot3(n, cross(al, A) + cross(om, oa))
        curv = f.r * (cn * c2 / sig + c1 * c1 / sig ** 3) if sig > 0.0 else 0.0
        return g, ordered(n, Jp), dot3(n, ak) + curv, sig, p

    def _sphere_cylinder(self, kin: Kinematics, f: Feature, rows: bool):
        """A sphere (centre p in joint_a, radius r) against a cylinder (centre p_b, axis a in joint_b,
        radius r_b, half length hl): g = dist(centre, cylinder) - r, the distance of the side (radial
        distance - r_b), a cap (axial - hl), or a rim, or inside minus the smaller depth. With
        dv = v_A(x) - v_B(x) at the centre x: gamma = n'dv, drift n'(abar_A - abar_B) + 2 (w_B x n)'dv
        + dv' K dv, K = dn/dx the normal's gradient (docs/theory.md §7.2)."""
        pc, va, aa, Ja = kin.point(f.joint_a, f.p, rows)
        R, t, w, _, _, _ = kin.frame0(f.joint_b)
        A = dots(R, f.a)
        x = pc - (dots(R, f.p_b) + t)
        z = dot3(x, A)
        y = x - z * A
        rho = float(np.sqrt(dot3(y, y)))
        e = y / rho if rho > 0.0 else _perp(A)
        az, sz = abs(z), (1.0 if z >= 0.0 else -1.0)
        K = np.zeros((3, 3))
        tt = np.outer(tg := cross(A, e), tg)
        if az > f.hl and rho > f.r_b:  # rim region
            dx = x - (sz * f.hl * A + f.r_b * e)
            dist = float(np.sqrt(dot3(dx, dx)))
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
            return g, None, 0.0, True, None
        _, vb, ab, Jb = kin.point(f.joint_b, dots(R.T, pc - t), True)
        dv = va - vb
        drift = dot3(n, aa - ab) + 2.0 * dot3(cross(dots(R, w), n), dv) + dot3(dots(dv, K.T), dv)  # (dv'K) dv
        return g, ordered(n, Ja - Jb), drift, True, (pc - f.r * n, pc - dist * n, n)

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
