"""The midpoint Moreau step (docs/theory.md §2.1) as named stages: assemble (q_m, the closed contacts, M, W,
u_free, v_free) -> solve_impact (the law, §1.3 and §2.7; a corner's set-valued law, §3) -> q_{k+1} ->
correct_positions (§2.5) -> cap_energy (§2.10). The options' rules on top of the plain step: §2.2-2.7. The compiled step
(compiled.py) takes the steps it covers first."""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, replace

import numpy as np
import pinocchio as pin

from . import compiled, drive_step, qp
from .constraints import CornerPieces, assemble_constraints, closed_limits, corner_faces
from .contacts import NO_CONTACTS, Contacts, FeatureKind, detect, pair_distances
from .corners import MAX_PIECES, corner_law
from .data import Data
from .energy import kinetic, potential
from .errors import SimulationError
from .law import ENERGY_ROUNDOFF, outcome, percussion, project, restitution_bounds
from .limits import limit_gaps
from .model import Model
from .options import Bias, Options, PositionCorrection, QPForm, StepImpl, Tunnelling
from .qp import QPResult
from .results import HOLD, MIDPOINT_ITERATIONS, MIDPOINT_TOLERANCE, RESTING, StepResult
from .sums import ordered
from .state import State
from .tunnelling import swept_detect

_EMPTY = np.zeros(0)


@dataclass(frozen=True, slots=True)
class ContactProblem:
    """What a step knows before the impact law: h [s], e, the start (q, u) = (q_k, u_k), the
    midpoint q_m, the contacts closed at q_m, u_free [velocity]; and when a contact is closed
    (`closed`): M = M(q_m), Minv, W (nv, m) the rows of the distinct smooth contacts, the corner
    pieces (or None), v_free = (u_free + e u_k)/(1 + e). Without a closed contact those are None.
    tau: the joint torques of the step [N or N m] (None: no actuation); rate: dg_i/dt of the
    contacts against a moving static [m/s] (None: none; docs/theory.md §2.9); drive: the driven joints' step
    (drive_step.DriveStep; u_free then has u_d = xdot(t_{k+1}), §2.13; None: none)."""

    h: float
    e: float
    q: np.ndarray
    u: np.ndarray
    q_m: np.ndarray
    contacts: Contacts
    u_free: np.ndarray
    v_free: np.ndarray | None = None
    M: np.ndarray | None = None
    Minv: np.ndarray | None = None
    W: np.ndarray | None = None
    pieces: CornerPieces | None = None
    tau: np.ndarray | None = None
    rate: np.ndarray | None = None
    drive: drive_step.DriveStep | None = None  # a step with a driven joint (drive_step.py, docs/theory.md §2.13)
    blocks: tuple | None = None  # M's diagonal blocks by tree (Forest.blocks): the projections' islands (§1.3); None
    # in a driven step (its reduced M; src/step.cpp passes no blocks there either)

    @property
    def closed(self) -> bool:
        return self.M is not None


@dataclass(frozen=True, slots=True)
class ImpactSolution:
    """The law applied to a ContactProblem: u_next = u_{k+1}; the contacts that can push and their
    rows W (at a corner: the smooth contacts, then one entry per face of the chosen piece(s), kind
    CORNER); P [N s] aligned with them; gamma_minus = W'u_k, gamma_plus = W'u_{k+1} [m/s];
    contact_work W_c = sum_i P_i (gamma_plus_i + gamma_minus_i)/2 [J] (docs/theory.md §5); qp the
    QP result; branch (solution, chosen index, u_plus of each candidate) at a corner impact with
    several admissible outcomes, else None."""

    u_next: np.ndarray
    contacts: Contacts
    W: np.ndarray
    P: np.ndarray
    gamma_minus: np.ndarray
    gamma_plus: np.ndarray
    contact_work: float
    qp: QPResult
    branch: tuple | None = None
    obstacle_work: float = 0.0


