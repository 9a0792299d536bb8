"""Scene -> immutable :class:`Model`: one Pinocchio model of every body (bodies.py) and the forest of
the bodies' own models (trees.py, docs/theory.md §2.12), coal geometry with the statics, collision
pairs (chosen by pair_rules.py), per-shape features (shapes.py), and the options (``model.options``).
Per-run scratch is :class:`~moreau_sim.data.Data`.
"""

from __future__ import annotations

import dataclasses
import math
import weakref
from dataclasses import InitVar, dataclass
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin

from . import actuation as act, broad_phase, drive as drives, limits, pair_rules, pair_table, prescribed as presc, self_pairs, shapes
from .actuation import Actuation
from .bodies import load_body
from .errors import SceneError, out_of_memory
from .memory import check_data_size, new_data
from .limits import UNLIMITED
from .options import Options, RootJoint
from .pair_table import Pair, PairTable
from .prescribed import Prescribed
from .scene import Scene
from .state import State
from .trees import Forest, Kinematics, whole_model


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

    pin: Pinocchio model (gravity set from the scene); geom (geometry_model): coal geometry + pairs;
    pairs: the collision pairs; vertices[g]: (k, 3) polytope vertices of geometry g in its
    joint frame (empty for smooth shapes); bounds[g]: a cheap lower bound of the distance from a
    point to geometry g, ("sphere", centre, radius) in its joint frame or ("plane", n, d) for a
    half-space {n.x <= d} (contacts.py uses it to skip far vertices); face_normals[g]: outward
    face normals of a polytope in its joint frame (empty otherwise); face_planes[g]: a box's
    (normals, offsets) in its joint frame, else None; vertex_edges[g]: the edge directions leaving
    each vertex (corner detection in contacts.py); support_mask[j] (a property): 1 on the
    velocity indices that move joint j; q0/u0: the initial state; excluded: the pairs the
    automatic rule would make that are left out, each with why (the SRDF, an overlap at a reference
    pose, the scene's [collisions] exclude);
    limits: the joint limits (limits.JointLimit: unilateral constraints of the same law, pair indices
    after the pairs');
    actuation, drive, prescribed: the joint torques (actuation.py), the driven joints ([[drives]], drive.py), the
    statics that move (prescribed.py), each None where there is none; forest: one Pinocchio model per body
    (trees.py: the Python time-stepping step's dynamics and kinematics; None: one tree, the whole model).
    """

    scene: Scene
    pin: pin.Model
    geometry_model: pin.GeometryModel | None  # None: made at first use of `geom` (a scene of many pairs)
    pairs: tuple[Pair, ...] | PairTable
    vertices: tuple[np.ndarray, ...]
    bounds: tuple[tuple, ...]
    face_normals: tuple[np.ndarray, ...]
    face_planes: tuple
    vertex_edges: tuple
    bodies: tuple[BodyInfo, ...]
    geometry_body: tuple[str, ...]
    q0: np.ndarray
    u0: np.ndarray
    excluded: tuple[tuple[str, str], ...] = ()  # (pair name, why): automatic pairs left out (build_model)
    limits: tuple = ()  # limits.JointLimit of every limited joint of the bodies with joint_limits on
    actuation: Actuation | None = None
    drive: drives.Drive | None = None
    prescribed: Prescribed | None = None
    forest: Forest | None = None
    pair_table: PairTable | None = None  # the pairs without their list (pair_table.py); None: made from pairs
    geometry_objects: tuple = ()  # every geometry object when geometry_model is None (then `geometries`)
    scratch: InitVar[pin.Data | None] = None  # a Data of `pin` for the velocity-bias probe below, if not given
    velocity_bias_of_bodies: InitVar[bool | None] = None  # that probe made body by body (build_model)

    def __post_init__(self, scratch, velocity_bias_of_bodies):
        if self.forest is None:  # a Model made by hand: the whole model is the forest's one tree
            object.__setattr__(self, "forest", Forest.build([self.pin], [pin.SE3.Identity()], self.pin.gravity.linear))
        if self.pair_table is None:  # a Model made by hand: its pairs' table from the list
            object.__setattr__(self, "pair_table", pair_table.table_of(self.geom, self.pairs))
        listed = isinstance(self.pairs, tuple)
        if listed:
            pj = np.array([(p.joint_first, p.joint_second) for p in self.pairs], dtype=np.int64).reshape(-1, 2)
            pj.setflags(write=False)
        else:
            pj = pair_table.PairJoints(self.pair_table)
        object.__setattr__(self, "_pair_joints", pj)
        # (a static's vertices do not move with u: a slab far from the world's origin is no lever arm)
        reach = max([float(np.linalg.norm(V, axis=1).max()) for V, go in zip(self.vertices, self.geometries)
                     if len(V) and go.parentJoint] + [1.0])
        object.__setattr__(self, "_reach", reach)
        def sides(go):  # (smallest, largest) side of the shape's box (coal's local AABB); inf for a half-space
            geo = go.geometry
            if isinstance(geo, (coal.Halfspace, coal.Plane)):
                return np.inf, np.inf
            geo.computeLocalAABB()
            b = geo.aabb_local
            return float(min(b.width(), b.height(), b.depth())), float(max(b.width(), b.height(), b.depth()))
        box = [sides(go) for go in self.geometries]  # once per geometry, not per pair
        ext = [s for s, _ in box]
        largest = [s for _, s in box if s < np.inf]
        object.__setattr__(self, "_gap_reach", 0.5 * float(np.median(largest)) if largest else 0.0)
        t = self.pair_table
        object.__setattr__(self, "_thinnest_pair", min([ext[p.first] + ext[p.second] for p in self.pairs] + [np.inf])
                           if listed else pair_table.thinnest(t, np.array(ext)))
        poly = [g for g in range(t.G) if len(self.vertices[g]) and self.bounds[g][0] == "sphere"]
        object.__setattr__(self, "_polytope_pairs", tuple(map(tuple, pair_table.pairs_among(t, poly).tolist())))
        object.__setattr__(self, "_polytope_pair_ids", {p[0]: p[1:] for p in self._polytope_pairs})
        faces = [g for g in range(t.G) if len(self.face_normals[g]) and len(self.vertices[g])]
        object.__setattr__(self, "_polytope_pair_set", frozenset(pair_table.pairs_among(t, faces)[:, 0].tolist()))
        # does h(q, u) depend on u (Coriolis, gyroscopic)? A random state tells (structurally zero
        # for translations and prismatic chains); stepper.free_velocity skips the midpoint iteration.
        if velocity_bias_of_bodies is None:  # tree by tree: no Data of the whole model
            velocity_bias_of_bodies = (_velocity_bias(self.pin, scratch) if scratch is not None else
                                       any(_velocity_bias(t.model, t.model.createData()) for t in self.forest.trees))
        object.__setattr__(self, "_velocity_bias", bool(velocity_bias_of_bodies))

    def whole_data_fits(self) -> bool:
        """Whether one Data of the whole model (pin) fits the memory limit (check_data_size): the
        adaptive and event-driven integrators' compiled parts need it (compiled.loop_refusal); the
        time-stepping step, Python and compiled, runs on the forest without it."""
        fits = self.__dict__.get("_whole_data_fits")
        if fits is None:
            try:
                check_data_size(self.pin, self.scene.name)
                fits = True
            except SceneError:
                fits = False
            object.__setattr__(self, "_whole_data_fits", fits)
        return fits

    @property
    def support_mask(self) -> np.ndarray:
        """(njoints, nv), made at first use (a dense njoints x nv: 800 MB at 10,000 joints)."""
        mask = self.__dict__.get("_support_mask")
        if mask is None:
            model = self.pin
            mask = np.zeros((model.njoints, model.nv))
            for j in range(1, model.njoints):
                for s in model.supports[j][1:]:
                    jm = model.joints[s]
                    mask[j, jm.idx_v:jm.idx_v + jm.nv] = 1.0
            mask.setflags(write=False)
            object.__setattr__(self, "_support_mask", mask)
        return mask

    @property
    def geom(self) -> pin.GeometryModel:
        """coal geometry and the pairs as one Pinocchio GeometryModel; without a list of pairs (listed) made
        at first use (compiled step, event integrators): the Python step queries coal (data.Data.collide)."""
        gm = self.geometry_model
        if gm is None:
            gm = pair_table.geometry_model(self.geometry_objects, self.pairs)
            object.__setattr__(self, "geometry_model", gm)
        return gm

    @property
    def geometries(self):
        """Every geometry object (coal shape, parent joint, placement in it) by geometry id."""
        return self.geometry_objects if self.geometry_objects else self.geom.geometryObjects

    @property
    def listed(self) -> bool:
        """Whether the pairs are a list (with a GeometryModel and GeometryData), not a PairTable (> LAZY_PAIRS)."""
        return isinstance(self.pairs, tuple)

    @property
    def options(self) -> Options:
        """The integration options (the scene's): docs/scenes.md."""
        return self.scene.options

    @property
    def nq(self) -> int:
        return self.pin.nq

    @property
    def nv(self) -> int:
        return self.pin.nv

    @property
    def reach(self) -> float:
        """max(1, largest distance of a moving vertex from its joint origin) [m]: bounds a vertex's speed
        by reach * |u|_inf for unit-scale joints (contacts.detect, corner margin). Statics' vertices do not
        count: they do not move with u (docs/theory.md §6.3)."""
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
    def polytope_pair_ids(self) -> dict:
        """polytope_pairs by pair index: {pair: (geometry 1, geometry 2, joint 1, joint 2)}."""
        return self._polytope_pair_ids

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
        """(pairs, 2) int array: the joints of each pair's first and second geometry (a pair table: made per index)."""
        return self._pair_joints

    @property
    def pair_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.pairs)

    @property
    def gaps_per_geometry(self) -> bool:
        """Whether a sample records a gap per geometry (contacts.geometry_gaps: n geometries, not n^2 / 2 pairs), not
        per pair: a model of more than GAP_PAIRS pairs (every model without a pair list)."""
        return not self.listed or len(self.pairs) > GAP_PAIRS

    @property
    def gap_names(self) -> tuple[str, ...]:
        """The names of the recorded gap columns (trajectory "gap"): the collision pairs', or the geometries'
        (gaps_per_geometry)."""
        return tuple(go.name for go in self.geometries) if self.gaps_per_geometry else self.pair_names

    @property
    def gap_reach(self) -> float:
        """[m] how far from a geometry the records of a model of gaps_per_geometry look for its nearest partner
        (contacts.geometry_gaps; farther: +inf): half the median, over the bounded geometries, of the largest
        side of their boxes (coal's local AABB), so about half a body of the scene."""
        return self._gap_reach

    def coordinates(self) -> dict[str, list[str]]:
        """Names and SI units of every coordinate of q and velocity of u (joint name, then the
        component: x y z qx qy qz qw for a free root's world position and quaternion, vx vy vz
        wx wy wz for its world linear and body angular velocity; s_a s_b theta for a planar root)."""
        q_names, u_names, q_units, u_units = [], [], [], []
        for j in range(1, self.pin.njoints):
            jm, name = self.pin.joints[j], self.pin.names[j]
            parts = jm.extract().joints if jm.shortname() == "JointModelComposite" else [jm]
            for sub in parts:
                kind = sub.shortname()
                if "Translation" in kind:
                    qs, us, qu, uu = ["x", "y", "z"], ["vx", "vy", "vz"], ["m"] * 3, ["m/s"] * 3
                elif "Spherical" in kind:
                    qs, us, qu, uu = ["qx", "qy", "qz", "qw"], ["wx", "wy", "wz"], ["1"] * 4, ["rad/s"] * 3
                elif "Prismatic" in kind or kind.startswith("JointModelP"):
                    qs, us, qu, uu = [_axis(kind, "s")], [_axis(kind, "v")], ["m"], ["m/s"]
                elif "Revolute" in kind or kind.startswith("JointModelR"):
                    qs, us, qu, uu = [_axis(kind, "theta")], [_axis(kind, "omega")], ["rad"], ["rad/s"]
                else:  # any other joint: its coordinates by index, units unknown
                    qs = [f"q{i}" for i in range(sub.nq)]
                    us = [f"u{i}" for i in range(sub.nv)]
                    qu, uu = ["?"] * sub.nq, ["?"] * sub.nv
                if len(parts) > 1 and len(qs) == 1:  # one of several 1-dof parts: number them
                    qs, us = [f"{qs[0]}{len(q_names) - _start(q_names, name)}"], [f"{us[0]}{len(u_names) - _start(u_names, name)}"]
                q_names += [f"{name}/{x}" for x in qs]
                u_names += [f"{name}/{x}" for x in us]
                q_units += qu
                u_units += uu
        return {"q_names": q_names, "u_names": u_names, "q_units": q_units, "u_units": u_units}

    def joints(self) -> list[dict]:
        """Every joint in the order of q: name, type, its index ranges in q and u ([start, stop)),
        and its position limits from the Pinocchio model (lower, upper per coordinate; None where
        unlimited, and for every joint but a revolute or prismatic one: a quaternion's or a
        continuous joint's (cos, sin) bounds are no limits)."""
        out = []
        for j in sorted(range(1, self.pin.njoints), key=lambda j: self.pin.joints[j].idx_q):
            jm = self.pin.joints[j]
            sl = slice(jm.idx_q, jm.idx_q + jm.nq)
            kind = joint_type(jm)
            lim = [[None if not abs(x) < UNLIMITED or not kind.startswith(("revolute", "prismatic")) else float(x)
                    for x in v[sl]] for v in (self.pin.lowerPositionLimit, self.pin.upperPositionLimit)]
            out.append({"name": self.pin.names[j], "type": kind, "q": [sl.start, sl.stop],
                        "u": [jm.idx_v, jm.idx_v + jm.nv], "lower": lim[0], "upper": lim[1]})
        return out

    def describe(self) -> dict:
        """A JSON-able summary (for `moreau-sim info` and output metadata)."""
        o = self.options
        return {
            "scene": self.scene.name, "nq": self.nq, "nv": self.nv,
            "joints": self.joints(),
            "bodies": [{"name": b.name, "root_joint": b.root_joint.value, "nq": b.q_slice.stop - b.q_slice.start,
                        "nv": b.v_slice.stop - b.v_slice.start, "urdf": str(b.urdf),
                        "srdf": None if s.srdf is None else str(s.srdf),
                        "joints": [self.pin.names[j] for j in b.joints]}
                       for b, s in zip(self.bodies, self.scene.bodies)],
            "geometries": [g.name for g in self.geometries],
            # a model without a pair list (more than LAZY_PAIRS pairs) names none of them: its gaps are per geometry
            "collision_pairs": list(self.pair_names) if self.listed else None,
            "pair_count": len(self.pairs),
            "gap_columns": "geometries" if self.gaps_per_geometry else "pairs",
            "gap_reach": self.gap_reach if self.gaps_per_geometry else None,
            "excluded_pairs": [{"pair": name, "why": why} for name, why in self.excluded],
            "joint_limits": [{"pair": lim.pair, "name": lim.name, "bound": lim.bound} for lim in self.limits],
            "restitution": o.restitution,
            "dt": o.dt,
            "duration": o.duration,
            "gravity": list(o.gravity),
        }


def build_model(scene: Scene) -> Model:
    """Build the immutable :class:`Model` of `scene`. Raises :class:`SceneError`: one line naming the
    scene and its size when memory runs out (errors.out_of_memory)."""
    try:
        return _build_model(scene)
    except (MemoryError, RuntimeError) as exc:
        msg = out_of_memory(exc, str(scene.path or scene.name), "building its model",
                            f"{len(scene.bodies)} bodies, {len(scene.statics)} statics")
        if msg is None:
            raise
        raise SceneError(msg) from None


def _build_model(scene: Scene) -> Model:
    where = str(scene.path) if scene.path else "<scene>"
    infos, authored, body_models = [], [], []  # body_models: each body's own Pinocchio model (M checked on it)
    loaded: dict = {}  # each URDF as loaded once (_load)
    placed = []  # each body's (model, geometry) placed in the world: the forest's trees
    names: set[str] = set()
    nq = nv = 0
    nj = 1
    for i, body in enumerate(scene.bodies):
        w = f"{where} [[bodies]][{i}] ({body.name})"
        m, g, said = _load(body, w, loaded)
        authored.append(said)
        body_models.append(m)
        placement = pin.SE3(pin.rpy.rpyToMatrix(*body.rpy), np.array(body.position, float))
        if body.root_joint is RootJoint.FREE:
            placement = pin.SE3.Identity()  # a free body's pose is its q (world frame): see _initial
        tm, tg = pin.appendModel(pin.Model(), m, pin.GeometryModel(), g, 0, placement)
        clash = next((n for n in list(tm.names)[1:] if n in names), None)
        if clash is not None:
            raise SceneError(f"{w}: Pinocchio cannot add this body to the scene's model: "
                             f"The two models have conflicting joint names ({clash}).")
        names.update(list(tm.names)[1:])
        placed.append((tm, tg, body.name))
        infos.append(BodyInfo(body.name, body.root_joint, tuple(range(nj, nj + tm.njoints - 1)),
                              slice(nq, nq + tm.nq), slice(nv, nv + tm.nv), body.urdf))
        nq, nv, nj = nq + tm.nq, nv + tm.nv, nj + tm.njoints - 1
    model, gobs, geometry_body = whole_model(placed, where)
    model.name = scene.name
    first_static = len(gobs)
    for s in scene.statics:
        shape, placement = shapes.static_shape(s)
        gobs.append(pin.GeometryObject(s.name, 0, 0, placement, shape))
        geometry_body.append(s.name)
    model.gravity.linear = np.array(scene.options.gravity, float)
    if model.nv == 0:
        raise SceneError(f"{where} [[bodies]]: nothing moves (every body has a fixed root and no joints)")
    # no Data of the whole model here: the mass matrix and the velocity bias are checked body by body,
    # on each body's own model; the time-stepping step runs on the forest (trees.py). The paths that
    # still need the whole model's Data (adaptive and event-driven, and their compiled parts) check its size
    # when they make it (new_data, Data.pin): refused there with one line, never here.
    forest = Forest.of_placed([tm for tm, _, _ in placed], scene.options.gravity)
    if forest.trees:  # the largest tree's Data is the largest any path needs: refused here if it cannot be made
        body, info = max(zip(scene.bodies, infos), key=lambda bi: bi[1].v_slice.stop - bi[1].v_slice.start)
        check_data_size(max((t.model for t in forest.trees), key=lambda m: m.nv),
                        f"{where} ({len(scene.bodies)} bodies; the largest: {body.urdf}, "
                        f"nv = {info.v_slice.stop - info.v_slice.start})")

    vertices = tuple(shapes.vertices(go.geometry, go.placement) for go in gobs)
    table, why = pair_rules.choose(scene, model, gobs, geometry_body, authored, [info.q_slice for info in infos],
                                   vertices, lambda: new_data(model, where), where)
    lazy = len(table) > LAZY_PAIRS and not any(s.motion is not None for s in scene.statics)
    pairs = table if lazy else tuple(table)
    geom = None if lazy else pair_table.geometry_model(gobs, pairs)

    moving = None if lazy else presc.build(geom, scene.statics, first_static, pairs, vertices, where)  # at t = 0
    bounds = tuple(shapes.distance_bound(go.geometry, go.placement) for go in gobs)
    face_normals = tuple(shapes.face_normals(go.geometry, go.placement) for go in gobs)
    face_planes = tuple(shapes.face_planes(go.geometry, go.placement) for go in gobs)
    vertex_edges = tuple(shapes.vertex_edges(go.geometry, go.placement) for go in gobs)

    q0, u0 = _initial(scene, model, infos, where)
    bias = _check_bodies(scene, body_models, infos, q0, where)
    actuation = act.build(model, infos, scene.actuators, q0, mjcf={b.name: b.urdf for b in scene.bodies if b.mjcf},
                          where=where)
    limited = [j for body, info in zip(scene.bodies, infos) if body.joint_limits
               for j in info.joints[(body.root_joint is not RootJoint.FIXED):]]  # a root joint has no limits
    joint_limits = limits.joint_limits(model, limited, len(pairs))
    return Model(scene=scene, pin=model, geometry_model=geom, pairs=pairs, pair_table=table,
                 geometry_objects=tuple(gobs) if lazy else (), vertices=vertices, bounds=bounds, face_normals=face_normals, face_planes=face_planes, vertex_edges=vertex_edges,
                 bodies=tuple(infos), geometry_body=tuple(geometry_body), q0=q0, u0=u0, limits=joint_limits,
                 actuation=actuation, prescribed=moving, forest=forest,
                 drive=drives.build(scene, model, infos, actuation, q0, u0, joint_limits),
                 excluded=tuple((pair_rules.pair_name(gobs, i, j), w) for (i, j), w in sorted(why.items())),
                 velocity_bias_of_bodies=bias)


def _load(body, where: str, loaded: dict) -> tuple[pin.Model, pin.GeometryModel, self_pairs.Authored]:
    """bodies.load_body's model, geometry and SRDF of a body; a URDF body loaded as another before it
    (the same file, root joint, axes, meshes, package folders and SRDF: a column's beads, a pile's boxes)
    is a copy of that one renamed (its names' prefix, its coal shapes cloned): reading and checking
    each file once, not once per body (0.5 ms a body)."""
    key = None if body.mjcf else (body.urdf, body.root_joint, body.axis, body.axes, body.package_dirs, body.meshes,
                                  body.srdf)
    first = loaded.get(key)
    if first is None:
        m, g, _, said = load_body(body, where)
        if key is not None:
            loaded[key] = (m, g, said, f"{body.name}/")
        return m, g, said
    m0, g0, said0, p0 = first
    p, k = f"{body.name}/", len(p0)
    m, g = pin.Model(m0), pin.GeometryModel()
    for i in range(1, m.njoints):
        m.names[i] = p + m.names[i][k:]
    for i in range(1, m.nframes):
        m.frames[i].name = p + m.frames[i].name[k:]
    for go in g0.geometryObjects:
        go = go.copy()
        go.name, go.geometry = p + go.name[k:], go.geometry.clone()
        g.addGeometryObject(go)
    disabled = frozenset(frozenset(p + n[k:] for n in pair) for pair in said0.disabled)
    return m, g, dataclasses.replace(said0, disabled=disabled)


LAZY_PAIRS = 20_000  # above this many pairs no list, GeometryModel nor GeometryData of them is made with the model
GAP_PAIRS = 1000  # above this many pairs a sample records a gap per geometry, not per pair (Model.gaps_per_geometry)


def _velocity_bias(model: pin.Model, data: pin.Data) -> bool:
    """Whether h(q, u) depends on u (Coriolis, gyroscopic terms) at a generic state drawn from a seeded generator:
    q = neutral (+) a random tangent, u random. Not pin.randomConfiguration: it draws from the C library's global
    rand(), so the probe (and with it the midpoint fixed point of §2.4) depended on what the process had drawn
    before (the 4th build of a scene in one process came out without it). Undefined (NaN) counts as a bias."""
    rng = np.random.default_rng(0)
    qr = pin.integrate(model, pin.neutral(model), rng.standard_normal(model.nv))
    ur = rng.standard_normal(model.nv)
    c = pin.nonLinearEffects(model, data, qr, ur) - pin.nonLinearEffects(model, data, qr, np.zeros(model.nv))
    return not bool(np.abs(c).max(initial=0.0) <= 1e-12)


def _check_bodies(scene: Scene, body_models: list, infos, q0: np.ndarray, where: str) -> bool:
    """The mass matrix and the velocity bias body by body, each on the body's own Pinocchio model
    and a Data of its size: every body hangs from the world (pin.appendModel at joint 0), so M is
    block diagonal by bodies and its block of a body is that body's M (its root placement only
    changes the world frame). Linear in bodies; no nv^3 Data of the whole model. Returns whether
    any body's h(q, u) depends on u."""
    bias = False
    for i, (body, m, info) in enumerate(zip(scene.bodies, body_models, infos)):
        if m.nv == 0:
            continue
        w = f"{where} [[bodies]][{i}] ({body.name})"
        d = new_data(m, w, checked=True)  # smaller than the whole model's, checked already
        _check_mass_matrix(m, d, q0[info.q_slice], w)
        bias = bias or _velocity_bias(m, d)
    return bias


def _check_mass_matrix(model: pin.Model, data: pin.Data, q0: np.ndarray, where: str) -> None:
    """M(q0) must be positive definite: every moving dof must carry mass or inertia (a zero mass
    or inertia otherwise surfaces as a failed QP or a NaN state at the first step)."""
    M = pin.crba(model, data, q0)
    if np.isfinite(M).all():
        try:
            np.linalg.cholesky(0.5 * (M + M.T))
            return
        except np.linalg.LinAlgError:
            pass
    bad = []
    for j in range(1, model.njoints):
        Y = model.inertias[j]
        if not (Y.mass > 0.0 and np.linalg.eigvalsh(0.5 * (Y.inertia + Y.inertia.T)).min() > 0.0):
            bad.append(model.names[j])
    raise SceneError(f"{where}: the mass matrix at the initial state is singular: every moving link "
                     f"needs a mass > 0 and a positive-definite inertia (links without: {', '.join(bad) or 'none'})")


DISTANCE_FAILED = 1e100  # [m] coal's distance of a failed GJK/EPA query is -DBL_MAX: no distance at all


def check_start(model: Model, kin: Kinematics, q: np.ndarray, where: str, tol: float) -> None:
    """A start with a pair deeper than `tol` [m] (the contact tolerance) inside another is bad
    input: no rule removes such a depth honestly (the rest rule of docs/theory.md §2.5 is for the
    step's own penetration of about h/2 |gamma|: it would lift any depth in one step and book the
    energy; a moving body keeps it). One SceneError naming the pair and its depth. initial_state
    checks q0 with it; contacts.check_initial is the same rule for a state given to a run. kin: the
    forest's scratch (placements at q)."""
    pairs = model.pairs
    if not pairs:
        return
    if model.listed:
        gd = pin.GeometryData(model.geom)  # fresh coal requests: coal's default tolerances, no cached guess
        model.forest.place(kin, q, model.geometries, gd.oMg)
        pin.computeDistances(model.geom, gd)
        g = np.array([r.min_distance for r in gd.distanceResults])
    else:  # many pairs: coal's distance of those whose boxes come within tol (the others are apart)
        oMg = [pin.SE3.Identity()] * len(model.geometries)
        model.forest.place(kin, q, model.geometries, oMg)
        shape, g = [go.geometry for go in model.geometries], np.full(len(pairs), np.inf)
        for k in broad_phase.within(model, tol).candidates_at(kin.oMi).tolist():
            p, tf = pairs[k], [coal.Transform3s(oMg[x]) for x in (pairs[k].first, pairs[k].second)]
            g[k] = coal.distance(shape[p.first], tf[0], shape[p.second], tf[1], coal.DistanceRequest(), coal.DistanceResult())
    g[~(np.abs(g) < DISTANCE_FAILED)] = np.nan  # a failed query proves nothing: the run's records report it
    deep = np.flatnonzero(g < -tol)
    if len(deep):
        k = int(deep[np.argmin(g[deep])])
        a, b = (x.split("/", 1)[0] for x in pairs[k].name.split("|"))
        more = f" ({len(deep) - 1} more pair(s) too)" if len(deep) > 1 else ""
        fix = (f"two parts of body {a}: change its q0, or leave the pair out with [collisions] exclude"
               if a == b and "/" in pairs[k].name.split("|")[0] else "place the bodies apart or touching")
        raise SceneError(f"{where}: pair {pairs[k].name} starts {-g[k]:.3g} m inside (more than contact_tolerance "
                         f"= {tol:g} m){more}; {fix}")


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


_STARTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # model -> the q0 bytes whose checks passed


def initial_state(model: Model, data=None) -> State:
    """The scene's initial state; a SceneError if it starts a pair deeper than contact_tolerance
    inside another (check_start: every run from q0 starts here). data: the run's Data, whose
    forest scratch the check uses (default: a new one). The checks run once per model and q0 (_STARTS):
    a model is not changed after it is built, so a passed check stays passed."""
    key = model.q0.tobytes()
    if _STARTS.get(model) == key:
        return State(0.0, model.q0.copy(), model.u0.copy())
    where = str(model.scene.path) if model.scene.path else "<scene>"
    kin = data.kinematics if data is not None else Kinematics(model.forest, make=lambda m: new_data(m, where))
    check_start(model, kin, model.q0, where, model.options.contact_tolerance)
    check_limits(model.limits, model.q0, where, model.options.contact_tolerance)
    _STARTS[model] = key
    return State(0.0, model.q0.copy(), model.u0.copy())


def joint_type(jm) -> str:
    """A Pinocchio joint model's kind in words: "revolute z", "continuous y" (a URDF continuous
    joint: cos, sin in q), "prismatic x", "spherical", "free flyer", "translation", and for a
    composite the kinds of its parts joined by " + " (the free root: "translation + spherical")."""
    kind = jm.shortname().removeprefix("JointModel")
    if kind == "Composite":
        return " + ".join(joint_type(sub) for sub in jm.extract().joints)
    words = {"FreeFlyer": "free flyer", "Spherical": "spherical", "SphericalZYX": "spherical zyx",
             "Translation": "translation", "Planar": "planar", "RevoluteUnaligned": "revolute (unaligned axis)",
             "PrismaticUnaligned": "prismatic (unaligned axis)",
             "RevoluteUnboundedUnaligned": "continuous (unaligned axis)"}
    if kind in words:
        return words[kind]
    for prefix, word in (("RUB", "continuous"), ("R", "revolute"), ("P", "prismatic")):
        if kind.startswith(prefix) and kind[len(prefix):] in ("X", "Y", "Z"):
            return f"{word} {kind[-1].lower()}"
    return kind


def check_limits(joint_limits: tuple, q: np.ndarray, where: str, tol: float) -> None:
    """A start beyond a joint limit by more than `tol` is bad input, as a pair deeper than the tolerance
    (check_start): one SceneError naming the joint, its limit and q."""
    for lim in joint_limits:
        g = lim.gap(q)
        if g < -tol:
            raise SceneError(f"{where}: joint {lim.name.rsplit(' ', 1)[0]} starts at q = {q[lim.idx_q]:.6g}, "
                             f"{-g:.3g} beyond its {lim.name.rsplit(' ', 1)[1]} limit {lim.bound:.6g}; start it within "
                             "its limits or set joint_limits = false on the body")


def _axis(kind: str, base: str) -> str:
    """'theta_y' for JointModelRY, 'theta' for an unaligned axis."""
    tail = kind.removeprefix("JointModel")
    return f"{base}_{tail[-1].lower()}" if len(tail) == 2 and tail[-1] in "XYZ" else base


def _start(names: list[str], joint: str) -> int:
    """Index of the first name of `joint` in names (len(names) if none yet)."""
    prefix = f"{joint}/"
    return next((i for i, n in enumerate(names) if n.startswith(prefix)), len(names))
