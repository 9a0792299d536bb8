"""Prescribed joint motion, the rheonomic joint (docs/theory.md §2.13): the 1-dof joints whose q follow a
schedule ([[drives]], docs/scenes.md), as the model holds them (Model.drive, made by build_model and checked
here). What a driven step does with them is drive_step.py's."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .joints import find_joint, one_dof
from .errors import SceneError
from .limits import UNLIMITED
from .prescribed import Schedule

_FLOATING = ("free", "planar", "translation")


@dataclass(frozen=True)
class Driven:
    """One driven joint: its velocity row, its q index, q(0) [m or rad] and its schedule x(t); the joint
    follows q(t) = q(0) + x(t) - x(0)."""

    name: str
    idx_q: int
    idx_v: int
    q0: float
    schedule: Schedule

    def position(self, t: float) -> float:
        return self.q0 + float(self.schedule.at(t)[0][0] - self.schedule.at(0.0)[0][0])


class Drive:
    """The driven joints of a model."""

    def __init__(self, nv: int, joints: tuple[Driven, ...]):
        self.joints = joints
        self.d = np.array([j.idx_v for j in joints])
        self.r = np.setdiff1d(np.arange(nv), self.d)

    def velocity(self, t: float) -> np.ndarray:
        return np.array([float(j.schedule.at(t)[1][0]) for j in self.joints])


def build(scene, pm, bodies, actuation, q0: np.ndarray, u0: np.ndarray, limits: tuple) -> Drive | None:
    """The Drive of a model (model.build_model: Model.drive; None without [[drives]]) from the scene, its
    Pinocchio model pm, the bodies' BodyInfo, the actuation (None: none), q0, u0 and the joint limits.
    SceneError naming the [[drives]] entry and field."""
    specs = getattr(scene, "drives", ())
    if not specs:
        return None
    seen: dict[int, str] = {}
    joints = []
    acted = set() if actuation is None else {int(v) for g in actuation.groups for v in g.v_index}
    for s in specs:
        info = next((b for b in bodies if b.name == s.body), None)
        if info is None:
            raise SceneError(f"{s.where} body: names no body of the scene ({s.body!r})")
        j = find_joint(pm, s.body, s.joint)
        if j is None:
            raise SceneError(f"{s.where} joint: '{s.joint}' names no joint of {s.body} (its joints: "
                             f"{[pm.names[j].split('/', 1)[1] for j in info.joints]})")
        jm = pm.joints[j]
        if j == info.joints[0] and info.root_joint.value in _FLOATING:
            raise SceneError(f"{s.where} joint: '{s.joint}' is the root joint of a floating base: not driven")
        if not one_dof(pm, j):
            raise SceneError(f"{s.where} joint: '{s.joint}' is not a 1-dof revolute or prismatic joint")
        if jm.idx_v in seen:
            raise SceneError(f"{s.where} joint: '{s.joint}' is driven twice (also by {seen[jm.idx_v]})")
        if jm.idx_v in acted:
            raise SceneError(f"{s.where} joint: '{s.joint}' also has an actuator ([[actuators]]): "
                             "a driven joint takes none")
        xdot0 = float(s.motion.at(0.0)[1][0])
        if abs(u0[jm.idx_v] - xdot0) > 1e-12 * (1.0 + abs(xdot0)):
            raise SceneError(f"{s.where} motion: the body's u0 for '{s.joint}' ({u0[jm.idx_v]:.6g}) must be the "
                             f"motion's velocity at t = 0 ({xdot0!r}): give it in the body's u0")
        seen[jm.idx_v] = s.where
        d = Driven(pm.names[j], jm.idx_q, jm.idx_v, float(q0[jm.idx_q]), s.motion)
        _check_range(d, s, pm, scene.options.duration, any(lim.joint == j for lim in limits))
        joints.append(d)
    return Drive(pm.nv, tuple(sorted(joints, key=lambda x: x.idx_v)))


def _check_range(d: Driven, s, pm, duration: float, limited: bool) -> None:
    """SceneError if the trajectory over [0, duration] leaves the joint's limits (when they are on)."""
    if not limited:
        return
    lo, hi = float(pm.lowerPositionLimit[d.idx_q]), float(pm.upperPositionLimit[d.idx_q])
    lo, hi = (lo if abs(lo) < UNLIMITED else -np.inf), (hi if abs(hi) < UNLIMITED else np.inf)
    sc = s.motion
    ts = np.concatenate([np.linspace(0.0, duration, 2001), sc.t[(sc.t >= 0) & (sc.t <= duration)]])
    q = np.array([d.position(t) for t in ts])
    if q.min() < lo or q.max() > hi:
        raise SceneError(f"{s.where} motion: the trajectory ({q.min():.6g} .. {q.max():.6g}) leaves the joint's "
                         f"limits [{lo:.6g}, {hi:.6g}] (set joint_limits = false on the body to drive past them)")


def refuse(model, integrator: str) -> None:
    """SceneError (one line) if the model has a driven joint: only the time-stepping integrator takes one."""
    if model.drive is not None:
        raise SceneError(f"{model.scene.name}: integrator {integrator!r} does not take a driven joint "
                         "([[drives]]): use integrator = \"time-stepping\"")

