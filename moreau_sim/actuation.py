"""Joint torques tau (nv,) [N or N m] of a model: the scene's PD targets ([[actuators]], docs/scenes.md),
an MJCF body's <motor> and <position> actuators (mjcf_actuators.py) and a Python controller
f(t, q, u) -> tau (simulate(..., controller=f)), evaluated once per step at the
step's force evaluation (t_m, q_m, u_k) and clamped by the effort limits (docs/theory.md §2.1, §5.5).
The root joint of a body that is not fixed to the world (free, planar, ...) is never actuated."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .joints import find_joint, one_dof
from . import mjcf_actuators
from .errors import SceneError, SimulationError
from .options import require
from .prescribed import Schedule, constant, parse_schedule

Controller = Callable[[float, np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class PDGroup:
    """One [[actuators]] entry resolved on the model: joints' q and v indices, gains kp [N m/rad or
    N/m] and kd [N m s/rad or N s/m], the target position schedule and the target velocity schedule
    (None: the target's own derivative), the entry's effort clamp (inf: none)."""

    name: str
    q_index: np.ndarray
    v_index: np.ndarray
    kp: float
    kd: float
    target: Schedule
    velocity: Schedule | None
    effort: float
    joint_names: tuple[str, ...] = ()

    def torque(self, t: float, q: np.ndarray, u: np.ndarray) -> np.ndarray:
        x, xd = self.target.at(t)
        if self.velocity is not None:
            xd = self.velocity.at(t)[0]
        tau = self.kp * (x - q[self.q_index]) + self.kd * (xd - u[self.v_index])
        return np.clip(tau, -self.effort, self.effort)

    def describe(self) -> list[dict]:
        name = "[[actuators]]" + self.name.rpartition("[[actuators]]")[2]  # without the scene's path
        return [{"name": name, "joint": j, "kind": "pd", "kp": self.kp, "kd": self.kd,
                 "target": self.target.kind, "effort": None if not np.isfinite(self.effort) else self.effort}
                for j in self.joint_names]


class Actuation:
    """tau(t, q, u) of one model. limit (nv,): the effort limit of each velocity row [N or N m]
    (inf: none); root (nv,) bool: the rows of unfixed root joints, never actuated, named by
    root_names for errors."""

    def __init__(self, nv: int, limit: np.ndarray, root: np.ndarray, root_names: str, groups: tuple[PDGroup, ...],
                 controller: Controller | None = None):
        self.nv, self.limit, self.root, self.root_names = nv, limit, root, root_names
        self.groups, self.controller = groups, controller
        self.replay: tuple | None = None  # (t, q, u, tau) of a step the compiled run handed back (compiled_run.py)
        self._clamped = bool(np.isfinite(limit).any())
        self._rooted = bool(root.any())

    def with_controller(self, controller: Controller | None) -> "Actuation":
        return Actuation(self.nv, self.limit, self.root, self.root_names, self.groups, controller)

    def torque(self, t: float, q: np.ndarray, u: np.ndarray) -> np.ndarray:
        """tau [N or N m] at time t [s], configuration q and velocity u, clamped by the effort limits."""
        tau = np.zeros(self.nv)
        for g in self.groups:
            np.add.at(tau, g.v_index, g.torque(t, q, u))  # two actuators on one joint add
        if self.controller is not None:
            tau += self._call(t, q, u)
        if self._clamped:
            np.minimum(tau, self.limit, out=tau)
            np.maximum(tau, -self.limit, out=tau)
        return tau

    def describe(self) -> list[dict]:
        """One dict per actuated joint of each group (moreau-sim info): name, joint, kind, gains, limits;
        effort_limits: the model's clamp of each actuated joint (None: none)."""
        out = [d for g in self.groups for d in g.describe()]
        for d, vi in zip(out, [int(v) for g in self.groups for v in g.v_index]):
            d["effort_limit"] = None if not np.isfinite(self.limit[vi]) else float(self.limit[vi])
        return out

    def _call(self, t: float, q: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The controller's torques, checked (one line naming what is wrong); it sees read-only views."""
        if self.replay is not None:  # the compiled run asked the controller for this step already
            t0, q0, u0, f0 = self.replay
            self.replay = None
            if t0 == t and np.array_equal(q0, q) and np.array_equal(u0, u):
                return f0
        qc, uc = q.view(), u.view()
        qc.flags.writeable = uc.flags.writeable = False
        try:
            f = self.controller(t, qc, uc)
        except SimulationError:
            raise
        except Exception as exc:  # noqa: BLE001 - the user's function: name it, one line
            raise self.failure(t, exc) from None
        return self.checked(t, f)

    def failure(self, t: float, exc: BaseException) -> BaseException:
        """What the run raises where the controller raised `exc` at time t [s]: an Exception as one line naming
        the step's time, a SimulationError or a BaseException (KeyboardInterrupt) as it is."""
        if isinstance(exc, SimulationError) or not isinstance(exc, Exception):
            return exc
        return SimulationError(f"the controller raised {type(exc).__name__}: {exc} (at t = {t:.6g} s)")

    def checked(self, t: float, f) -> np.ndarray:
        """The controller's answer `f` at time t [s] as (nv,) floats [N or N m], or a SimulationError (one line
        naming the step's time): not convertible, the wrong shape, not finite, a torque on a root row."""
        try:
            f = np.asarray(f, dtype=float)
        except SimulationError:
            raise
        except Exception as exc:  # noqa: BLE001 - the user's object: name it, one line
            raise self.failure(t, exc) from None
        if f.shape != (self.nv,):
            raise SimulationError(f"the controller returned shape {f.shape}, expected ({self.nv},) "
                                  f"(one torque per velocity row, nv = {self.nv}) at t = {t:.6g} s")
        if not np.isfinite(f).all():
            raise SimulationError(f"the controller returned a non-finite torque at t = {t:.6g} s")
        if self._rooted and f[self.root].any():
            raise SimulationError(f"the controller returned a torque on the rows of a root joint that is not "
                                  f"fixed ({self.root_names}) at t = {t:.6g} s: floating bases are not actuated")
        return f


def refuse_driven(model, integrator: str) -> None:
    """SceneError (one line) if `model` has joint torques or a moving static: the event-driven and
    adaptive integrators do not take them."""
    if model.actuation is not None or model.prescribed is not None:
        what = "joint torques (a controller or [[actuators]])" if model.actuation is not None else "a moving static"
        raise SceneError(f"{model.scene.name}: integrator {integrator!r} does not take {what}: "
                         "use integrator = \"time-stepping\"")


def effort_limits(effort: np.ndarray) -> np.ndarray:
    """The URDF effort limits as clamps: a limit that is not finite and positive (Pinocchio's 1.8e308 of a
    joint without one, and the effort = "0" many hand-written URDFs carry) is no clamp."""
    e = np.asarray(effort, float).copy()
    e[~(np.isfinite(e) & (e > 0.0) & (e < 1e300))] = np.inf
    return e


_FLOATING = ("free", "planar", "translation")  # root joints that are a floating base, never actuated


def build(pm, bodies, actuators, q0: np.ndarray, *, always: bool = False, mjcf: dict | None = None,
          where: str = "") -> Actuation | None:
    """The Actuation of a model (None without [[actuators]] or MJCF actuators): pm the Pinocchio model, bodies
    the model's BodyInfo, actuators the scene's, q0 the initial configuration (the default target); mjcf: the
    MJCF file of each body read from one (by body name), whose <actuator> is read; where: the scene file.
    always: an Actuation even without entries (a controller's). Raises SceneError naming the entry and field."""
    nv = pm.nv
    root = np.zeros(nv, bool)
    names = []
    for b in bodies:
        if b.root_joint.value in _FLOATING and b.joints:
            jm = pm.joints[b.joints[0]]
            root[jm.idx_v:jm.idx_v + jm.nv] = True
            names.append(pm.names[b.joints[0]])
    groups: list = []
    controls: dict[str, list] = {}  # body -> its [[actuators]] entries that give MJCF actuators' ctrl
    for a in actuators:
        if a.mjcf is not None:
            controls.setdefault(a.body, []).append(a)
    for info in bodies:
        if info.name not in (mjcf or {}):
            if info.name in controls:
                raise SceneError(f"{controls[info.name][0].where} mjcf: the body is not read from an MJCF file: "
                                 "drive its joints with kp and target")
            continue
        specs = mjcf_actuators.read(mjcf[info.name], f"{where} ({info.name})")
        ctrl = _controls(specs, controls.get(info.name, []))
        if specs:
            groups.append(mjcf_actuators.build(pm, info, specs, ctrl, f"{where} ({info.name})"))
    for a in actuators:
        if a.mjcf is not None:
            continue
        info = next(b for b in bodies if b.name == a.body)
        own = [j for j in info.joints if not (root[pm.joints[j].idx_v] and j == info.joints[0])]
        if a.joints is None:
            joints = [j for j in own if one_dof(pm, j)]
            require(bool(joints), f"{a.where} joints", "the body has no 1-dof joint to actuate")
        else:
            joints = []
            for name in a.joints:
                j = find_joint(pm, a.body, name)
                require(j is not None, f"{a.where} joints",
                        f"'{name}' names no joint of {a.body} (its joints: "
                        f"{[pm.names[j].split('/', 1)[1] for j in own]})")
                require(j in own, f"{a.where} joints", f"'{name}' is the root joint of a floating base: not actuated")
                require(one_dof(pm, j), f"{a.where} joints",
                        f"'{name}' is not a 1-dof revolute or prismatic joint (nq = {pm.joints[j].nq})")
                joints.append(j)
        qi = np.array([pm.joints[j].idx_q for j in joints])
        vi = np.array([pm.joints[j].idx_v for j in joints])
        n = len(joints)
        target = constant(q0[qi]) if a.target is None else parse_schedule(a.target, n, f"{a.where} target", key="q")
        velocity = None if a.velocity is None else parse_schedule(a.velocity, n, f"{a.where} velocity", key="u")
        groups.append(PDGroup(a.where, qi, vi, a.kp, a.kd, target, velocity,
                              np.inf if a.effort is None else a.effort, tuple(pm.names[j] for j in joints)))
    if not groups and not always:
        return None
    return Actuation(nv, effort_limits(pm.effortLimit), root, ", ".join(names) or "none", tuple(groups))


def _controls(specs, entries) -> dict:
    """{MJCF actuator name: its ctrl schedule} from the scene's [[actuators]] entries with `mjcf` of one body."""
    out: dict = {}
    names = [s.name for s in specs]
    for a in entries:
        chosen = names if a.mjcf == "all" else list(a.mjcf)
        require(bool(chosen), f"{a.where} mjcf", "the body's MJCF file has no <actuator>")
        for n in chosen:
            require(n in names, f"{a.where} mjcf", f"'{n}' names no MJCF actuator of {a.body} (its actuators: {names})")
            require(n not in out, f"{a.where} mjcf", f"'{n}' is given a ctrl by two entries")
        sched = parse_schedule(a.ctrl, len(chosen), f"{a.where} ctrl", key="ctrl")
        for k, n in enumerate(chosen):
            out[n] = _component(sched, k)
    return out


def _component(s: Schedule, k: int) -> Schedule:
    """Component k of a schedule, as a schedule of one component."""
    pick = (lambda v: v[..., k:k + 1]) if s.n > 1 else (lambda v: v)
    return Schedule(s.kind, pick(s.x), s.t, pick(s.amplitude) if s.amplitude.size else s.amplitude, s.frequency,
                    s.phase, None if s.rate is None else pick(s.rate))


def for_controller(pm, bodies, actuation: Actuation | None, controller: Controller | None) -> Actuation | None:
    """The model's actuation with a Python controller added (or removed: None)."""
    if actuation is None:
        if controller is None:
            return None
        actuation = build(pm, bodies, (), np.zeros(pm.nq), always=True)
    return actuation.with_controller(controller)
