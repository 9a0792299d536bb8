"""The adaptive integrator's extrapolated step between events at compiled speed (src/events.hpp): the
midpoint steps and their extrapolation (docs/theory.md §8) without a persistent set, operation by operation as
adaptive.AdaptiveRun._step computes them (docs/theory.md §2.8), so that a run gives the Python run's arrays bit
for bit; the samples on the dense output between events with what each records, all the samples of a step in
one call, and the gaps of points on static planes (the ball's) and of sphere pairs (the cradle's) with their
rows (src/adaptive.hpp); the impact at a located event (src/impact.hpp: event_rules._impact but at corners and
where features coal misses are added); and a step in free flight in one call (src/phase.hpp: the step sizes, the
step's end, the event location, the landing). The persistent set at events and the constrained phases stay in
Python."""

from __future__ import annotations

import weakref
from collections.abc import Callable

import numpy as np

from . import compiled
from .hermite import QUINTIC
from .results import MIDPOINT_ITERATIONS


def unsupported(model) -> str | None:
    """Why the compiled extrapolated step does not take this model's free-flight steps (None: it does)."""
    why = compiled.loop_refusal(model, "Extrapolator", "the extrapolated step")
    if why is not None:
        return why
    if model.nv == 0:
        return "no degrees of freedom"
    return None


def extrapolator(model, *, seq: tuple[int, ...], ratios: tuple[tuple[float, ...], ...], lie: bool, rtol: float,
                 atol: float, fixed_point: float) -> Callable | None:
    """The compiled AdaptiveRun._step without a persistent set, (q0, u0, H [s]) -> (q1, u1, error estimate), or
    None where it does not apply (unsupported). seq, ratios: the extrapolation's (AdaptiveRun.seq, .ratios);
    lie: a joint with nq != nv; rtol, atol, fixed_point: the midpoint's fixed-point tolerance (AdaptiveRun)."""
    if unsupported(model) is not None:
        return None
    ex = compiled._module.Extrapolator(model.pin, list(seq), [list(r) for r in ratios], bool(lie),
                                       bool(model.velocity_bias), float(rtol), float(atol), float(fixed_point),
                                       int(MIDPOINT_ITERATIONS))
    return ex.step


def sampler_unsupported(model, data, *, lie: bool) -> str | None:
    """Why the compiled samples on the dense output do not take this model's (None: they do)."""
    why = compiled.loop_refusal(model, "DenseSampler", "the dense output's samples")
    if why is not None:
        return why
    if lie:
        return "a joint with nq != nv (the dense output through dIntegrate)"
    if model.prescribed is not None:
        return "moving statics"
    ctx = compiled._context(model, data)
    return ctx.why if ctx.stepper is None else None


def sampler(model, data, *, lie: bool, basis) -> Callable | None:
    """The samples of one step on its dense output, (t0, q0, u0, a0, t1, q1, u1, a1, grid) -> (q (n, nq), u (n, nv),
    kinetic (n,) [J], potential (n,) [J], pair distances (n, pairs) [m]) as AdaptiveRun._segment's dense(t) and
    Recorder.sample give them, or None where it does not apply (sampler_unsupported). basis: hermite.QUINTIC."""
    if sampler_unsupported(model, data, lie=lie) is not None:
        return None
    ds = compiled._module.DenseSampler(compiled._context(model, data).stepper, *compiled.forest_args(model, data),
                                       _rows(basis))
    return ds.samples


def figures(model, data) -> Callable | None:
    """What a sample records of given states, (Q (n, nq), U (n, nv)) -> (kinetic (n,) [J], potential (n,) [J], pair
    distances (n, pairs) [m]) as Recorder.sample gives them (the event-driven integrator's samples on scipy's dense
    output, recorded at once), or None where the compiled figures do not apply (sampler_unsupported, any
    configuration space)."""
    if sampler_unsupported(model, data, lie=False) is not None or not hasattr(compiled._module.DenseSampler, "figures"):
        return None  # (an extension built before figures: Recorder.sample's)
    ds = compiled._module.DenseSampler(compiled._context(model, data).stepper, *compiled.forest_args(model, data),
                                       _rows(QUINTIC))  # (the basis: samples' only)
    return ds.figures


_ROWS: list = []  # (basis, its rows as lists of floats): the last basis sampler() converted


