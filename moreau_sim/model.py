"""Scene -> immutable :class:`Model` (Pinocchio model, coal geometry, collision pairs) and
reusable scratch :class:`Data`.

Each body's URDF is loaded by Pinocchio with the scene's root joint, its names prefixed
``"<body>/"`` so several instances of one URDF coexist, and appended to one model at its
placement. Statics are coal shapes on the universe joint.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin

from . import robots
from .errors import SceneError
from .scene import Body, RootJoint, Scene, Static, StaticShape
from .state import State

_AXES = {(1.0, 0.0, 0.0): "X", (0.0, 1.0, 0.0): "Y", (0.0, 0.0, 1.0): "Z"}
GJK_TOLERANCE = 1e-12  # coal's GJK/EPA tolerances for the contact normal (default 1e-6 is too coarse)
# Faces parallel to within this [m] over their extent form a contact patch. Coal's EPA normal of
# exactly touching boxes is still ~1e-6 rad off at GJK_TOLERANCE, i.e. ~1e-7 m over 0.1 m: a
# tighter value makes the patch flicker between 1 and 8 points from one step to the next.
PATCH_TOLERANCE = 1e-6
GATE_MARGIN = 1e-6  # [m] see Data: pairs this close are examined (contacts still need g <= tol)


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


@dataclass(frozen=True)
class BodyInfo:
    name: str
    root_joint: RootJoint
    joints: tuple[int, ...]  # Pinocchio joint ids of this body
    q_slice: slice
    v_slice: slice
    urdf: Path


@dataclass(frozen=True, eq=False)
class Model:
    """What the scene is. Never modified after :func:`build_model`.

    pin: Pinocchio model (gravity set from the scene); geom: coal geometry + pairs;
    pairs: the collision pairs; vertices[g]: (k, 3) polytope vertices of geometry g in its
    joint frame (empty for smooth shapes); bounds[g]: a cheap lower bound of the distance from a
    point to geometry g, ("sphere", centre, radius) in its joint frame or ("plane", n, d) for a
    half-space {n.x <= d} (contacts.py uses it to skip far vertices); face_normals[g]: outward
    face normals of a polytope in its joint frame (empty otherwise); face_planes[g]: a box's
    (normals, offsets) in its joint frame, else None; vertex_edges[g]: the edge directions leaving
    each vertex (corner detection in contacts.py); support_mask[j]: 1 on the
    velocity indices that move joint j; q0/u0: the initial state.
    """

    scene: Scene
    pin: pin.Model
    geom: pin.GeometryModel
    pairs: tuple[Pair, ...]
    vertices: tuple[np.ndarray, ...]
    bounds: tuple[tuple, ...]
    face_normals: tuple[np.ndarray, ...]
    face_planes: tuple
    vertex_edges: tuple
    support_mask: np.ndarray
    bodies: tuple[BodyInfo, ...]
    geometry_body: tuple[str, ...]
    q0: np.ndarray
    u0: np.ndarray

    def __post_init__(self):
        pj = np.array([(p.joint_first, p.joint_second) for p in self.pairs], dtype=np.int64).reshape(-1, 2)
        pj.setflags(write=False)
        object.__setattr__(self, "_pair_joints", pj)
        reach = max([float(np.linalg.norm(V, axis=1).max()) for V in self.vertices if len(V)] + [1.0])
        object.__setattr__(self, "_reach", reach)
        def extent(g):
            geo = self.geom.geometryObjects[g].geometry
            if isinstance(geo, (coal.Halfspace, coal.Plane)):
                return np.inf
            geo.computeLocalAABB()
            b = geo.aabb_local
            return float(min(b.width(), b.height(), b.depth()))
        object.__setattr__(self, "_thinnest_pair", min([extent(p.first) + extent(p.second) for p in self.pairs]
                                                       + [np.inf]))
        object.__setattr__(self, "_polytope_pairs", tuple(
            (p.index, p.first, p.second, p.joint_first, p.joint_second) for p in self.pairs
            if len(self.vertices[p.first]) and len(self.vertices[p.second])
            and self.bounds[p.first][0] == "sphere" and self.bounds[p.second][0] == "sphere"))
        object.__setattr__(self, "_polytope_pair_set", frozenset(
            p.index for p in self.pairs if len(self.face_normals[p.first]) and len(self.face_normals[p.second])
            and len(self.vertices[p.first]) and len(self.vertices[p.second])))
        # does h(q, u) depend on u (Coriolis, gyroscopic)? A random state tells (structurally zero
        # for translations and prismatic chains); stepper.free_velocity skips the midpoint iteration.
        rng = np.random.default_rng(0)
        d = self.pin.createData()
        qr = pin.randomConfiguration(self.pin, -np.ones(self.nq), np.ones(self.nq))
        ur = rng.standard_normal(self.nv)
        c = pin.nonLinearEffects(self.pin, d, qr, ur) - pin.nonLinearEffects(self.pin, d, qr, np.zeros(self.nv))
        object.__setattr__(self, "_velocity_bias", bool(np.abs(c).max(initial=0.0) > 1e-12))

    @property
    def nq(self) -> int:
        return self.pin.nq

    @property
    def nv(self) -> int:
        return self.pin.nv

    @property
    def reach(self) -> float:
        """max(1, largest distance of a vertex from its joint origin) [m]: bounds a vertex's speed
        by reach * |u|_inf for unit-scale joints (contacts.detect, corner margin)."""
        return self._reach

    @property
    def thinnest_pair(self) -> float:
        """min over pairs of the sum of the two shapes' smallest extents [m] (inf for half-spaces):
        a body moving less than this in a step cannot pass through the other (stepper: tunnelling)."""
        return self._thinnest_pair

    @property
    def polytope_pairs(self) -> tuple:
        """(pair index, geometry 1, geometry 2, joint 1, joint 2) of the pairs of two polytopes
        with bounding spheres (contacts._near_polytopes)."""
        return self._polytope_pairs

    @property
    def polytope_pair_set(self) -> frozenset:
        """Indices of the pairs of two polytopes (contacts._face_axis)."""
        return self._polytope_pair_set

    @property
    def velocity_bias(self) -> bool:
        """Whether the bias forces h(q, u) depend on u (Coriolis / gyroscopic terms)."""
        return self._velocity_bias

    @property
    def pair_joints(self) -> np.ndarray:
        """(pairs, 2) int array: the joints of each pair's first and second geometry."""
        return self._pair_joints

    @property
    def pair_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.pairs)

    def describe(self) -> dict:
        """A JSON-able summary (for `moreau-sim info` and output metadata)."""
        o = self.scene.options
        return {
            "scene": self.scene.name,
            "nq": self.nq,
            "nv": self.nv,
            "bodies": [{"name": b.name, "root_joint": b.root_joint.value, "nq": b.q_slice.stop - b.q_slice.start,
                        "nv": b.v_slice.stop - b.v_slice.start, "urdf": str(b.urdf),
                        "joints": [self.pin.names[j] for j in b.joints]} for b in self.bodies],
            "geometries": [g.name for g in self.geom.geometryObjects],
            "collision_pairs": list(self.pair_names),
            "restitution": o.restitution,
            "dt": o.dt,
            "duration": o.duration,
            "gravity": list(o.gravity),
        }


