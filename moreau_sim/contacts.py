"""Contact detection with coal: the closed contacts H(q) with signed gaps g_i, witness points
and normals (docs/theory.md §6). Their rows w_i are built in constraints.py.

Method (general, no special case per shape pair): for every collision pair whose gap is
<= the contact tolerance (coal's narrow phase with a security margin gates this),
  1. every polytope vertex of either shape (boxes, convex meshes, cylinder rims) whose
     signed distance to the other shape is <= tolerance, measured by coal (point vs shape);
     a vertex is only queried when a cheap lower bound of that distance (the other shape's
     bounding sphere, or its plane for a half-space) is within tolerance, so none is missed.
     (coal's own contact normal is not used for this: for exactly touching boxes its EPA
     normal can be tilted by ~5 deg at its default GJK/EPA tolerance; data.GJK_TOLERANCE.)
  2. where two faces are parallel (to within the tolerance), the corners of coal's contact
     patch, the polygon where the faces overlap (two equal boxes stacked with a yaw touch only
     along the octagon of their overlap: no vertex of either lies on the other), except those
     that are already vertex contacts; they carry the pair's depth, exact for parallel faces;
  3. for two boxes, the crossings of an edge of one with an edge of the other (box_box.py), and where
     coal's patch has no polygon the corners of two nearly parallel faces, each with its own gap, except
     at points that are already contacts;
  4. otherwise, when steps 1-3 found nothing, coal's closest-point contact (smooth shapes: spheres,
     capsules, cylinders, curved meshes; edge on edge of other polytopes).
A box lying on a face therefore has its 4 corners as contacts with their exact gaps; a
tilted box its lowest corner(s) with their own gaps, never one depth shared by a polygon.

Sign convention: the normal n points from the second shape B to the first shape A, the gap
g grows when A moves along n, and the row is w = J_A(p_A)' n - J_B(p_B)' n (size nv), so
gamma = w' u is the normal relative velocity (> 0 separating).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import coal
import numpy as np
import pinocchio as pin

from . import box_box, broad_phase, pair_table
from .data import GATE_MARGIN, Data
from .model import DISTANCE_FAILED, Model, check_start
from .sums import dots, ordered



class FeatureKind(enum.IntEnum):
    """What a contact is, with its index `feature` within the kind (docs/theory.md §6)."""

    VERTEX = 0  # polytope vertex `feature` of the pair (B's vertices numbered after A's)
    WITNESS = 1  # coal's closest-point contact of the pair (feature 0)
    PATCH = 2  # corner `feature` of coal's contact patch (the overlap polygon of two parallel faces)
    CORNER = 3  # face `feature` of a corner: the way of staying apart that pushed (docs/theory.md §3)
    SWEPT = 4  # found by the swept test along a fast motion (tunnelling.py; feature 0)
    JOINT_LIMIT = 5  # a joint's lower or upper position limit (limits.py; feature = the Pinocchio joint id)
    EDGE = 6  # two boxes' edges crossing (box_box.py): feature 12 k + l, A's edge k and B's edge l
    FACE = 7  # corner `feature` of two nearly parallel box faces' clipped overlap, its own gap (box_box.face_patch)


SAME_POINT = 1e-9  # [m] a patch corner this close to a vertex contact is that contact
# The normals of a vertex of B on A's face and of a vertex of A on B's face at the same point (SAME_POINT) that differ
# by at most this in every component are one touching point: one row, A's vertex (docs/theory.md §6.2, 1b). It is the
# tolerance to which the detection already takes two faces as parallel at a vertex (box_box.CONE, _corner_normals'
# cone test); src/step.cpp reads the same constant (C_.cone).
TWIN_NORMAL = box_box.CONE


@dataclass(frozen=True, slots=True)
class Corner:
    """A closed contact where the gap is not smooth (docs/theory.md §3): a vertex at an edge or a
    vertex of a box, within the contact tolerance of k >= 2 face planes. Each face is one way of
    staying apart: normals (k, 3) from B to A (unit), at the point; the admissible set there is
    the union of the k half-spaces {n_f'(v_A(p) - v_B(p)) >= 0}, not their intersection.

    g: signed gap [m]; point_a, point_b (3,) [m]; pair, joint_a, joint_b; features: the vertex
    features that meet there (one of A's, and one of B's for vertex on vertex)."""

    g: float
    point_a: np.ndarray
    point_b: np.ndarray
    normals: np.ndarray
    pair: int
    joint_a: int
    joint_b: int
    features: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class Contacts:
    """The closed contacts at one configuration: m smooth ones in arrays, and the corners.

    g (m,) signed gaps [m]; point_a / point_b (m, 3) witness points on A and B [m, world];
    normal (m, 3) unit normals from B to A; pair (m,) collision-pair index; kind (m,)
    :class:`FeatureKind` values; feature (m,) the index within the kind; joint_a / joint_b (m,)
    Pinocchio joints of A and B; corners: the non-smooth contacts (:class:`Corner`), handled by
    the set-valued law.
    """

    g: np.ndarray
    point_a: np.ndarray
    point_b: np.ndarray
    normal: np.ndarray
    pair: np.ndarray
    kind: np.ndarray
    feature: np.ndarray
    joint_a: np.ndarray
    joint_b: np.ndarray
    corners: tuple = ()

    ARRAYS = ("g", "point_a", "point_b", "normal", "pair", "kind", "feature", "joint_a", "joint_b")

    @property
    def m(self) -> int:
        return len(self.g)

    @staticmethod
    def empty(corners: tuple = ()) -> "Contacts":
        """No smooth contact (and these corners)."""
        z3, z = np.zeros((0, 3)), np.zeros(0)
        zi = np.zeros(0, dtype=np.int64)
        return Contacts(z, z3, z3, z3, zi, zi, zi, zi, zi, corners)

    def select(self, keep: np.ndarray) -> "Contacts":
        """The smooth contacts where `keep` is true (corners unchanged)."""
        return Contacts(*(getattr(self, f)[keep] for f in Contacts.ARRAYS), self.corners)

    def concat(self, *others: "Contacts", corners: tuple | None = None) -> "Contacts":
        """These contacts followed by `others`' smooth contacts; corners: self's unless given."""
        return Contacts(*(np.concatenate([getattr(self, f)] + [getattr(o, f) for o in others]) for f in Contacts.ARRAYS),
                        self.corners if corners is None else corners)

    def keys(self) -> set:
        """{(pair, kind, feature)} of the smooth contacts: which contacts these are, across steps."""
        return set(zip(self.pair.tolist(), self.kind.tolist(), self.feature.tolist()))


NO_CONTACTS = Contacts.empty()


def _corner_normals(model: Model, g_vert: int, i: int, oMi, g_other: int, oMo, p: np.ndarray,
                    margin: float, body: np.ndarray, tol: float):
    """The ways of staying apart of vertex i of g_vert touching box g_other at p (docs/theory.md
    §3): the outward normals (world) of g_other's faces whose signed distance from p is within
    `margin` of the largest one (the faces p is nearest to, or crossed within the step) and whose
    planes leave the vertex's own local cone (its edges) on their outer side - a face plane the
    vertex's body would cross does not separate them. Two or more: a corner; one: a smooth contact
    with that face normal; None: g_other is no box or the vertex's cone is unknown (coal's). A vertex
    outside within `margin` of one face plane only is over that face (its projection inside it: with
    its gap <= tol <= margin the other planes are behind it) and gets that face's normal, the exact one
    (docs/theory.md §6.2); inside, nearest to one face, coal's. A face plane crossed by the vertex's edges
    (by more than the cone test's 1e-9) still separates when the vertex's whole body (`body`: its vertices,
    world) lies outside it to within `tol`, the contact tolerance: a slightly tilted cube's vertex at the
    other's top corner, its edges dipping by the tilt, gets the top face's normal, not coal's (issue 23,
    docs/theory.md §6.2 item 1c). Returns (the normals, their faces' signed distances from p [m], the largest signed
    distance of any face), or None."""
    planes, edges = model.face_planes[g_other], model.vertex_edges[g_vert]
    if planes is None or edges is None:
        return None
    n, d = planes
    # (the sums in src/step.cpp's order, `dots` and `ordered`: exact both ways for any face normal, a box turned on
    # the universe too; docs/theory.md §2.8)
    s = dots(n, dots(oMo.rotation.T, p - oMo.translation)) - d  # signed distance to each face plane
    s_max = s.max()
    on = np.flatnonzero(s >= s_max - margin)
    if len(on) < 2:
        if not s_max > 0.0:
            return None
        nw = ordered(n[on], oMo.rotation.T)  # src/step.cpp vertex_contacts: the same rule
        return nw, s[on], s_max
    nw = ordered(n[on], oMo.rotation.T)
    r = ordered(edges[i], oMi.rotation.T)  # (k, 3) edges leaving the vertex, world
    ok = dots(nw[:, None, :], r[None, :, :]).min(axis=1, initial=0.0) >= -1e-9 if len(r) else np.ones(len(nw), bool)
    if not ok.all():  # the body outside a face plane to tol: it separates (§6.2, 1c; src/step.cpp the same sums)
        sb = [dots(n, dots(oMo.rotation.T, v - oMo.translation)) - d for v in body]
        ok |= np.array([min(float(x[f]) for x in sb) >= -tol for f in on])
    if not ok.any():
        return None
    return nw[ok], s[on][ok], s_max


def _vertex_contacts(model: Model, data: Data, g_vert: int, joint_v: int, g_other: int, joint_other: int,
                     tol: float, out: list, pair: int, offset: int, v_is_a: bool, corners: list,
                     margin: float) -> None:
    """Contacts of the vertices of geometry g_vert that lie within tol of geometry g_other
    (appended to `out`, or to `corners` where the vertex is at an edge or vertex of g_other)."""
    V = model.vertices[g_vert]
    if not len(V):
        return
    oMi, oMo = data.kinematics.oMi[joint_v], data.kinematics.oMi[joint_other]
    Vw = ordered(V, oMi.rotation.T) + oMi.translation  # ordered: src/step.cpp makes the same sums (§2.8)
    kind, a, b = model.bounds[g_other]  # a lower bound of each vertex's distance (shapes.distance_bound)
    if kind == "plane":  # a half-space: the bound is the exact signed distance, no coal query needed
        n = ordered(oMo.rotation, a)
        est = ordered(Vw, n) - (b + ordered(n, oMo.translation))
        for i in np.flatnonzero(est <= tol):
            d = float(est[i])
            if v_is_a:
                out.append((d, Vw[i], Vw[i] - d * n, n, pair, FeatureKind.VERTEX, offset + i))
            else:
                out.append((d, Vw[i] - d * n, Vw[i], -n, pair, FeatureKind.VERTEX, offset + i))
        return
    est = np.sqrt(((Vw - (ordered(oMo.rotation, a) + oMo.translation)) ** 2).sum(axis=1)) - b
    cand = np.flatnonzero(est <= tol)
    if not len(cand):
        return
    query = data.point_query(g_other)
    tf_other = data.oMg[g_other]
    tf, req, res = data.point_tf, data.distance_request, data.distance_result
    for i in cand:
        tf.setTranslation(Vw[i])
        d = query(tf, tf_other, req, res)
        if d <= tol:
            nrm = np.array(res.normal)  # from the vertex towards the other shape (a copy: a view of coal's result)
            p_on_other = res.getNearestPoint2()
            if not (np.isfinite(nrm).all() and abs(d) < 1e100):
                # coal leaves the normal undefined for a point exactly on the surface: take the
                # nearest face's (a box), else drop the vertex (coal's pair contact stands in)
                planes = model.face_planes[g_other]
                if planes is None or abs(d) >= 1e100:
                    continue
                sd = planes[0] @ (oMo.rotation.T @ (Vw[i] - oMo.translation)) - planes[1]
                f = int(np.argmax(sd))
                d, nrm = float(sd[f]), -(oMo.rotation @ planes[0][f])
                p_on_other = Vw[i] + d * nrm
            got = _corner_normals(model, g_vert, i, oMi, g_other, oMo, Vw[i], margin, Vw, tol)
            faces = None if got is None else got[0]
            if faces is not None and len(faces) >= 2:  # outward normals of the other: B -> A if the vertex is A's
                corners.append((d, Vw[i] if v_is_a else p_on_other, p_on_other if v_is_a else Vw[i],
                                faces if v_is_a else -faces, pair, offset + i))
                continue
            if faces is not None:  # one face separates: a smooth contact with its exact normal
                nrm = -faces[0]
                if got[1][0] < got[2] - tol:  # beyond tol of the nearest face's: the gap along this normal is its
                    d = float(got[1][0])  # plane's (coal's is the nearest face's: docs/theory.md §6.2, 1d)
                    p_on_other = Vw[i] + d * nrm
            if v_is_a:
                out.append((d, Vw[i], p_on_other, -nrm, pair, FeatureKind.VERTEX, offset + i))
            else:
                out.append((d, p_on_other, Vw[i], nrm, pair, FeatureKind.VERTEX, offset + i))


def _twin(first: list, r: tuple) -> bool:
    """Whether row r (a vertex of B on A's face) is the twin of a row of `first` (A's vertices on B's face, of the
    same pair): the same touching point, its point on A within SAME_POINT of that row's (max-norm), and its normal
    within TWIN_NORMAL of that row's in every component (docs/theory.md §6.2, 1b; src/step.cpp twin)."""
    return any(float(np.abs(x[1] - r[1]).max()) <= SAME_POINT and float(np.abs(x[3] - r[3]).max()) <= TWIN_NORMAL
               for x in first)


