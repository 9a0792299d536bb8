"""The collision pairs of a model without their list: every two geometries i < j but a sparse set left
out (same joint, a link and its parent in one body, the SRDF's, the scene's [collisions] exclude, self
pairs overlapping at a reference pose), in the order of (i, j). Pair k is made from its index and the
index of (i, j) from the pair, so a scene of n bodies keeps O(n) memory and not its n^2 / 2 pairs
(docs/theory.md §6.1: the broad phase names the few pairs the narrow phase examines).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import coal
import numpy as np
import pinocchio as pin


@dataclass(frozen=True)
class Pair:
    """A collision pair: geometry ids (first = coal's shape 1), their joints, its name, and
    whether contacts.py asks coal for the contact patch: only when both shapes have flat faces,
    and not when one is a half-space and the other a polytope (the overlap of a face with a
    half-space is that face, whose corners are already vertex contacts)."""

    index: int
    first: int
    second: int
    joint_first: int
    joint_second: int
    name: str
    patch: bool = True


class PairTable(Sequence):
    """The pairs (i, j), i < j, of G geometries less the sorted keys i G + j of `removed`, as Pair
    objects made on demand. joint[g]: geometry g's joint; names[g]: its name; half, poly, flat[g]:
    whether it is a half-space or plane, a polytope, a shape with flat faces (the pair's patch flag)."""

    def __init__(self, joint, names, half, poly, flat, removed):
        self.G = G = len(joint)
        self.joint = np.asarray(joint, dtype=np.int64)
        self.names = tuple(names)
        self.half, self.poly, self.flat = (np.asarray(x, bool) for x in (half, poly, flat))
        self.removed = np.unique(np.asarray(sorted(removed), dtype=np.int64).reshape(-1))
        rows = self.removed // G if G else self.removed
        per_row = np.bincount(rows, minlength=G) if G else np.zeros(0, np.int64)
        count = (G - 1 - np.arange(G)) - per_row
        self.start = np.concatenate([[0], np.cumsum(count)]).astype(np.int64)
        self._made: dict[int, Pair] = {}

    def __len__(self) -> int:
        return int(self.start[-1])

    def chosen(self, i, j) -> np.ndarray:
        """Whether geometries (i, j) (arrays, any order) form a pair."""
        i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
        lo, hi = np.minimum(i, j), np.maximum(i, j)
        key = lo * self.G + hi
        pos = np.minimum(np.searchsorted(self.removed, key), max(len(self.removed) - 1, 0))
        gone = self.removed[pos] == key if len(self.removed) else np.zeros(key.shape, bool)
        return (lo != hi) & ~gone

    def index(self, i, j) -> np.ndarray:
        """The pair indices of geometries (i, j) (arrays, any order; each a pair: chosen)."""
        i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
        lo, hi = np.minimum(i, j), np.maximum(i, j)
        G = self.G
        before = np.searchsorted(self.removed, lo * G + hi) - np.searchsorted(self.removed, lo * G + lo)
        return self.start[lo] + (hi - lo - 1) - before

    def geometries(self, k: int) -> tuple[int, int]:
        """(i, j), i < j, of pair k."""
        i = int(np.searchsorted(self.start, k, side="right")) - 1
        j = i + 1 + (k - int(self.start[i]))
        G = self.G
        a = int(np.searchsorted(self.removed, i * G + i))
        b = int(np.searchsorted(self.removed, (i + 1) * G))
        for key in self.removed[a:b].tolist():  # the row's left-out partners, in order: skip each at or before j
            if key - i * G <= j:
                j += 1
            else:
                break
        return i, j

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[x] for x in range(*k.indices(len(self)))]
        k = int(k)
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError(k)
        p = self._made.get(k)
        if p is None:
            p = self._made[k] = self._make(k, *self.geometries(k))
        return p

    def _make(self, k: int, i: int, j: int) -> Pair:
        # shape 1 = the moving one with the larger joint id: normals then point from it to the other
        if self.joint[i] < self.joint[j]:
            i, j = j, i
        half, poly = self.half, self.poly
        patch = bool(self.flat[i] and self.flat[j] and not ((half[i] and poly[j]) or (half[j] and poly[i])))
        return Pair(k, i, j, int(self.joint[i]), int(self.joint[j]), f"{self.names[i]}|{self.names[j]}", patch)

    def __iter__(self):
        G, k = self.G, 0
        for i in range(G - 1):
            js = np.arange(i + 1, G)
            a, b = np.searchsorted(self.removed, [i * G + i, (i + 1) * G])
            if b > a:
                js = np.setdiff1d(js, self.removed[a:b] - i * G, assume_unique=True)
            for j in js.tolist():
                yield self._made.get(k) or self._make(k, i, j)
                k += 1

    def joints(self, ks) -> np.ndarray:
        """(len(ks), 2) joints of pairs ks (first, second)."""
        pairs = [self[k] for k in np.asarray(ks).reshape(-1).tolist()]
        return np.array([(p.joint_first, p.joint_second) for p in pairs], dtype=np.int64).reshape(-1, 2)


class PairJoints:
    """model.pair_joints of a PairTable: [k] -> (joint first, joint second); [array] -> (len, 2)."""

    def __init__(self, table: PairTable):
        self.table = table

    def __getitem__(self, k):
        if np.ndim(k) == 0:
            p = self.table[int(k)]
            return np.array([p.joint_first, p.joint_second], dtype=np.int64)
        return self.table.joints(k)

    def __len__(self) -> int:
        return len(self.table)


def table_of(geom: pin.GeometryModel, pairs) -> PairTable:
    """The PairTable of a listed model's pairs (a Model made by hand)."""
    gobs = list(geom.geometryObjects)
    G = len(gobs)
    keep = {min(p.first, p.second) * G + max(p.first, p.second) for p in pairs}
    half = [isinstance(go.geometry, (coal.Halfspace, coal.Plane)) for go in gobs]
    return PairTable([go.parentJoint for go in gobs], [go.name for go in gobs], half, [False] * G, [False] * G,
                     [i * G + j for i in range(G) for j in range(i + 1, G) if i * G + j not in keep])


def thinnest(t: PairTable, ext: np.ndarray) -> float:
    """min over the pairs of t of ext[i] + ext[j] without listing them: each geometry's thinnest partner."""
    order = np.argsort(ext, kind="stable")
    best = np.full(t.G, np.inf)
    todo = np.arange(t.G)
    for g in order.tolist():
        if not len(todo):
            break
        ok = t.chosen(todo, np.full(len(todo), g))
        best[todo[ok]] = ext[todo[ok]] + ext[g]
        todo = todo[~ok]
    return float(best.min(initial=np.inf))


def ordered(t: PairTable, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first, second) of the pairs of geometries (i, j) (arrays, any order) as PairTable's Pair has them: the
    geometry on the larger joint first (coal's shape 1), the smaller geometry id first on equal joints."""
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    swap = t.joint[lo] < t.joint[hi]
    return np.where(swap, hi, lo), np.where(swap, lo, hi)


def pairs_among(t: PairTable, geoms: list) -> np.ndarray:
    """(n, 5) rows (pair index, first, second, joint first, joint second) of the pairs of t between
    geometries `geoms`, in pair order, first and second as PairTable's Pair has them (the geometry on
    the larger joint first): in arrays, without making a Pair of each (a pile's boxes: N^2 / 2 pairs)."""
    g = np.asarray(geoms, dtype=np.int64)
    i, j = np.triu_indices(len(g), 1)
    i, j = g[i], g[j]
    ok = t.chosen(i, j)
    lo, hi = np.minimum(i[ok], j[ok]), np.maximum(i[ok], j[ok])
    k = t.index(lo, hi).astype(np.int64)
    first, second = ordered(t, lo, hi)
    order = np.argsort(k, kind="stable")
    return np.stack([k, first, second, t.joint[first], t.joint[second]], axis=1).reshape(-1, 5)[order]


def rule_removed(model: pin.Model, gobs: list, geometry_body: list) -> set[tuple[int, int]]:
    """(i, j), i < j, of the geometries the automatic rule leaves unpaired: two on one joint (both
    static among them), a link and its parent in one body. Quadratic only within a body and among the
    world's geometries: a scene of many bodies pairs all the rest (the detection's broad phase,
    broad_phase.py, keeps the narrow phase to the pairs that are near)."""
    joint = [go.parentJoint for go in gobs]
    parent = [model.parents[j] for j in joint]
    out = set()
    for group in [*_groups(geometry_body).values(), [g for g, j in enumerate(joint) if j == 0]]:
        for x, i in enumerate(group):
            for j in group[x + 1:]:
                if joint[i] == joint[j] or (geometry_body[i] == geometry_body[j]
                                            and (parent[j] == joint[i] or parent[i] == joint[j])):
                    out.add((min(i, j), max(i, j)))
    return out


def _groups(geometry_body: list) -> dict[str, list[int]]:
    out: dict[str, list[int]] = {}
    for g, b in enumerate(geometry_body):
        out.setdefault(b, []).append(g)
    return out


def same_body(geometry_body: list) -> list[tuple[int, int]]:
    """(i, j), i < j, of two geometries of one body."""
    return [(i, j) for group in _groups(geometry_body).values() for x, i in enumerate(group) for j in group[x + 1:]]


def geometry_model(gobs, pairs) -> pin.GeometryModel:
    """The scene's coal geometry and pairs as one Pinocchio GeometryModel (whose every
    addGeometryObject resizes a G x G table: cubic in geometries, made only where it is needed)."""
    geom = pin.GeometryModel()
    for go in gobs:
        geom.addGeometryObject(go)
    for p in pairs:
        geom.addCollisionPair(pin.CollisionPair(p.first, p.second))
    return geom