class Data:
    """Scratch reused by every step: Pinocchio data, coal results, cached queries, and the pairs
    that had contacts at the last detection (a hint that keeps a resting pair examined when coal's
    narrow phase misses it for a step, contacts._near_polytopes).

    Create one per thread and per run with :func:`make_data`; the state itself is in State."""

    def __init__(self, model: Model):
        self.pin = model.pin.createData()
        # GeometryData must be created after every geometry and pair exists (segfault otherwise).
        self.geom = pin.GeometryData(model.geom)
        tol = model.scene.options.contact_tolerance
        for req in self.geom.collisionRequests:
            # gate of the active set: a pair is examined when coal puts it within GATE_MARGIN (its
            # contacts are then kept where g <= tol); coal's narrow phase misses exactly touching
            # coplanar boxes now and then at a margin of 1e-9 m (gap -5e-12 reported as apart)
            req.security_margin = max(tol, GATE_MARGIN)
            req.num_max_contacts = 1
            req.enable_contact = True  # normal, depth and witness points (EPA when penetrating)
            # GJK/EPA default tolerances (1e-6) tilt the normal of exactly touching boxes by ~5 deg
            req.gjk_tolerance = req.epa_tolerance = GJK_TOLERANCE
        for preq in self.geom.contactPatchRequests:
            preq.setPatchTolerance(PATCH_TOLERANCE)
        self.closed_pairs: set = set()  # pairs with contacts at the last detection (contacts.py)
        self.patch_request = coal.ContactPatchRequest()
        self.patch_request.setPatchTolerance(PATCH_TOLERANCE)
        self.patch_collision = coal.CollisionResult()
        self.patch_result = coal.ContactPatchResult(self.patch_request)
        self.fallback_request = coal.CollisionRequest()  # coal's default GJK/EPA tolerances
        self.fallback_request.security_margin = tol
        self.fallback_request.enable_contact = True
        self.fallback_result = coal.CollisionResult()
        self.point = coal.Sphere(0.0)  # a vertex, for point-vs-shape signed distances
        self.point_tf = coal.Transform3s()
        self.distance_request = coal.DistanceRequest()
        self.distance_result = coal.DistanceResult()
        self._point_queries: dict[int, coal.ComputeDistance] = {}
        geoms = model.geom.geometryObjects
        self.shapes = [g.geometry for g in geoms]

    def point_query(self, g: int) -> coal.ComputeDistance:
        """Cached coal functor: signed distance from a point to geometry g."""
        f = self._point_queries.get(g)
        if f is None:
            f = self._point_queries[g] = coal.ComputeDistance(self.point, self.shapes[g])
        return f