def step(model: Model, data: Data, state: State, *, h: float | None = None, e: float | None = None,
         t_next: float | None = None, form: QPForm | None = None, eps: float | None = None,
         corner_choice: int | None = None) -> StepResult:
    """Advance `state` by one midpoint Moreau step (docs/theory.md §2).

    h [s], e: step and restitution (default: model.options.dt and .restitution).
    t_next: the new time (default state.t + h; the loop passes k h to avoid round-off drift).
    form / eps: the impact QP's form and tolerance (default: the model's options).
    corner_choice: at a corner with several admissible outcomes, continue with candidate number
    corner_choice (in the order of corners.stationary_points) instead of the options' policy.
    A failed QP is returned in the result (qp.ok False); :func:`simulate` turns it into an error."""
    opts = model.options
    h = opts.dt if h is None else h
    e = opts.restitution if e is None else e
    t1 = state.t + h if t_next is None else t_next
    tau = None if model.actuation is None else torque(model, state, h)  # once a step, whichever step takes it
    if (opts.step_impl is StepImpl.COMPILED and form is None and eps is None and corner_choice is None
            and compiled.available()):  # (on the forest's Datas, as this step: docs/theory.md §2.12)
        r = compiled.step(model, data, state, h, e, t1, tau)  # None: a step the compiled one does not cover
        if r is not None:
            return r
    pb = assemble(model, data, state, h=h, e=e, tau=tau)
    start = warm_start(data, pb.contacts) if pb.closed and pb.pieces is None else None
    data.active_rows = frozenset()  # until this step's projection says otherwise (keep_active)
    if not pb.closed:
        q_next = pin.integrate(model.pin, pb.q_m, 0.5 * h * pb.u_free)
        return StepResult(State(t1, q_next, pb.u_free), NO_CONTACTS, _EMPTY, _EMPTY, _EMPTY, 0.0, None,
                          u_free=pb.u_free, tau=pb.tau, obstacle_work=0.0 if pb.drive is None else pb.drive.work_free)
    ds = pb.drive  # a driven joint (§2.13): the law in the free rows, then u_{k+1} = (u_r, xdot(t_{k+1}))
    imp = solve_impact(pb if ds is None else ds.reduced(pb), opts, form=form, eps=eps, corner_choice=corner_choice,
                       start=start)
    imp = imp if ds is None else ds.expanded(pb, imp)
    if pb.pieces is None:
        keep_active(data, imp)
    q_next = pin.integrate(model.pin, pb.q_m, 0.5 * h * imp.u_next)
    corr, u_law = 0.0, None
    if opts.position_correction is PositionCorrection.PROJECTION and imp.qp.ok:  # a failed QP: simulate names it
        q_next, corr, u_c = correct_positions(model, data, pb if ds is None else ds.for_correction(pb), imp, q_next)
        if u_c is not imp.u_next:  # a paid lift (§2.5): the ledger measures the law on u_{k+1} before it (§5.2)
            u_law = imp.u_next
            imp = replace(imp, u_next=u_c, gamma_plus=ordered(imp.W.T, u_c))
    if imp.qp.ok and ds is None:  # §2.10 (a driven joint: §2.13)
        imp = cap_energy(model, data, pb, imp, q_next, corr)
    return StepResult(State(t1, q_next, imp.u_next), imp.contacts, imp.P, imp.gamma_minus, imp.gamma_plus,
                      imp.contact_work, imp.qp, imp.branch, corr, u_free=pb.u_free, tau=pb.tau,
                      obstacle_work=imp.obstacle_work, u_law=u_law,
                      drive_work_free=0.0 if ds is None else ds.work_free)


def torque(model: Model, state: State, h: float) -> np.ndarray:
    """The step's joint torques tau [N or N m], evaluated at (t_m, q_m, u_k) (docs/theory.md §2.1)."""
    q_m = pin.integrate(model.pin, state.q, 0.5 * h * state.u)
    return model.actuation.torque(state.t + 0.5 * h, q_m, state.u)


def step_in_place(model: Model, data: Data, t: float, q: np.ndarray, u: np.ndarray, *, h: float | None = None,
                  e: float | None = None) -> StepView:
    """step() without its result objects: overwrites q and u (float arrays of nq and nv) with q_{k+1}, u_{k+1}
    of the step from time t [s] (h [s], e: default the model's options) and returns a StepView of what the
    step did. Where the compiled step takes the step (§2.8) nothing else is built; elsewhere it is step()
    itself. Same numbers as step(), bit for bit."""
    opts = model.options
    h = opts.dt if h is None else h
    e = opts.restitution if e is None else e
    tau = None if model.actuation is None else torque(model, State(t, q, u), h)
    if opts.step_impl is StepImpl.COMPILED and compiled.available():
        r = compiled.raw_step(model, data, q, u, h, e, tau, t=t)
        if r is not None:
            q[:], u[:] = compiled.next_state(data, r)
            return StepView(model, data, t + h, r, None, tau)
    res = step(model, data, State(t, q.copy(), u.copy()), h=h, e=e)
    q[:], u[:] = res.state.q, res.state.u
    return StepView(model, data, t + h, None, res, tau)


class StepView:
    """What step_in_place did: the new time `t` [s], how many contacts were closed, whether the step's QPs
    succeeded, and the whole StepResult built on demand (`result()`; the compiled step's arrays are its own
    buffers, one pair per step, so a view stays valid after the next step)."""

    __slots__ = ("_model", "_data", "t", "_r", "_res", "_tau")

    def __init__(self, model: Model, data: Data, t: float, r, res: StepResult | None, tau: np.ndarray | None):
        self._model, self._data, self.t, self._r, self._res, self._tau = model, data, t, r, res, tau

    @property
    def n_contacts(self) -> int:
        return self._r.m if self._res is None else self._res.contacts.m

    @property
    def ok(self) -> bool:
        """False where a QP of the step failed (step(): qp.ok); simulate turns that into an error."""
        return self._res is None or self._res.qp is None or self._res.qp.ok

    def result(self) -> StepResult:
        """The step's StepResult, as step() returns it."""
        if self._res is None:
            self._res = compiled.result(self._model, self._data, self._r, self.t, self._tau)
        return self._res