_SNAP = 0.5  # [rad] the patch is computed about the face normal nearest to coal's normal, if within
# this: coal's EPA normal of exactly touching faces drifts (4e-3 rad seen, and now and then far
# more); a patch only forms where faces are parallel (to PATCH_TOLERANCE), and face normals of a
# box are 90 deg apart, so the nearest one is the contact normal there
SNAP_COS = np.cos(_SNAP)  # its cosine, as _snap compares it (src/step.cpp's snap reads it: compiled.CONSTANTS)


def _face_axis(model: Model, data: Data, pair) -> np.ndarray:
    """For two polytopes: the face normal (of A or B, oriented B -> A) along which they are least
    interpenetrating, s(n) = min_A n.x - max_B n.x largest: the normal of a face-on-face contact.
    Used instead of coal's GJK/EPA normal, which for exactly touching boxes can point anywhere
    (along a side face, 90 deg off, seen in a 10-box stack)."""
    oa, ob = data.kinematics.oMi[pair.joint_first], data.kinematics.oMi[pair.joint_second]
    Va = ordered(model.vertices[pair.first], oa.rotation.T) + oa.translation  # ordered: src/box_box.hpp face_axis
    Vb = ordered(model.vertices[pair.second], ob.rotation.T) + ob.translation
    N = np.concatenate((-ordered(model.face_normals[pair.first], oa.rotation.T),
                        ordered(model.face_normals[pair.second], ob.rotation.T)))
    sep = ordered(Va, N.T).min(axis=0) - ordered(Vb, N.T).max(axis=0)
    return N[int(np.argmax(sep))]


