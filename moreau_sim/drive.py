"""Prescribed joint motion, the rheonomic joint (docs/theory.md §2.13): a 1-dof joint whose q follows a
schedule ([[drives]], docs/scenes.md). A step splits the velocity rows into free (r) and driven (d) ones,
takes u_d from xdot(t_k) to xdot(t_{k+1}), solves the impact law in r-space with the driven rows'
contribution as a constraint rate (§2.9), and books the drive's work (§5.5)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .errors import SceneError, SimulationError
from .options import Bias
from .results import MIDPOINT_ITERATIONS, MIDPOINT_TOLERANCE
from .limits import UNLIMITED
from .qp import ordered
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


@dataclass(frozen=True)
class DriveStep:
    """What a driven step knows (stepper.assemble): the driven rows d (indices) and free rows r, the
    driven velocity at the step's end xdot = xdot(t_{k+1}) [m/s or rad/s], M = M(q_m), the unconstrained free
    velocity u_f, the driven one u_c (u_c,d = xdot), u_k; work_free: the drive's work in the contact-free step [J]."""

    r: np.ndarray
    d: np.ndarray
    xdot: np.ndarray
    M: np.ndarray
    u_f: np.ndarray
    u_c: np.ndarray
    u_k: np.ndarray
    work_free: float

    def work(self, u_next: np.ndarray) -> float:
        """W_p = ubar_d' [M (u_{k+1} - u_f)]_d, ubar_d = (u_d^k + xdot)/2: the work of the drive's reaction
        (and of the percussions on the driven rows beyond their rate's share, booked in W_o) [J] (§5.5)."""
        ubar = 0.5 * (self.u_k[self.d] + self.xdot)
        return float(ordered(ubar, (self.M @ (u_next - self.u_f))[self.d]))

    def reduced(self, pb):
        """The problem in r-space: M_rr, W_r, u_r, u_free_r, v_free_r, and the rate W_d' (xdot + e u_d^k)/(1 + e)
        added (§2.9, §2.13).
        A contact that only driven rows move (W_r = 0) is left out where it opens or holds (rate >= 0); where
        the drive closes it (rate < 0) nothing can stop it: SimulationError naming the pair."""
        if pb.pieces is not None:
            raise SimulationError("a corner impact (docs/theory.md §3) with a driven joint: not supported")
        r, d = self.r, self.d
        Mrr = pb.M[np.ix_(r, r)]
        rate = pb.W[d].T @ ((self.xdot + pb.e * self.u_k[d]) / (1.0 + pb.e))  # (gamma^{k+1} + e gamma^k)/(1 + e)
        rate = rate if pb.rate is None else pb.rate + rate
        W, contacts = pb.W[r], pb.contacts
        rigid = ~(W != 0.0).any(axis=0)
        if rigid.any():
            if (rate[rigid] < 0.0).any():
                i = int(np.flatnonzero(rigid & (rate < 0.0))[0])
                raise SimulationError(f"a driven joint drives collision pair {int(contacts.pair[i])} (contact gap "
                                      f"{contacts.g[i]:.3g} m) into an obstacle that nothing else can move: a "
                                      "prescribed motion cannot be stopped (change the trajectory or the scene)")
            keep = ~rigid
            W, contacts, rate = W[:, keep], contacts.select(keep), rate[keep]
        return replace(pb, u=pb.u[r], u_free=pb.u_free[r], v_free=pb.v_free[r], M=Mrr, Minv=np.linalg.inv(Mrr),
                       W=W, rate=rate, contacts=contacts)

    def expanded(self, pb, imp):
        """The r-space solution made whole: u_{k+1} = (u_r^{k+1}, xdot), W with its driven rows zeroed (the
        position correction moves the free rows only), the QP's problem embedded (M with a zero d block: the
        ledger's D and L of the free rows), obstacle_work + W_p."""
        r, d, nv = self.r, self.d, len(self.u_k)
        u = np.empty(nv)
        u[r], u[d] = imp.u_next, self.xdot
        W = np.zeros((nv, imp.W.shape[1]))
        W[r] = imp.W
        q = imp.qp
        if q.M is not None:
            M = np.zeros((nv, nv))
            M[np.ix_(r, r)] = q.M
            q = replace(q, M=M, W=W, v=self._embed(q.v), v0=self._embed(q.v0))
        else:
            q = replace(q, v=self._embed(q.v))
        return replace(imp, u_next=u, W=W, qp=q, obstacle_work=imp.obstacle_work + self.work(u))

    def for_correction(self, pb):
        """The position correction's problem (§2.5, free rows only): M block-diagonal (M_rr, M_dd), so that
        with the driven rows of W zero the displacement leaves the driven joints where they are."""
        r, d = self.r, self.d
        M = np.zeros_like(self.M)
        M[np.ix_(r, r)] = self.M[np.ix_(r, r)]
        M[np.ix_(d, d)] = self.M[np.ix_(d, d)]
        return replace(pb, M=M, Minv=np.linalg.inv(M))

    def _embed(self, v: np.ndarray) -> np.ndarray:
        out = np.empty(len(self.u_k))
        out[self.r], out[self.d] = v, self.xdot
        return out