def assemble(model: Model, data: Data, state: State, *, h: float, e: float,
             tau: np.ndarray | None = None) -> ContactProblem:
    """The step's problem: q_m, the contacts closed at q_m (swept ones added where the options ask,
    docs/theory.md §2.6), and if any: M, M^-1, W, corner pieces (constraints.assemble_constraints),
    u_free and v_free. Leaves data's kinematics at q_m. tau: the step's joint torques (default: the
    model's, evaluated here; torque())."""
    q, u = state.q, state.u
    opts = model.options
    q_m = pin.integrate(model.pin, q, 0.5 * h * u)
    t_m = state.t + 0.5 * h  # the force evaluation: torques and obstacles at (t_m, q_m, u_k), §2.1, §2.9
    if model.prescribed is not None:
        model.prescribed.place(model.geom, t_m)
    if tau is None and model.actuation is not None:
        tau = model.actuation.torque(t_m, q_m, u)
    # how far a vertex can move in the step (|u| times the largest lever arm): a thinner pair may be passed
    # through; a corner struck within the step may have crossed one face plane by up to its two bodies' own
    # (Forest.joint_travel: per tree)
    travel = h * float(np.abs(u).max(initial=0.0)) * model.reach
    contacts = detect(model, data, q_m, corner_margin=model.forest.joint_travel(u, h, model.reach))
    if opts.tunnelling is Tunnelling.ALWAYS or (opts.tunnelling is Tunnelling.SWEPT and travel > model.thinnest_pair):
        contacts = swept_detect(model, data, q, u, h, q_m, contacts)  # a thin obstacle crossed in the step
    if model.limits:  # the joint limits closed at q_m: constraints of the same law (limits.py)
        contacts = contacts.concat(closed_limits(model, q_m, opts.contact_tolerance))
    drive = model.drive
    if contacts.m == 0 and not contacts.corners:
        u_free = free_velocity(model, data, q_m, u, h, opts.bias, tau)
        ds = None if drive is None else drive_step.start(drive, model, data, q_m, u, u_free, t_m, h, tau=tau)
        return ContactProblem(h, e, q, u, q_m, NO_CONTACTS, u_free if ds is None else ds.u_c, tau=tau, drive=ds)
    cs = assemble_constraints(model, data, q_m, contacts)
    Minv = model.forest.inverse_mass_matrix(data.kinematics, q_m)
    u_free = free_velocity(model, data, q_m, u, h, opts.bias, tau)
    ds = None if drive is None else drive_step.start(drive, model, data, q_m, u, u_free, t_m, h, cs.M, tau)
    u_free = u_free if ds is None else ds.u_c
    v_free = (u_free + e * u) / (1.0 + e)
    rate = None if model.prescribed is None else model.prescribed.rates(model.pairs, cs.contacts, t_m)
    return ContactProblem(h, e, q, u, q_m, cs.contacts, u_free, v_free, cs.M, Minv, cs.W, cs.pieces, tau, rate, ds,
                          model.forest.blocks if ds is None else None)


def free_velocity(model: Model, data: Data, q_m: np.ndarray, u: np.ndarray, h: float, bias: Bias,
                  tau: np.ndarray | None = None) -> np.ndarray:
    """u_free = u_k + h M(q_m)^-1 (tau - h(q_m, u_bar)) [velocity]: u_bar = u_k (EXPLICIT) or the fixed
    point u_bar = (u_k + u_free)/2 (MIDPOINT, docs/theory.md §2.4; a few ABA calls; exact for models
    whose bias does not depend on u, where it stops after one). tau: the step's joint torques [N or N m],
    fixed over the iteration (evaluated once, at (t_m, q_m, u_k): §2.1; None: zero)."""
    forest, kin = model.forest, data.kinematics
    zero = np.zeros(model.nv) if tau is None else tau
    u_free = u + h * forest.acceleration(kin, q_m, u, zero)
    if bias is Bias.EXPLICIT or not model.velocity_bias:
        return u_free
    scale = MIDPOINT_TOLERANCE * (1.0 + float(np.abs(u).max()))
    return midpoint_fixed_point(lambda v: forest.acceleration(kin, q_m, v, zero), u, h, u_free, scale)


def midpoint_fixed_point(acc, u: np.ndarray, h: float, u1: np.ndarray, tol: float) -> np.ndarray:
    """The midpoint bias's fixed point u1 = u + h acc((u + u1)/2) (docs/theory.md §2.4, §8), swept
    from u1 until a sweep changes it by at most tol, MIDPOINT_ITERATIONS sweeps at most."""
    for _ in range(MIDPOINT_ITERATIONS):
        nxt = u + h * acc(0.5 * (u + u1))
        done = float(np.abs(nxt - u1).max()) <= tol
        u1 = nxt
        if done:
            break
    return u1