def _snap(model: Model, data: Data, pair, n: np.ndarray) -> np.ndarray:
    """The face normal of A or B (oriented B -> A) nearest to coal's patch normal n, if within
    _SNAP: for parallel faces the contact normal is a face normal, and coal's EPA normal of
    exactly touching faces is ~1e-6 rad off it, enough to make a resting box slide. (ordered: src/step.cpp's
    snap makes the same sums.)"""
    best, cos_best = n, SNAP_COS
    for g, j, sign in ((pair.first, pair.joint_first, -1.0), (pair.second, pair.joint_second, 1.0)):
        F = model.face_normals[g]
        if len(F):
            Fw = sign * ordered(F, data.kinematics.oMi[j].rotation.T)  # A's outward normals point A -> B: flip
            c = ordered(Fw, n)
            i = int(np.argmax(c))
            if c[i] > cos_best:
                best, cos_best = Fw[i], c[i]
    return best


def _near_polytopes(model: Model, data: Data, tol: float) -> set:
    """Pairs of two polytopes in contact at the previous detection whose bounding spheres are still
    within tol: examined for vertex contacts whatever coal's narrow phase says (for exactly touching
    coplanar boxes it now and then reports a gap of -5e-12 m as no collision, and a resting box
    would drop through its support for a step)."""
    out = set()
    if not data.warm_start_pairs:
        return out
    for k in model.polytope_pair_ids.keys() & data.warm_start_pairs:  # the warm pairs, not every polytope pair
        g1, g2, j1, j2 = model.polytope_pair_ids[k]
        (_, c1, r1), (_, c2, r2) = model.bounds[g1], model.bounds[g2]
        o1, o2 = data.kinematics.oMi[j1], data.kinematics.oMi[j2]
        d = (o1.rotation @ c1 + o1.translation) - (o2.rotation @ c2 + o2.translation)
        if math.sqrt(d @ d) - r1 - r2 <= tol:
            out.add(k)
    return out