def _rows(basis) -> list:
    """basis (a 2-d array) as DenseSampler takes it, rows of Python floats, converted once for the same array."""
    if not _ROWS or _ROWS[0][0] is not basis:
        _ROWS[:] = [(basis, [list(map(float, r)) for r in basis])]
    return _ROWS[0][1]


def phase_step(extrapolate, gaps, locate, *, rtol: float, atol: float, order: int, h_min: float, safety: float,
               min_factor: float, land_iter: int, g_land: float) -> Callable | None:
    """AdaptiveRun.step's free flight in one call (src/phase.hpp: the same floats), on the run's compiled extrapolated
    step (extrapolator()'s), gaps (feature_gaps()'s FeatureGaps) and event location (locator()'s), or None where one
    of them is missing. (t, q, u, H, limit, t_end, t0, q0, u0, g0, gamma0, gdd0, idx, nw) -> (status, h, err,
    rejected, ends, landings, accepted, event), PhaseStep.step's (status: phase_statuses()); the constants are
    adaptive's."""
    if extrapolate is None or gaps is None or locate is None:
        return None
    return compiled._module.PhaseStep(extrapolate.__self__, gaps, locate.__self__, float(rtol), float(atol),
                                      int(order), float(h_min), float(safety), float(min_factor), int(land_iter),
                                      float(g_land)).step


def phase_statuses():
    """Why a free-flight step in one call returned (moreau_sim._step.PhaseStatus, src/phase.hpp: ACCEPTED, LANDED,
    REFUSED, NONFINITE, LOCATE); only where phase_step made one (the extension loaded)."""
    return compiled._module.PhaseStatus


COMPILED_KINDS = {"point_plane": 0, "sphere_sphere": 1}  # the feature kinds FeatureGaps takes (src/adaptive.hpp)


def feature_gaps(model, data, feats):
    """The gaps of `feats` compiled where every feature is a point on a static plane ("point_plane": vertices and
    spheres on half-spaces) or a pair of spheres ("sphere_sphere") and the compiled step loads, else None (the
    Python gaps): .features(q, u, idx, rows) -> (g, W, drift, gamma) as gaps.Gaps.features; .end(q, u, idx) ->
    (a, g, gamma, gdd) as AdaptiveRun._end in free flight (a: the free accelerations, gdd = W'a + drift)."""
    if not feats or compiled.loop_refusal(model, "FeatureGaps", "the compiled gaps") is not None:
        return None
    args = _feature_args(model, feats)
    return None if args is None else compiled._module.FeatureGaps(model.pin, data.pin, *args)


_FEATURE_ARGS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # model -> (feats, FeatureGaps's arguments)


def _feature_args(model, feats) -> tuple | None:
    """FeatureGaps's arguments after (model, data) for `feats` (None: a kind it does not take), made once per model
    and features (a model is never modified after build_model; the FeatureGaps itself is made per run: its Pinocchio
    Data is the run's)."""
    got = _FEATURE_ARGS.get(model)
    if got is not None and got[0] is feats:
        return got[1]
    args = None
    if all(f.kind in COMPILED_KINDS and (f.kind != "point_plane" or f.joint_b == 0) for f in feats):
        args = ([COMPILED_KINDS[f.kind] for f in feats], [int(f.joint_a) for f in feats],
                [int(f.joint_b) for f in feats], np.array([f.p for f in feats], float).reshape(-1, 3),
                np.array([f.n for f in feats], float).reshape(-1, 3),
                np.array([f.p_b for f in feats], float).reshape(-1, 3), [float(f.d) for f in feats],
                [float(f.r) for f in feats], [float(f.r_b) for f in feats], np.asarray(model.support_mask, float))
    _FEATURE_ARGS[model] = (feats, args)
    return args