def warm_start(data: Data, contacts) -> np.ndarray | None:
    """The projection's start above qp.SPARSE_ROWS rows (docs/theory.md §1.3): the rows whose contact's identity
    (pair, kind, feature) pushed in the last step's projection (data.active_rows, keep_active); a row without a
    match starts inactive. None at or below qp.SPARSE_ROWS rows (the cold start) or without a kept set."""
    prev = data.active_rows
    if contacts.m <= qp.SPARSE_ROWS or not prev:
        return None
    keys = zip(contacts.pair.tolist(), contacts.kind.tolist(), contacts.feature.tolist())
    return np.fromiter((k in prev for k in keys), bool, contacts.m)


def keep_active(data: Data, imp: ImpactSolution) -> None:
    """data.active_rows after a step's projection where it had more than qp.SPARSE_ROWS rows and solved: the
    identities of the rows of the active set's final set (its first pass's: independent rows by construction, so
    that the next start G_AA lam_A = r_A is not singular), or where piqp answered of its rows with lam_i > 0; else
    none (warm_start reads them at the next step; src/step.cpp keeps the same)."""
    c, res = imp.contacts, imp.qp
    if c.m <= qp.SPARSE_ROWS or not res.ok or len(res.lam) != c.m:
        data.active_rows = frozenset()
        return
    sel = np.flatnonzero(res.lam > 0.0 if res.active is None else res.active)
    data.active_rows = frozenset(zip(c.pair[sel].tolist(), c.kind[sel].tolist(), c.feature[sel].tolist()))


def solve_impact(pb: ContactProblem, options: Options, *, form: QPForm | None = None, eps: float | None = None,
                 corner_choice: int | None = None, start: np.ndarray | None = None) -> ImpactSolution:
    """The discrete impact law on a problem with closed contacts: the projection of v_free with the
    per-contact restitution bounds (docs/theory.md §2.7), or at a corner the set-valued law (§3)
    with the options' selection policy (or candidate `corner_choice`). start: the projection's warm start
    above qp.SPARSE_ROWS rows (warm_start; None: from nothing)."""
    u, e, W, contacts = pb.u, pb.e, pb.W, pb.contacts
    branch = None
    if pb.pieces is not None:
        res, contacts, W, branch = _corner_law(pb, options, corner_choice)
        gamma_minus = ordered(W.T, u)
    else:
        gamma_minus = ordered(W.T, u)
        if pb.rate is not None:  # a moving static: gamma = W'u + dg/dt (§2.9)
            gamma_minus = gamma_minus + pb.rate
        b = restitution_bounds(W, u, pb.u_free, gamma_minus, e, separating=options.separating,
                               slow_impacts=options.slow_impacts)
        if pb.rate is not None:
            b = -pb.rate if b is None else b - pb.rate
        res = project(pb.M, W, pb.v_free, b=b, Minv=pb.Minv, form=form or options.qp_form,
                      eps=eps or options.qp_tolerance, start=start, blocks=pb.blocks)
    u_next = outcome(res.v, u, e)
    P = percussion(res.lam, e)
    gamma_plus = ordered(W.T, u_next)
    obstacle_work = 0.0
    if pb.rate is not None and pb.pieces is None:
        gamma_plus = gamma_plus + pb.rate
        obstacle_work = -float(ordered(P, pb.rate))
    work = float(ordered(P, gamma_plus + gamma_minus)) * 0.5
    return ImpactSolution(u_next, contacts, W, P, gamma_minus, gamma_plus, work, res, branch, obstacle_work)


