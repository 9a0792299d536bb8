"""The forest: one Pinocchio model per kinematic tree of the scene (each body hangs from the world),
each with a small Data, and the dynamics and kinematics the time-stepping step needs assembled from
the trees: M block diagonal, h, energies, joint placements and WORLD Jacobians (docs/theory.md §2.12).
:class:`Forest` is part of the immutable Model; :class:`Kinematics` is scratch held by the run's Data.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from .errors import SceneError


@dataclass(frozen=True)
class Tree:
    """One kinematic tree: its Pinocchio model (the body's own, placed in the world as the scene's
    model places it), its slices of q and u, and its first joint's id in the scene's model (its local
    joint k >= 1 is joint `offset + k` there)."""

    model: pin.Model
    q: slice
    v: slice
    offset: int

    @property
    def single(self) -> bool:
        """One joint: the tree's energy sums are one term each (bitwise the scene model's, see energies)."""
        return self.model.njoints == 2


class Forest:
    """The trees of a scene in the order of q and u (the scene's model appends them in that order).
    Built in time linear in the bodies: no Data of the whole scene (docs/theory.md §2.12)."""

    def __init__(self, trees: list[Tree], nq: int, nv: int, njoints: int):
        self.trees = tuple(trees)
        self.nq, self.nv, self.njoints = nq, nv, njoints
        # the scene's joint id -> (tree index, local joint id); the world (joint 0) is tree -1
        self.tree_of_joint = np.full(njoints, -1, dtype=np.int64)
        self.local_joint = np.zeros(njoints, dtype=np.int64)
        for t, tr in enumerate(self.trees):
            ids = np.arange(1, tr.model.njoints)
            self.tree_of_joint[tr.offset + ids] = t
            self.local_joint[tr.offset + ids] = ids
        self.tree_of_joint.setflags(write=False)
        self.local_joint.setflags(write=False)
        # (first velocity, nv) of each tree: M's and M^-1's diagonal blocks (qp.solve's islands: docs/theory.md §1.3)
        self.blocks = tuple((tr.v.start, tr.v.stop - tr.v.start) for tr in self.trees)
        moving = [t for t, tr in enumerate(self.trees) if tr.v.stop > tr.v.start]
        self._moving = np.array(moving, dtype=np.int64)  # the trees with velocities, and where theirs start
        self._v_starts = np.array([self.trees[t].v.start for t in moving], dtype=np.int64)

    def joint_travel(self, u: np.ndarray, h: float, reach: float) -> np.ndarray:
        """How far a vertex of each joint's tree can move in a step of h [s] at the velocities u: h |u_tree|_inf
        reach [m] (reach: Model.reach), one entry per joint of the scene's model, 0 for the world (contacts.detect's
        corner margins, docs/theory.md §6.3; src/step.cpp step_ the same floats)."""
        per_tree = np.zeros(len(self.trees) + 1)  # (the last entry: the world's, tree -1)
        if len(self._moving):
            per_tree[self._moving] = h * np.maximum.reduceat(np.abs(u), self._v_starts) * reach
        return per_tree[self.tree_of_joint]

    @classmethod
    def build(cls, body_models, placements, gravity) -> Forest:
        """The forest of bodies (their own Pinocchio models and root placements, in scene order) under
        gravity [m/s^2]: each placed by pin.appendModel on an empty model, as the scene's model is built
        (model.build_model), so every joint placement is the scene model's bit for bit."""
        return cls.of_placed([pin.appendModel(pin.Model(), m, 0, p) for m, p in zip(body_models, placements)], gravity)

    @classmethod
    def of_placed(cls, models, gravity) -> Forest:
        """The forest of bodies' models already placed in the world (model.build_model), in scene order."""
        trees, nq, nv, nj = [], 0, 0, 1
        for tm in models:
            if tm.njoints <= 1:
                continue  # a fixed body without joints: no tree (its shapes are on the world)
            tm.gravity.linear = np.asarray(gravity, float)
            trees.append(Tree(tm, slice(nq, nq + tm.nq), slice(nv, nv + tm.nv), nj - 1))
            nq, nv, nj = nq + tm.nq, nv + tm.nv, nj + tm.njoints - 1
        return cls(trees, nq, nv, nj)

    # ---- dynamics (each tree's own algorithm, assembled) -------------------------------------------
    def mass_matrix(self, kin: Kinematics, q: np.ndarray) -> np.ndarray:
        """M(q) (nv, nv) [kg, kg m^2], dense and block diagonal by trees (CRBA per tree, WORLD
        convention): also fills kin.J, the WORLD joint Jacobians (6, nv) at q (contact rows)."""
        M = np.zeros((self.nv, self.nv))
        J = kin.J
        for tr, d in zip(self.trees, kin.datas()):
            M[tr.v, tr.v] = pin.crba(tr.model, d, q[tr.q], pin.Convention.WORLD)
            J[:, tr.v] = d.J.reshape(6, -1)
        return M

    def mass_blocks(self, kin: Kinematics, q: np.ndarray) -> list[np.ndarray]:
        """M(q)'s diagonal blocks, one per tree (the sparse form: large scenes never form nv x nv)."""
        return [pin.crba(tr.model, d, q[tr.q], pin.Convention.WORLD).copy() for tr, d in zip(self.trees, kin.datas())]

    def inverse_mass_matrix(self, kin: Kinematics, q: np.ndarray) -> np.ndarray:
        """M(q)^-1 (nv, nv), dense and block diagonal (Pinocchio's computeMinverse per tree)."""
        Minv = np.zeros((self.nv, self.nv))
        for tr, d in zip(self.trees, kin.datas()):
            Minv[tr.v, tr.v] = pin.computeMinverse(tr.model, d, q[tr.q])
        return Minv

    def delassus(self, kin: Kinematics, q: np.ndarray, W: np.ndarray) -> np.ndarray:
        """The contact-space matrix W' M(q)^-1 W (m, m) summed over trees: each tree's block of
        M^-1 only meets the rows of W on its own velocities; no nv x nv matrix is formed."""
        G = np.zeros((W.shape[1], W.shape[1]))
        for tr, d in zip(self.trees, kin.datas()):
            Wt = W[tr.v]
            rows = np.flatnonzero((Wt != 0.0).any(axis=0))
            if len(rows):
                Wr = Wt[:, rows]
                G[np.ix_(rows, rows)] += Wr.T @ (pin.computeMinverse(tr.model, d, q[tr.q]) @ Wr)
        return G

    def acceleration(self, kin: Kinematics, q: np.ndarray, u: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """M(q)^-1 (tau - h(q, u)) [velocity / s] by ABA per tree."""
        out = np.empty(self.nv)
        for tr, d in zip(self.trees, kin.datas()):
            out[tr.v] = pin.aba(tr.model, d, q[tr.q], u[tr.v], tau[tr.v])
        return out

    def bias(self, kin: Kinematics, q: np.ndarray, u: np.ndarray) -> np.ndarray:
        """h(q, u) [N, N m]: gravity, Coriolis and gyroscopic terms (nonLinearEffects per tree)."""
        out = np.empty(self.nv)
        for tr, d in zip(self.trees, kin.datas()):
            out[tr.v] = pin.nonLinearEffects(tr.model, d, q[tr.q], u[tr.v])
        return out

    # ---- energies: Pinocchio's sums, term by term in the scene model's order ---------------------------
    def kinetic(self, kin: Kinematics, q: np.ndarray, u: np.ndarray) -> float:
        """T = 1/2 u'M(q)u [J]: sum over joints of v_i' I_i v_i in joint order, then halved, as
        pin.computeKineticEnergy sums on the scene's model (bit for bit)."""
        s = 0.0
        for tr, d in zip(self.trees, kin.datas()):
            if tr.single:  # one term: Pinocchio's own sum is it (times 1/2, exact)
                s += 2.0 * pin.computeKineticEnergy(tr.model, d, q[tr.q], u[tr.v])
                continue
            pin.forwardKinematics(tr.model, d, q[tr.q], u[tr.v])
            for k in range(1, tr.model.njoints):
                s += tr.model.inertias[k].vtiv(d.v[k])
        return 0.5 * s

    def potential(self, kin: Kinematics, q: np.ndarray) -> float:
        """V = -sum_i m_i g . c_i [J] (zero at the world origin), summed in the scene model's joint
        order. One-joint trees are bitwise pin.computePotentialEnergy on the scene's model; a tree of
        several joints adds its own sum, another association: within 1e-15 relative of it."""
        s = 0.0
        for tr, d in zip(self.trees, kin.datas()):
            s += pin.computePotentialEnergy(tr.model, d, q[tr.q])
        return s

    # ---- kinematics ------------------------------------------------------------------------------------
    def place(self, kin: Kinematics, q: np.ndarray, geometries=None, oMg=None) -> None:
        """Forward kinematics of every tree at q (kin.oMi, the scene's joint ids), and when geometries
        (model.Model.geometries) and oMg (their world placements, data.Data.oMg) are given, those
        placements oMg[g] = oMi[joint] * placement, as pin.updateGeometryPlacements makes them."""
        for tr, d in zip(self.trees, kin.datas()):
            pin.forwardKinematics(tr.model, d, q[tr.q])
        if geometries is not None:
            oMi = kin.oMi
            for g, go in enumerate(geometries):
                oMg[g] = oMi[go.parentJoint] * go.placement if go.parentJoint else go.placement

    def motion_subspace(self, kin: Kinematics, joint: int) -> np.ndarray:
        """(6, nv_j) motion subspace S of the scene's joint `joint` after place() (its local frame)."""
        t = int(self.tree_of_joint[joint])
        return np.asarray(kin.datas()[t].joints[int(self.local_joint[joint])].S).reshape(6, -1)


class Kinematics:
    """Scratch of a forest: each tree's Pinocchio Data (made at first use), the placements oMi of
    every joint by the scene's joint id (views of the trees' Datas: place() updates them), and J
    (6, nv) the WORLD Jacobians mass_matrix() fills. make: a tree's model -> its Data (default
    pin.Data; memory.new_data refuses one above the memory limit in one line)."""

    def __init__(self, forest: Forest, make=None):
        self.forest = forest
        self._make = make or pin.Data
        self._datas: list | None = None
        self.oMi: list = []
        self.J = np.zeros((6, forest.nv))

    def datas(self) -> list:
        if self._datas is None:
            self._datas = [self._make(tr.model) for tr in self.forest.trees]
            oMi = [pin.SE3.Identity()] * self.forest.njoints
            for tr, d in zip(self.forest.trees, self._datas):
                for k in range(1, tr.model.njoints):
                    oMi[tr.offset + k] = d.oMi[k]  # a reference into the tree's Data
            self.oMi = oMi
        return self._datas


def whole_model(placed: list, where: str) -> tuple[pin.Model, list, list[str]]:
    """The scene's whole Pinocchio model and geometry from the bodies' placed (model, geometry, name),
    as main's pairwise pin.appendModel of them made them (Pinocchio's ==: names, parents, placements,
    inertias, frames, limits), in time linear in the bodies: each tree's joints, bodies and frames added
    to one model (assembled; Pinocchio's own addJoint and addFrame kept linear by Growing). appendModel
    is quadratic in the two models' sizes (it scans every frame at every joint and checks names by linear
    search): 17 s at 10,000 beads pairwise. Trees with mimic joints are appended (appended). The
    geometries in appendModel's order: those on the world first (body order), then those on joints
    (joint order)."""
    models = [tm for tm, _, _ in placed]
    try:
        model = assembled(models) if len(models) > 1 and not any(len(tm.mimicking_joints) for tm in models) \
            else appended(models)
    except ValueError as exc:  # Pinocchio: "The two models have conflicting frame names." and the like
        raise SceneError(f"{where}: Pinocchio cannot join the bodies into the scene's model: {exc}") from None
    frame_id = {(f.name, int(f.type)): k for k, f in enumerate(model.frames)}
    geom, geometry_body = [], []
    for on_world in (True, False):
        offset = 0
        for tm, tg, name in placed:
            for go in tg.geometryObjects:
                if (go.parentJoint == 0) != on_world:
                    continue
                go = go.copy()
                if go.parentJoint:
                    go.parentJoint = go.parentJoint + offset
                if go.parentFrame:
                    f = tm.frames[go.parentFrame]
                    go.parentFrame = frame_id[(f.name, int(f.type))]
                geom.append(go)
                geometry_body.append(name)
            offset += tm.njoints - 1
    return model, geom, geometry_body


def appended(models: list) -> pin.Model:
    """The models appended pairwise with pin.appendModel (O(log n) levels, each quadratic in its
    models' sizes): the reference assembled() reproduces. One model: itself; none: an empty one."""
    while len(models) > 1:
        models = [pin.appendModel(models[k], models[k + 1], 0, pin.SE3.Identity()) if k + 1 < len(models)
                  else models[k] for k in range(0, len(models), 2)]
    return models[0] if models else pin.Model()


def assembled(models: list) -> pin.Model:
    """appended(models) (two or more, without mimic joints) built by adding
    every joint, body and frame once, as appendModel adds them at its last append of a left part L
    (the first trees) and a right part R: L's world frames, L's joints each with its frames, R's world
    frames, R's joints each with its frames (a part's frames keep its trees' order: appendModel regroups
    them the same way at every level); the world's inertia summed as the appends sum it; a reference
    configuration of some trees (an MJCF's qpos0) is theirs on their joints, neutral on the others'.
    Linear in the bodies: Pinocchio's addJoint and addFrame, quadratic one call after another, go through
    Growing.
    Raises ValueError with Pinocchio's words for two joints or two frames of one name and type."""
    n = len(models)
    ident = pin.SE3.Identity()
    scratch = pin.Model()  # one joint whose inertia takes appendBodyToJoint's sums, bit for bit
    scratch.addJoint(0, pin.JointModelRX(), ident, "scratch")

    def appended_to(*inertias):
        scratch.inertias[1] = pin.Inertia.Zero()
        for Y in inertias:
            scratch.appendBodyToJoint(1, Y, ident)
        return pin.Inertia(scratch.inertias[1])

    # the pairwise appends' parts level by level, each part's world inertia as its append sums it, and
    # how many appends each tree goes through (each adds its joints' inertias to zero again: rounding)
    segments, sums, appends = [(k, k + 1) for k in range(n)], [tm.inertias[0] for tm in models], [0] * n
    while len(segments) > 1:
        pairs = range(0, len(segments), 2)
        for k in pairs[:len(segments) // 2]:
            for t in range(segments[k][0], segments[k + 1][1]):
                appends[t] += 1
        if len(segments) > 2:
            sums = [appended_to(sums[k], sums[k + 1]) if k + 1 < len(sums) else sums[k] for k in pairs]
            segments = [(segments[k][0], segments[k + 1][1]) if k + 1 < len(segments) else segments[k]
                        for k in pairs]
        else:
            break
    split = segments[0][1]
    grow = Growing(pin.Model())
    model = grow.model
    joint_names = {model.names[0]}
    frame_id = {(f.name, int(f.type)): k for k, f in enumerate(model.frames)}
    offsets = np.cumsum([0] + [tm.njoints - 1 for tm in models])
    sums_of: dict = {}  # a joint inertia -> its sums over `appends` appends (every bead's is the same)

    def add_frame(tm, f, parent_joint: int, on_world: bool) -> None:
        key = (f.name, int(f.type))
        if key in frame_id:
            raise ValueError("The two models have conflicting frame names.")
        f = pin.Frame(f)
        f.parentJoint = parent_joint
        if f.parentFrame:
            up = tm.frames[f.parentFrame]
            f.parentFrame = frame_id[(up.name, int(up.type))]  # added before (appendModel's getFrameId)
        if on_world:
            f.placement = ident * f.placement  # appendModel: (world frame's placement * aMb) * placement
        frame_id[key] = grow.add_frame(f)

    def summed(Y, times: int):
        """Y after `times` appends (appendModel re-adds it to a zero inertia each time: rounding),
        stopping where the sum stays."""
        key = (np.concatenate(([Y.mass], Y.lever, Y.inertia.ravel())).tobytes(), times)  # bit for bit
        out = sums_of.get(key)
        if out is None:
            out = Y
            for _ in range(times):
                out, last = appended_to(out), out
                if out == last:
                    break
            sums_of[key] = out
        return out

    for part, world in ((range(split), sums[0]), (range(split, n), sums[1])):
        if world == world:  # appendModel adds a part's world inertia unless NaN
            model.appendBodyToJoint(0, world, ident)
        for t in part:
            tm = models[t]
            for f in list(tm.frames)[1:]:
                if f.parentJoint == 0:
                    add_frame(tm, f, 0, True)
        for t in part:
            tm, off = models[t], int(offsets[t])
            frames = list(tm.frames)
            by_joint: dict[int, list] = {}
            for f in frames[1:]:
                if f.parentJoint:
                    by_joint.setdefault(f.parentJoint, []).append(f)
            limits = (tm.lowerEffortLimit, tm.upperEffortLimit, tm.lowerVelocityLimit, tm.upperVelocityLimit,
                      tm.lowerPositionLimit, tm.upperPositionLimit, tm.positionLimitMargin,
                      tm.lowerDryFrictionLimit, tm.upperDryFrictionLimit, tm.damping)
            for j in range(1, tm.njoints):
                name = tm.names[j]
                if name in joint_names:
                    raise ValueError("The two models have conflicting joint names.")
                joint_names.add(name)
                jm = tm.joints[j]
                q, v = slice(jm.idx_q, jm.idx_q + jm.nq), slice(jm.idx_v, jm.idx_v + jm.nv)
                parent = tm.parents[j]
                k = grow.add_joint(off + parent if parent else 0, jm, ident * tm.jointPlacements[j], name,
                                   *(x[s] for x, s in zip(limits, (v, v, v, v, q, q, q, v, v, v))))
                model.appendBodyToJoint(k, summed(tm.inertias[j], appends[t] - 1), ident)
                for f in by_joint.get(j, ()):
                    add_frame(tm, f, k, False)
    grow.done()
    model.rotorInertia = np.concatenate([tm.rotorInertia for tm in models])
    model.rotorGearRatio = np.concatenate([tm.rotorGearRatio for tm in models])
    for key in sorted({e.key() for tm in models for e in tm.referenceConfigurations}):
        model.referenceConfigurations[key] = np.concatenate([tm.referenceConfigurations[key]
                                                             if key in tm.referenceConfigurations else pin.neutral(tm)
                                                             for tm in models])
    return model


class Growing:
    """A Pinocchio model grown joint by joint and frame by frame in time linear in them. Pinocchio's
    Model::addJoint resizes the sparsity pattern of every joint already added to the new nv (zeros at
    the end), and Model::addFrame compares the new frame's name with every frame's: both quadratic
    (2.7 s at 10,000 joints and 20,000 frames). Growing keeps those two lists of the model short: every
    BATCH joints it takes the patterns out (copies; Pinocchio's zeros are added back at the end), and
    every BATCH frames the frames (the caller has checked their names: the model's nframes counts them);
    done() puts both back, giving the model addJoint and addFrame make (Pinocchio's ==, tests)."""

    BATCH = 64

    def __init__(self, model: pin.Model):
        self.model = model
        self.patterns: list[np.ndarray] = []
        self.frames: list = [pin.Frame(f) for f in model.frames]
        self._held = len(self.frames)  # frames in the model's list

    def add_joint(self, *args) -> int:
        m = self.model
        k = m.addJoint(*args)
        sp = m.sparsity_pattern_vector
        if len(sp) >= self.BATCH:
            self.patterns.extend(np.array(s, dtype=bool) for s in sp)  # copies: the list is replaced below
            m.sparsity_pattern_vector = []
        return k

    def add_frame(self, f) -> int:
        m = self.model
        self.frames.append(f)
        if self._held >= self.BATCH:
            m.frames = []
            self._held = 0
        self._held += 1
        return m.addFrame(f, False)

    def done(self) -> pin.Model:
        """The model with every joint's sparsity pattern (zeros up to nv) and every frame back in it."""
        m = self.model
        self.patterns.extend(np.array(s, dtype=bool) for s in m.sparsity_pattern_vector)
        m.sparsity_pattern_vector = []
        sp = m.sparsity_pattern_vector  # the model's own list: BATCH rows at a time, no (njoints, nv) copy
        for k in range(0, len(self.patterns), self.BATCH):
            rows = np.zeros((len(self.patterns[k:k + self.BATCH]), m.nv), dtype=bool)
            for row, s in zip(rows, self.patterns[k:k + self.BATCH]):
                row[:len(s)] = s
            sp.extend(list(rows))  # (its append keeps a reference to each array it copies: eigenpy 3.13)
        m.frames = self.frames
        return m