class CompiledImpact:
    """event_rules._impact compiled (src/impact.hpp): the detection at q, the constraints, the Zeno rule and law.impact
    with Pinocchio's M^-1, the same floats as Python (docs/theory.md §2.8), on the run's compiled Stepper. Called as
    (q, u, e, t, last_impact, fs, closed_pairs) -> (arrays, zeno, speed, a_n, contact_work) or None where Python must
    take the event (a corner, more rows than qp.WARM_ROWS without a start, an active set that does not settle, an event
    Python refuses). arrays: the StepOut's named arrays (compiled._Context.arrays: u_next = u+, v, lam, P,
    gamma_minus, gamma_plus, M, W, the contacts); fs: event_rules.features at (q, u); closed_pairs: the pairs of its
    closed features (added to contacts.detect's warm start). reasons: why events were handed back, counted."""

    __slots__ = ("ctx", "ev", "data", "reasons")

    def __init__(self, ctx, data, ev):
        self.ctx, self.data, self.ev = ctx, data, ev
        self.reasons: dict = {}  # why events were handed back -> count

    def takes(self, coal_rows: bool) -> bool:
        """Whether to try the event compiled: coal_rows, the contacts' rows are coal's (no feature event_rules'
        missed_features adds; else counted as handed back)."""
        if not coal_rows:
            self.reasons["features coal's rows miss"] = self.reasons.get("features coal's rows miss", 0) + 1
        return coal_rows

    def __call__(self, q, u, e: float, t: float, last_impact: float, fs, closed_pairs):
        ctx, data = self.ctx, self.data
        # contacts.detect's warm start: the run's pairs with contacts at the last detection, with the closed features'
        ctx.stepper.warm = sorted(set(data.warm_start_pairs) | closed_pairs)
        r, zeno, speed, a_n = self.ev.impact(q, u, e, t, last_impact, fs.g, fs.gamma, fs.W, fs.drift)
        if r.outcome is not compiled._module.Outcome.CONTACT:
            self.reasons[r.reason] = self.reasons.get(r.reason, 0) + 1
            return None
        data.warm_start_pairs = set(self.ev.warm)
        return ctx.arrays(r), zeno, speed, a_n, r.contact_work


def impact_unsupported(model, data, feats) -> str | None:
    """Why the compiled impact at an event does not take this model's events (None: it does, but for the events it
    hands back, CompiledImpact, and those where event_rules.missed_features may add rows to coal's: two boxes'
    closed vertices and edges, cylinders' closed features)."""
    why = compiled.loop_refusal(model, "EventImpact", "the compiled impact")
    if why is not None:
        return why
    if not feats:
        return "no features"
    if model.prescribed is not None or model.drive is not None:
        return "moving statics or driven joints"
    ctx = compiled._context(model, data)
    return ctx.why if ctx.stepper is None else None


def impact(model, data, feats, *, gap_tol: float, v_tol: float, g_zeno: float, v_zeno: float,
           dt_zeno: float) -> CompiledImpact | None:
    """The compiled impact at an event of `model` on `feats` (CompiledImpact), or None where it does not apply
    (impact_unsupported). gap_tol [m]: event_rules.Rules.gap_tol; v_tol, g_zeno, v_zeno, dt_zeno: event_rules'
    V_TOL, G_ZENO, V_ZENO, DT_ZENO."""
    if impact_unsupported(model, data, feats) is not None:
        return None
    ctx = compiled._context(model, data)
    ev = compiled._module.EventImpact(ctx.stepper, float(gap_tol), float(v_tol), float(g_zeno), float(v_zeno),
                                      float(dt_zeno))
    return CompiledImpact(ctx, data, ev)


_LOCATOR: list = []  # the one EventLocator (it keeps nothing from call to call: constants only)


def locator(model, *, check, check_basis, quintic, v_tol: float) -> Callable | None:
    """AdaptiveRun._first_event in free flight without box features compiled (src/locate.hpp: the same floats; scipy's
    brentq's arithmetic), (t0, g0, gamma0, gdd0, t1, g1, gamma1, gdd1, nw) -> (status, tau, kind, k): status 1 an
    event at tau of kind 0 (a gap) or 1 (a return) of watched feature k, 0 none, -1 Python's to locate; or None
    where it does not apply (the compiled step does not load, or predates it; step_impl python). check, check_basis,
    quintic: hermite.CHECK, CHECK_BASIS, QUINTIC; v_tol: event_rules.V_TOL."""
    if compiled.loop_refusal(model, "EventLocator", "the compiled event location") is not None:
        return None
    if not _LOCATOR:
        _LOCATOR.append(compiled._module.EventLocator(np.asarray(check, float), np.asarray(check_basis, float),
                                                      np.asarray(quintic, float), float(v_tol)).first)
    return _LOCATOR[0]
