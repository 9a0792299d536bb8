"""The event-driven integrator (docs/theory.md §7): smooth phases to tolerance, impacts at
located instants.

    traj = simulate_event_driven(model)            # same Trajectory arrays as ms.simulate

Between events the motion is an ODE integrated by scipy's ``solve_ivp`` (DOP853 by default,
rtol = atol = 1e-12): u' = a, q' = u. Euclidean q (prismatic, revolute, planar/translation
composites) is integrated directly; a Lie-group q (the free root's quaternion) in a local chart
q = q_b (+) delta, delta' = dIntegrate(q_b, delta)^-1 u, with the chart re-centred at every
event and whenever |delta|_inf > 1. Accelerations: a = ABA(q, u, 0) + M^-1 W_C lam, where C is
the set of persistent contacts, held as bilateral constraints W_C' a + Wdot_C' u = 0
(lam from the Delassus system G lam = -(W_C' a_free + Wdot_C' u), G = W_C' M^-1 W_C).

Gaps (event functions): our own analytic signed gaps per *feature*, with rows w and the drift
term Wdot' u (from Pinocchio's bias accelerations), for the pair types of the bundled scenes:
every vertex of a polytope against a half-space, a sphere against a half-space, a sphere
against a sphere, a sphere against a static box. Per-vertex gaps (not coal's pair distance,
which is the minimum over corners and stays 0 while a block pivots) make each corner of a
rocking block its own event. Other pair types raise :class:`UnsupportedModel` naming the pair.

Events (terminal): a free feature's gap crossing 0 downwards (impact); a persistent
contact's multiplier crossing -LAM_EPS downwards (release). A free feature that starts a phase
within G_RES = 1e-13 m of contact (it just bounced or separated) is watched instead by its rise
to G_RES and by its normal velocity returning below -2 V_TOL: the sign of so small a gap is
rounding noise, and the root finder would take a noise crossing for an impact (while it rises,
ODE steps stay below half its time to apex, so that no rise-and-fall hides inside one step).
At every event (and at the start) :func:`EventDrivenRun.resolve` applies, in order:
  1. Impact: if a closed feature (g <= the scene's contact_tolerance, 1e-9 m by default)
     approaches (gamma < -V_TOL), the SAME law as the stepper, ``law.impact`` (docs/theory.md §1)
     on the contacts ``contacts.detect`` closes at q (coal, tolerance 1e-9 m), with the scene's e.
  2. Zeno rule (accumulation points): the impact is plastic (e = 0) if, for every approaching
     contact, its rebound would rise less than G_ZENO = 1e-12 m, (e gamma-)^2 < 2 |a_n| G_ZENO
     with a_n its free normal acceleration, or it is slower than V_ZENO = 1e-8 m/s; or if the
     last impact was less than DT_ZENO = 1e-12 s ago. The rest of the infinite bounce sequence
     is skipped and the contact becomes persistent. (Gaps are computed from positions of order
     1 m, with a rounding of ~3e-17 m: lower bounces cannot be located reliably.) Under a locally
     constant a_n < 0 the skipped bounces last 2 e |gamma-| / ((1 - e) |a_n|) (a geometric
     series, ~1e-6 s at most for the ball); that is added to the declaration time and recorded
     in meta["zeno"] as "t_accumulation".
  3. Persistent contacts: the closed features with |gamma| <= V_TOL go through the
     acceleration-level contact problem, min 1/2 (a - a_free)' M (a - a_free) s.t.
     W' a >= -Wdot' u (piqp via ``law.project``): those with zero relative acceleration
     (pushing, lam > 0, or neutral, lam = 0 with nothing pulling them apart - the touching
     balls of a cradle) form C; the others separate. A contact released by its multiplier
     event is not re-admitted at that instant.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import coal
import numpy as np
import pinocchio as pin
from scipy.integrate import solve_ivp

from .constraints import assemble_constraints
from .contacts import detect
from .data import Data, make_data
from .errors import MoreauSimError, SimulationError
from .law import impact, project
from .model import Model, initial_state
from .recording import LOG_RELATIVE, PercussionRow, Recorder, run_metadata
from .state import State
from .trajectory import Trajectory

V_TOL = 1e-9  # [m/s] |gamma| <= this on a closed feature: touching, not impacting
G_RES = 1e-13  # [m] smallest gap whose sign is trusted (~3000x the rounding of positions ~ 1 m)
G_ZENO = 1e-12  # [m] a rebound whose apex would stay below this is not resolved (Zeno rule)
V_ZENO = 1e-8  # [m/s] nor an impact slower than this
DT_ZENO = 1e-12  # [s] nor an impact this soon after the previous one
LAM_EPS = 1e-9  # [N] a persistent contact is released when its multiplier falls below -LAM_EPS
ACC_TOL = 1e-8  # [m/s^2] relative acceleration below this (scaled): a touching contact persists
CHART_MAX = 1.0  # [rad or m] re-centre the Lie-group chart when |delta|_inf exceeds this


class UnsupportedModel(MoreauSimError, ValueError):
    """The reference cannot integrate this model (a pair type it has no analytic gap for)."""


@dataclass(frozen=True, slots=True)
class _Feature:
    """One gap function. kind "point_plane": point `p` (joint frame of joint_a) above the plane
    n' x = d (world); "sphere_sphere": centres p (joint_a) and p_b (joint_b), radii r, r_b;
    "sphere_box": centre p (joint_a), radius r, static box (rotation R, centre c, half sides h)."""

    kind: str
    pair: int
    feature: int
    joint_a: int
    joint_b: int
    p: np.ndarray
    n: np.ndarray = field(default_factory=lambda: np.zeros(3))
    d: float = 0.0
    r: float = 0.0
    p_b: np.ndarray = field(default_factory=lambda: np.zeros(3))
    r_b: float = 0.0
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    h: np.ndarray = field(default_factory=lambda: np.zeros(3))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _features(model: Model) -> tuple[_Feature, ...]:
    """The gap functions of every collision pair (UnsupportedModel for other pair types)."""
    out = []
    gobs = model.geom.geometryObjects
    for pair in model.pairs:
        ga, gb = gobs[pair.first], gobs[pair.second]
        sa, sb = ga.geometry, gb.geometry
        ja, jb = pair.joint_first, pair.joint_second
        if isinstance(sb, coal.Halfspace) and jb == 0:
            _, n, d = model.bounds[pair.second]
            if isinstance(sa, coal.Sphere) and sa.radius > 0:
                centre = ga.placement.translation.copy()
                out.append(_Feature("point_plane", pair.index, -1, ja, 0, centre, n, d + sa.radius))
                continue
            if len(model.vertices[pair.first]):
                out += [_Feature("point_plane", pair.index, i, ja, 0, v.copy(), n, d)
                        for i, v in enumerate(model.vertices[pair.first])]
                continue
        if isinstance(sa, coal.Sphere) and isinstance(sb, coal.Sphere):
            out.append(_Feature("sphere_sphere", pair.index, -1, ja, jb, ga.placement.translation.copy(),
                                r=sa.radius, p_b=gb.placement.translation.copy(), r_b=sb.radius))
            continue
        if isinstance(sa, coal.Sphere) and isinstance(sb, coal.Box) and jb == 0:
            out.append(_Feature("sphere_box", pair.index, -1, ja, 0, ga.placement.translation.copy(), r=sa.radius,
                                R=gb.placement.rotation.copy(), p_b=gb.placement.translation.copy(),
                                h=np.asarray(sb.halfSide, float).copy()))
            continue
        raise UnsupportedModel(f"{model.scene.name}: pair '{pair.name}' ({type(sa).__name__} vs "
                               f"{type(sb).__name__}): the event-driven reference has gaps for polytope or "
                               "sphere vs half-space, sphere vs sphere and sphere vs static box only")
    return tuple(out)


@dataclass(frozen=True, slots=True)
class _FeatureState:
    """Gaps g [m], rows W (nv, k), drift Wdot' u [m/s^2] and gamma = W' u [m/s] of features."""

    g: np.ndarray
    W: np.ndarray
    drift: np.ndarray
    gamma: np.ndarray


class EventDrivenRun:
    """One event-driven run (mutable bookkeeping; the public API is simulate_event_driven)."""

    def __init__(self, model: Model, data: Data, e: float, rtol: float, atol: float, method: str,
                 max_step: float, max_events: int):
        self.model, self.data, self.e = model, data, e
        # a feature is closed when its gap is <= this [m]: the tolerance contacts.detect uses
        self.gap_tol = max(model.options.contact_tolerance, G_RES)
        self.pm, self.pd = model.pin, data.pin
        self.nv = model.nv
        self.lie = any(model.pin.joints[j].nq != model.pin.joints[j].nv for j in range(1, model.pin.njoints))
        self.feats = _features(model)
        self.rtol, self.atol, self.method, self.max_step, self.max_events = rtol, atol, method, max_step, max_events
        self.zero = np.zeros(self.nv)
        self.rec: Recorder | None = None  # set by simulate_event_driven
        self.zeno: list[dict] = []
        self.work = 0.0  # contact work since the last sample [J] (= -energy lost in impacts)
        self.last_impact = -np.inf
        self.events = self.impacts = self.nfev = 0

    # ---- kinematics of the features -------------------------------------------------------
    def _point(self, j: int, p_local: np.ndarray, rows: bool):
        """World position, velocity, bias acceleration (q'' = 0) and Jacobian (3, nv) of a
        point fixed in joint j's frame (needs forwardKinematics(q, u, 0) and, for rows, J)."""
        if j == 0:
            return p_local, np.zeros(3), np.zeros(3), (np.zeros((3, self.nv)) if rows else None)
        M, v, a = self.pd.oMi[j], self.pd.v[j], self.pd.a[j]
        R = M.rotation
        w, vl = v.angular, v.linear + _cross(v.angular, p_local)
        p = R @ p_local + M.translation
        vel = R @ vl
        acc = R @ (a.linear + _cross(a.angular, p_local) + _cross(w, vl))
        Jp = None
        if rows:
            J = self.pd.J.reshape(6, -1)
            Jp = (J[:3] - pin.skew(p) @ J[3:]) * self.model.support_mask[j]
        return p, vel, acc, Jp

    def features(self, q: np.ndarray, u: np.ndarray, idx=None, rows: bool = True) -> _FeatureState:
        """Gaps (and rows, drift, gamma if `rows`) of the features `idx` (default all) at (q, u)."""
        pm, pd = self.pm, self.pd
        if rows:
            pin.computeJointJacobians(pm, pd, q)
        pin.forwardKinematics(pm, pd, q, u, self.zero)
        idx = range(len(self.feats)) if idx is None else idx
        k = len(idx)
        g, drift, W = np.empty(k), np.zeros(k), np.zeros((self.nv, k))
        for col, i in enumerate(idx):
            f = self.feats[i]
            pa, va, aa, Ja = self._point(f.joint_a, f.p, rows)
            if f.kind == "point_plane":
                n, curv = f.n, 0.0
                g[col] = n @ pa - f.d
                vrel, arel, Jrel = va, aa, Ja
            elif f.kind == "sphere_sphere":
                pb, vb, ab, Jb = self._point(f.joint_b, f.p_b, rows)
                dv = pa - pb
                dist = float(np.sqrt(dv @ dv))
                n = dv / dist
                g[col] = dist - f.r - f.r_b
                vrel, arel = va - vb, aa - ab
                Jrel = Ja - Jb if rows else None
                curv = (vrel @ vrel - (n @ vrel) ** 2) / dist
            else:  # sphere_box: distance from the centre to a static box (face, edge or vertex region)
                cl = f.R.T @ (pa - f.p_b)
                clamp = np.clip(cl, -f.h, f.h)
                out = np.abs(cl) > f.h
                vl = f.R.T @ va
                if out.any():
                    diff = cl - clamp
                    dist = float(np.sqrt(diff @ diff))
                    nl = diff / dist
                    g[col] = dist - f.r
                    # curvature of the distance: the velocity across the closest edge/vertex
                    vp = np.where(out, vl, 0.0)
                    curv = (vp @ vp - (nl @ vl) ** 2) / dist if out.sum() > 1 else 0.0
                else:  # centre inside the box: the nearest face
                    s = f.h - np.abs(cl)
                    ax = int(np.argmin(s))
                    nl = np.zeros(3)
                    nl[ax] = np.sign(cl[ax]) or 1.0
                    g[col] = -s[ax] - f.r
                    curv = 0.0
                n = f.R @ nl
                vrel, arel, Jrel = va, aa, Ja
            if rows:
                drift[col] = n @ arel + curv
                W[:, col] = n @ Jrel
        gamma = W.T @ u if rows else np.zeros(k)
        return _FeatureState(g, W, drift, gamma)

    # ---- dynamics --------------------------------------------------------------------------
    def q_of(self, qb: np.ndarray, delta: np.ndarray) -> np.ndarray:
        return pin.integrate(self.pm, qb, delta) if self.lie else qb + delta

    def dynamics(self, q, u, C):
        """(a, lam): free accelerations (ABA) plus the bilateral forces of the persistent set C."""
        self.nfev += 1
        a = pin.aba(self.pm, self.pd, q, u, self.zero).copy()
        if not C:
            return a, np.zeros(0)
        fs = self.features(q, u, C)
        Minv = pin.computeMinverse(self.pm, self.pd, q)
        MiW = Minv @ fs.W
        G = fs.W.T @ MiW
        rhs = -(fs.W.T @ a + fs.drift)
        try:
            lam = np.linalg.solve(G, rhs)
        except np.linalg.LinAlgError:
            lam = np.linalg.lstsq(G, rhs, rcond=1e-12)[0]  # redundant rows: minimum-norm forces
        return a + MiW @ lam, lam

    # ---- events ----------------------------------------------------------------------------
    def resolve(self, t: float, q: np.ndarray, u: np.ndarray, released: frozenset):
        """Impact (with the Zeno rule), then the persistent set C at (t, q, u) (module doc).
        Returns (u, C, shadow): C persistent features, shadow: duplicates of C's rows."""
        fs = self.features(q, u)
        closed = fs.g <= self.gap_tol
        if (closed & (fs.gamma < -V_TOL)).any():
            u = self._impact(t, q, u, fs)
            fs = self.features(q, u)
        touching = [i for i in np.flatnonzero(closed & (np.abs(fs.gamma) <= V_TOL)) if i not in released]
        if not touching:
            return u, (), ()
        # distinct rows only (the front and back corners of a planar block repeat each other)
        keep, shadow = [], []
        scale = 1e-12 * (1.0 + np.abs(fs.W).max())
        for i in touching:
            (shadow if any(np.abs(fs.W[:, i] - fs.W[:, j]).max() <= scale for j in keep) else keep).append(i)
        a_free = pin.aba(self.pm, self.pd, q, u, self.zero).copy()
        M = pin.crba(self.pm, self.pd, q)
        Wk, dk = fs.W[:, keep], fs.drift[keep]
        res = project(M, Wk, a_free, b=-dk)
        if not res.ok:
            raise SimulationError(f"t = {t:.12g} s: the contact-force QP failed ({res.status})", t=t)
        rel = Wk.T @ res.v + dk
        tol = ACC_TOL * (1.0 + np.abs(dk).max() + np.abs(Wk.T @ a_free).max())
        C = tuple(int(i) for i, r in zip(keep, rel) if r <= tol)
        if C:  # remove the residual normal velocity of the persistent contacts (~1e-16)
            Minv = pin.computeMinverse(self.pm, self.pd, q)
            W = fs.W[:, list(C)]
            MiW = Minv @ W
            u = u - MiW @ np.linalg.lstsq(W.T @ MiW, W.T @ u, rcond=1e-12)[0]
        shadow = tuple(int(i) for i in shadow if any(np.abs(fs.W[:, i] - fs.W[:, j]).max() <= scale for j in C))
        return u, C, shadow

    def _impact(self, t, q, u, fs: _FeatureState) -> np.ndarray:
        """The impact law (law.impact, docs/theory.md §1) on the contacts detect() closes at q."""
        pm, pd, model = self.pm, self.pd, self.model
        c = detect(model, self.data, q)
        if c.corners:
            raise SimulationError(f"t = {t:.12g} s: a corner impact (docs/theory.md §3); the event-driven "
                                  "reference handles smooth contacts only", t=t)
        cs = assemble_constraints(model, self.data, q, c)
        c, M, W = cs.contacts, cs.M, cs.W
        if c.m == 0:
            raise SimulationError(f"t = {t:.12g} s: a gap event but coal finds no closed contact", t=t)
        gm = W.T @ u
        if not (gm < -V_TOL).any():
            raise SimulationError(f"t = {t:.12g} s: a feature approaches (gamma = {fs.gamma.min():.3g} m/s) but "
                                  "none of coal's closed contacts does", t=t)
        # the Zeno rule (module doc) on the approaching features: their free normal accelerations a_n
        appr = np.flatnonzero((fs.g <= self.gap_tol) & (fs.gamma < -V_TOL))
        a_n = fs.W[:, appr].T @ pin.aba(pm, pd, q, u, self.zero) + fs.drift[appr]
        speed = -fs.gamma[appr]
        low = ((self.e * speed) ** 2 < -2.0 * a_n * G_ZENO) | (speed < V_ZENO)
        zeno = bool(low.all()) or t - self.last_impact < DT_ZENO
        imp = impact(M, W, u, 0.0 if zeno else self.e)
        if zeno and self.e < 1.0:
            k = int(np.argmax(speed))
            dt = 2.0 * self.e * speed[k] / ((1.0 - self.e) * -a_n[k]) if a_n[k] < 0 else 0.0
            self.zeno.append({"t": t, "t_accumulation": float(t + dt), "speed": float(speed[k]),
                              "pairs": sorted(set(c.pair.tolist()))})
        gp = W.T @ imp.u_plus
        cut = LOG_RELATIVE * float(imp.P.max(initial=0.0))
        for i in np.flatnonzero((imp.P > cut) & (imp.P > 0)):  # step: the index of the next sample
            self.rec.log(PercussionRow(self.rec.n, t, int(c.pair[i]), int(c.kind[i]), int(c.feature[i]), float(c.g[i]),
                                       float(imp.P[i]), float(gm[i]), float(gp[i]), c.point_a[i], c.normal[i], True))
        self.work -= imp.energy_loss
        self.last_impact = t
        self.impacts += 1
        return imp.u_plus

    # ---- the run ---------------------------------------------------------------------------
    def _phase_events(self, qb, C, free, low):
        """Terminal event functions of one phase and a tag per function (module doc): gaps of the
        free features, rise and return of those in `low` (within G_RES at the start), the
        multipliers of C, and the chart's extent."""
        cache: dict = {}
        watch = [i for i in free if i not in low]

        def evaluate(y):
            key = y.tobytes()
            if key not in cache:
                cache.clear()
                q, u = self.q_of(qb, y[:self.nv]), y[self.nv:]
                lam = self.dynamics(q, u, C)[1] if C else np.zeros(0)
                fs = self.features(q, u, watch + low, rows=bool(low)) if free else None
                cache[key] = (fs, lam)
            return cache[key]

        fns, tags = [], []
        for k, i in enumerate(watch):
            # an exact 0.0 counts as open: scipy takes (0, 0) for a downward crossing
            fns.append((lambda t, y, k=k: evaluate(y)[0].g[k] or 1e-300, -1.0))  # gap closing: an impact
            tags.append(("gap", i))
        for k, i in enumerate(low, start=len(watch)):
            fns.append((lambda t, y, k=k: evaluate(y)[0].g[k] - G_RES, 1.0))  # risen: watch its gap
            tags.append(("rise", i))
            fns.append((lambda t, y, k=k: evaluate(y)[0].gamma[k] + 2.0 * V_TOL, -1.0))  # coming back
            tags.append(("return", i))
        for k, i in enumerate(C):
            fns.append((lambda t, y, k=k: evaluate(y)[1][k] + LAM_EPS, -1.0))  # contact force vanishing
            tags.append(("release", i))
        if self.lie:
            fns.append((lambda t, y: np.abs(y[:self.nv]).max() - CHART_MAX, 1.0))  # re-centre the chart
            tags.append(("chart", -1))
        for f, direction in fns:
            f.terminal, f.direction = True, direction
        return [f for f, _ in fns], tags

    def _rhs(self, qb, C):
        nv = self.nv

        def f(t, y):
            delta, u = y[:nv], y[nv:]
            q = self.q_of(qb, delta)
            a = self.dynamics(q, u, C)[0]
            if self.lie:
                dq = np.linalg.solve(pin.dIntegrate(self.pm, qb, delta, pin.ArgumentPosition.ARG1), u)
            else:
                dq = u
            return np.concatenate((dq, a))
        return f

    def _max_step(self, q, u, C, low) -> float:
        """max_step, or less while a feature that just bounced rises: its rise to G_RES and
        its fall back must not fit in one ODE step (a double crossing is invisible), so steps
        stay below half its time to apex gamma / |a_n|."""
        if not low:
            return self.max_step
        fs = self.features(q, u, low)
        a_n = fs.W.T @ self.dynamics(q, u, C)[0] + fs.drift
        up = (fs.gamma > V_TOL) & (a_n < 0)
        return float(min(self.max_step, *(0.5 * fs.gamma[up] / -a_n[up]))) if up.any() else self.max_step

    def sample(self, t: float, q: np.ndarray, u: np.ndarray, n_contacts: int) -> None:
        """Record a sample with the contact work since the previous one."""
        self.rec.sample(State(t, q, u), self.work, 0.0, n_contacts)
        self.work = 0.0

    def run(self, state: State, t_end: float, t_grid: np.ndarray) -> None:
        nv, nf = self.nv, len(self.feats)
        t, q, u = float(state.t), np.array(state.q, float), np.array(state.u, float)
        gi = 0
        while gi < len(t_grid) and t_grid[gi] <= t:  # the initial state, before any impact (as simulate)
            self.sample(t, q, u, 0)
            gi += 1
        released: frozenset = frozenset()
        stuck = 0
        while True:
            u, C, shadow = self.resolve(t, q, u, released)
            free = [i for i in range(nf) if i not in C and i not in shadow]
            g0 = self.features(q, u, free, rows=False).g if free else np.zeros(0)
            low = [i for i, g in zip(free, g0) if g < 0.5 * G_RES]
            qb = q.copy()
            events, tags = self._phase_events(qb, C, free, low)
            sol = solve_ivp(self._rhs(qb, C), (t, t_end), np.concatenate((np.zeros(nv), u)), method=self.method,
                            dense_output=True, events=events or None, rtol=self.rtol, atol=self.atol,
                            max_step=self._max_step(q, u, C, low))
            if sol.status < 0:
                raise SimulationError(f"t = {t:.12g} s: solve_ivp failed: {sol.message}", t=t)
            t_stop, end = float(sol.t[-1]), sol.status == 0
            while gi < len(t_grid) and (t_grid[gi] < t_stop or (end and t_grid[gi] <= t_stop)):
                y = sol.sol(t_grid[gi])
                self.sample(float(t_grid[gi]), self.q_of(qb, y[:nv]), y[nv:], len(C))
                gi += 1
            if end:
                return
            self.events += 1
            if self.events > self.max_events:
                raise SimulationError(f"t = {t_stop:.12g} s: more than {self.max_events} events", t=t_stop)
            stuck = stuck + 1 if t_stop - t < 1e-13 else 0
            if stuck > 100:
                raise SimulationError(f"t = {t_stop:.12g} s: 100 events without time advancing", t=t_stop)
            y = sol.y[:, -1]
            q, u, t = self.q_of(qb, y[:nv]), y[nv:].copy(), t_stop
            released = frozenset(i for (kind, i), te in zip(tags, sol.t_events)
                                 if kind == "release" and len(te) and abs(te[-1] - t_stop) <= 1e-12)


