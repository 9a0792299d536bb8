"""Which pairs of geometries of a scene may touch: every two less those the rules leave out (on one
rigid body, both static, a link and its parent: pair_table.rule_removed), those its SRDF disables,
those the scene's [collisions] excludes (include puts one back), and a body's own pairs that overlap
at its reference poses (self_pairs.py). The pairs as a pair_table.PairTable, and why each is left out.
"""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import coal
import numpy as np
import pinocchio as pin

from . import pair_table, self_pairs, shapes
from .errors import SceneError
from .pair_table import PairTable
from .scene import Scene


def choose(scene: Scene, model: pin.Model, gobs: list, geometry_body: list, authored: list, q_slices: list,
           vertices: tuple, whole_data, where: str) -> tuple[PairTable, dict]:
    """The pairs of the scene's geometries `gobs` (on `model`, the scene's whole model; geometry_body:
    each one's body or static; authored: each body's self_pairs.Authored; q_slices: each body's slice of q;
    vertices: each geometry's polytope vertices) and {(i, j): why} of those left out. whole_data: makes a
    Data of `model` (only when a body has pairs of its own to test at its reference poses)."""
    # different joints, not both static, not a link and its parent
    links = [model.frames[go.parentFrame].name if go.parentFrame < model.nframes else go.name for go in gobs]
    named: dict[str, list[int]] = {}  # a name (geometry, body or link) -> its geometries: one look-up per rule
    for k, go in enumerate(gobs):
        for name in dict.fromkeys((go.name, geometry_body[k], links[k])):
            named.setdefault(name, []).append(k)

    def pairs_matching(a: str, b: str, key: str) -> list[tuple[int, int]]:
        ia, ib = named.get(a, []), named.get(b, [])
        for name, found in ((a, ia), (b, ib)):
            if not found:
                raise SceneError(f"{where} [collisions] {key}: '{name}' names no body, static, link or geometry")
        return [(min(x, y), max(x, y)) for x in ia for y in ib if x != y]

    # the pairs are every two geometries less `removed` (pair_table.PairTable): never listed one by one
    removed, why = pair_table.rule_removed(model, gobs, geometry_body), {}
    chosen = lambda i, j: i != j and (min(i, j), max(i, j)) not in removed  # noqa: E731
    disabled = frozenset().union(*(a.disabled for a in authored))
    by_name: dict[str, list[int]] = {}
    for k, go in enumerate(gobs):
        by_name.setdefault(go.name, []).append(k)
    for names in disabled:
        a, b = (*names, *names)[:2]
        for i, j in {(min(x, y), max(x, y)) for x in by_name.get(a, []) for y in by_name.get(b, [])}:
            if chosen(i, j):
                removed.add((i, j))
                why[(i, j)] = "disabled by the SRDF"  # the robot's author disabled it (self_pairs.read_authored)
    included = set()
    for a, b in scene.collisions.include:
        for i, j in pairs_matching(a, b, "include"):
            if gobs[i].parentJoint == gobs[j].parentJoint:
                raise SceneError(f"{where} [collisions] include: {gobs[i].name} and {gobs[j].name} "
                                 "are on one rigid body (or both static) and can never touch")
            removed.discard((i, j))
            included.add((i, j))
            why.pop((i, j), None)
    for a, b in scene.collisions.exclude:
        for ij in set(pairs_matching(a, b, "exclude")):
            if chosen(*ij):
                removed.add(ij)
                why[ij] = "[collisions] exclude"
    own = {ij for ij in pair_table.same_body(geometry_body) if chosen(*ij) and ij not in included}  # self pairs
    poses = [] if not own else [[(name, _in_scene(model, sl, pose)) for name, pose in said.poses]
                                for sl, said in zip(q_slices, authored)]
    d = whole_data() if own else None  # a Data of the whole model only for them
    for body, found in zip(scene.bodies, [] if not own else self_pairs.leave_out_overlapping(
            model, d, SimpleNamespace(geometryObjects=gobs), [b.name for b in scene.bodies], poses, geometry_body,
            own, scene.options.contact_tolerance)):
        for ij, (dist, pose) in found.items():
            removed.add(ij)
            why[ij] = f"overlaps {-dist:.3g} m at the reference pose {pose}"
        if found:
            listed = ", ".join(f"{pair_name(gobs, i, j)} ({-dist * 1e3:.3g} mm at {pose})"
                               for (i, j), (dist, pose) in sorted(found.items()))
            warnings.warn_explicit(f"{len(found)} self pair(s) of body {body.name} overlap at its reference pose(s) "
                                   f"and are left out: {listed}; to keep one, name it in [collisions] include "
                                   f"[{where}]", UserWarning, str(body.urdf), 0)
    half = [isinstance(go.geometry, (coal.Halfspace, coal.Plane)) for go in gobs]
    poly = [len(v) > 0 for v in vertices]
    flat = [isinstance(go.geometry, shapes.FLAT) for go in gobs]  # a patch needs two flat faces
    G = len(gobs)
    table = PairTable([go.parentJoint for go in gobs], [go.name for go in gobs], half, poly, flat,
                      [i * G + j for i, j in removed])
    return table, why


def pair_name(gobs, i: int, j: int) -> str:
    """"first|second": the geometry on the larger joint id first (shape 1 of the pair: build_model)."""
    i, j = (j, i) if gobs[i].parentJoint < gobs[j].parentJoint else (i, j)
    return f"{gobs[i].name}|{gobs[j].name}"


def _in_scene(model: pin.Model, q_slice: slice, pose: np.ndarray) -> np.ndarray:
    """A body's pose (its own q) as the scene's q: the other bodies at their neutral q."""
    q = pin.neutral(model)
    q[q_slice] = pose
    return q
