"""A scene body (URDF or MJCF) -> its Pinocchio model and collision geometry, attached to the
world by the scene's root joint, names prefixed "<body>/" so several instances of one URDF
coexist (model.build_model appends them into one model)."""

from __future__ import annotations

import dataclasses
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin

from . import robots, self_pairs
from .errors import SceneError, one_line
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
        _check_inertial(link, f"{path}: link '{name}'", where)
        for col in link.findall("collision"):
            geo = col.find("geometry")
            kinds = [c.tag for c in geo] if geo is not None else []
            if len(kinds) != 1 or kinds[0] not in ("box", "sphere", "cylinder", "mesh"):
                raise SceneError(f"{path}: link '{name}': collision geometry {kinds or 'missing'} cannot be parsed "
                                 f"by Pinocchio's URDF reader (supported: box, sphere, cylinder, mesh) [{where} urdf]")
            _check_sizes(geo[0], f"{path}: link '{name}': <{kinds[0]}>", where)
    return counts


_SIZES = {"sphere": ("radius",), "cylinder": ("radius", "length"), "box": ("size",), "mesh": ("scale",)}


def _numbers(text: str | None, where: str, key: str, urdf_where: str) -> list[float]:
    try:
        values = [float(x) for x in (text or "").split()]
    except ValueError:
        raise SceneError(f"{where} {key}={_short(text)}: not numbers [{urdf_where} urdf]") from None
    return values


def _check_sizes(shape, where: str, urdf_where: str) -> None:
    """Sizes of a collision shape: finite and > 0 (a negative radius would load and run with
    wrong dynamics); a mesh scale finite and non-zero."""
    for key in _SIZES[shape.tag]:
        if shape.tag == "mesh" and shape.get(key) is None:
            continue
        values = _numbers(shape.get(key), where, key, urdf_where)
        n = 3 if key in ("size", "scale") else 1
        ok = len(values) == n and all(math.isfinite(v) for v in values)
        point = shape.tag == "sphere"  # a sphere of radius 0 is a point particle (one vertex)
        positive = [v != 0 if key == "scale" else v > 0 or (point and v == 0) for v in values]
        ok = ok and all(positive)
        if not ok:
            need = (f"{n} finite non-zero numbers" if key == "scale" else
                    "a finite radius >= 0 [m] (0: a point)" if point else f"{n} finite number(s) > 0 [m]")
            raise SceneError(f"{where} {key}={_short(shape.get(key))}: must be {need} [{urdf_where} urdf]")


def _check_inertial(link, where: str, urdf_where: str) -> None:
    """A link's <inertial>: mass finite and >= 0, inertia finite (a link without one is massless).
    Whether the model can move at all (M(q) positive definite) is checked once it is built."""
    inertial = link.find("inertial")
    if inertial is None:
        return
    mass = inertial.find("mass")
    if mass is not None:
        m = _numbers(mass.get("value"), f"{where} <mass>", "value", urdf_where)
        if len(m) != 1 or not math.isfinite(m[0]) or m[0] < 0:
            raise SceneError(f"{where} <mass> value={_short(mass.get('value'))}: must be a finite mass >= 0 [kg] "
                             f"[{urdf_where} urdf]")
    inertia = inertial.find("inertia")
    if inertia is not None:
        for key in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz"):
            v = _numbers(inertia.get(key, "0"), f"{where} <inertia>", key, urdf_where)
            if len(v) != 1 or not math.isfinite(v[0]):
                raise SceneError(f"{where} <inertia> {key}={_short(inertia.get(key))}: must be a finite number "
                                 f"[kg m^2] [{urdf_where} urdf]")


INERTIA_RTOL = 1e-4  # round-off allowed in the triangle inequality, relative to the largest principal moment


