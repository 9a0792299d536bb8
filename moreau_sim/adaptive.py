"""The adaptive integrator (docs/theory.md §8): extrapolated symmetric midpoint steps with error
control and a quintic Hermite dense output between events, impacts located on the per-feature
gaps (gaps.py) and resolved by event_rules.resolve, fixed Moreau steps where
those do not apply; the loop is driver.drive (§9).

    traj = simulate_adaptive(model)          # or ms.run(path, integrator="adaptive", rtol=..., atol=...)
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pinocchio as pin

from . import compiled_events
from .adaptive_carried import NO_ROWS, Carried, End, Mode
from .adaptive_static import FIXED_POINT, extrapolator_of, features_of, static_of
from .actuation import refuse_driven
from .drive import refuse as refuse_drives
from .data import Data
from .errors import SimulationError
from .hermite import CHECK, CHECK_BASIS, CHECK_FLOATS, QUINTIC, poly, polyslope, polyval
from .checkpoint import Checkpoint
from .driver import Check, drive, run_data
from .event_rules import (G_REGION, G_RES, LAM_EPS, V_TOL, dynamics, features, make_rules,
                          phase_sets, resolve, sample_grid, thin_limit)
from .model import Model, initial_state
from .options import Bias
from .protocol import FixedStep, Report, Segment, Status
from .qp import _lu_solve
from .sums import ordered
from .recording import run_metadata
from .state import State
from .stepper import free_velocity, midpoint_fixed_point, step
from .trajectory import Trajectory

ORDERS = (4, 6, 8)  # n = 1..order/2 midpoint steps of H/n, extrapolated in h^2
DEFAULT_ORDER = 6
SAFETY, MIN_FACTOR, MAX_FACTOR = 0.9, 0.2, 10.0  # step-size control as scipy's solve_ivp
LAND_ITER = 4  # Newton corrections of a landed step (dt = -g/gamma)
G_LAND = 1e-15  # [m] a landed gap within this of 0 is not corrected further
BURST_EVENTS = 64  # this many events within one fixed step dt: an accumulation, fixed steps
V_BACK = 1e-6  # [m/s] closed contacts slower than this after a fixed step: at rest
H_MIN = 1e-14  # [s] smallest extrapolated step before giving up on a phase (fixed steps then)
BOX_TRAVEL = 0.25  # a step's travel while boxes are near, in their smallest half side (_box_limit)


def brentq(f, a: float, b: float, **kwargs) -> float:
    """scipy.optimize.brentq, imported on first use: scipy.optimize is ~40 MB of RSS that a
    time-stepping run never needs (the fault tests patch this name)."""
    from scipy.optimize import brentq as root

    return root(f, a, b, **kwargs)


def _root(f, lo: float, hi: float, xtol: float) -> float:
    """The crossing of f from > 0 to <= 0 in [lo, hi] (Brent); lo if f(lo) <= 0 already, hi if
    f(hi) > 0 after all (round-off between the bracket test and f)."""
    if f(lo) <= 0.0:
        return lo
    if f(hi) > 0.0:
        return hi
    return brentq(f, lo, hi, xtol=xtol)


class AdaptiveRun:
    """The adaptive integrator behind the step protocol (protocol.py; the public API is
    simulate_adaptive): a step is an accepted extrapolated step, a landing on an event, or a
    fixed step."""

    grid = True

    def __init__(self, model: Model, data: Data, e: float, rtol: float, atol: float, order: int,
                 max_step: float, max_events: int, *, state: State | None = None, t_end: float = np.inf):
        feats, self.unsupported = features_of(model)
        self.rules = make_rules(model, data, e, feats)  # what the event rules read of the model (event_rules.py)
        self.model, self.data, self.e, self.feats, self.gap_tol = model, data, e, self.rules.feats, self.rules.gap_tol
        self.pm, self.pd, self.nv, self.zero = model.pin, data.pin, model.nv, np.zeros(model.nv)
        st = static_of(model, self.feats)
        self.is_box, self.box_half, self.any_box, self.lie = st.is_box, st.box_half, st.any_box, st.lie
        self.neutral, self.flat, self._fars = st.neutral, st.flat, st.far
        if order not in ORDERS:
            raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
        self.rtol, self.atol, self.order, self.max_step, self.max_events = rtol, atol, order, max_step, max_events
        self.seq = tuple(range(1, order // 2 + 1))
        seq = self.seq  # the extrapolation's divisors: ratios[j][m - 1] = (seq[j] / seq[j - m])^2 - 1
        self.ratios = tuple(tuple((seq[j] / seq[j - m]) ** 2 - 1.0 for m in range(1, j + 1)) for j in range(len(seq)))
        # the compiled _step without a persistent set (src/events.hpp; None: the Python one, step_impl = "python")
        self.extrapolate = extrapolator_of(model, self.seq, self.ratios, self.lie, rtol, atol)
        # the samples on the dense output and their figures, a step's at once (None: dense() one by one)
        self.sampler = compiled_events.sampler(model, data, lie=self.lie, basis=QUINTIC)
        # the event location in free flight without box features (src/locate.hpp; None: the Python one)
        self.locate = None if self.any_box else compiled_events.locator(
            model, check=CHECK, check_basis=CHECK_BASIS, quintic=QUINTIC, v_tol=V_TOL)
        # a step in free flight in one call (src/phase.hpp: the three above and the step-size control, the same
        # floats; None: they are called one by one)
        self.phase = None if not self.flat else compiled_events.phase_step(
            self.extrapolate, self.rules.gaps.compiled, self.locate, rtol=rtol, atol=atol, order=order, h_min=H_MIN,
            safety=SAFETY, min_factor=MIN_FACTOR, land_iter=LAND_ITER, g_land=G_LAND)
        self.phase_status = None if self.phase is None else compiled_events.phase_statuses()
        self.h_fix = model.options.dt
        state = state or initial_state(model, data)
        self.s = Carried(State(float(state.t), np.array(state.q, float), np.array(state.u, float)), float(state.t),
                         H=min(self.max_step, 10.0 * self.h_fix))
        self.t0, self.t_end = self.s.state.t, float(t_end)
        if self.unsupported is not None:
            self.s.mode = Mode.FIXED
            self.s.previous_fresh = True
            self.s.fallbacks.append({"t": self.s.t, "reason": self.unsupported})

    @property
    def state(self) -> State:
        """The current accepted state (protocol.Integrator.state)."""
        return self.s.state

    # ---- the extrapolated step -------------------------------------------------------------
    def _midpoint(self, q, u, h, C):
        """The symmetric midpoint step (module doc), free or on the constrained set C. Without C
        and without velocity-dependent forces it is stepper.free_velocity's single ABA; otherwise
        the fixed point u1 = u + h a(q_m, (u + u1)/2) is iterated to FIXED_POINT times the step's
        tolerance (atol + rtol |u|), well below what the extrapolation resolves."""
        pm = self.pm
        q_m = pin.integrate(pm, q, 0.5 * h * u)
        if not C and not self.model.velocity_bias:
            u1 = free_velocity(self.model, self.data, q_m, u, h, Bias.MIDPOINT)
        else:
            at_q: dict = {}  # (the fixed point keeps q_m: what depends on it alone is computed once, dynamics)

            def acc(v):
                return dynamics(self.rules, self.s.ev, q_m, v, C, at_q)[0] if C else pin.aba(pm, self.pd, q_m, v,
                                                                                               self.zero)
            tol = FIXED_POINT * (self.atol + self.rtol * float(np.abs(u).max()))
            u1 = midpoint_fixed_point(acc, u, h, u + h * acc(u), tol)
        return pin.integrate(pm, q_m, 0.5 * h * u1), u1

    def _delta(self, q0, q):
        return pin.difference(self.pm, q0, q) if self.lie else q - q0

    def _step(self, q0, u0, H, C):
        """The extrapolated step of size H: (q1, u1, error estimate in (delta, u) coordinates); without C
        compiled where it applies (compiled_events: the same floats)."""
        if not C and self.extrapolate is not None:
            return self.extrapolate(q0, u0, H)
        seq, nv = self.seq, self.nv
        rows = []
        for j, n in enumerate(seq):
            h = H / n
            q, u = q0, u0
            for _ in range(n):
                q, u = self._midpoint(q, u, h, C)
            row = [np.concatenate((self._delta(q0, q), u))]
            for m in range(1, j + 1):
                row.append(row[m - 1] + (row[m - 1] - rows[j - 1][m - 1]) / self.ratios[j][m - 1])
            rows.append(row)
        y = rows[-1][-1]
        q1 = pin.integrate(self.pm, q0, y[:nv]) if self.lie else q0 + y[:nv]
        return q1, y[nv:].copy(), y - rows[-1][-2]

    def _size(self, q, u) -> np.ndarray:
        """|(pin.difference(neutral, q), u)|, the error test's scale of a step end (§8). On a vector space (no joint
        with nq != nv) whose neutral is 0 that difference is q - 0 elementwise: q's own floats but the sign of a zero,
        which the absolute value drops."""
        if self.flat:
            return np.abs(np.concatenate((q, u)))
        return np.abs(np.concatenate((pin.difference(self.pm, self.neutral, q), u)))

    def _error(self, z0, q1, u1, d) -> float:
        """The error estimate d of a step from a point of scale z0 (_size) to (q1, u1), in units of the tolerance:
        the RMS of d / (atol + rtol max(z0, z1)), summed in index order (§2.8: Python's sum adds in order from its
        first term, as sums.ordered does)."""
        z = d / (self.atol + self.rtol * np.maximum(z0, self._size(q1, u1)))
        if not len(z):
            return math.nan
        return math.sqrt((sum((z * z).tolist()) + 0.0) / len(z))

    def _far(self, k: int) -> np.ndarray:
        """End.near of k compiled features (no box among them: all False), made once per k and read-only."""
        got = self._fars.get(k)
        if got is None:
            got = self._fars[k] = np.zeros(k, bool)
            got.flags.writeable = False
        return got

    def _free_end(self, t, q, u, a, g, gamma, gdd) -> End:
        """The step end at (t, q, u) in free flight on compiled features: their (a, g, gamma, gdd) as FeatureGaps.end
        gives them (no multipliers, no regions, no box feature near)."""
        return End(t, q, u, a, NO_ROWS, g, gamma, gdd, NO_ROWS, self._far(len(g)))

    def _end(self, t, q, u, C, idx, end=None) -> End:
        """The step end at (t, q, u) with the persistent set C, of the watched features idx; end: their compiled
        (a, g, gamma, gdd) at (q, u) where already computed (_land's)."""
        pg = self.rules.gaps.compiled
        if pg is not None and not C and idx:  # free flight, compiled features: the same floats
            self.s.ev.nfev += 1  # (dynamics counts its calls)
            return self._free_end(t, q, u, *(pg.end(q, u, idx) if end is None else end))
        a, lam, fc = dynamics(self.rules, self.s.ev, q, u, C)
        margin = fc.margin if C else np.zeros(0)  # C's distances to their regions' ends
        if idx:
            fs = features(self.rules, self.s.ev, q, u, idx)
            near = self.is_box[idx] & np.isfinite(fs.margin)
            return End(t, q, u, a, lam, fs.g, fs.gamma, ordered(fs.W.T, a) + fs.drift, margin, near)
        z = np.zeros(0)
        return End(t, q, u, a, lam, z, z, z, margin, np.zeros(0, bool))

    # ---- dense output ----------------------------------------------------------------------
    def _dense(self, e0: End, e1: End):
        """tau in [0, 1] -> (q, u) on the step from e0 to e1 (quintic Hermite in the tangent space
        about e0.q; for a Lie group the end slopes through dIntegrate)."""
        H = e1.t - e0.t
        d1 = self._delta(e0.q, e1.q)
        if self.lie:  # delta' = J^-1 u, delta'' = J^-1 a + (J^-1)' u, the last by central differences
            def slope(d):
                return _lu_solve(pin.dIntegrate(self.pm, e0.q, d, pin.ArgumentPosition.ARG1), e1.u)
            s1 = slope(d1)
            eps = 1e-5 / (1.0 + float(np.abs(s1).max()))
            Jinv_dot_u = (slope(d1 + eps * s1) - slope(d1 - eps * s1)) / (2.0 * eps)
            c1 = _lu_solve(pin.dIntegrate(self.pm, e0.q, d1, pin.ArgumentPosition.ARG1), e1.a) + Jinv_dot_u
        else:
            s1, c1 = e1.u, e1.a
        p = poly(np.array([np.zeros(self.nv), H * e0.u, H * H * e0.a, d1, H * s1, H * H * c1]))

        def at(tau: float):
            d, s = polyval(p, tau), (polyslope(p, tau) / H if H > 0 else e0.u)
            if not self.lie:
                return e0.q + d, s
            J = pin.dIntegrate(self.pm, e0.q, d, pin.ArgumentPosition.ARG1)
            return pin.integrate(self.pm, e0.q, d), ordered(J, s)
        return at

    def _segment(self, e0: End, e1: End, n_contacts: int, last: bool) -> Segment:
        """The grid instants before e1.t (up to and including it if `last`) on the step, sampled on
        its dense output (built on first use); compiled, all at once, where it applies (the same floats)."""
        if self.sampler is not None:
            def batch(tgs):
                return self.sampler(e0.t, e0.q, e0.u, e0.a, e1.t, e1.q, e1.u, e1.a, tgs)
        else:
            batch = None
        return Segment(self._dense_at(e0, e1), e1.t, last, n_contacts, batch)

    def _dense_at(self, e0: End, e1: End):
        """dense(t) -> (q, u) on the step e0 -> e1 at the instant t [s] (_dense, clamped to the step)."""
        H, at = e1.t - e0.t, []

        def dense(tg: float):
            if tg >= e1.t:
                return e1.q, e1.u
            if H > 0:
                if not at:
                    at.append(self._dense(e0, e1))
                return at[0](min(max((tg - e0.t) / H, 0.0), 1.0))
            return e0.q, e0.u
        return dense

    unit = "step"

    def position(self) -> tuple[int, float]:
        return self.s.accepted + self.s.rejected + self.s.fixed + 1, self.s.t

    # ---- events ----------------------------------------------------------------------------
    def _first_event(self, e0: End, e1: End, nw: int, C, watched):
        """The earliest event on the step e0 -> e1 as (tau, kind, index into watched = watch+low / C),
        or None; without C and box features compiled where it applies (compiled_events.locator: the same floats)."""
        if self.locate is not None and not len(C):
            status, tau, kind, k = self.locate(e0.t, e0.g, e0.gamma, e0.gdd, e1.t, e1.g, e1.gamma, e1.gdd, nw)
            if status >= 0:
                return (tau, "gap" if kind == 0 else "return", k) if status else None
        H = e1.t - e0.t
        best = None
        taus = CHECK
        if len(e0.g):
            coef = np.array([e0.g, H * e0.gamma, H * H * e0.gdd, e1.g, H * e1.gamma, H * H * e1.gdd])
            # box-box gaps (docs/theory.md §7.1) are maxima over faces and an edge pair's stand-in: not
            # smooth enough for the quintic. Where one could close within the step (its gap below how far
            # a point can travel in it), it is evaluated on the dense output at the check instants
            travel = H * float(max(np.abs(e0.u).max(), np.abs(e1.u).max())) * self.model.reach + self.gap_tol
            box = self.is_box[watched]
            near = np.flatnonzero(box[:nw] & (np.minimum(e0.g, e1.g)[:nw] <= travel))
            if len(near):
                at = self._dense(e0, e1)
                ids = [watched[k] for k in near]
                Gd = np.array([e0.g[near]]
                              + [features(self.rules, self.s.ev, *at(x), ids, rows=False).g for x in taus[1:-1]]
                              + [e1.g[near]])
                for col in np.flatnonzero((Gd < 0.0).any(axis=0)):
                    j, k = int(np.argmax(Gd[:, col] < 0.0)), int(near[col])

                    def fg(x, k=k):
                        if not x < 1.0:
                            return e1.g[k]
                        return float(features(self.rules, self.s.ev, *at(x), [watched[k]], rows=False).g[0])
                    tau = _root(fg, taus[j - 1], taus[j], 1e-15) if j else 0.0
                    if best is None or tau < best[0]:
                        best = (tau, "gap", k)
            done = box  # located above, or too far to close
            G = ordered(CHECK_BASIS, coef)  # (points, features)
            G[-1] = e1.g
            crossing = np.flatnonzero((G[:, :nw] < 0.0).any(axis=0) & ~done[:nw])
            first = {int(k): int(np.argmax(G[:, k] < 0.0)) for k in crossing}
            j_min = min(first.values(), default=0)
            if best is not None:  # a densely located one: the polynomial's brackets after it do not count
                j_min = min(j_min, int(np.searchsorted(taus, best[0])))
            for k, j in first.items():
                if j > j_min:  # a later bracket: its root is later than one of the first bracket's
                    continue
                pk = poly(coef[:, k])

                def f(x, pk=pk):
                    return float(polyval(pk, x))
                tau = _root(f, taus[j - 1], taus[j], 1e-15)
                if best is None or tau < best[0]:
                    best = (tau, "gap", k)
            # a feature within G_RES of contact coming back: gamma below -2 V_TOL (cubic Hermite of gamma)
            for k in range(nw, len(e0.g)):
                # Python floats: the same IEEE operations as on numpy's float64 scalars (x ** 3 is libm's pow on
                # both), at a fraction of their cost
                gc = (float(e0.gamma[k] + 2 * V_TOL), float(H * e0.gdd[k]), float(e1.gamma[k] + 2 * V_TOL),
                      float(H * e1.gdd[k]))

                def fr(x, gc=gc):
                    return float(gc[0] * (1 - 3 * x * x + 2 * x ** 3) + gc[1] * (x - 2 * x * x + x ** 3)
                                 + gc[2] * (3 * x * x - 2 * x ** 3) + gc[3] * (x ** 3 - x * x))
                vals = np.array([fr(x) for x in CHECK_FLOATS])
                if (vals[1:] < 0).any() and vals[0] >= 0:
                    j = int(np.argmax(vals[1:] < 0)) + 1
                    tau = _root(fr, taus[j - 1], taus[j], 1e-15)
                    if best is None or tau < best[0]:
                        best = (tau, "return", k)
        if len(C) and (e1.lam < -LAM_EPS).any():
            at = self._dense(e0, e1)
            for k in np.flatnonzero(e1.lam < -LAM_EPS):
                def fl(x, k=k):
                    q, u = at(x)
                    return float(dynamics(self.rules, self.s.ev, q, u, C)[1][k]) + LAM_EPS
                tau = _root(fl, 0.0, 1.0, 1e-13)
                if best is None or tau < best[0]:
                    best = (tau, "release", int(k))
        if len(C) and (e1.margin < -G_REGION).any():  # a box feature passing its region's end (§7.1)
            at = self._dense(e0, e1)
            for k in np.flatnonzero(e1.margin < -G_REGION):
                def fm(x, k=k):
                    return float(dynamics(self.rules, self.s.ev, *at(x), C)[2].margin[k]) + G_REGION
                tau = _root(fm, 0.0, 1.0, 1e-13)
                if best is None or tau < best[0]:
                    best = (tau, "release", int(k))
        return best

    def _land(self, e0: End, H: float, C, watched: list, k: int | None):
        """Re-take the step from e0 with size H onto the event; for a gap (watched[k]), Newton on g = 0.
        Returns (size, q1, u1, end): end, in free flight on compiled features, (a, g, gamma, gdd) of `watched` at
        (q1, u1) as _end computes them (the iterations' own: their g and gamma are features()'s), else None."""
        hs, q1, u1, end = 0.0, e0.q, e0.u, None  # the last step taken: its size and end
        pg = self.rules.gaps.compiled if not C else None
        for _ in range(LAND_ITER if k is not None else 1):
            if H <= 0.0:
                break
            hs, (q1, u1, _) = H, self._step(e0.q, e0.u, H, C)
            self.s.landings += 1
            if k is None:
                break
            if pg is None:
                fs = features(self.rules, self.s.ev, q1, u1, [watched[k]])
                g, gam = float(fs.g[0]), float(fs.gamma[0])
            else:
                end = pg.end(q1, u1, watched)
                g, gam = float(end[1][k]), float(end[2][k])
            if abs(g) <= G_LAND or gam >= 0.0:
                break
            H -= g / gam
        return hs, q1, u1, end

    # ---- the run: one step() per accepted point ---------------------------------------------
    def step(self, t_sample: float = np.inf) -> Report:
        """A fixed step in fixed mode; else, at a phase's start, the decisions there
        (event_rules.resolve), then extrapolated steps until one is accepted, lands on an event
        or no step size passes (module doc). t_sample [s]: the next output instant (fixed steps land on it)."""
        if self.s.mode is Mode.FIXED:
            return self._fixed_step(t_sample)
        records, work = (), 0.0
        if self.s.mode is Mode.EVENT:
            records, work = self._start_phase()
        t, q, u, t_end = self.s.state.t, self.s.state.q, self.s.state.u, self.t_end
        C, watch, low = self.s.C, self.s.watch, self.s.low
        e0, H = self.s.e0, self.s.H
        limit = min(self.max_step, self._rise_limit(e0, len(watch)), self._box_limit(e0),
                    thin_limit(self.rules, u, e0.a))  # (functions of the step's start)
        self.s.t = t
        watched = watch + low
        landed = None
        if self.phase is not None and not C and watched:  # compiled in one call: the same floats (src/phase.hpp)
            status, h, err, rejected, ends, landings, got, landed = self.phase(
                t, q, u, H, limit, t_end, e0.t, e0.q, e0.u, e0.g, e0.gamma, e0.gdd, watched, len(watch))
            self.s.rejected += rejected
            self.s.ev.nfev += ends
            self.s.landings += landings
            S = self.phase_status
            if status is S.NONFINITE:
                self._nonfinite(h)
            if status is S.REFUSED:
                return self._refused(t, records, work)
            if got is not None:  # accepted (the event location Python's where the locator handed it back)
                t1, q1, u1 = got[:3]
                e1 = self._free_end(*got)
                ev = None if status is S.ACCEPTED else self._first_event(e0, e1, len(watch), C, watched)
            else:
                ev = (landed[0], "gap" if landed[1] == 0 else "return", landed[2])
        else:
            z0 = self._size(q, u)
            while True:
                h = min(H, limit, t_end - t)
                q1, u1, d = self._step(q, u, h, C)
                err = self._error(z0, q1, u1, d)
                if not np.isfinite(err):
                    self._nonfinite(h)
                if err <= 1.0:
                    break
                self.s.rejected += 1
                H = h * max(MIN_FACTOR, SAFETY * err ** (-1.0 / (self.order - 1)))
                if H < H_MIN:  # no step size passes: fixed steps
                    return self._refused(t, records, work)
            t1 = t_end if h >= t_end - t else t + h
            e1 = self._end(t1, q1, u1, C, watched)
            ev = self._first_event(e0, e1, len(watch), C, watched)
        last = h >= t_end - t
        grow = MAX_FACTOR if err == 0.0 else min(MAX_FACTOR, SAFETY * err ** (-1.0 / (self.order - 1)))
        if ev is None:
            self.s.accepted += 1
            seg = self._segment(e0, e1, len(C), last)
            self.s.state, self.s.e0 = State(t1, q1, u1), e1
            self.s.H = h * grow if h >= H else H
            if last:
                return Report(Status.FINISHED, t1, self.s.state, records, work, segments=(seg,))
            risen = [i for k, i in enumerate(low) if e1.g[len(watch) + k] >= G_RES]
            if risen:  # a feature rose above G_RES: its gap is watched from now on
                self.s.low = [i for i in low if i not in risen]
                self.s.watch = watch + risen
                self.s.e0 = self._end(t1, q1, u1, C, self.s.watch + self.s.low)
            return Report(Status.RUNNING, t1, self.s.state, records, work, segments=(seg,))
        tau, kind, k = ev
        if landed is None:
            hs, q1, u1, end = self._land(e0, tau * h, C, watched, k if kind == "gap" else None)
            hs = min(hs, t_end - t)
            e1 = self._end(t + hs, q1, u1, C, watched, end)
        else:  # (compiled: the landing and its end, _land's and _end's)
            hs, q1, u1 = landed[3:6]
            e1 = self._free_end(t + hs, *landed[4:])
        segs = (self._segment(e0, e1, len(C), False),)
        self.s.stuck = self.s.stuck + 1 if hs < 1e-13 else 0
        t = t + hs
        self.s.state = State(t, q1, u1)
        self.s.H = max(h, H_MIN)
        self.s.released = frozenset({C[k]}) if kind == "release" else frozenset()
        self.s.mode = Mode.EVENT
        if not t < t_end:  # (a NaN time too: the samples left then stop the run as non-finite)
            return Report(Status.FINISHED, t, self.s.state, records, work, segments=segs + self._rest())
        self.s.events += 1
        if self.s.events > self.max_events:
            raise SimulationError(f"more than {self.max_events} events")
        self.s.burst.append(t)
        while self.s.burst and self.s.burst[0] < t - self.h_fix:
            self.s.burst.pop(0)
        if len(self.s.burst) >= BURST_EVENTS or self.s.stuck > 100:
            self.s.mode = self._fall(t, self.s.t_back, f"{len(self.s.burst)} events within dt = {self.h_fix:g} s"
                                   if len(self.s.burst) >= BURST_EVENTS else "100 events without time advancing")
        return Report(Status.RUNNING, t, self.s.state, records, work, segments=segs)

    def _nonfinite(self, h: float) -> None:
        """An overflow (or a failed library call) in a step of size h [s]: no step size helps."""
        raise SimulationError(f"the error estimate of an extrapolated step of {h:.3g} s is non-finite")

    def _refused(self, t: float, records: tuple, work: float) -> Report:
        """No step size passes the error test at t [s]: fixed steps from here."""
        self.s.H = min(self.max_step, 10.0 * self.h_fix)
        self.s.mode = self._fall(t, self.s.t_back, "the error test refused every step size")
        return Report(Status.RUNNING, t, self.s.state, records, work)

    def _start_phase(self) -> tuple[tuple, float]:
        """The decisions at an event (or the start, or back from fixed steps); the phase's sets."""
        t, q, u = self.s.state.t, self.s.state.q, self.s.state.u
        self.s.t = t
        res = resolve(self.rules, self.s.ev, t, q, u, self.s.released)
        self.s.state = State(t, q, res.u)
        self.s.released = frozenset()
        self._phase(res.C, res.shadow, g=res.g)
        records, work = res.records, res.work
        self.s.mode = Mode.PHASE
        return records, work

    def _phase(self, C, shadow, low=None, watch=None, g=None) -> None:
        """The persistent set C, the watched features (watch; low: within G_RES of contact at the
        phase's start, watched by their rise and return) and the step end e0 at the current state;
        g: the gaps of all features there where known (event_rules.Resolution.g)."""
        t, q, u = self.s.state.t, self.s.state.q, self.s.state.u
        if low is None:
            free, _, low = phase_sets(self.rules, self.s.ev, q, u, C, shadow, g=g)
            watch = [i for i in free if i not in low]
        self.s.C, self.s.shadow, self.s.low, self.s.watch = tuple(C), tuple(shadow), list(low), list(watch)
        self.s.e0 = self._end(t, q, u, C, watch + low)

    def _rest(self) -> tuple[Segment, ...]:
        """The grid instants left at the end (the state there, no contacts)."""
        q, u = self.s.state.q, self.s.state.u
        return (Segment(lambda tg: (q, u), np.inf, True, 0),)

    def _rise_limit(self, e0: End, nw: int) -> float:
        """While a feature within G_RES of contact rises, steps stay below half its time to apex
        (its rise and fall must not fit in one step)."""
        if nw >= len(e0.gamma):  # none within G_RES
            return np.inf
        # on Python floats: the same IEEE operations as numpy's, (0.5 gamma) / -gdd, at a fraction of their cost
        up = [0.5 * gam / -gdd for gam, gdd in zip(e0.gamma[nw:].tolist(), e0.gdd[nw:].tolist())
              if gam > V_TOL and gdd < 0]
        return min(up) if up else np.inf

    def _box_limit(self, e0: End) -> float:
        """While two boxes' bounding spheres overlap, no point moves more than BOX_TRAVEL of the
        smallest half side in a step: the dense checks of their gaps (_first_event) then see a
        corner's or an edge's passage through a face."""
        if not self.any_box or not e0.near.any():
            return np.inf
        v = float(np.abs(e0.u).max()) * self.model.reach
        return BOX_TRAVEL * self.box_half / v if v > 0.0 else np.inf

    def _fall(self, t: float, t_back: float, reason: str) -> "Mode":
        if t - t_back < 10 * self.s.back_steps * self.h_fix:
            self.s.back_steps *= 2
        self.s.fallbacks.append({"t": t, "reason": reason})
        self.s.previous_fresh, self.s.quiet = True, 0
        return Mode.FIXED

    def _fixed_step(self, t_sample: float) -> Report:
        """A fixed midpoint Moreau step of the scene's dt (landing on the next sample instant);
        back to extrapolated steps after back_steps quiet ones when the model has features."""
        t, q, u, t_end = self.s.state.t, self.s.state.q, self.s.state.u, self.t_end
        self.s.t = t
        nxt = min(t_sample, t_end)
        # a step of dt, or onto the next sample instant when that is at most dt (+ round-off) away
        t1 = nxt if nxt - t <= self.h_fix * (1.0 + 1e-9) else t + self.h_fix
        h = t1 - t
        r = step(self.model, self.data, self.s.state, h=h, e=self.e, t_next=t1)
        if r.qp is not None and not r.qp.ok:
            raise SimulationError(f"a fixed step's impact QP failed with status {r.qp.status}")
        if not r.state.finite():
            raise SimulationError("a fixed step's state became non-finite (NaN or inf)")
        self.s.fixed += 1
        rec = FixedStep(None, t + 0.5 * h, self.s.state, r, h, self.e, self.s.previous_fresh)
        self.s.previous_fresh = False
        q, u = r.state.q, r.state.u
        self.s.state = State(t1, q, u)
        segs = (Segment(lambda tg: (q, u), t1, True, r.contacts.m),)
        out = Report(Status.RUNNING, t1, self.s.state, (rec,), r.contact_work, r.correction_energy, segments=segs)
        if self.unsupported is None:
            calm = r.branch is None and (r.contacts.m == 0 or float(np.abs(r.gamma_plus).max()) <= V_BACK)
            self.s.quiet = self.s.quiet + 1 if calm else 0
            if self.s.quiet >= self.s.back_steps:
                self.s.fallbacks.append({"t": t1, "reason": "back to extrapolated steps"})
                self.s.mode, self.s.t_back, self.s.stuck = Mode.EVENT, t1, 0
                self.s.burst.clear()
        if not t1 < t_end:
            return Report(Status.FINISHED, t1, self.s.state, (rec,), r.contact_work, r.correction_energy,
                          segments=segs + self._rest())
        return out

    def progress(self) -> tuple[float, float, str]:
        return self.s.state.t - self.t0, self.t_end - self.t0, "s"

    def state_dict(self) -> dict:
        return self.s.to_json()

    def load_state_dict(self, d: dict) -> None:
        self.s = Carried.from_json(d)
        if self.s.mode is Mode.PHASE:  # the step end e0 is a function of the state and the sets
            nfev, constrained = self.s.ev.nfev, self.s.ev.constrained
            self._phase(self.s.C, self.s.shadow, self.s.low, self.s.watch)
            self.s.ev.nfev, self.s.ev.constrained = nfev, constrained

    def meta(self, status: str, wall: float, points: int) -> dict:
        settings = {"rtol": self.rtol, "atol": self.atol, "order": self.order, "max_step": self.max_step,
                    "features": len(self.feats), "unsupported": self.unsupported, "lie_group": self.lie}
        run = {"steps": self.s.accepted + self.s.fixed, "steps_extrapolated": self.s.accepted,
               "steps_refused": self.s.rejected, "steps_landed": self.s.landings, "steps_fixed": self.s.fixed,
               "events": self.s.events, "impacts": self.s.ev.impacts, "nfev": self.s.ev.nfev,
               "nfev_constrained": self.s.ev.constrained, "wall_seconds": wall}
        return run_metadata(self.model, status, run, integrator="adaptive", adaptive=settings, zeno=self.s.ev.zeno,
                            fallbacks=self.s.fallbacks)


def simulate_adaptive(model: Model, *, state: State | None = None, t_end: float | None = None,
                      rtol: float | None = None, atol: float | None = None, order: int = DEFAULT_ORDER,
                      t_eval=None, max_step: float = 1.0, max_events: int = 1_000_000,
                      data: Data | None = None, progress: bool = False, checkpoint: Checkpoint | None = None,
                      spill: str | Path | None = None, check: Check | None = None) -> Trajectory:
    """Integrate `model` adaptively (module doc) from `state` (default: the scene's initial
    state) to `t_end` [s] (default: state.t + the scene's duration), restitution = the scene's e.

    rtol, atol: the error tolerances of the extrapolated steps (default: the scene's options
    rtol, atol); order: 4, 6 or 8; max_step [s]: bound on an extrapolated step; t_eval: sample
    instants [s] in [t0, t_end] (default: every save_every * dt, the instants ms.simulate
    records); max_events: give up beyond this many events; progress, checkpoint, spill, check: as
    ms.simulate (driver.drive).

    Returns a :class:`Trajectory` with ms.simulate's arrays: samples at t_eval (a sample at an
    impact instant is the post-impact state); one log row per contact percussion (log_t: the
    located impact instant, or a fixed step's midpoint); contact_work and correction_energy
    since the previous sample. meta: "integrator": "adaptive", "status", "adaptive" (settings),
    "zeno", "fallbacks", "run" (steps extrapolated / refused / fixed, events, impacts,
    wall_seconds). Raises SimulationError (with .trajectory up to the failure)."""
    refuse_driven(model, "adaptive")
    refuse_drives(model, "adaptive")
    with run_data(model, data) as data:
        state = state or initial_state(model, data)
        opts = model.options
        t_end, t_grid = sample_grid(model, state, t_end, t_eval)
        rtol = opts.rtol if rtol is None else float(rtol)
        atol = opts.atol if atol is None else float(atol)
        integ = AdaptiveRun(model, data, opts.restitution, rtol, atol, order, max_step, max_events, state=state,
                            t_end=t_end)
        return drive(integ, model, data, grid=t_grid, progress=progress, checkpoint=checkpoint, spill=spill,
                     check=check, capacity=len(t_grid))
