"""Triangle meshes of what the replay draws: coal shapes, a half-space's stand-in box, and the
visual geometry a URDF or MJCF text describes (docs/viewer.md)."""

from __future__ import annotations

import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin

from .. import robots
from ..errors import SceneError
from ..model import Model

MESH_SUFFIXES = (".stl", ".obj", ".dae", ".ply", ".off", ".glb", ".gltf")


def shape_mesh(geometry):
    """A trimesh of a coal shape in its own frame (boxes, spheres, cylinders, capsules, ellipsoids,
    convex hulls, triangle meshes); None for a half-space or a plane (see :func:`ground_box`)."""
    import trimesh

    if isinstance(geometry, coal.Box):
        return trimesh.creation.box(extents=2 * np.asarray(geometry.halfSide))
    if isinstance(geometry, coal.Sphere):
        return trimesh.creation.icosphere(subdivisions=3, radius=max(float(geometry.radius), 2e-3))
    if isinstance(geometry, coal.Ellipsoid):
        m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        m.apply_scale(np.asarray(geometry.radii, float))
        return m
    if isinstance(geometry, coal.Cylinder):
        return trimesh.creation.cylinder(radius=geometry.radius, height=2 * geometry.halfLength, sections=32)
    if isinstance(geometry, coal.Capsule):
        return trimesh.creation.capsule(radius=geometry.radius, height=2 * geometry.halfLength, count=[24, 24])
    if isinstance(geometry, (coal.Halfspace, coal.Plane)):
        return None
    if isinstance(geometry, coal.ConvexBase):
        pts = np.array([geometry.points(i) for i in range(geometry.num_points)], float)
        return trimesh.convex.convex_hull(pts)
    if isinstance(geometry, coal.BVHModelBase):
        v = np.array([geometry.vertices(i) for i in range(geometry.num_vertices)], float)
        f = np.array([[t[0], t[1], t[2]] for t in (geometry.tri_indices(i) for i in range(geometry.num_tris))], int)
        return trimesh.Trimesh(v, f, process=False)
    geometry.computeLocalAABB()  # anything else: its bounding box
    lo, hi = np.asarray(geometry.aabb_local.min_), np.asarray(geometry.aabb_local.max_)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((hi + lo) / 2))


