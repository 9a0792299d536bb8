"""Per-feature gaps of the contact layer, and what an integrator that locates events does with them.

A *feature* is one gap function of a collision pair, with its row w, the drift term Wdot' u
(from Pinocchio's bias accelerations) and gamma = w' u: every vertex of a polytope against a
half-space, a sphere against a half-space, a sphere against a sphere, a sphere against a static
box. Per-vertex gaps (not coal's pair distance, which is the minimum over corners and stays 0
while a block pivots) make each corner of a rocking block its own event. Other pair types raise
:class:`UnsupportedModel` naming the pair.

:class:`FeatureContacts` holds what the event-driven integrator (event_driven.py, docs/theory.md
§7) and the adaptive one (adaptive.py, §8) share: the features' kinematics, the constrained
accelerations of a persistent set C (a = ABA + M^-1 W_C lam, W_C' a + Wdot_C' u = 0), and
:meth:`FeatureContacts.resolve` at an event: the impact (law.impact on the contacts
contacts.detect closes, with the Zeno rule), then the acceleration-level contact problem that
decides which touching contacts persist (event_driven.py's module doc states the rules).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import coal
import numpy as np
import pinocchio as pin

from .constraints import assemble_constraints
from .contacts import detect
from .data import Data
from .errors import MoreauSimError, SimulationError, named_stops
from .law import impact, project
from .model import Model
from .recording import LOG_RELATIVE, PercussionRow, Recorder
from .state import State
from .trajectory import Trajectory

V_TOL = 1e-9  # [m/s] |gamma| <= this on a closed feature: touching, not impacting
G_RES = 1e-13  # [m] smallest gap whose sign is trusted (~3000x the rounding of positions ~ 1 m)
G_ZENO = 1e-12  # [m] a rebound whose apex would stay below this is not resolved (Zeno rule)
V_ZENO = 1e-8  # [m/s] nor an impact slower than this
DT_ZENO = 1e-12  # [s] nor an impact this soon after the previous one
LAM_EPS = 1e-9  # [N] a persistent contact is released when its multiplier falls below -LAM_EPS
ACC_TOL = 1e-8  # [m/s^2] relative acceleration below this (scaled): a touching contact persists


class UnsupportedModel(MoreauSimError, ValueError):
    """The reference cannot integrate this model (a pair type it has no analytic gap for)."""


@dataclass(frozen=True, slots=True)
class Feature:
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


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for 3-vectors (in Python floats: the same IEEE operations, without numpy's per-element cost)."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def feature_list(model: Model) -> tuple[Feature, ...]:
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
                out.append(Feature("point_plane", pair.index, -1, ja, 0, centre, n, d + sa.radius))
                continue
            if len(model.vertices[pair.first]):
                out += [Feature("point_plane", pair.index, i, ja, 0, v.copy(), n, d)
                        for i, v in enumerate(model.vertices[pair.first])]
                continue
        if isinstance(sa, coal.Sphere) and isinstance(sb, coal.Sphere):
            out.append(Feature("sphere_sphere", pair.index, -1, ja, jb, ga.placement.translation.copy(),
                                r=sa.radius, p_b=gb.placement.translation.copy(), r_b=sb.radius))
            continue
        if isinstance(sa, coal.Sphere) and isinstance(sb, coal.Box) and jb == 0:
            out.append(Feature("sphere_box", pair.index, -1, ja, 0, ga.placement.translation.copy(), r=sa.radius,
                                R=gb.placement.rotation.copy(), p_b=gb.placement.translation.copy(),
                                h=np.asarray(sb.halfSide, float).copy()))
            continue
        raise UnsupportedModel(f"{model.scene.name}: pair '{pair.name}' ({type(sa).__name__} vs "
                               f"{type(sb).__name__}): the event-driven reference has gaps for polytope or "
                               "sphere vs half-space, sphere vs sphere and sphere vs static box only")
    return tuple(out)


@dataclass(frozen=True, slots=True)
class FeatureState:
    """Gaps g [m], rows W (nv, k), drift Wdot' u [m/s^2] and gamma = W' u [m/s] of features."""

    g: np.ndarray
    W: np.ndarray
    drift: np.ndarray
    gamma: np.ndarray


class CornerImpact(SimulationError):
    """An impact at a corner (docs/theory.md §3): the feature integrators handle smooth contacts only."""


class FeatureContacts:
    """The features of a model and the contact decisions at events (module doc). Mutable
    bookkeeping shared by the event-driven and the adaptive runs: the Recorder `rec` (set by the
    caller), the Zeno declarations, the contact work since the last sample, counters."""

    def __init__(self, model: Model, data: Data, e: float, feats: tuple[Feature, ...] | None = None):
        self.model, self.data, self.e = model, data, e
        # a feature is closed when its gap is <= this [m]: the tolerance contacts.detect uses
        self.gap_tol = max(model.options.contact_tolerance, G_RES)
        self.pm, self.pd = model.pin, data.pin
        self.nv = model.nv
        self.feats = feature_list(model) if feats is None else feats
        self.zero = np.zeros(self.nv)
        self.rec: Recorder | None = None
        self.zeno: list[dict] = []
        self.work = 0.0  # contact work since the last sample [J] (= -energy lost in impacts)
        self.last_impact = -np.inf
        self.impacts = self.nfev = 0
        self.t = float("nan")  # [s] where the run is (errors name it): a step's or phase's start, an event

    # ---- kinematics of the features -------------------------------------------------------
    def _point(self, j: int, p_local: np.ndarray, rows: bool):
        """World position, velocity, bias acceleration (q'' = 0) and Jacobian (3, nv) of a
        point fixed in joint j's frame (needs forwardKinematics(q, u, 0) and, for rows, J)."""
        if j == 0:
            return p_local, np.zeros(3), np.zeros(3), (np.zeros((3, self.nv)) if rows else None)
        frame = self._frames.get(j)
        if frame is None:  # the joint's placement, twist and bias acceleration, read once per call
            M, v, a = self.pd.oMi[j], self.pd.v[j], self.pd.a[j]
            frame = self._frames[j] = (M.rotation, M.translation, v.angular, v.linear, a.angular, a.linear)
        R, t, w, v_lin, a_ang, a_lin = frame
        vl = v_lin + cross(w, p_local)
        p = R @ p_local + t
        vel = R @ vl
        acc = R @ (a_lin + cross(a_ang, p_local) + cross(w, vl))
        Jp = None
        if rows:
            if self._J is None:
                self._J = self.pd.J.reshape(6, -1)
            J = self._J
            Jp = (J[:3] - pin.skew(p) @ J[3:]) * self.model.support_mask[j]
        return p, vel, acc, Jp

    def features(self, q: np.ndarray, u: np.ndarray, idx=None, rows: bool = True) -> FeatureState:
        """Gaps (and rows, drift, gamma if `rows`) of the features `idx` (default all) at (q, u)."""
        pm, pd = self.pm, self.pd
        if rows:
            pin.computeJointJacobians(pm, pd, q)
        pin.forwardKinematics(pm, pd, q, u, self.zero)
        self._frames, self._J = {}, None
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
        return FeatureState(g, W, drift, gamma)


    # ---- dynamics --------------------------------------------------------------------------
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
        self.t = t
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
            raise SimulationError(f"the contact-force QP failed ({res.status}) at t = {t:.12g} s")
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

    def _impact(self, t, q, u, fs: FeatureState) -> np.ndarray:
        """The impact law (law.impact, docs/theory.md §1) on the contacts detect() closes at q."""
        pm, pd, model = self.pm, self.pd, self.model
        c = detect(model, self.data, q)
        if c.corners:
            raise CornerImpact(f"a corner impact at t = {t:.12g} s (docs/theory.md §3); the event-driven "
                                  "reference handles smooth contacts only", t=t)
        cs = assemble_constraints(model, self.data, q, c)
        c, M, W = cs.contacts, cs.M, cs.W
        if c.m == 0:
            raise SimulationError(f"a gap event at t = {t:.12g} s but coal finds no closed contact")
        gm = W.T @ u
        if not (gm < -V_TOL).any():
            raise SimulationError(f"a feature approaches at t = {t:.12g} s (gamma = {fs.gamma.min():.3g} m/s) but "
                                  "none of coal's closed contacts does")
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
        self.rec.account_impact(t, q, u, imp.u_plus, M, imp.qp.v, 0.0 if zeno else self.e, imp.P)
        self.work -= imp.energy_loss
        self.last_impact = t
        self.impacts += 1
        return imp.u_plus



    unit = "phase"  # what position() counts, in error messages

    def position(self) -> tuple[int, float]:
        """(the number of the step or phase under way, its time [s]): what an error names."""
        return self.events + 1, self.t

    def sample(self, t: float, q: np.ndarray, u: np.ndarray, n_contacts: int, corr: float = 0.0) -> None:
        """Record a sample with the contact work (and correction energy) since the previous one;
        a non-finite one stops the run (nothing non-finite is ever complete)."""
        if not (np.isfinite(q).all() and np.isfinite(u).all()):
            raise SimulationError(f"the state at t = {t:.6g} s became non-finite (NaN or inf)")
        self.rec.sample(State(t, q, u), self.work, corr, n_contacts)
        self.work = 0.0
        if not self.rec.finite():
            raise SimulationError(f"the energies or gaps at t = {t:.6g} s became non-finite (an overflow: check "
                                  "gravity, masses and initial velocities)")


