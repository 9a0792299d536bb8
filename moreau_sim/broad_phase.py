"""The detection's broad phase: which collision pairs coal's narrow phase examines (docs/theory.md
§6.1). A sweep-and-prune on axis-aligned boxes: each geometry's local box (coal's AABB) carried to
the world and inflated by the narrow phase's security margin; a pair with a half-space is kept
when the other's box comes within that margin of its plane. A pair it drops is farther apart than
the margin, where the narrow phase finds no collision: the contacts are those of the all-pairs
narrow phase, bit for bit for coal's closed-form pairs. A pair coal resolves by GJK warm-starts
from its own previous query (pinocchio keeps the guess): skipped for a while, it starts again from
an older guess, and its witness points can differ in round-off (forced on every bundled scene,
panda_table's mesh pairs differ, the box stacks do not). Linear in geometries plus the pairs it
keeps (a column of n beads: ~n candidates, not n^2/2). The compiled step (src/step.cpp candidates)
computes the same candidates from the same data with the same sums (sums.dots, docs/theory.md §2.8).

coal's broad-phase managers would do the same in C++, but coal 3.0.3's Python binding cannot say
which pairs they found: ``CollisionCallBackCollect.getCollisionPairs()`` has no Python converter
(TypeError) and ``CollisionCallBackBase`` cannot be subclassed from Python.
"""

from __future__ import annotations

import weakref

import coal
import numpy as np

from .sums import dots

MIN_PAIRS = 64  # models with more collision pairs than this use the broad phase (below: all pairs, one call)
SLACK = 1e-6  # [m] added to the margin: the boxes' round-off never drops a pair within the margin

_tables: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