def make_data(model: Model) -> Data:
    return Data(model)


def _unit(v, where: str) -> np.ndarray:
    a = np.asarray(v, float)
    n = np.linalg.norm(a)
    if n < 1e-12:
        raise SceneError(f"{where}: axis must not be zero")
    return a / n


def _root_joint(body: Body, where: str):
    rj = body.root_joint
    if rj is RootJoint.FIXED:
        return None
    if rj is RootJoint.FREE:
        # translation (world-frame rates) then spherical (body-frame angular velocity): unlike
        # the FreeFlyer's body-frame twist, the explicit bias term then leaves the linear momentum
        # of free flight exact and drifts less in energy (pinocchio-coal-piqp.md C4).
        j = pin.JointModelComposite()
        j.addJoint(pin.JointModelTranslation())
        j.addJoint(pin.JointModelSpherical())
        return j
    if rj in (RootJoint.PRISMATIC, RootJoint.REVOLUTE):
        a = _unit(body.axis, f"{where} axis")
        kind = "P" if rj is RootJoint.PRISMATIC else "R"
        aligned = _AXES.get(tuple(float(x) for x in a))
        if aligned:
            return getattr(pin, f"JointModel{kind}{aligned}")()
        return pin.JointModelPrismaticUnaligned(a) if kind == "P" else pin.JointModelRevoluteUnaligned(a)
    if rj is RootJoint.TRANSLATION:  # prismatic joints along each axis (world rates)
        j = pin.JointModelComposite()
        for x in body.axes or np.eye(3):
            j.addJoint(pin.JointModelPrismaticUnaligned(_unit(x, f"{where} axes")))
        return j
    # planar: translations along the two in-plane axes (world rates), then rotation about a x b.
    a, b = (_unit(x, f"{where} axes") for x in (body.axes or ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0))))
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


def _load_body(body: Body, where: str) -> tuple[pin.Model, pin.GeometryModel, str]:
    """A body's Pinocchio model and collision geometry, names prefixed "<body>/". URDF meshes
    and MJCF files go through robots.py (package:// resolution, MJCF root joint); meshes become
    convex hulls or stay BVHs per the body's `meshes` key."""
    path = body.urdf
    root = _root_joint(body, where)
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


def _static_shape(s: Static):
    if s.shape is StaticShape.HALFSPACE:
        n = _unit(s.normal, f"[[statics]] ({s.name}) normal")
        return coal.Halfspace(n, float(s.offset)), pin.SE3.Identity()
    placement = pin.SE3(pin.rpy.rpyToMatrix(*s.rpy), np.array(s.position, float))
    if s.shape is StaticShape.BOX:
        return coal.Box(*s.size), placement
    if s.shape is StaticShape.SPHERE:
        return coal.Sphere(s.radius), placement
    return coal.Cylinder(s.radius, s.length), placement


def _vertices(geometry, placement: pin.SE3) -> np.ndarray:
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


def _face_normals(geometry, placement: pin.SE3) -> np.ndarray:
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


def _vertex_edges(geometry, placement: pin.SE3) -> np.ndarray | None:
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