def _patch(data: Data, pair, c, n: np.ndarray):
    """coal's contact patch of a pair computed about normal n (ours, B -> A) instead of coal's own."""
    res = data.patch_collision
    res.clear()
    g1, g2 = data.shapes[pair.first], data.shapes[pair.second]
    res.addContact(coal.Contact(g1, g2, -1, -1, np.asarray(c.pos), -n, c.penetration_depth))
    out = data.patch_result
    out.clear()
    coal.computeContactPatch(g1, coal.Transform3s(data.oMg[pair.first]), g2,
                             coal.Transform3s(data.oMg[pair.second]), res, data.patch_request, out)
    return out.getContactPatch(0)


def _fallback_contact(data: Data, pair):
    """coal's contact of a pair at its default GJK/EPA tolerances, or None if it finds none."""
    res = data.fallback_result
    res.clear()
    g1, g2 = data.shapes[pair.first], data.shapes[pair.second]
    if coal.collide(g1, coal.Transform3s(data.oMg[pair.first]), g2, coal.Transform3s(data.oMg[pair.second]),
                    data.fallback_request, res) == 0:
        return None
    c = res.getContact(0)
    return c if abs(c.penetration_depth) < 1e100 and np.isfinite(np.asarray(c.normal)).all() else None


# A cached GJK guess [m] shorter than this is rescaled to unit length before coal's next call
# (docs/theory.md §6). coal warm-starts GJK from the request's cached guess (pinocchio enables
# enable_cached_gjk_guess); exactly touching shapes leave one of ~1e-12 m, and from such a guess
# (anything up to about coal's GJK tolerance) coal 3.0.3 reports a 6-14 mm overlap as no collision
# and a resting pair's distance as -DBL_MAX. Only its direction is a warm start: longer guesses are
# left as they are (src/step.cpp's fresh_guesses is the same rule, bit for bit). No coal issue reports
# this one; related: coal-library/coal#325 (a distance of -infinity from a degenerate GJK simplex).
GUESS_MIN = 1e-3


