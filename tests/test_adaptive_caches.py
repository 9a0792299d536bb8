"""What the adaptive integrator keeps per model and shares between calls (docs/theory.md §8): the per-model caches
(adaptive_static.static_of, compiled_events._feature_args) go with their model and are never shared by two models, a run
after others of its model gives a fresh run's bits, the shared read-only arrays stay unwritten, and the shortcuts
that replace a general computation by its special case give the general one's floats: the error scale on a vector
space (q for pin.difference(neutral, q)), the rank test (np.linalg.matrix_rank at its tolerance's edge), the gaps an
event's resolution hands to the phase's sets. The physics are asserted against the closed forms of §4 (the ball's
impact times and apexes, the touching cradle's simultaneous impact), parameterized over e, both ways (step_impl
"python" and "compiled")."""

from __future__ import annotations

import gc
import weakref

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
from moreau_sim import adaptive, adaptive_static, compiled_events, event_rules
from moreau_sim.adaptive import AdaptiveRun
from moreau_sim.data import make_data
from moreau_sim.event_rules import features, phase_sets, resolve
from moreau_sim.model import initial_state
from moreau_sim.testing import references as ref

from helpers import scene

TIGHT = dict(rtol=1e-12, atol=1e-12)


def model_of(name: str, **options) -> ms.Model:
    return ms.build_model(scene(name, integrator="adaptive", **options))


def bits(tr: ms.Trajectory) -> dict:
    return {k: np.asarray(v).tobytes() for k, v in tr.arrays.items()}


def run_of(model: ms.Model) -> AdaptiveRun:
    data = make_data(model)
    o = model.options
    return AdaptiveRun(model, data, o.restitution, o.rtol, o.atol, adaptive.DEFAULT_ORDER, 1.0, 10 ** 6,
                       state=initial_state(model, data), t_end=o.duration)


# ---- physics: the closed forms of §4, both ways -------------------------------------------------------------------
@pytest.mark.parametrize("impl", ["compiled", "python"])
@pytest.mark.parametrize("e", [0.5, 0.8, 1.0])
def test_ball_impacts_and_apexes_both_ways(e, impl):
    n = 5
    tn = np.array(ref.ball_impact_times(e, n + 1))
    apex_t = np.array(ref.ball_apex_times(e, n))
    model = model_of("bouncing_ball", restitution=e, duration=float(tn[n]) + 0.01, step_impl=impl, **TIGHT)
    tr = ms.simulate(model, progress=False)
    assert tr.complete and tr.meta["run"]["steps_fixed"] == 0 and tr.meta["run"]["impacts"] == n + 1
    assert np.abs(tr.log_t[:n + 1] - tn).max() < 1e-9
    at = adaptive.simulate_adaptive(model, t_eval=np.r_[0.0, apex_t])
    assert np.abs(at.gap[1:, 0] - np.array(ref.ball_apex_gaps(e, n))).max() < 1e-9
    assert np.abs(at.u[1:, 0]).max() < 1e-9  # at rest at the apex
    assert abs(at.gap[0, 0] - ref.BALL_GAP) == 0.0


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_cradle_simultaneous_impact_both_ways(e):
    runs = {}
    for impl in ("compiled", "python"):
        tr = ms.simulate(model_of("newton_cradle_5", restitution=e, duration=0.3, step_impl=impl, **TIGHT),
                         progress=False)
        assert tr.complete and tr.meta["run"]["impacts"] == 1 and np.abs(tr.log_t).max() == 0.0
        assert np.abs(tr.u[-1] - np.array(ref.cradle_simultaneous(e))).max() < 1e-12
        assert abs(tr.u[-1].sum() - 1.0) < 1e-12  # momentum
        runs[impl] = bits(tr)
    assert runs["compiled"] == runs["python"]


# ---- the per-model caches ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("e", [0.5, 1.0])
def test_runs_of_a_model_give_a_fresh_runs_bits(e):
    """The second and third runs of a model (its caches made by the first) give the bits of a run of a model built
    afresh from the same scene (its caches made for it), and of each other."""
    tn = ref.ball_impact_times(e, 4)
    options = dict(restitution=e, duration=tn[-1] + 0.05, **TIGHT)
    model = model_of("bouncing_ball", **options)
    first, second, third = (bits(ms.simulate(model, progress=False)) for _ in range(3))
    fresh = bits(ms.simulate(model_of("bouncing_ball", **options), progress=False))
    assert first == second == third == fresh


def test_a_models_caches_go_with_it_and_two_models_do_not_share():
    """Two models of one scene get caches of their own, made once each; a model's caches keep it alive for no one
    (weakly keyed: with the model and its runs gone, its entries go)."""
    a, b = model_of("newton_cradle_5", duration=0.05), model_of("newton_cradle_5", duration=0.05)
    ra, rb = run_of(a), run_of(b)
    sa, sb = adaptive_static._STATICS[a], adaptive_static._STATICS[b]
    assert sa is not sb and sa.feats is ra.feats and sb.feats is rb.feats and sa.feats is not sb.feats
    assert compiled_events._FEATURE_ARGS[a] is not compiled_events._FEATURE_ARGS[b]
    assert run_of(a).flat is ra.flat and adaptive_static._STATICS[a] is sa  # made once per model
    gone = weakref.ref(a)
    del a, ra, sa
    gc.collect()
    # (the caches are weakly keyed: their entries of a go with it; test_run_caches: a model ms.simulate ran goes too)
    assert gone() is None
    assert adaptive_static._STATICS[b] is sb and b in compiled_events._FEATURE_ARGS and rb.step().t > 0.0


