"""Self-collision pairs as a robot's author meant them (docs/robots.md, "Self-collision pairs"):
the pairs the SRDF beside a URDF disables, read with Pinocchio's own SRDF reader
(``pin.removeCollisionPairs``, ``pin.loadReferenceConfigurations``), and the pairs of one body
whose shapes already overlap at its reference poses (its neutral q and the SRDF's
``<group_state>`` poses), which model.build_model leaves out (leave_out_overlapping) with one
warning naming them.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin

from .errors import SceneError, one_line
from .robots import quiet_output

@dataclass(frozen=True)
class Authored:
    """What a body's SRDF says about its self pairs. disabled: the geometry-name pairs (as
    frozensets of the body's geometry names) the SRDF's ``<disable_collisions>`` remove; poses:
    the reference poses of the body's model, ("neutral", q) first, then each ``<group_state>``."""

    srdf: Path | None
    disabled: frozenset = frozenset()
    poses: tuple = field(default_factory=tuple)


def read_authored(m: pin.Model, g: pin.GeometryModel, srdf: Path | None, where: str) -> Authored:
    """The disabled pairs and reference poses of one body's model `m` and geometry `g` (link names
    as in the file: call before names are prefixed). Leaves `g` without collision pairs.
    A malformed SRDF is a SceneError naming it."""
    poses: list[tuple[str, np.ndarray]] = [("neutral", pin.neutral(m))]
    if srdf is None:
        return Authored(None, frozenset(), tuple(poses))
    try:
        root = ET.parse(srdf).getroot()
    except ET.ParseError as exc:
        raise SceneError(f"{srdf}: malformed SRDF (XML error: {exc}) [{where} srdf]") from None
    except OSError as exc:
        raise SceneError(f"{srdf}: cannot read this SRDF ({exc.strerror or exc}) [{where} srdf]") from None
    if root.tag != "robot":
        raise SceneError(f"{srdf}: not an SRDF: root element is <{root.tag}>, expected <robot> [{where} srdf]")
    name = lambda k: g.geometryObjects[k].name  # noqa: E731
    g.removeAllCollisionPairs()
    g.addAllCollisionPairs()
    before = {frozenset((name(p.first), name(p.second))) for p in g.collisionPairs}
    ref = pin.Model(m)  # reference poses go into a copy: the body's model stays as read
    try:
        with quiet_output(1, 2):  # Pinocchio prints "Could not read joint config" for a pose of another model
            pin.removeCollisionPairs(m, g, str(srdf), False)
            pin.loadReferenceConfigurations(ref, str(srdf), False)
    except Exception as exc:  # Pinocchio raises RuntimeError/ValueError with boost's text
        raise SceneError(f"{srdf}: Pinocchio cannot read this SRDF: {one_line(exc)} [{where} srdf]") from None
    after = {frozenset((name(p.first), name(p.second))) for p in g.collisionPairs}
    g.removeAllCollisionPairs()
    poses += sorted((x.key(), np.array(x.data())) for x in ref.referenceConfigurations if len(x.data()) == m.nq)
    return Authored(srdf, frozenset(before - after), tuple(poses))


def overlapping(model: pin.Model, data: pin.Data, geom: pin.GeometryModel, candidates, poses, tol: float
                ) -> dict[tuple[int, int], tuple[float, str]]:
    """The candidate geometry pairs (i, j) that are more than `tol` [m] inside each other at one of
    `poses` (full configurations, named): {(i, j): (deepest signed distance [m], pose name)}.
    Uses a copy of `geom` holding only the candidates; a failed distance query proves nothing."""
    found: dict[tuple[int, int], tuple[float, str]] = {}
    candidates = list(candidates)
    if not candidates:
        return found
    probe = pin.GeometryModel()
    for go in geom.geometryObjects:
        probe.addGeometryObject(go)
    for i, j in candidates:
        probe.addCollisionPair(pin.CollisionPair(i, j))
    gd = pin.GeometryData(probe)
    for pose, q in poses:
        pin.computeDistances(model, data, probe, gd, q)
        for k, r in enumerate(gd.distanceResults):
            d = r.min_distance
            if -1e100 < d < -tol and d < found.get(candidates[k], (0.0, ""))[0]:
                found[candidates[k]] = (float(d), pose)
    return found


def leave_out_overlapping(model: pin.Model, data: pin.Data, geom: pin.GeometryModel, bodies, poses, geometry_body,
                          candidates, tol: float) -> list[dict[tuple[int, int], tuple[float, str]]]:
    """Per body (names `bodies`, its reference poses `poses[k]` as scene configurations), the self
    pairs among `candidates` (geometry index pairs; geometry_body[g] names each geometry's body)
    that overlap by more than `tol` [m] at one of them: shapes the robot's author made overlap
    (e.g. a thigh's hull in the base's), which would stop the first step. model.build_model leaves
    them out with one warning per body (docs/robots.md)."""
    return [overlapping(model, data, geom, [(i, j) for i, j in sorted(candidates)
                                            if geometry_body[i] == geometry_body[j] == name], body_poses, tol)
            for name, body_poses in zip(bodies, poses)]
