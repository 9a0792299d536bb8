"""Swept contact detection against tunnelling (docs/theory.md §2.6, stress scene ``fast_impact``).

The stepper closes a contact when its gap at the midpoint configuration is within the tolerance,
g_i(q_m) <= tol. A body that moves more than its overlap window in a step is then missed: a
marble (r = 1 cm) at 50 m/s moves 5 cm per step at h = 1e-3, while it overlaps a 1 cm plate over
only 3 cm of travel. Worse, a midpoint that lands in the plate's far half gets coal's contact
normal pointing *through* the plate, and the contact, seen as separating, pushes nothing. A
contact activation margin (g_i(q_m) <= tol + h |gamma_i|) does not fix this: at a midpoint already
past a thin obstacle the nearest feature, and so the normal, is on the wrong side.

    swept_contacts(model, data, q0, q1)

finds every collision pair whose shapes are apart at q0 and touch somewhere on the path
q(s) = q0 (+) s (q1 (-) q0), s in [0, 1] (Pinocchio's Lie-group interpolation), by conservative
advancement with coal's signed distance: at s the pair is d(s) apart and no point of either shape
moves faster than mu per unit s (:func:`motion_bounds`), so nothing can touch before
s + d(s) / mu. (Coal's own continuous collision is not exposed by its Python bindings, 3.0.3.)

:func:`swept_detect` corrects one step's midpoint contacts with it; the stepper calls it when the
option ``tunnelling`` is ``swept`` and a body may move further in a step than the thinnest pair is
thick, or on every step with ``tunnelling = "always"``.
"""

from __future__ import annotations

from dataclasses import dataclass

import coal
import numpy as np
import pinocchio as pin

from .contacts import Contacts, FeatureKind, from_rows
from .data import Data
from .model import Model

__all__ = ["SweptContact", "motion_bounds", "pair_distance", "swept_contacts", "swept_detect"]


@dataclass(frozen=True, slots=True)
class SweptContact:
    """A pair that comes into contact during the motion q0 -> q1.

    pair: collision-pair index; s: the fraction of the motion at the first contact (0 < s <= 1);
    q: the configuration there; gap0, gap1: signed distances at q0 and q1 [m]; normal: unit
    contact normal at the first contact, from the pair's second shape B to its first shape A (the
    convention of contacts.py: the gap grows when A moves along it); point_a, point_b: the
    witness points there [m, world]; tunnels: the pair is apart again at q1 (gap1 > tol), so
    neither endpoint sees it; iterations: conservative-advancement iterations used;
    converged: False when max_iter ran out before s* was bracketed to within the tolerance (the
    pair is then reported at the last safe s, conservatively)."""

    pair: int
    s: float
    q: np.ndarray
    gap0: float
    gap1: float
    normal: np.ndarray
    point_a: np.ndarray
    point_b: np.ndarray
    tunnels: bool
    iterations: int
    converged: bool = True


def pair_distance(model: Model, data: Data, q: np.ndarray, pair: int) -> coal.DistanceResult:
    """Coal's signed distance of collision pair `pair` at q (updates the geometry placements).
    Returns coal's DistanceResult (min_distance [m], normal from the first shape to the second,
    nearest points). A model without a pair list: the same query on the pair's own coal objects (data.Data.distance),
    not on a GeometryData of every pair."""
    model.forest.place(data.kinematics, q, model.geometries, data.oMg)
    if model.listed:
        return pin.computeDistance(model.geom, data.geom, pair)
    data.distance(pair)
    return data.distance_query(pair)[1]


def _shape_radius(model: Model, g: int) -> float:
    """Radius of a ball about geometry g's own origin that contains the shape (inf for unbounded
    shapes: half-spaces and planes, which are static)."""
    go = model.geometries[g]
    shape = go.geometry
    if isinstance(shape, (coal.Halfspace, coal.Plane)):
        return np.inf
    shape.computeLocalAABB()
    return float(np.linalg.norm(np.asarray(shape.aabb_center)) + shape.aabb_radius)