def fresh_guesses(requests) -> None:
    """Rescale each request's cached GJK guess shorter than GUESS_MIN (or non-finite) to unit
    length, (1, 0, 0) if it has no direction. Requests only: coal overwrites the results' copies."""
    for req in requests:
        gg = req.cached_gjk_guess
        x, y, z = gg.tolist()
        if max(abs(x), abs(y), abs(z)) >= GUESS_MIN and math.isfinite(x + y + z):
            continue
        n = math.sqrt(x * x + y * y + z * z)
        req.cached_gjk_guess = np.array([x / n, y / n, z / n] if 0.0 < n < math.inf else [1.0, 0.0, 0.0])


def detect(model: Model, data: Data, q: np.ndarray, *, corner_margin: float | np.ndarray | None = None) -> Contacts:
    """Closed contacts H(q) = {i : g_i(q) <= contact_tolerance} at configuration q.

    corner_margin [m]: a vertex inside or at a box is at a corner when its signed distances to two
    or more face planes differ by at most this, and at least the contact tolerance (default: the tolerance).
    A float is every pair's margin; an array (one entry per joint of the scene's model, the world's 0) gives a
    pair the sum of its two joints' entries: the stepper's is how far each body can move in the step (`travel`),
    so a corner struck within the step is seen as one, while the motion of bodies elsewhere makes none
    (docs/theory.md §6.3). Updates the forest's kinematics (data.kinematics.oMi) and the geometry placements at q."""
    model.forest.place(data.kinematics, q, model.geometries, data.oMg)
    if not model.pairs:
        return NO_CONTACTS
    tol = model.options.contact_tolerance
    bp = broad_phase.of(model, max(tol, GATE_MARGIN))
    if bp is None:  # few pairs: coal's narrow phase on all of them in one call
        gm, gd = model.geom, data.geom
        fresh_guesses(gd.collisionRequests)
        pin.computeCollisions(gm, gd, False)
        hits = [p.index for p in model.pairs if gd.collisionResults[p.index].isCollision()]
    else:  # the narrow phase on the broad phase's candidates, in pair order (the same results)
        cand = bp.candidates(data).tolist()
        fresh_guesses([data.collision_request(k) for k in cand])
        hits = [k for k in cand if data.collide(k)]
    near = _near_polytopes(model, data, tol)
    if not hits and not near:
        data.warm_start_pairs = set()
        return NO_CONTACTS
    if corner_margin is None or np.ndim(corner_margin) == 0:
        uniform = tol if corner_margin is None else max(tol, float(corner_margin))

        def margin_of(k: int) -> float:
            return uniform
    else:
        joints = model.pair_joints

        def margin_of(k: int) -> float:  # (src/step.cpp detect: the same sum)
            ja, jb = joints[k]
            return max(tol, float(corner_margin[ja]) + float(corner_margin[jb]))
    found: list = []
    corner_list: list = []
    hit_set = set(hits)
    for k in sorted(hit_set | near):
        pair = model.pairs[k]
        res = data.collision_result(k)
        hit = k in hit_set
        margin = margin_of(k)
        start = len(found)
        na, nb = len(model.vertices[pair.first]), len(model.vertices[pair.second])
        start_c = len(corner_list)
        if na:
            _vertex_contacts(model, data, pair.first, pair.joint_first, pair.second, pair.joint_second, tol,
                             found, pair.index, 0, True, corner_list, margin)
        mid = len(found)
        if nb:
            _vertex_contacts(model, data, pair.second, pair.joint_second, pair.first, pair.joint_first, tol,
                             found, pair.index, na, False, corner_list, margin)
            if start < mid < len(found):
                found[mid:] = [r for r in found[mid:] if not _twin(found[start:mid], r)]
        edges = _edge_contacts(model, data, pair, tol)
        if edges and len(corner_list) > start_c:  # a crossing within the corner margin of a corner is that corner's
            at = np.array([c[1] for c in corner_list[start_c:]] + [c[2] for c in corner_list[start_c:]])
            edges = [r for r in edges if min(np.abs(at - r[1]).max(axis=1).min(), np.abs(at - r[2]).max(axis=1).min())
                     > margin]
        if len(corner_list) > start_c:
            if len(found) == start and not edges:
                continue  # the corner is the contact of this pair: no patch, no witness
            # a corner beside smooth contacts of the same pair (a face resting on an edge): keep both
        if not hit:
            _add_new(found, start, edges)
            continue  # examined for its vertices and edges only (coal saw no collision): no patch, no witness
        c = res.getContact(0)
        n = -np.asarray(c.normal)  # coal: from shape 1 (A) to shape 2 (B); ours: B -> A
        fallback = not (abs(c.penetration_depth) < 1e100 and math.isfinite(n @ n)) or _too_deep(data, pair, c, tol)
        if fallback:  # EPA at data.GJK_TOLERANCE can fail on box-box overlaps: redo at coal's defaults
            c = _fallback_contact(data, pair)
            if c is None:
                continue
            n = -np.asarray(c.normal)
        k_patch = 0
        if pair.patch and not fallback and c.penetration_depth <= tol:
            # the patch (overlap polygon of parallel faces) about the face normal nearest to coal's
            # (whose EPA normal of resting faces drifts by up to 4e-3 rad: the polygon collapses)
            n_face = _face_axis(model, data, pair) if pair.index in model.polytope_pair_set else _snap(model, data, pair, n)
            # with vertex contacts, a patch must lie in their plane: coal's normal of coplanar
            # aligned boxes can point along a side face, which is no contact at all
            if len(found) == start or float(n_face @ found[start][3]) >= 1.0 - 1e-9:
                patch = _patch(data, pair, c, n_face)
                k_patch = patch.size()
        if k_patch > 1:  # coal's polygon: the face corners are its corners (docs/theory.md §6.2, 3b)
            edges = [r for r in edges if r[5] != FeatureKind.FACE]
            P1 = np.array([patch.getPointShape1(k) for k in range(k_patch)])
            new = np.ones(k_patch, bool)
            if len(found) > start:
                known = np.array([f[1] for f in found[start:]])
                new = np.abs(P1[:, None, :] - known[None, :, :]).max(axis=2).min(axis=1) > SAME_POINT
            for k in np.flatnonzero(new):
                found.append((c.penetration_depth, P1[k], np.array(patch.getPointShape2(int(k))), n_face, pair.index,
                              FeatureKind.PATCH, int(k)))
        elif len(found) == start and not edges and c.penetration_depth <= tol:  # no vertex: smooth shapes
            found.append((c.penetration_depth, np.array(c.getNearestPoint1()), np.array(c.getNearestPoint2()),
                          n, pair.index, FeatureKind.WITNESS, 0))
        _add_new(found, start, edges)
    corners = _merge_corners(model, corner_list, margin_of) if corner_list else ()
    data.warm_start_pairs = {f[4] for f in found} | {c[4] for c in corner_list}
    if not found:
        return Contacts.empty(corners) if corners else NO_CONTACTS
    return from_rows(model, found, corners)


