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
    createData; model.py's new_data refuses one above the memory limit in one line)."""

    def __init__(self, forest: Forest, make=None):
        self.forest = forest
        self._make = make or (lambda m: m.createData())
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
    as appending them one by one with pin.appendModel makes them, in O(n log n) model appends and one
    pass over the geometries (appendModel with geometries visits every geometry at every joint: cubic
    in bodies). The models are appended pairwise (joint and frame order as one by one: each append puts
    both models' world frames first, then their joints in order); the geometries in appendModel's
    order: those on the world first (body order), then those on joints (joint order)."""
    models = [tm for tm, _, _ in placed]
    try:
        while len(models) > 1:
            models = [pin.appendModel(models[k], models[k + 1], 0, pin.SE3.Identity()) if k + 1 < len(models)
                      else models[k] for k in range(0, len(models), 2)]
    except ValueError as exc:  # Pinocchio: "The two models have conflicting frame names." and the like
        raise SceneError(f"{where}: Pinocchio cannot join the bodies into the scene's model: {exc}") from None
    model = models[0] if models else pin.Model()
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