def cap_energy(model: Model, data: Data, pb: ContactProblem, imp: ImpactSolution, q_next: np.ndarray,
               corr: float = 0.0) -> ImpactSolution:
    """The energy cap of a contact step (docs/theory.md §2.10): T + V at (q_{k+1}, u_{k+1}) is never above
    E* + W_a + W_o beyond round-off (E* = E_k + min(W_c, 0) + corr, corr [J] the change of T + V the position
    correction made; W_a = h tau.(u_k + u_{k+1})/2 and W_o the work of the torques and of a moving static,
    §5.5; ENERGY_ROUNDOFF), plus max(S_k, 0) in a step that bounces under torques (bounces_under_torques; S_k
    the free step's own error, smooth_error). Where the step ends above it (the drift after the impact moves M(q)
    and V(q) along u_{k+1}, first order in h |Δu|), the velocities of the trees in contact (every entry of
    u_{k+1} of a kinematic tree one of the rows involves) are scaled by the alpha of _alpha; gamma_plus scales
    with them (signs kept). Steps that end at or below the bound are returned as they are."""
    T0, V0 = kinetic(model, data, pb.q, pb.u), potential(model, data, pb.q)
    T1, V1 = kinetic(model, data, q_next, imp.u_next), potential(model, data, q_next)
    target = (((T0 + V0) + min(imp.contact_work, 0.0)) + corr) + imp.obstacle_work  # W_o: P fixed, no alpha
    if bounces_under_torques(pb, imp):  # the smooth step's gain is the integrator's, not the impact's (§2.10)
        target = target + max(smooth_error(model, data, pb, T0 + V0), 0.0)
    f = None if pb.tau is None else (0.5 * pb.h) * pb.tau  # W_a = f.(u_k + u_{k+1})
    work = 0.0 if f is None else float(ordered(f, pb.u + imp.u_next))
    if T1 + V1 <= (target + work) + _roundoff(T0, V0, T1, V1):
        return imp
    u_S, u_R, a, T_R = _split(model, data, q_next, imp.u_next, (imp.W != 0.0).any(axis=1))
    if not a > 0.0:
        return imp
    b = (T1 - a) - T_R
    c = T_R - (target - V1)
    if f is not None:  # the torques' work is linear in alpha: f.(u_k + u_R) + alpha f.u_S
        b = b - float(ordered(f, u_S))
        c = c - float(ordered(f, pb.u + u_R))
    floor = 0.0
    if pb.rate is not None and pb.pieces is None:  # a moving static: gamma = alpha W'u_S + dg/dt keeps its sign
        wu = ordered(imp.W.T, u_S)
        for i in np.flatnonzero((pb.rate < 0.0) & (imp.gamma_plus >= 0.0) & (wu > 0.0)):
            floor = max(floor, float(-pb.rate[i] / wu[i]))
    alpha = _alpha(a, b, c, min(floor, 1.0))
    u_next = u_R + alpha * u_S
    gamma_plus = ordered(imp.W.T, u_next)
    if pb.rate is not None and pb.pieces is None:
        gamma_plus = gamma_plus + pb.rate
    return replace(imp, u_next=u_next, gamma_plus=gamma_plus)


def bounces_under_torques(pb: ContactProblem, imp: ImpactSolution) -> bool:
    """Whether the cap's bound allows the smooth step's gain (docs/theory.md §2.10): a step with torques in which
    a contact with a percussion leaves with gamma+ = -e gamma- != 0 (e > 0). Scaling it changes that bounce's
    restitution, which only the impact's own error, not the integrator's, may do."""
    return pb.tau is not None and pb.e > 0.0 and bool((imp.P > 0.0).any())


def smooth_error(model: Model, data: Data, pb: ContactProblem, E: float) -> float:
    """S_k [J] (docs/theory.md §5.3, §5.5): T + V at the free step's end (q_m (+) h/2 u_free, u_free) less
    E = T_k + V_k and the torques' work h tau.(u_k + u_free)/2 there: the smooth integrator's error in the step,
    as the ledger measures it (recording.account_step)."""
    q_free = pin.integrate(model.pin, pb.q_m, (0.5 * pb.h) * pb.u_free)
    S = (kinetic(model, data, q_free, pb.u_free) + potential(model, data, q_free)) - E
    if pb.tau is not None:
        S = S - float(ordered((0.5 * pb.h) * pb.tau, pb.u + pb.u_free))
    return S


def _roundoff(T0: float, V0: float, T1: float, V1: float) -> float:
    """ENERGY_ROUNDOFF (T_k + |V_k| + T_{k+1} + |V_{k+1}|) [J]: the round-off of a step's energy balance."""
    return ENERGY_ROUNDOFF * (((T0 + abs(V0)) + T1) + abs(V1))


def _trees(model: Model, involved: np.ndarray) -> np.ndarray:
    """The velocity indices of every kinematic tree (the joints below one child of the universe) that has an
    index in `involved` (docs/theory.md §2.10: its rows touch a trunk, its legs swing in the same step)."""
    tree = _TREES.get(model)
    if tree is None:  # the tree (its root joint) of each velocity index, once per model
        pm = model.pin
        parents, idx_v, nv = list(pm.parents), list(pm.idx_vs), list(pm.nvs)
        tree = np.empty(pm.nv, dtype=np.int64)
        for j in range(1, pm.njoints):
            root = j
            while parents[root] != 0:
                root = parents[root]
            tree[idx_v[j]:idx_v[j] + nv[j]] = root
        _TREES[model] = tree
    hit = np.zeros(model.pin.njoints, dtype=bool)
    hit[tree[involved]] = True
    return hit[tree]


_TREES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _alpha(a: float, b: float, c: float, floor: float) -> float:
    """The scale of the trees in contact (docs/theory.md §2.10): the largest root of a alpha^2 + b alpha + c
    (the scaled step's T + V less its bound [J]) in [floor, 1]; where none is, the alpha of least value
    -b/(2a), clipped (b < 0 where the velocities kept move against the scaled ones: alpha = 0 is not the
    least)."""
    disc = b * b - (4.0 * a) * c
    alpha = (math.sqrt(disc) - b) / (2.0 * a) if disc >= 0.0 else -b / (2.0 * a)  # else: the least value
    return min(1.0, max(floor, alpha))