def _boxes(data: Data, pair) -> tuple | None:
    """(R, c, half) in the world of each of a pair's two boxes (box_box's box_a, box_b), None unless both are boxes."""
    ga, gb = data.shapes[pair.first], data.shapes[pair.second]
    if not (isinstance(ga, coal.Box) and isinstance(gb, coal.Box)):
        return None
    fa, fb = data.oMg[pair.first], data.oMg[pair.second]
    return (fa.rotation, fa.translation, np.asarray(ga.halfSide)), (fb.rotation, fb.translation, np.asarray(gb.halfSide))


def _too_deep(data: Data, pair, c, tol: float) -> bool:
    """coal's contact of two boxes deeper than box_box.depth_floor: its EPA failed (docs/theory.md §6.2; at
    data.GJK_TOLERANCE it gave a cube resting on a slab a depth of 0.2 m, and the patch corners that gap)."""
    if not c.penetration_depth < -tol:
        return False
    boxes = _boxes(data, pair)
    return boxes is not None and c.penetration_depth < box_box.depth_floor(*boxes, tol)


def _edge_contacts(model: Model, data: Data, pair, tol: float) -> list:
    """The edge crossings of a pair of two boxes (box_box.edge_crossings, docs/theory.md §6.2) as contact
    rows (g, p_A, p_B, n, pair, EDGE, 12 k + l), then the corners of its nearly parallel faces (box_box.face_patch)
    as rows (g, p_A, p_B, n, pair, FACE, i), which detect keeps only where coal's patch has no polygon; [] for
    any other pair."""
    boxes = _boxes(data, pair)
    if boxes is None:
        return []
    cache = data.box_edges  # per geometry, in its joint frame
    for g in (pair.first, pair.second):
        if g not in cache:
            cache[g] = box_box.box_edges(data.shapes[g], model.geometries[g].placement)
    oMi = data.kinematics.oMi
    A, B = box_box.world(cache[pair.first], oMi[pair.joint_first]), box_box.world(cache[pair.second], oMi[pair.joint_second])
    box_a, box_b = boxes
    hits = box_box.edge_crossings(A, B, box_a, box_b, tol)
    faces = box_box.face_patch(A, B, box_a, box_b, tol)
    return ([(g, pa, pb, n, pair.index, FeatureKind.EDGE, 12 * k + j) for g, pa, pb, n, k, j in hits]
            + [(g, pa, pb, n, pair.index, FeatureKind.FACE, i) for g, pa, pb, n, i in faces])