def _face_planes(geometry, placement: pin.SE3):
    """(normals (k, 3), offsets (k,)) of a box's faces in its joint frame, the solid being
    {x : normals x <= offsets}; None for other shapes (contacts.py: corner detection)."""
    if not isinstance(geometry, coal.Box):
        return None
    n = np.concatenate([np.eye(3), -np.eye(3)]) @ placement.rotation.T
    d = np.tile(np.asarray(geometry.halfSide, float), 2) + n @ placement.translation
    n.setflags(write=False)
    d.setflags(write=False)
    return n, d


_FLAT = (coal.Box, coal.ConvexBase, coal.Cylinder, coal.Cone, coal.Halfspace, coal.Plane)


def _bound(geometry, placement: pin.SE3) -> tuple:
    """("plane", n, d) of a half-space, else ("sphere", centre, radius) from coal's local AABB."""
    if isinstance(geometry, coal.Halfspace):
        n = placement.rotation @ geometry.n
        return ("plane", n, float(geometry.d + n @ placement.translation))
    geometry.computeLocalAABB()
    return ("sphere", placement.act(np.array(geometry.aabb_center)), float(geometry.aabb_radius))


def _matches(name: str, gname: str, body: str, link: str) -> bool:
    return name in (gname, body, link)


def build_model(scene: Scene) -> Model:
    """Build the immutable :class:`Model` of `scene`. Raises :class:`SceneError`."""
    where = str(scene.path) if scene.path else "<scene>"
    model, geom = pin.Model(), pin.GeometryModel()
    model.name = scene.name
    body_of_joint: dict[int, str] = {}
    geometry_body: list[str] = []
    infos = []
    for i, body in enumerate(scene.bodies):
        w = f"{where} [[bodies]][{i}] ({body.name})"
        m, g, _ = _load_body(body, w)
        placement = pin.SE3(pin.rpy.rpyToMatrix(*body.rpy), np.array(body.position, float))
        if body.root_joint is RootJoint.FREE:
            placement = pin.SE3.Identity()  # a free body's pose is its q (world frame): see _initial
        nj0 = model.njoints
        model, geom = pin.appendModel(model, m, geom, g, 0, placement)
        joints = tuple(range(nj0, model.njoints))
        for j in joints:
            body_of_joint[j] = body.name
        geometry_body += [body.name] * (geom.ngeoms - len(geometry_body))
        if joints:
            q_sl = slice(model.joints[joints[0]].idx_q, model.joints[joints[-1]].idx_q + model.joints[joints[-1]].nq)
            v_sl = slice(model.joints[joints[0]].idx_v, model.joints[joints[-1]].idx_v + model.joints[joints[-1]].nv)
        else:
            q_sl = v_sl = slice(model.nq, model.nq)
        infos.append(BodyInfo(body.name, body.root_joint, joints, q_sl, v_sl, body.urdf))
    for s in scene.statics:
        shape, placement = _static_shape(s)
        geom.addGeometryObject(pin.GeometryObject(s.name, 0, 0, placement, shape))
        geometry_body.append(s.name)
    model.gravity.linear = np.array(scene.options.gravity, float)

    # --- collision pairs: different joints, not both static, not a link and its parent
    gobs = list(geom.geometryObjects)
    links = [model.frames[go.parentFrame].name if go.parentFrame < model.nframes else go.name for go in gobs]
    def pairs_matching(a: str, b: str, key: str) -> list[tuple[int, int]]:
        ia = [k for k, go in enumerate(gobs) if _matches(a, go.name, geometry_body[k], links[k])]
        ib = [k for k, go in enumerate(gobs) if _matches(b, go.name, geometry_body[k], links[k])]
        for name, found in ((a, ia), (b, ib)):
            if not found:
                raise SceneError(f"{where} [collisions] {key}: '{name}' names no body, static, link or geometry")
        return [(min(x, y), max(x, y)) for x in ia for y in ib if x != y]

    chosen = set()
    for i in range(len(gobs)):
        for j in range(i + 1, len(gobs)):
            ji, jj = gobs[i].parentJoint, gobs[j].parentJoint
            if ji == jj:
                continue  # one rigid body (or both static)
            if geometry_body[i] == geometry_body[j] and (model.parents[ji] == jj or model.parents[jj] == ji):
                continue  # a link and its parent in one body
            chosen.add((i, j))
    for a, b in scene.collisions.include:
        for i, j in pairs_matching(a, b, "include"):
            if gobs[i].parentJoint == gobs[j].parentJoint:
                raise SceneError(f"{where} [collisions] include: {gobs[i].name} and {gobs[j].name} "
                                 "are on one rigid body (or both static) and can never touch")
            chosen.add((i, j))
    for a, b in scene.collisions.exclude:
        chosen -= set(pairs_matching(a, b, "exclude"))
    pairs = []
    geom.removeAllCollisionPairs()  # appendModel pairs the bodies' geometries itself: start clean
    for k, (i, j) in enumerate(sorted(chosen)):
        # shape 1 = the moving one with the larger joint id: normals then point from it to the other
        if gobs[i].parentJoint < gobs[j].parentJoint:
            i, j = j, i
        geom.addCollisionPair(pin.CollisionPair(i, j))
        assert geom.collisionPairs[k].first == i and geom.collisionPairs[k].second == j
        half = [isinstance(gobs[x].geometry, (coal.Halfspace, coal.Plane)) for x in (i, j)]
        poly = [len(_vertices(gobs[x].geometry, gobs[x].placement)) > 0 for x in (i, j)]
        flat = [isinstance(gobs[x].geometry, _FLAT) for x in (i, j)]  # a patch needs two flat faces
        patch = all(flat) and not ((half[0] and poly[1]) or (half[1] and poly[0]))
        pairs.append(Pair(k, i, j, gobs[i].parentJoint, gobs[j].parentJoint, f"{gobs[i].name}|{gobs[j].name}",
                          patch))

    vertices = tuple(_vertices(go.geometry, go.placement) for go in gobs)
    bounds = tuple(_bound(go.geometry, go.placement) for go in gobs)
    face_normals = tuple(_face_normals(go.geometry, go.placement) for go in gobs)
    face_planes = tuple(_face_planes(go.geometry, go.placement) for go in gobs)
    vertex_edges = tuple(_vertex_edges(go.geometry, go.placement) for go in gobs)
    mask = np.zeros((model.njoints, model.nv))
    for j in range(1, model.njoints):
        for s in model.supports[j][1:]:
            jm = model.joints[s]
            mask[j, jm.idx_v:jm.idx_v + jm.nv] = 1.0
    mask.setflags(write=False)

    if model.nv == 0:
        raise SceneError(f"{where} [[bodies]]: nothing moves (every body has a fixed root and no joints)")
    q0, u0 = _initial(scene, model, infos, where)
    return Model(scene=scene, pin=model, geom=geom, pairs=tuple(pairs), vertices=vertices, bounds=bounds, face_normals=face_normals, face_planes=face_planes, vertex_edges=vertex_edges, support_mask=mask,
                 bodies=tuple(infos), geometry_body=tuple(geometry_body), q0=q0, u0=u0)