def test_shared_arrays_are_read_only():
    """The arrays a run shares with others (FeatureState's margins and smooth flags of compiled features, an _End's
    empty multipliers and far flags, the neutral configuration) cannot be written to."""
    run = run_of(model_of("bouncing_ball"))
    q, u = run.s.state.q, run.s.state.u
    fs = features(run.rules, run.s.ev, q, u)
    e0 = run._end(0.0, q, u, (), [0])
    for arr in (fs.margin, fs.smooth, e0.lam, e0.margin, e0.near, run.neutral, run.is_box):
        with pytest.raises(ValueError):
            arr[...] = 0


# ---- the special cases give the general computation's floats ------------------------------------------------------
@pytest.mark.parametrize("name", ["newton_cradle_5", "bouncing_ball", "pendulum_wall"])
def test_error_scale_on_a_vector_space_is_pin_difference(name):
    """_size's q for pin.difference(neutral, q) on a vector space with neutral 0: the same floats (signed zeros and
    all, after the absolute value)."""
    run = run_of(model_of(name))
    assert run.flat and not run.lie
    rng = np.random.default_rng(4)
    for q in (rng.standard_normal(run.model.nq) * 10.0 ** rng.integers(-300, 300, run.model.nq),
              np.full(run.model.nq, -0.0), np.r_[np.full(run.model.nq - 1, 0.0), -5e-324]):
        u = rng.standard_normal(run.nv)
        general = np.abs(np.concatenate((pin.difference(run.pm, run.neutral, q), u)))
        assert run._size(q, u).tobytes() == general.tobytes()


def test_error_scale_on_a_lie_group_uses_pin_difference():
    run = run_of(model_of("box_drop"))
    assert run.lie and not run.flat
    q = pin.randomConfiguration(run.pm, -np.ones(run.model.nq), np.ones(run.model.nq))
    u = np.arange(run.nv, dtype=float)
    assert run._size(q, u).tobytes() == np.abs(np.concatenate((pin.difference(run.pm, run.neutral, q), u))).tobytes()


@pytest.mark.parametrize("k", [1, 2, 4])
@pytest.mark.parametrize("side", [0.5, 0.999, 1.001, 2.0])
def test_rank_test_at_its_tolerance_edge(k, side):
    """event_rules._rank is np.linalg.matrix_rank at its tolerance S.max() * max(shape) * eps: a smallest singular
    value `side` times that tolerance counts (side > 1) or not (side < 1), as matrix_rank counts it."""
    rng = np.random.default_rng(k)
    n = 6
    U, _ = np.linalg.qr(rng.standard_normal((n, n)))
    V, _ = np.linalg.qr(rng.standard_normal((k, k)))
    s = np.linspace(1.0, 0.5, k)
    if k > 1:
        s[-1] = side * n * np.finfo(float).eps
    W = U[:, :k] * s @ V.T
    assert event_rules._rank(W) == np.linalg.matrix_rank(W)
    S = np.linalg.svd(W, compute_uv=False)
    if k > 1 and abs(S[-1] / (S[0] * n * np.finfo(float).eps) - 1.0) > 0.01:  # clearly on one side
        assert event_rules._rank(W) == (k if S[-1] > S[0] * n * np.finfo(float).eps else k - 1)


@pytest.mark.parametrize("e", [0.5, 1.0])
@pytest.mark.parametrize("name", ["bouncing_ball", "newton_cradle_5"])
def test_resolution_gaps_are_the_phase_sets_own(name, e, monkeypatch):
    """resolve's gaps of the compiled features (Resolution.g) are, bit for bit, what phase_sets computes at the same
    q, at every event of a run (the ball's impacts, the cradle's strike)."""
    seen = []

    def spy(r, st, t, q, u, released):
        res = resolve(r, st, t, q, u, released)
        seen.append((r, st, q.copy(), res))
        return res
    monkeypatch.setattr(adaptive, "resolve", spy)
    duration = ref.ball_impact_times(e, 3)[-1] + 0.01 if name == "bouncing_ball" else 0.05
    tr = ms.simulate(model_of(name, restitution=e, duration=duration), progress=False)
    assert tr.meta["run"]["impacts"] == (3 if name == "bouncing_ball" else 1) and len(seen) >= 1
    for r, st, q, res in seen:
        assert r.gaps.compiled is not None and res.g is not None
        for g in (res.g, None):
            free, g0, _ = phase_sets(r, st, q, res.u, res.C, res.shadow, g=g)
            assert g0.tobytes() == features(r, st, q, res.u, free, rows=False).g.tobytes()