class Drive:
    """The driven joints of a model."""

    def __init__(self, nv: int, joints: tuple[Driven, ...]):
        self.joints = joints
        self.d = np.array([j.idx_v for j in joints])
        self.r = np.setdiff1d(np.arange(nv), self.d)

    def velocity(self, t: float) -> np.ndarray:
        return np.array([float(j.schedule.at(t)[1][0]) for j in self.joints])

    def start(self, model, data, q_m: np.ndarray, u: np.ndarray, u_free: np.ndarray, t_m: float, h: float,
              M: np.ndarray | None = None, tau: np.ndarray | None = None) -> DriveStep:
        """The driven step at (t_m, q_m, u_k) of size h [s] from the unconstrained free velocity u_free:
        u_c,r = u_f,r + M_rr^-1 M_rd (u_f,d - xdot), u_c,d = xdot = xdot(t_{k+1}) (M_rr (u_c,r - u_k,r) =
        h (tau_r - b_r) - M_rd (xdot - u_k,d)); with the midpoint bias b at the driven step's own mean velocity
        (a fixed point, as stepper.free_velocity's). tau: the step's torques (None: none)."""
        if M is None:
            M = model.forest.mass_matrix(data.kinematics, q_m)
        r, d = self.r, self.d
        xdot = self.velocity(t_m + 0.5 * h)
        Mrr, Mrd = M[np.ix_(r, r)], M[np.ix_(r, d)]
        u_c = np.empty_like(u_free)
        u_c[d] = xdot
        u_c[r] = u_free[r] + np.linalg.solve(Mrr, Mrd @ (u_free[d] - xdot))
        if model.velocity_bias and model.options.bias is Bias.MIDPOINT:  # b at the driven step's own mean (§2.4)
            zero = np.zeros(len(u)) if tau is None else tau
            scale = MIDPOINT_TOLERANCE * (1.0 + float(np.abs(u).max()))
            for _ in range(MIDPOINT_ITERATIONS):
                u_free = u + h * model.forest.acceleration(data.kinematics, q_m, 0.5 * (u + u_c), zero)
                nxt = u_free[r] + np.linalg.solve(Mrr, Mrd @ (u_free[d] - xdot))
                done = float(np.abs(nxt - u_c[r]).max(initial=0.0)) <= scale
                u_c[r] = nxt
                if done:
                    break
        ubar = 0.5 * (u[d] + xdot)
        work_free = float(ordered(ubar, (M @ (u_c - u_free))[d]))
        return DriveStep(r, d, xdot, M, u_free, u_c, u, work_free)


def of(model) -> Drive | None:
    """The model's Drive (None without [[drives]]), built once per model (SceneError naming the field)."""
    cached = model.__dict__.get("_drive", False)
    if cached is not False:
        return cached
    drive = build(model)
    object.__setattr__(model, "_drive", drive)
    return drive


def build(model) -> Drive | None:
    specs = getattr(model.scene, "drives", ())
    if not specs:
        return None
    pm = model.pin
    seen: dict[int, str] = {}
    joints = []
    acted = set() if model.actuation is None else {int(v) for g in model.actuation.groups for v in g.v_index}
    for s in specs:
        info = next((b for b in model.bodies if b.name == s.body), None)
        if info is None:
            raise SceneError(f"{s.where} body: names no body of the scene ({s.body!r})")
        full = f"{s.body}/{s.joint}"
        if not pm.existJointName(full):
            raise SceneError(f"{s.where} joint: '{s.joint}' names no joint of {s.body} (its joints: "
                             f"{[pm.names[j].split('/', 1)[1] for j in info.joints]})")
        j = pm.getJointId(full)
        jm = pm.joints[j]
        if j == info.joints[0] and info.root_joint.value in _FLOATING:
            raise SceneError(f"{s.where} joint: '{s.joint}' is the root joint of a floating base: not driven")
        if not (jm.nq == 1 and jm.nv == 1):
            raise SceneError(f"{s.where} joint: '{s.joint}' is not a 1-dof revolute or prismatic joint")
        if jm.idx_v in seen:
            raise SceneError(f"{s.where} joint: '{s.joint}' is driven twice (also by {seen[jm.idx_v]})")
        if jm.idx_v in acted:
            raise SceneError(f"{s.where} joint: '{s.joint}' also has an actuator ([[actuators]]): "
                             "a driven joint takes none")
        xdot0 = float(s.motion.at(0.0)[1][0])
        if abs(model.u0[jm.idx_v] - xdot0) > 1e-12 * (1.0 + abs(xdot0)):
            raise SceneError(f"{s.where} motion: the body's u0 for '{s.joint}' ({model.u0[jm.idx_v]:.6g}) must be the "
                             f"motion's velocity at t = 0 ({xdot0!r}): give it in the body's u0")
        seen[jm.idx_v] = s.where
        d = Driven(pm.names[j], jm.idx_q, jm.idx_v, float(model.q0[jm.idx_q]), s.motion)
        _check_range(d, s, pm, model.scene.options.duration,
                     any(lim.joint == j for lim in model.limits))
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
    if of(model) is not None:
        raise SceneError(f"{model.scene.name}: integrator {integrator!r} does not take a driven joint "
                         "([[drives]]): use integrator = \"time-stepping\"")