def sample_grid(model: Model, state: State, t_end: float | None, t_eval) -> tuple[float, np.ndarray]:
    """t_end [s] (default: state.t + the scene's duration) and the sample instants of a run that
    locates events: t_eval, checked to increase strictly within [t0, t_end], or by default every
    save_every * dt of the scene's options (the instants ms.simulate records)."""
    opts = model.options
    t_end = state.t + opts.duration if t_end is None else float(t_end)
    if not t_end > state.t:
        raise ValueError(f"t_end = {t_end} s must be after the initial time {state.t} s")
    if t_eval is None:
        n = max(1, int(round((t_end - state.t) / (opts.dt * opts.save_every))))
        return t_end, state.t + (t_end - state.t) * np.arange(n + 1) / n
    t_grid = np.asarray(t_eval, float)
    if t_grid.ndim != 1 or np.any(np.diff(t_grid) <= 0) or t_grid[0] < state.t or t_grid[-1] > t_end:
        raise ValueError(f"t_eval must increase strictly within [{state.t}, {t_end}] s")
    return t_end, t_grid


def run_recorded(integ: FeatureContacts, state: State, t_end: float, t_grid: np.ndarray, meta) -> Trajectory:
    """integ.run(state, t_end, t_grid) into a new Recorder; the Trajectory with meta(model, integ,
    status, wall0), or (errors.named_stops) SimulationError naming integ.position() with
    .trajectory up to the failure, SimulationInterrupted on Ctrl-C."""
    integ.rec = Recorder(integ.model, integ.data, len(t_grid))
    integ.t = float(state.t)
    wall0 = time.perf_counter()

    def partial(status: str) -> Trajectory:
        return integ.rec.trajectory(meta(integ.model, integ, status, wall0))

    with named_stops(integ.position, partial, unit=integ.unit):
        integ.run(state, t_end, t_grid)
    return integ.rec.trajectory(meta(integ.model, integ, "complete", wall0))