def ground_box(normal, offset: float, center, size: float) -> tuple[pin.SE3, np.ndarray]:
    """(placement, half sides) of a thin box standing for the half-space {n.x <= offset}: its top
    face on the boundary plane, `size` wide, centred under `center`, 1 % of `size` thick."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    thick = 0.01 * size
    c = np.asarray(center, float)
    c = c - (n @ c - offset) * n - 0.5 * thick * n  # project on the plane, then half a thickness inside
    R = pin.Quaternion.FromTwoVectors(np.array([0.0, 0.0, 1.0]), n).matrix()
    return pin.SE3(R, c), np.array([size / 2, size / 2, thick / 2])


def _float_list(text, n, default):
    try:
        v = [float(x) for x in (text or "").split()]
    except ValueError:
        return list(default)
    return v if len(v) == n else list(default)


def _origin(el) -> pin.SE3:
    o = el.find("origin") if el is not None else None
    xyz = _float_list(o.get("xyz") if o is not None else None, 3, (0, 0, 0))
    rpy = _float_list(o.get("rpy") if o is not None else None, 3, (0, 0, 0))
    return pin.SE3(pin.rpy.rpyToMatrix(*rpy), np.array(xyz))


def _resolve_mesh(uri: str, dirs: list[Path], base: Path) -> Path | None:
    """The mesh file a stored URDF names (check_named_files has vetted the text), or None."""
    if Path(uri.split("?")[0]).suffix.lower() not in MESH_SUFFIXES:
        return None
    try:
        p = robots.resolve(uri, dirs, base)
    except SceneError:
        return None
    return p if p is not None and p.suffix.lower() in MESH_SUFFIXES else None


def _load_mesh(path: Path, scale):
    """A mesh file as a trimesh: read by coal (assimp: .dae, .obj, .stl, ...), else by trimesh."""
    import trimesh

    try:
        b = coal.MeshLoader().load(str(path), np.asarray(scale, float))
        v = np.asarray(b.vertices(), float)
        f = np.array([[t[0], t[1], t[2]] for t in (b.tri_indices(i) for i in range(b.num_tris))], np.int64)
        if len(v) and len(f):
            return trimesh.Trimesh(v, f, process=False)
    except Exception:  # noqa: BLE001 (assimp's errors: try trimesh, then the collision geometry)
        pass
    try:
        m = trimesh.load(str(path), force="mesh", process=False)
    except Exception:  # noqa: BLE001
        return None
    if not isinstance(m, trimesh.Trimesh) or not len(m.faces):
        return None
    m.apply_scale(np.asarray(scale, float))
    return m


def urdf_visuals(text: str, dirs: list[Path], base: Path) -> dict:
    """link name -> [(placement in the link frame, mesh, rgb or None)] of a URDF's <visual>s that load."""
    import trimesh

    try:
        root = ET.fromstring(text)
    except ET.ParseError:
        return {}
    named = {m.get("name"): m.find("color") for m in root.findall("material")}
    out: dict[str, list] = {}
    for link in root.findall("link"):
        for vis in link.findall("visual"):
            geo = vis.find("geometry")
            kid = geo[0] if geo is not None and len(geo) else None
            if kid is None:
                continue
            mesh = None
            if kid.tag == "mesh":
                path = _resolve_mesh(kid.get("filename", ""), dirs, base)
                mesh = _load_mesh(path, _float_list(kid.get("scale"), 3, (1, 1, 1))) if path else None
            elif kid.tag == "box":
                mesh = trimesh.creation.box(extents=_float_list(kid.get("size"), 3, (0, 0, 0)))
            elif kid.tag == "sphere":
                mesh = trimesh.creation.icosphere(subdivisions=3, radius=float(kid.get("radius", 0)))
            elif kid.tag == "cylinder":
                mesh = trimesh.creation.cylinder(radius=float(kid.get("radius", 0)),
                                                 height=float(kid.get("length", 0)), sections=32)
            if mesh is None:
                continue
            rgb = None
            mat = vis.find("material")
            if mat is not None:
                col = mat.find("color") if mat.find("color") is not None else named.get(mat.get("name"))
                if col is not None:
                    rgba = _float_list(col.get("rgba"), 4, (0.7, 0.7, 0.7, 1))
                    rgb = tuple(int(round(255 * min(max(c, 0.0), 1.0))) for c in rgba[:3])
            out.setdefault(link.get("name"), []).append((_origin(vis), mesh, rgb))
    return out


def mjcf_visuals(model: Model, body, text: str, original: Path | None) -> list:
    """[(link, frame of model.pin, placement in that frame, mesh, rgb)] of an MJCF body's visual
    geometry: Pinocchio's reader with GeometryType.VISUAL (every geom but MuJoCo's collision-only
    group > 2; contype = conaffinity = 0 geoms are visual only), placed as bodies.load_body places
    the collision geometry, with each geom's rgba or its material's. The stored text is read from
    the `original` file when that file still holds it (its meshes are then found), else from a
    temporary copy; [] when Pinocchio cannot load it (the collision geometry is drawn instead)."""
    from ..bodies import root_joint

    where = f"trajectory metadata, body {body.name!r}"
    with tempfile.TemporaryDirectory(prefix="moreau-sim-view-") as tmp:
        path = Path(tmp) / "model.xml"
        path.write_text(text, encoding="utf-8")
        try:
            if original is not None and original.is_file() and original.read_text(encoding="utf-8") == text:
                path = original
            m, g = robots.load_mjcf(path, root_joint(body, where), where, pin.GeometryType.VISUAL)
        except (OSError, SceneError):
            return []
    pm = model.pin
    fixed = pin.SE3(pin.rpy.rpyToMatrix(*body.rpy), np.array(body.position, float))  # a fixed root's placement
    out = []
    for go in g.geometryObjects:
        mesh = shape_mesh(go.geometry)
        if mesh is None:
            continue
        rgb = tuple(int(round(255 * min(max(float(c), 0.0), 1.0))) for c in go.meshColor[:3])
        frame = m.frames[go.parentFrame]
        name = f"{body.name}/{frame.name}"
        if go.parentFrame > 0 and pm.existFrame(name):
            out.append((name, pm.getFrameId(name), frame.placement.inverse() * go.placement, mesh, rgb))
        elif go.parentJoint == 0:  # a geom of the MJCF's world body under a fixed root
            out.append((name, 0, fixed * go.placement, mesh, rgb))
    return out