def _initial(scene: Scene, model: pin.Model, infos, where: str) -> tuple[np.ndarray, np.ndarray]:
    q, u = pin.neutral(model), np.zeros(model.nv)
    for i, (body, info) in enumerate(zip(scene.bodies, infos)):
        w = f"{where} [[bodies]][{i}] ({body.name})"
        nq, nv = info.q_slice.stop - info.q_slice.start, info.v_slice.stop - info.v_slice.start
        if body.root_joint is RootJoint.FREE:
            # q = [x y z qx qy qz qw]: the world pose, from position and rpy unless q0 is given
            R = pin.rpy.rpyToMatrix(*body.rpy)
            q[info.q_slice.start:info.q_slice.start + 7] = np.concatenate([body.position, pin.Quaternion(R).coeffs()])
        if body.q0 is not None:
            if body.root_joint is RootJoint.FREE and (any(body.position) or any(body.rpy)):
                raise SceneError(f"{w} q0: give either q0 or position/rpy for a free body, not both")
            if len(body.q0) != nq:
                raise SceneError(f"{w} q0: has {len(body.q0)} values, the body has nq = {nq}")
            q[info.q_slice] = body.q0
        if body.u0 is not None:
            if len(body.u0) != nv:
                raise SceneError(f"{w} u0: has {len(body.u0)} values, the body has nv = {nv}")
            u[info.v_slice] = body.u0
        if body.root_joint is RootJoint.FREE and body.q0 is not None:
            quat = q[info.q_slice.start + 3:info.q_slice.start + 7]
            if not math.isclose(np.linalg.norm(quat), 1.0, abs_tol=1e-6):
                raise SceneError(f"{w} q0: the quaternion [qx qy qz qw] = {quat.tolist()} must have norm 1")
    return q, u


def initial_state(model: Model) -> State:
    return State(0.0, model.q0.copy(), model.u0.copy())