def _scaled(model: Model, data: Data, q: np.ndarray, u: np.ndarray, involved: np.ndarray, K: float,
            T: float) -> np.ndarray:
    """u with the velocities of the trees in contact (_trees of `involved`) scaled so that T(q, u) <= K [J]
    (T = T(q, u) given): T is quadratic in the scale, a alpha^2 + b alpha + T_R (_alpha, floor 0)."""
    u_S, u_R, a, T_R = _split(model, data, q, u, involved)
    if not a > 0.0:
        return u
    return u_R + _alpha(a, (T - a) - T_R, T_R - K, 0.0) * u_S


def _split(model: Model, data: Data, q: np.ndarray, u: np.ndarray, involved: np.ndarray) -> tuple:
    """u = u_S + u_R with u_S the velocities of the trees in contact (_trees of `involved`), and T(q, u_S),
    T(q, u_R) [J]: the terms of T(q, u_R + alpha u_S) = a alpha^2 + b alpha + T_R (§2.10); T_R is not
    evaluated (nan) where a is not positive."""
    u_S = np.where(_trees(model, involved), u, 0.0)
    u_R = u - u_S
    a = kinetic(model, data, q, u_S)
    return u_S, u_R, a, (kinetic(model, data, q, u_R) if a > 0.0 else float("nan"))