class BroadPhase:
    """What the sweep-and-prune needs of a model (model.Model), made once and linear in geometries: every
    geometry's box in its joint's frame (centre, half extents), the half-spaces' planes, and the model's
    pair table (pair_table.PairTable: which geometries pair, and the pair index of each two)."""

    def __init__(self, model, margin: float):
        gobs = list(model.geometries)
        G = len(gobs)
        self.table = t = model.pair_table
        self.margin = float(margin) + SLACK
        self.joint = np.array([go.parentJoint for go in gobs], dtype=np.int64)
        self.centre, self.half = np.zeros((G, 3)), np.zeros((G, 3))
        bounded = np.ones(G, bool)
        for g, go in enumerate(gobs):
            geo = go.geometry
            if isinstance(geo, (coal.Halfspace, coal.Plane)):
                bounded[g] = False
                continue
            geo.computeLocalAABB()
            lo, hi = np.array(geo.aabb_local.min_), np.array(geo.aabb_local.max_)
            R, tr = go.placement.rotation, go.placement.translation
            self.centre[g] = R @ (0.5 * (lo + hi)) + tr
            self.half[g] = np.abs(R) @ (0.5 * (hi - lo))
        self.G, self.bounded = G, np.flatnonzero(bounded)
        # pairs with a half-space {n.x <= d} (n, d in its joint's frame): (pair, half-space, other)
        spaces = [a for a in np.flatnonzero(~bounded).tolist() if isinstance(gobs[a].geometry, coal.Halfspace)]
        bb = self.bounded
        half = [(a, b) for a in spaces for b in bb[t.chosen(np.full(len(bb), a), bb)].tolist()]
        self.half_geom = np.array([a for a, _ in half], dtype=np.int64)
        self.half_other = np.array([b for _, b in half], dtype=np.int64)
        self.half_pairs = t.index(self.half_geom, self.half_other).astype(np.int64)
        self.half_n = np.array([model.bounds[a][1] for a, _ in half], float).reshape(-1, 3)
        self.half_d = np.array([model.bounds[a][2] for a, _ in half], float)
        # any other pair with an unbounded shape (a two-sided plane): always examined
        every = np.arange(G)
        unbounded = [t.index(np.full(int(ok.sum()), a), every[ok]) for a in np.flatnonzero(~bounded).tolist()
                     for ok in [t.chosen(np.full(G, a), every)]]
        unbounded = np.concatenate([np.zeros(0, np.int64), *unbounded]).astype(np.int64)
        self.always = np.setdiff1d(unbounded, self.half_pairs)
        geoms = [t.geometries(k) for k in self.always.tolist()]  # (i, j) of each: few (the two-sided planes')
        self.always_geoms = np.array(geoms, dtype=np.int64).reshape(-1, 2).T
        self.any_bounded = bool(len(t)) and len(self.bounded) >= 2

    def candidates(self, data) -> np.ndarray:
        """Sorted indices of the pairs whose inflated boxes overlap at the configuration of data.kinematics.oMi
        (contacts.detect has placed it)."""
        return self.candidates_at(data.kinematics.oMi)

    def candidates_at(self, oMi) -> np.ndarray:
        """candidates() at the joint placements oMi (the scene's joint ids)."""
        return self.candidate_geometries_at(oMi)[0]

    def candidate_geometries_at(self, oMi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """candidates_at(oMi) and the two geometries of each, (pairs, one, other) (in either order)."""
        R = np.array([o.rotation for o in oMi])
        p = np.array([o.translation for o in oMi])
        Rg, pg = R[self.joint], p[self.joint]
        c = dots(Rg, self.centre[:, None, :]) + pg  # dots: src/step.cpp's candidates makes the same sums
        h = dots(np.abs(Rg), self.half[:, None, :])
        out = [(self.always, self.always_geoms[0], self.always_geoms[1]), self._sweep(c, h)]
        if len(self.half_pairs):
            n = dots(Rg[self.half_geom], self.half_n[:, None, :])  # the plane in the world
            d = self.half_d + dots(n, pg[self.half_geom])
            o = self.half_other
            gap = dots(n, c[o]) - dots(np.abs(n), h[o]) - d
            near = gap <= self.margin
            out.append((self.half_pairs[near], self.half_geom[near], o[near]))
        k, first = np.unique(np.concatenate([x[0] for x in out]), return_index=True)
        return (k, np.concatenate([x[1] for x in out])[first].astype(np.int64),
                np.concatenate([x[2] for x in out])[first].astype(np.int64))

    def _sweep(self, c: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pairs of bounded geometries whose boxes, inflated by the margin, overlap, and their geometries: sorted
        along the axis where the centres spread most, each box against those starting before it ends."""
        b = self.bounded
        if not self.any_bounded:
            none = np.zeros(0, dtype=np.int64)
            return none, none, none
        lo, hi = c[b] - h[b] - self.margin, c[b] + h[b] + self.margin
        axis = int(np.argmax(c[b].var(axis=0)))
        order = np.argsort(lo[:, axis], kind="stable")
        ls, hs = lo[order, axis], hi[order, axis]
        end = np.searchsorted(ls, hs, side="right")
        count = np.maximum(end - np.arange(len(b)) - 1, 0)
        a = np.repeat(np.arange(len(b)), count)
        k = a + 1 + np.arange(len(a)) - np.repeat(np.cumsum(count) - count, count)
        i, j = order[a], order[k]
        overlap = ((lo[i] <= hi[j]) & (lo[j] <= hi[i])).all(axis=1)
        gi, gj = b[i[overlap]], b[j[overlap]]
        ok = self.table.chosen(gi, gj)
        gi, gj = gi[ok], gj[ok]
        return self.table.index(gi, gj).astype(np.int64), gi, gj


def of(model, margin: float) -> BroadPhase | None:
    """The model's broad phase for the narrow phase's security margin [m] (made once per model), or
    None when the model has at most MIN_PAIRS pairs (coal's narrow phase on all of them is cheaper)."""
    if len(model.pairs) <= MIN_PAIRS:
        return None
    return within(model, margin)


def within(model, margin: float) -> BroadPhase:
    """The model's broad phase at `margin` [m], whatever its number of pairs (made once per model and
    margin: the detection's and the records' (contacts.geometry_gaps) are kept side by side)."""
    kept = _tables.get(model)
    if kept is None:
        kept = _tables[model] = {}
    bp = kept.get(float(margin))
    if bp is None:
        bp = kept[float(margin)] = BroadPhase(model, margin)
    return bp
