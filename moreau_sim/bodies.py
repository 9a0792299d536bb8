"""A scene body (URDF or MJCF) -> its Pinocchio model and collision geometry, attached to the
world by the scene's root joint, names prefixed "<body>/" so several instances of one URDF
coexist (model.build_model appends them into one model)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin

from . import robots
from .errors import SceneError
from .options import RootJoint
from .scene import Body
from .shapes import unit

_AXES = {(1.0, 0.0, 0.0): "X", (0.0, 1.0, 0.0): "Y", (0.0, 0.0, 1.0): "Z"}


def root_joint(body: Body, where: str):
    rj = body.root_joint
    if rj is RootJoint.FIXED:
        return None
    if rj is RootJoint.FREE:
        # translation (world-frame rates) then spherical (body-frame angular velocity): unlike
        # the FreeFlyer's body-frame twist, the explicit bias term then leaves the linear momentum
        # of free flight exact and drifts less in energy (docs/theory.md §2.4).
        j = pin.JointModelComposite()
        j.addJoint(pin.JointModelTranslation())
        j.addJoint(pin.JointModelSpherical())
        return j
    if rj in (RootJoint.PRISMATIC, RootJoint.REVOLUTE):
        a = unit(body.axis, f"{where} axis")
        kind = "P" if rj is RootJoint.PRISMATIC else "R"
        aligned = _AXES.get(tuple(float(x) for x in a))
        if aligned:
            return getattr(pin, f"JointModel{kind}{aligned}")()
        return pin.JointModelPrismaticUnaligned(a) if kind == "P" else pin.JointModelRevoluteUnaligned(a)
    if rj is RootJoint.TRANSLATION:  # prismatic joints along each axis (world rates)
        j = pin.JointModelComposite()
        for x in body.axes or np.eye(3):
            j.addJoint(pin.JointModelPrismaticUnaligned(unit(x, f"{where} axes")))
        return j
    # planar: translations along the two in-plane axes (world rates), then rotation about a x b.
    a, b = (unit(x, f"{where} axes") for x in (body.axes or ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0))))
    n = np.cross(a, b)
    j = pin.JointModelComposite()
    j.addJoint(pin.JointModelPrismaticUnaligned(a))
    j.addJoint(pin.JointModelPrismaticUnaligned(b))
    j.addJoint(pin.JointModelRevoluteUnaligned(n / np.linalg.norm(n)))
    return j


def _check_urdf(path: Path, where: str) -> dict[str, int]:
    """Parse the URDF as XML first (clear errors), return {link: number of <collision>}."""
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise SceneError(f"{path}: malformed URDF (XML error: {exc}) [{where} urdf]") from None
    if root.tag != "robot":
        raise SceneError(f"{path}: not a URDF: root element is <{root.tag}>, expected <robot> [{where} urdf]")
    counts = {}
    for link in root.findall("link"):
        name = link.get("name")
        if not name:
            raise SceneError(f"{path}: a <link> has no name [{where} urdf]")
        counts[name] = len(link.findall("collision"))
        for col in link.findall("collision"):
            geo = col.find("geometry")
            kinds = [c.tag for c in geo] if geo is not None else []
            if len(kinds) != 1 or kinds[0] not in ("box", "sphere", "cylinder", "mesh"):
                raise SceneError(f"{path}: link '{name}': collision geometry {kinds or 'missing'} cannot be parsed "
                                 f"by Pinocchio's URDF reader (supported: box, sphere, cylinder, mesh) [{where} urdf]")
    return counts


def load_body(body: Body, where: str) -> tuple[pin.Model, pin.GeometryModel, str]:
    """A body's Pinocchio model and collision geometry, names prefixed "<body>/". URDF meshes
    and MJCF files go through robots.py (package:// resolution, MJCF root joint); meshes become
    convex hulls or stay BVHs per the body's `meshes` key."""
    path = body.urdf
    root = root_joint(body, where)
    if body.mjcf:
        m, g = robots.load_mjcf(path, root, where)
    else:
        counts = _check_urdf(path, where)
        xml = robots.urdf_with_resolved_meshes(path, body.package_dirs, where)
        try:
            if root is None:
                m = pin.buildModelFromUrdf(str(path))
            else:
                m = pin.buildModelFromUrdf(str(path), root, "root")
            g = pin.buildGeomFromUrdfString(m, xml, pin.GeometryType.COLLISION, package_dirs=[str(path.parent)],
                                            mesh_loader=_MESH_LOADER)
        except Exception as exc:  # Pinocchio raises plain RuntimeError/ValueError with C++ text
            raise SceneError(f"{path}: Pinocchio cannot load this URDF: {exc} [{where} urdf]") from None
        loaded: dict[str, int] = {}
        for go in g.geometryObjects:
            link = m.frames[go.parentFrame].name
            loaded[link] = loaded.get(link, 0) + 1
        for link, n in counts.items():
            if loaded.get(link, 0) != n:
                raise SceneError(f"{path}: link '{link}' has {n} <collision> element(s) but Pinocchio loaded "
                                 f"{loaded.get(link, 0)} [{where} urdf]")
    robots.apply_mesh_mode(g, body.meshes, f"{path} [{where}]")
    robots.unique_frame_names(m)  # a link and a joint of one name: appendModel would refuse the model
    # prefix every name with the body name so several instances of one URDF can coexist
    p = f"{body.name}/"
    for i in range(1, m.njoints):
        m.names[i] = p + m.names[i]
    for i in range(1, m.nframes):
        m.frames[i].name = p + m.frames[i].name
    for go in g.geometryObjects:
        go.name = p + go.name
    return m, g, (path.read_text(encoding="utf-8"))


# One mesh loader for every body: coal caches each mesh file (by name, scale and modification
# time), so a model built again (tests, sweeps) does not re-read and re-split its meshes.
_MESH_LOADER = coal.CachedMeshLoader()