def check_inertias(m: pin.Model, path: Path, where: str, kind: str) -> None:
    """Every moving rigid body's rotational inertia about its centre of mass (a link and the links
    welded to it: Pinocchio merges them, and only the sum moves) must be one that a mass
    distribution can have: principal moments I1 <= I2 <= I3 with I1 >= 0 and I3 <= I1 + I2, to
    INERTIA_RTOL * max|I| (values written with 4-5 digits) plus 1e-12 of the model's largest moment
    (a point mass's round-off). Raises SceneError naming the file, the
    link, its joint and the three moments."""
    moments = [np.linalg.eigvalsh(0.5 * (m.inertias[j].inertia + m.inertias[j].inertia.T))
               for j in range(m.njoints)]
    floor = 1e-12 * max([float(np.abs(w).max()) for w in moments if np.isfinite(w).all()] + [0.0])
    for j in range(1, m.njoints):
        w = moments[j]
        scale = float(np.abs(w).max())
        if not np.isfinite(w).all() or scale <= floor:
            continue  # no rotational inertia (a point mass; 1e-18 of round-off): the mass-matrix check names it
        tol = INERTIA_RTOL * scale + floor
        if w[0] >= -tol and w[2] - w[0] - w[1] <= tol:
            continue
        links = [f.name for f in m.frames if f.type == pin.FrameType.BODY and f.parentJoint == j]
        what = (f"a negative principal moment ({w[0]:.6g} kg m^2)" if w[0] < -tol else
                f"I3 - I1 - I2 = {w[2] - w[0] - w[1]:.3g} kg m^2 > {INERTIA_RTOL:g} I3 "
                "(the triangle inequality I3 <= I1 + I2)")
        welded = f" with the links welded to it ({', '.join(links[1:])})" if len(links) > 1 else ""
        raise SceneError(f"{path}: {'link' if kind == 'urdf' else 'body'} '{links[0] if links else m.names[j]}'"
                         f"{welded} (joint '{m.names[j]}'): principal moments of inertia {w[0]:.6g}, {w[1]:.6g}, "
                         f"{w[2]:.6g} kg m^2 are physically impossible: {what} [{where} {kind}]")


def _short(value, n: int = 40) -> str:
    """repr of a value, cut to n characters (an error message never repeats a huge input)."""
    text = repr(value)
    return text if len(text) <= n else text[:n - 5] + "...'"


def load_body(body: Body, where: str) -> tuple[pin.Model, pin.GeometryModel, str, self_pairs.Authored]:
    """A body's Pinocchio model and collision geometry, names prefixed "<body>/", its file's text,
    and what its SRDF says (self_pairs.Authored: disabled pairs by prefixed geometry names,
    reference poses). URDF meshes and MJCF files go through robots.py (package:// resolution,
    MJCF root joint); meshes become convex hulls or stay BVHs per the body's `meshes` key."""
    path = body.urdf
    root = root_joint(body, where)
    if body.mjcf:
        m, g = robots.load_mjcf(path, root, where)
    else:
        counts = _check_urdf(path, where)
        xml = robots.urdf_with_resolved_meshes(path, body.package_dirs, where)
        try:
            with robots.quiet_output(2):  # urdfdom and assimp print their own lines; the error below says what failed
                if root is None:
                    m = pin.buildModelFromUrdf(str(path))
                else:
                    m = pin.buildModelFromUrdf(str(path), root, "root")
                g = pin.buildGeomFromUrdfString(m, xml, pin.GeometryType.COLLISION, package_dirs=[str(path.parent)],
                                                mesh_loader=_MESH_LOADER)
        except Exception as exc:  # Pinocchio raises plain RuntimeError/ValueError with multi-line C++ text
            raise SceneError(f"{path}: Pinocchio cannot load this URDF: {one_line(exc)} [{where} urdf]") from None
        loaded: dict[str, int] = {}
        for go in g.geometryObjects:
            link = m.frames[go.parentFrame].name
            loaded[link] = loaded.get(link, 0) + 1
        for link, n in counts.items():
            if loaded.get(link, 0) != n:
                raise SceneError(f"{path}: link '{link}' has {n} <collision> element(s) but Pinocchio loaded "
                                 f"{loaded.get(link, 0)} [{where} urdf]")
    check_inertias(m, path, where, "mjcf" if body.mjcf else "urdf")
    robots.apply_mesh_mode(g, body.meshes, f"{path} [{where}]")
    robots.unique_frame_names(m)  # a link and a joint of one name: appendModel would refuse the model
    authored = self_pairs.read_authored(m, g, body.srdf, where)  # the file's link names: before the prefix
    # prefix every name with the body name so several instances of one URDF can coexist
    p = f"{body.name}/"
    for i in range(1, m.njoints):
        m.names[i] = p + m.names[i]
    for i in range(1, m.nframes):
        m.frames[i].name = p + m.frames[i].name
    for go in g.geometryObjects:
        go.name = p + go.name
    authored = dataclasses.replace(authored, disabled=frozenset(frozenset(p + n for n in pair)
                                                                for pair in authored.disabled))
    return m, g, path.read_text(encoding="utf-8"), authored


# One mesh loader for every body: coal caches each mesh file (by name, scale and modification
# time), so a model built again (tests, sweeps) does not re-read and re-split its meshes.
_MESH_LOADER = coal.CachedMeshLoader()