def motion_bounds(model: Model, data: Data, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """mu[g] >= the largest speed, per unit s, of any point of geometry g along the path
    q(s) = q0 (+) s dq, dq = q1 (-) q0 (0 for static geometries).

    Along the path each joint's velocity coordinates are constant (dq), so a point's speed is at
    most sum over the joints j supporting it and their velocity columns c of
    |dq_c| (|S_lin,c| + |S_ang,c| L_j), S the joint's motion subspace in its own frame and L_j a
    bound of the point's distance from joint j's origin that holds along the whole path: the
    lengths of the joint placements between j and the geometry, the largest prismatic
    displacement of the joints in between at either end (linear in s), the geometry's offset and
    its shape's bounding radius. Exact for one body; conservative for chains."""
    pm = model.pin
    dq = pin.difference(pm, q0, q1)
    model.forest.place(data.kinematics, q0)
    ngeom = len(model.geometries)
    mu = np.zeros(ngeom)
    # per joint: speed coefficients (linear, angular) of its velocity columns
    lin = {}
    ang = {}
    for j in range(1, pm.njoints):
        jm = pm.joints[j]
        S = model.forest.motion_subspace(data.kinematics, j)
        lin[j] = np.abs(dq[jm.idx_v:jm.idx_v + jm.nv]) @ np.linalg.norm(S[:3], axis=0)
        ang[j] = np.abs(dq[jm.idx_v:jm.idx_v + jm.nv]) @ np.linalg.norm(S[3:], axis=0)
    disp = {}  # bound of a joint's own translation along the path (prismatic-like coordinates)
    for j in range(1, pm.njoints):
        jm = pm.joints[j]
        if jm.nq == 1 and jm.nv == 1 and lin[j] > 0.0 and ang[j] == 0.0:
            disp[j] = max(abs(q0[jm.idx_q]), abs(q1[jm.idx_q]))
    for g, go in enumerate(model.geometries):
        jg = go.parentJoint
        if jg == 0:
            continue
        r = _shape_radius(model, g) + float(np.linalg.norm(go.placement.translation))
        chain = [j for j in pm.supports[jg] if j != 0]  # root ... jg
        total = 0.0
        for k, j in enumerate(chain):
            L = r
            for i in chain[k + 1:]:
                L += float(np.linalg.norm(pm.jointPlacements[i].translation)) + disp.get(i, 0.0)
            total += lin[j] + ang[j] * L
        mu[g] = total
    return mu


def swept_contacts(model: Model, data: Data, q0: np.ndarray, q1: np.ndarray, *, tol: float | None = None,
                   pairs=None, max_iter: int = 100, include_touching: bool = False) -> list[SweptContact]:
    """Pairs whose shapes are apart at q0 (gap > tol) and touch (gap <= tol) somewhere on the path
    q(s) = q0 (+) s (q1 (-) q0), s in (0, 1] (see the module doc), in order of pair index.

    tol: the contact tolerance [m] (default: the scene's); pairs: the pair indices to examine
    (default all); max_iter: conservative-advancement iterations per pair; include_touching:
    also report pairs already within tol at q0 (with s = 0).
    Updates data's kinematics and geometry placements (to the last configuration examined)."""
    tol = model.options.contact_tolerance if tol is None else float(tol)
    pm = model.pin
    dq = pin.difference(pm, q0, q1)
    mu_g = motion_bounds(model, data, q0, q1)
    out: list[SweptContact] = []
    for p in (model.pairs if pairs is None else [model.pairs[i] for i in pairs]):
        mu = mu_g[p.first] + mu_g[p.second]
        r0 = _result(pair_distance(model, data, q0, p.index))  # (coal's result is overwritten by the next query)
        d0 = r0[0]
        if d0 <= tol:
            if include_touching:
                out.append(_contact(p.index, 0.0, q0, d0, d0, r0, False, 0, True))
            continue
        if mu <= 0.0 or d0 - tol >= mu:  # cannot close the distance within the motion
            continue
        s, it, res, converged = 0.0, 0, r0, False
        while it < max_iter:
            it += 1
            s_next = s + (res[0] - 0.5 * tol) / mu  # nothing can touch before this
            if s_next > 1.0:
                res = None
                break
            s = s_next
            res = _result(pair_distance(model, data, pin.integrate(pm, q0, s * dq), p.index))
            if res[0] <= tol:
                converged = True
                break
        if res is None:
            continue  # no contact on the path
        d1 = float(pair_distance(model, data, q1, p.index).min_distance)
        out.append(_contact(p.index, s, pin.integrate(pm, q0, s * dq), d0, d1, res, d1 > tol, it, converged))
    return out


def _result(r: coal.DistanceResult) -> tuple:
    """(distance, normal B -> A, point on A, point on B) copied out of coal's reused result."""
    n = -np.array(r.normal, float)  # coal: from shape 1 (A) to shape 2 (B); ours: B -> A
    nn = np.linalg.norm(n)
    return (float(r.min_distance), n / nn if nn > 0 else n, np.array(r.getNearestPoint1(), float),
            np.array(r.getNearestPoint2(), float))


def _contact(pair, s, q, d0, d1, res, tunnels, it, converged) -> SweptContact:
    return SweptContact(int(pair), float(s), np.array(q, float), float(d0), float(d1), res[1], res[2], res[3],
                        bool(tunnels), int(it), bool(converged))


def _carry(model: Model, data: Data, joint: int, q_from: np.ndarray, p: np.ndarray, q_to: np.ndarray) -> np.ndarray:
    """World point p attached to `joint` at q_from, carried rigidly to q_to (joint 0: fixed)."""
    if joint == 0:
        return p
    kin = data.kinematics
    model.forest.place(kin, q_from)
    local = kin.oMi[joint].actInv(p)
    model.forest.place(kin, q_to)
    return kin.oMi[joint].act(local)


def swept_detect(model: Model, data: Data, q: np.ndarray, u: np.ndarray, h: float, q_m: np.ndarray,
                 contacts: Contacts) -> Contacts:
    """The active set of one step: `contacts` (detected at the midpoint q_m) corrected by a
    swept test over q_k = q -> q_k (+) 1.5 h u_k (up to the next step's midpoint if u stays).

    For every pair that is apart at q_k and touches on that path at time s* (in steps), with the
    first contact's witness points carried rigidly along (their signed distance along its normal):
    - the midpoint found a contact of the pair whose normal agrees with the first contact's
      (n_mid . n_swept > 0): nothing changes (the usual case: a thick obstacle);
    - s* <= 1/2 (it touched before q_m), the midpoint missed it or saw it from the far side (q_m
      past the obstacle's mid-plane), and q_m is past the first contact's plane: the pair's
      midpoint contacts are replaced by the swept one;
    - s* > 1/2 (it touches after q_m), the path ends past the first contact's plane, and the next
      midpoint would miss it too (apart there, or seen from the far side): the swept contact is
      added now, up to half a step early (a position error <= h |gamma|, the order of the midpoint
      rule's penetration). Otherwise the next step takes it as usual.
    A graze (a corner dipping below the plane and back within the path) changes nothing.
    A swept contact carries the first contact's normal and body-fixed witness points moved to q_m,
    and as gap their signed distance along that normal at q_m (kind FeatureKind.SWEPT). Non-tunnelling runs
    are unchanged. Limit: after a replaced contact q_{k+1} lies h|gamma|(1-e)/2 beyond q_k at most;
    an obstacle thinner than twice that can still be left on the wrong side (then a normal kept
    from the previous step would be needed).

    Leaves data's kinematics and geometry placements at q_m (as contacts.detect does)."""
    tol = model.options.contact_tolerance
    q_far = pin.integrate(model.pin, q, 1.5 * h * u)
    drop: set = set()
    extra = []
    for c in swept_contacts(model, data, q, q_far):
        mine = contacts.pair == c.pair
        if mine.any() and (contacts.normal[mine] @ c.normal).max() > 0.0:
            continue  # the midpoint sees it from the right side: as now
        pr = model.pairs[c.pair]
        pa = _carry(model, data, pr.joint_first, c.q, c.point_a, q_m)
        pb = _carry(model, data, pr.joint_second, c.q, c.point_b, q_m)
        g_m = float(c.normal @ (pa - pb))
        if 1.5 * c.s <= 0.5:  # touched before q_m
            if g_m >= -tol:
                continue  # a graze: q_m is not past the first contact's plane
        else:  # touches after q_m: is the path through, and does the next midpoint miss it?
            fa = _carry(model, data, pr.joint_first, c.q, c.point_a, q_far)
            fb = _carry(model, data, pr.joint_second, c.q, c.point_b, q_far)
            if float(c.normal @ (fa - fb)) >= -tol:
                continue  # a graze
            r = pair_distance(model, data, q_far, c.pair)
            if r.min_distance <= tol and -np.array(r.normal) @ c.normal > 0.0:
                continue  # the next step's midpoint takes it, as now
        drop.add(c.pair)
        extra.append((g_m, pa, pb, c.normal, c.pair, FeatureKind.SWEPT, 0))
    model.forest.place(data.kinematics, q_m, model.geometries, data.oMg)
    if not extra:
        return contacts
    keep = ~np.isin(contacts.pair, list(drop))
    base = contacts.select(keep) if contacts.m else contacts
    return base.concat(from_rows(model, extra))