def simulate_event_driven(model: Model, *, state: State | None = None, t_end: float | None = None,
                          rtol: float = 1e-12, atol: float = 1e-12, method: str = "DOP853",
                          t_eval=None, max_step: float = 1e-2, max_events: int = 100_000,
                          data: Data | None = None) -> Trajectory:
    """Integrate `model` event by event (module doc) from `state` (default: the scene's initial
    state) to `t_end` [s] (default: state.t + the scene's duration), restitution = the scene's e.

    rtol, atol: solve_ivp tolerances of the smooth phases; method: "DOP853" (default) or another
    explicit solve_ivp method; max_step [s]: bound on an ODE step (no gap dips below 0 and back
    unseen within one step); t_eval: sample instants [s] in [t0, t_end] (default: every
    save_every * dt of the scene's options, the instants ms.simulate records);
    max_events: give up beyond this many events.

    Returns a :class:`Trajectory` with ms.simulate's arrays: samples at t_eval (a sample at an
    impact instant is the post-impact state, one at t0 the initial state); one log row per
    contact percussion with log_t the exact impact time, log_step the index of the next
    sample, log_impact True; contact_work = -(energy lost in impacts) since the previous
    sample; branch arrays empty. meta: "integrator": "event-driven", "status", "zeno" (the
    accumulation points declared: t, t_accumulation, speed, pairs), "reference" (tolerances and
    thresholds), "run" (events, impacts, nfev, wall_seconds). Raises UnsupportedModel for a pair
    without an analytic gap, SimulationError (with .trajectory up to the failure) otherwise."""
    data = data or make_data(model)
    state = state or initial_state(model)
    opts = model.options
    t_end = state.t + opts.duration if t_end is None else float(t_end)
    if not t_end > state.t:
        raise ValueError(f"t_end = {t_end} s must be after the initial time {state.t} s")
    if t_eval is None:
        n = max(1, int(round((t_end - state.t) / (opts.dt * opts.save_every))))
        t_grid = state.t + (t_end - state.t) * np.arange(n + 1) / n
    else:
        t_grid = np.asarray(t_eval, float)
        if t_grid.ndim != 1 or np.any(np.diff(t_grid) <= 0) or t_grid[0] < state.t or t_grid[-1] > t_end:
            raise ValueError(f"t_eval must increase strictly within [{state.t}, {t_end}] s")
    integ = EventDrivenRun(model, data, opts.restitution, rtol, atol, method, max_step, max_events)
    integ.rec = Recorder(model, data, len(t_grid))
    wall0 = time.perf_counter()
    try:
        integ.run(state, t_end, t_grid)
    except SimulationError as exc:
        exc.trajectory = integ.rec.trajectory(_meta(model, integ, f"failed: {exc}", wall0))
        raise
    return integ.rec.trajectory(_meta(model, integ, "complete", wall0))


def _meta(model: Model, integ: EventDrivenRun, status: str, wall0: float) -> dict:
    reference = {"method": integ.method, "rtol": integ.rtol, "atol": integ.atol, "max_step": integ.max_step,
                 "gap_tol": integ.gap_tol, "v_tol": V_TOL, "g_res": G_RES, "g_zeno": G_ZENO, "v_zeno": V_ZENO,
                 "dt_zeno": DT_ZENO, "lam_eps": LAM_EPS, "lie_group_chart": integ.lie}
    run = {"steps": None, "events": integ.events, "impacts": integ.impacts, "nfev": integ.nfev,
           "wall_seconds": time.perf_counter() - wall0}
    return run_metadata(model, status, run, integrator="event-driven", reference=reference, zeno=integ.zeno)
