"""What contacts.py needs to know of each coal shape, computed once when the model is built:
polytope vertices, outward face normals and planes, the edges leaving each vertex, a cheap
lower bound of the distance to the shape; and the coal shapes of the scene's statics
(docs/theory.md §6). Everything is in the shape's joint frame."""

from __future__ import annotations

import coal
import numpy as np
import pinocchio as pin

from .errors import SceneError
from .options import StaticShape
from .scene import Static


def unit(v, where: str) -> np.ndarray:
    """v / |v|, or SceneError naming `where` for a zero vector."""
    a = np.asarray(v, float)
    n = np.linalg.norm(a)
    if n < 1e-12:
        raise SceneError(f"{where}: axis must not be zero")
    return a / n


def static_shape(s: Static):
    if s.shape is StaticShape.HALFSPACE:
        n = unit(s.normal, f"[[statics]] ({s.name}) normal")
        return coal.Halfspace(n, float(s.offset)), pin.SE3.Identity()
    placement = pin.SE3(pin.rpy.rpyToMatrix(*s.rpy), np.array(s.position, float))
    if s.shape is StaticShape.BOX:
        return coal.Box(*s.size), placement
    if s.shape is StaticShape.SPHERE:
        return coal.Sphere(s.radius), placement
    return coal.Cylinder(s.radius, s.length), placement


def vertices(geometry, placement: pin.SE3) -> np.ndarray:
    """Polytope vertices of a shape, in its joint frame (contacts.py: one contact per vertex)."""
    if isinstance(geometry, coal.Box):
        hx, hy, hz = geometry.halfSide
        local = np.array([[sx * hx, sy * hy, sz * hz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    elif isinstance(geometry, coal.ConvexBase):
        local = np.array(geometry.points(), float).reshape(-1, 3)
    elif isinstance(geometry, coal.Sphere) and geometry.radius == 0.0:
        local = np.zeros((1, 3))  # a point particle: its centre is its one vertex
    else:
        return np.zeros((0, 3))
    out = local @ placement.rotation.T + placement.translation
    out.setflags(write=False)
    return out


def face_normals(geometry, placement: pin.SE3) -> np.ndarray:
    """Outward face normals of a polytope in its joint frame (contacts.py snaps patch normals)."""
    if isinstance(geometry, coal.Box):
        local = np.concatenate([np.eye(3), -np.eye(3)])
    elif isinstance(geometry, coal.ConvexBase):
        local = np.array(geometry.normals(), float).reshape(-1, 3)
    else:
        return np.zeros((0, 3))
    out = local @ placement.rotation.T
    out.setflags(write=False)
    return out


def vertex_edges(geometry, placement: pin.SE3) -> np.ndarray | None:
    """(vertices, k, 3) unit directions of the edges leaving each vertex, joint frame: the
    generators of the shape's local cone at its vertices (a point particle: none). None when
    unknown (convex meshes)."""
    if isinstance(geometry, coal.Box):
        signs = [(sx, sy, sz) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]  # as _vertices
        E = np.array([[[-sx, 0, 0], [0, -sy, 0], [0, 0, -sz]] for sx, sy, sz in signs], float)
        out = E @ placement.rotation.T
    elif isinstance(geometry, coal.Sphere) and geometry.radius == 0.0:
        out = np.zeros((1, 0, 3))
    else:
        return None
    out.setflags(write=False)
    return out


def face_planes(geometry, placement: pin.SE3):
    """(normals (k, 3), offsets (k,)) of a box's faces in its joint frame, the solid being
    {x : normals x <= offsets}; None for other shapes (contacts.py: corner detection)."""
    if not isinstance(geometry, coal.Box):
        return None
    n = np.concatenate([np.eye(3), -np.eye(3)]) @ placement.rotation.T
    d = np.tile(np.asarray(geometry.halfSide, float), 2) + n @ placement.translation
    n.setflags(write=False)
    d.setflags(write=False)
    return n, d


FLAT = (coal.Box, coal.ConvexBase, coal.Cylinder, coal.Cone, coal.Halfspace, coal.Plane)


def distance_bound(geometry, placement: pin.SE3) -> tuple:
    """("plane", n, d) of a half-space, else ("sphere", centre, radius) from coal's local AABB."""
    if isinstance(geometry, coal.Halfspace):
        n = placement.rotation @ geometry.n
        return ("plane", n, float(geometry.d + n @ placement.translation))
    geometry.computeLocalAABB()
    return ("sphere", placement.act(np.array(geometry.aabb_center)), float(geometry.aabb_radius))