def _add_new(found: list, start: int, edges: list) -> None:
    """Append the edge contacts and face corners of a pair whose point on A is not already one of its
    contacts (a patch corner of two yawed faces is also the crossing of their edges)."""
    if not edges:
        return
    if len(found) > start:
        pa, known = np.array([r[1] for r in edges]), np.array([f[1] for f in found[start:]])
        new = np.abs(pa[:, None, :] - known[None, :, :]).max(axis=2).min(axis=1) > SAME_POINT
        edges = [r for r, k in zip(edges, new.tolist()) if k]
    crossings = [r for r in edges if r[5] == FeatureKind.EDGE]
    for r in edges:  # a face corner that is also an edge crossing (yawed faces) is that crossing
        if r[5] == FeatureKind.EDGE or all(np.abs(x[1] - r[1]).max() > SAME_POINT for x in crossings):
            found.append(r)


def from_rows(model: Model, rows: list, corners: tuple = ()) -> Contacts:
    """Contacts from rows (g, point_a, point_b, normal, pair, kind, feature)."""
    g, pa, pb, nn, pair_ids, kind, feat = zip(*rows)
    pair_ids = np.array(pair_ids, dtype=np.int64)
    joints = model.pair_joints[pair_ids]
    return Contacts(np.array(g, float), np.array(pa), np.array(pb), np.array(nn), pair_ids,
                    np.array(kind, dtype=np.int64), np.array(feat, dtype=np.int64), joints[:, 0], joints[:, 1],
                    corners)


def _merge_corners(model: Model, items: list, margin_of) -> tuple:
    """One :class:`Corner` per touching point of a pair: a vertex of A at a vertex of B is found
    from both sides (points within the pair's corner margin, margin_of(pair) [m]: they may have crossed
    within the step); its ways of
    staying apart are the faces of both (duplicates dropped), at the first point found (A's
    vertex, as A's vertices are queried first)."""
    out: list = []
    for d, pa, pb, normals, pair, feat in items:
        for k, c in enumerate(out):
            if c.pair == pair and np.abs(c.point_a - pa).max() <= margin_of(pair):
                allnormals = np.concatenate([c.normals, normals])
                keep = [i for i in range(len(allnormals))
                        if not any(np.abs(allnormals[i] - allnormals[j]).max() <= 1e-12 for j in range(i))]
                out[k] = Corner(min(c.g, d), c.point_a, c.point_b, allnormals[keep], pair, c.joint_a, c.joint_b,
                                c.features + (feat,))
                break
        else:
            ja, jb = model.pair_joints[pair]
            out.append(Corner(float(d), np.array(pa), np.array(pb), normals, int(pair), int(ja), int(jb), (feat,)))
    return tuple(out)