def correct_positions(model: Model, data: Data, pb: ContactProblem, imp: ImpactSolution,
                      q_next: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """PositionCorrection.PROJECTION (docs/theory.md §2.5): dq = argmin 1/2 dq'M dq s.t.
    g_i + w_i'dq >= 0 on the closed contacts (g_i: gaps at q_{k+1} linearized from q_m), applied
    as q_{k+1} (+) alpha dq with alpha <= 1 the largest step for which T + V at the end does not
    exceed T + V at the start of the step: the correction may give back energy the step dissipated,
    never more (where E is concave along dq and alpha = budget/dE overshoots, alpha is shortened once more) -
    except where every penetrating contact ends the step resting (_resting), or the bodies of the penetrating
    contacts are at rest along the normals of all their closed contacts (_normal_rest; the lift then keeps each of
    those closed, within HOLD tolerances): then alpha = 1 and the potential energy the lift adds is booked as
    correction energy (§2.5, §5);
    and except a persistent penetration between flat faces (_flat: two polytopes, or a polytope's vertex on a
    half-space; deeper than the step's own approach can make, h |gamma_minus| + tol) in a passive step whose
    budget does not cover the full lift: it is removed in full, paid in full with the kinetic energy of the bodies
    in contact (their velocities scaled, _scaled) so that T + V ends where the law's step ended, where they have
    enough (also in a step that gained). Rows no dq meets (a body deep inside another) are relaxed by the least
    uniform residual (shortfall, §2.5) and the rest is as above.
    Returns (q, the change of T + V it made [J], u_{k+1}: imp.u_next itself unless the lift was paid)."""
    tol = model.options.contact_tolerance
    u_next = imp.u_next
    g_next = imp.contacts.g + 0.5 * pb.h * imp.gamma_plus
    if not len(g_next) or g_next.min() >= -tol:
        return q_next, 0.0, u_next
    q, u = pb.q, pb.u
    T0, V0 = kinetic(model, data, q, u), potential(model, data, q)
    E0 = T0 + V0
    E1 = kinetic(model, data, q_next, u_next) + potential(model, data, q_next)
    budget = E0 - E1 + imp.obstacle_work  # what the step dissipated beyond the work done on it (§5.5)
    if pb.tau is not None:
        budget += 0.5 * pb.h * float(ordered(pb.tau, u + u_next))
    pen = g_next < -tol
    resting = _resting(pb, imp, pen)
    res = None
    rows = None if resting else _normal_rest(model, data, pb, imp, pen, q_next)
    if rows is not None:  # at rest along the normals: lifted in full, no closed contact of theirs opened (§2.5)
        res = qp.solve(pb.M, np.concatenate([imp.W, -imp.W[:, rows]], axis=1), np.zeros(model.nv),
                       b=np.concatenate([-g_next, g_next[rows] - np.maximum(g_next[rows], HOLD * tol)]), Minv=pb.Minv)
        resting = res.ok  # else (rows that cannot all be met) the budget rule
    # paid only in a passive step: the scaling's bound would need the torques' work at the scaled velocity
    deep = g_next < -(pb.h * np.abs(imp.gamma_minus) + tol)
    # only between flat faces (box faces sliding, a box rocking across an edge, a box's corner sliding on a
    # half-space): in a column of beads the lift paid with the velocities of beads falling together kept the top
    # bead bouncing past its rest (§2.5)
    persistent = (pb.tau is None and model.prescribed is None and pb.drive is None and bool(deep.any())
                  and all(_flat(model, imp.contacts, i) for i in np.flatnonzero(deep)))
    if budget <= 0.0 and not resting and not persistent:  # the step gained (the cap of §2.10 takes it back):
        return q_next, 0.0, u_next  # nothing to spend
    if res is None or not res.ok:  # above qp.SPARSE_ROWS rows warm-started from the law's final set (§2.5)
        law = imp.qp.active
        res = qp.solve(pb.M, imp.W, np.zeros(model.nv), b=-g_next, Minv=pb.Minv,
                       start=law if law is not None and len(law) == imp.W.shape[1] else None, blocks=pb.blocks)
    if res.status == INFEASIBLE:  # rows that contradict (a box pushed into another): the least residual (§2.5)
        res = qp.solve(pb.M, imp.W, np.zeros(model.nv), b=-(g_next + shortfall(imp.W, g_next, tol)), Minv=pb.Minv)
    if not res.ok:  # never leave the penetration silently: the run stops, naming the step (simulate)
        raise SimulationError(f"the position-correction QP failed with status {res.status} "
                              f"({imp.contacts.m} closed contacts)")
    q_c = pin.integrate(model.pin, q_next, res.v)
    T_c, V_c = kinetic(model, data, q_c, u_next), potential(model, data, q_c)
    dE = T_c + V_c - E1
    u_c = u_next
    if dE > budget and not resting:
        paid = False
        if persistent:  # the full lift, paid in full with the kinetic energy of the bodies in contact: T + V ends
            # where the law's step ended, E_1 (giving the step's dissipation back to such lifts fed a chatter, §2.5)
            u_c = _scaled(model, data, q_c, u_next, (imp.W != 0.0).any(axis=1), E1 - V_c, T_c)
            dE = kinetic(model, data, q_c, u_c) + V_c - E1
            paid = dE <= _roundoff(T0, V0, T_c, V_c)
        if not paid and budget <= 0.0:  # a step that gained: nothing to spend
            return q_next, 0.0, u_next
        if not paid:
            u_c = u_next
            alpha = budget / dE  # E is ~linear in dq here
            q_c = pin.integrate(model.pin, q_next, alpha * res.v)
            dE = kinetic(model, data, q_c, u_next) + potential(model, data, q_c) - E1
            if dE > budget + _roundoff(T0, V0, T_c, V_c):  # beyond round-off: E concave along dq (a leg lifted)
                alpha *= (budget / dE) * (budget / dE)  # shortened by the relative excess twice (§2.5)
                q_c = pin.integrate(model.pin, q_next, alpha * res.v)
                dE = kinetic(model, data, q_c, u_next) + potential(model, data, q_c) - E1
            if dE > budget:  # not linear after all: keep the uncorrected step rather than gain energy
                return q_next, 0.0, u_next
    # the displacement only knows the closed contacts: it must not push another pair into contact
    # (a column of beads: pushing 2 off 1 pushes 1 into 0), nor a joint past a limit that was not closed (the
    # limits' gaps follow the pairs', at their pair indices). Otherwise the step stays uncorrected.
    before, after = _guarded(model, data, q_next), _guarded(model, data, q_c)
    floor = np.minimum(before, 0.0)
    if u_c is not u_next:  # a paid lift: a pair it lifts may go deeper at a feature that was not closed (a box
        # rocking across an edge: one crossing lifted presses the other), by at most half the depth it lifts,
        # so that the next steps' lifts converge (§2.5)
        own = imp.contacts.pair < len(floor)
        lifted = np.zeros(len(floor))
        np.minimum.at(lifted, imp.contacts.pair[own], g_next[own])
        floor += 0.5 * lifted
    if (after < floor - tol).any():
        return q_next, 0.0, u_next
    return q_c, dE, u_c


def _guarded(model: Model, data: Data, q: np.ndarray) -> np.ndarray:
    """The correction's guard at q: every pair's signed distance [m] (pair_distances(near=True)), then every joint
    limit's gap [rad or m] (its pair index len(model.pairs) + its index: docs/theory.md §2.5)."""
    d = pair_distances(model, data, q, near=True)
    return np.concatenate([d, limit_gaps(model.limits, q)]) if model.limits else d


INFEASIBLE = "PIQP_PRIMAL_INFEASIBLE"  # qp.solve's status where no dq meets every linearized row


def shortfall(W: np.ndarray, g: np.ndarray, tol: float) -> np.ndarray:
    """The least uniform residual penetration t* [m] the linearized rows g_i + w_i'dq >= 0 allow (docs/theory.md
    §2.5): t* = min t s.t. g_i + w_i'dq + t >= 0 on the penetrating rows (g_i < 0), g_i + w_i'dq >= 0 on the
    others (a linear programme, HiGHS); returned as the row shifts s_i = t* + tol on the penetrating rows, 0
    elsewhere, so that g + s + W'dq >= 0 is feasible (dq = 0, t = max(-g) always is)."""
    from scipy.optimize import linprog  # here: infeasible corrections only (scipy.optimize's RSS, as corners.py)

    nv, pen = W.shape[0], (g < 0.0).astype(float)
    c = np.zeros(nv + 1)
    c[-1] = 1.0
    lp = linprog(c, A_ub=-np.column_stack([W.T, pen]), b_ub=g, bounds=[(None, None)] * nv + [(0.0, None)],
                 method="highs")
    t = float(lp.x[-1]) if lp.status == 0 else float(-g.min())
    return pen * (t + tol)


def _flat(model: Model, contacts: Contacts, i: int) -> bool:
    """Whether contact i is between two flat faces (docs/theory.md §2.5, the paid lift): a pair of two polytopes,
    or a polytope's vertex on a half-space."""
    pair = int(contacts.pair[i])
    if pair in model.polytope_pair_set:
        return True
    if contacts.kind[i] != FeatureKind.VERTEX or pair >= len(model.pairs):
        return False
    p = model.pairs[pair]
    return model.bounds[p.first][0] == "plane" or model.bounds[p.second][0] == "plane"


def _resting(pb: ContactProblem, imp: ImpactSolution, pen: np.ndarray) -> bool:
    """Whether the bodies of every penetrating contact (mask `pen`) end the step at rest: every
    velocity their rows involve is zero to round-off, |u_{k+1,j}| <= RESTING max|u_free - u_k| for
    each j with w_ij != 0 (the scale: what one step of the smooth forces adds). Their penetration
    would then stay for good: the correction lifts it in full, beyond the step's dissipation, and
    books the energy it adds (docs/theory.md §2.5). A contact of a moving body (a block rocking on
    its edge) keeps the budget rule."""
    scale = RESTING * float(np.abs(pb.u_free - pb.u).max(initial=0.0))
    involved = (imp.W[:, pen] != 0.0).any(axis=1)
    return bool((np.abs(imp.u_next[involved]) <= scale).all())


def _normal_rest(model: Model, data: Data, pb: ContactProblem, imp: ImpactSolution, pen: np.ndarray,
                 q_next: np.ndarray) -> np.ndarray | None:
    """The closed contacts R of the bodies of the penetrating contacts (mask `pen`: every row that involves a
    velocity a penetrating row involves) where those bodies are held at rest along the normals (docs/theory.md
    §2.5): no contact of R moves along its normal at either end of the step, |gamma_i^k| <= eps and
    |gamma_i^{k+1}| <= eps with eps = RESTING max|u_free - u_k| (sliding and turning about the normal do not count),
    and the step changes the kinetic energy of their trees by at most RESTING T(q_k, u_free - u_k) there (gravity
    and the contacts did no work on them: a block starting to turn about one corner, gamma = 0 at the corner, does
    not pass). Else None."""
    eps = RESTING * float(np.abs(pb.u_free - pb.u).max(initial=0.0))
    involved = (imp.W[:, pen] != 0.0).any(axis=1)
    rows = (imp.W[involved] != 0.0).any(axis=0)
    if not ((np.abs(imp.gamma_minus[rows]) <= eps).all() and (np.abs(imp.gamma_plus[rows]) <= eps).all()):
        return None
    S = _trees(model, involved)
    dT = kinetic(model, data, q_next, np.where(S, imp.u_next, 0.0)) - kinetic(model, data, pb.q, np.where(S, pb.u, 0.0))
    kick = kinetic(model, data, pb.q, np.where(S, pb.u_free - pb.u, 0.0))
    return rows if abs(dT) <= RESTING * kick else None


def _corner_law(pb: ContactProblem, options: Options, choice: int | None):
    """All stationary points over the union of pieces (corners.stationary_points), the one the
    selection policy picks, and the contacts/rows/multipliers of the chosen piece(s).

    With corners the Separating rule is not applied (the set-valued law takes no bound shift)."""
    cp, W, contacts = pb.pieces, pb.W, pb.contacts
    law = corner_law(pb.M, pb.v_free, pb.u, pb.e, W, cp.pieces, cp.rows, cp.choice,
                     selection=options.corner_selection, pick=choice)
    if law is None:
        res = QPResult(f"TOO_MANY_CORNER_PIECES ({len(cp.pieces)} > {MAX_PIECES})", False, 0, False, pb.v_free,
                       np.zeros(W.shape[1]))
        return res, contacts, W, None
    # the chosen candidate's active rows: the smooth contacts, then the faces of its pieces
    merged = contacts.concat(*[corner_faces(cp.corners[c], np.array([f])) for c, f in law.faces], corners=())
    res = QPResult("CORNER_LAW", True, law.solution.qp_solves, False, law.v, law.lam,
                   pb.M, law.W, pb.v_free, np.zeros(law.W.shape[1]))
    branch = None if law.u_plus is None else (law.solution, law.chosen, law.u_plus)
    return res, merged, law.W, branch