def pair_distances(model: Model, data: Data, q: np.ndarray, *, near: bool = False) -> np.ndarray:
    """Signed distance [m] of every collision pair at q (for records and plots, and the position
    correction's check); NaN where coal's query failed (its -DBL_MAX is never passed on as a
    distance). near: for a model of a pair table (no list: model.listed false) query only the broad
    phase's candidates at the detection's gate and give +inf for the others, whose boxes are apart
    (the correction's check: only distances below zero count); a listed model ignores it."""
    if not model.pairs:
        return np.zeros(0)
    if model.listed or not near:
        fresh_guesses(data.geom.distanceRequests)
        model.forest.place(data.kinematics, q, model.geometries, data.geom.oMg)
        pin.computeDistances(model.geom, data.geom)
        d = np.array([r.min_distance for r in data.distance_results])
    else:
        model.forest.place(data.kinematics, q, model.geometries, data.oMg)
        d = np.full(len(model.pairs), np.inf)
        cand = broad_phase.of(model, max(model.options.contact_tolerance, GATE_MARGIN)).candidates(data).tolist()
        fresh_guesses([data.distance_query(k)[0] for k in cand])
        d[cand] = [data.distance(k) for k in cand]
    d[~(np.abs(d) < DISTANCE_FAILED) & ~np.isposinf(d)] = np.nan
    return d


def geometry_gaps(model: Model, data: Data, q: np.ndarray) -> np.ndarray:
    """(geometries,) [m]: the records' gaps of a model of more than model.GAP_PAIRS pairs (Model.gaps_per_geometry;
    its n^2 / 2 pair distances are never all evaluated): each geometry's least signed distance to the geometries it
    pairs with, where it is at most model.gap_reach, else +inf; NaN where coal's query of a pair failed
    (docs/theory.md §2.12). coal examines the broad phase's candidates at that margin (broad_phase.within: a box is
    never farther than its shape, so every pair within the reach is among them): pin.computeDistance on the
    GeometryData of a listed model, the same query on each pair's own coal objects without a list (data.Data.distance,
    as pair_distances(near=True)), each warm-started from the pair's last query (fresh_guesses); src/step.cpp's
    Stepper::geometry_gaps is this function, for the compiled run loop."""
    out = np.full(len(model.geometries), np.inf)
    model.forest.place(data.kinematics, q, model.geometries, data.oMg)
    reach = model.gap_reach
    cand, gi, gj = broad_phase.within(model, reach).candidate_geometries_at(data.kinematics.oMi)
    if len(cand):
        # data.distance(k) of each candidate, its two placements made once per geometry, in its Pair's order
        first, second = pair_table.ordered(model.pair_table, gi, gj)
        if model.listed:
            gm, gd = model.geom, data.geom
            fresh_guesses([gd.distanceRequests[k] for k in cand.tolist()])
            d = np.array([pin.computeDistance(gm, gd, k).min_distance for k in cand.tolist()])
        else:
            oMg = data.oMg
            tf = {g: coal.Transform3s(oMg[g]) for g in np.union1d(first, second).tolist()}
            queries = [data.distance_query(k) for k in cand.tolist()]
            fresh_guesses([x[0] for x in queries])
            d = []
            for (req, res, f), a, b in zip(queries, first.tolist(), second.tolist()):
                res.clear()
                f(tf[a], tf[b], req, res)
                d.append(res.min_distance)
            d = np.array(d)
        d[~(np.abs(d) < DISTANCE_FAILED)] = np.nan
        d[d > reach] = np.inf  # a candidate beyond the reach (boxes are coarser than shapes): as the others
        np.minimum.at(out, first, d)  # (a NaN stays: np.minimum propagates it)
        np.minimum.at(out, second, d)
    return out


def record_gaps(model: Model, data: Data, q: np.ndarray) -> np.ndarray:
    """The gap column of a sample at q [m] (trajectory "gap", named by model.gap_names): every pair's distance
    (pair_distances), or each geometry's nearest (geometry_gaps) for a model of more than model.GAP_PAIRS pairs."""
    return geometry_gaps(model, data, q) if model.gaps_per_geometry else pair_distances(model, data, q)


def check_initial(model: Model, data: Data, q: np.ndarray) -> None:
    """model.check_start for a configuration q given to a run instead of the scene's q0 (a
    SceneError if a pair starts deeper than contact_tolerance inside another; docs/theory.md §2.5)."""
    where = str(model.scene.path) if model.scene.path else "<scene>"
    check_start(model, data.kinematics, q, where, model.options.contact_tolerance)
