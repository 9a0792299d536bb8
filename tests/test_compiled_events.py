"""Two implementations, one truth: the adaptive integrator's compiled extrapolated step (src/events.hpp,
moreau_sim/compiled_events.py) against its Python one (adaptive.AdaptiveRun._step), and its compiled samples on
the dense output (src/adaptive.hpp) against AdaptiveRun._segment's dense(t) and Recorder.sample.

Every bundled scene the adaptive integrator accepts runs both ways (step_impl = "python" and "compiled", the
durations of the byte-identity runs: 1 s, 0.3 s for the large models) and must give the same arrays bit for bit:
the C++ step makes the Python step's floating-point operations in the same order (docs/theory.md §2.8), and an
error estimate one ulp apart would move the next step size and so every later sample. How many steps ran
compiled is counted and, for the scenes with free flights between events, asserted > 0 (so that "equal because
nothing ran compiled" shows); the scenes whose extrapolated steps are all constrained or fixed show their
fallback by a count of 0. The same for the compiled samples (Lie-group models keep the Python dense output).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
import moreau_sim.compiled as compiled
from moreau_sim import compiled_events
from moreau_sim.actuation import refuse_driven
from moreau_sim.adaptive import AdaptiveRun
from moreau_sim.adaptive_static import FIXED_POINT
from moreau_sim.data import make_data
from moreau_sim.drive import refuse as refuse_drives
from moreau_sim.driver import drive
from moreau_sim.errors import SceneError
from moreau_sim.event_rules import make_rules, sample_grid
from moreau_sim.model import build_model, initial_state
from moreau_sim.options import StepImpl
from moreau_sim.scene import load_scene
from moreau_sim.sums import ordered

from helpers import slow_cases

SCENES = sorted((Path(__file__).resolve().parent.parent / "scenes").glob("*.toml"))
HEAVY = ("quadruped", "solo", "panda", "column_of_beads_100", "box_stack_10", "heavy_on_light_box_10000")
MUST_COMPILE = {"bouncing_ball", "zeno_ball", "newton_cradle_5", "newton_cradle_5_gapped", "fast_impact",
                "pendulum_wall", "box_drop", "spinning_box"}
MUST_SAMPLE = MUST_COMPILE - {"box_drop", "spinning_box"}  # free bodies: a Lie group, the Python dense output
G, D0 = 9.81, 0.9  # gravity [m/s^2]; the ball's initial gap [m] (centre at 1 m, r = 0.1 m)


def _counted(call, box: list):
    """`call`, counting its calls in box[0]."""
    def counted(*args):
        box[0] += 1
        return call(*args)
    return counted


def _run(scene, impl: StepImpl):
    """The adaptive run of `scene` with step_impl `impl`: (arrays, compiled extrapolated steps taken, one by one or
    in a free-flight step's one call (src/phase.hpp), compiled sample calls)."""
    model = build_model(scene.with_options(step_impl=impl.value, integrator="adaptive"))
    refuse_driven(model, "adaptive")  # as simulate_adaptive refuses them
    refuse_drives(model, "adaptive")
    data = make_data(model)
    state = initial_state(model, data)
    t_end, grid = sample_grid(model, state, None, None)
    o = model.options
    run = AdaptiveRun(model, data, o.restitution, o.rtol, o.atol, 6, 1.0, 10 ** 6, state=state, t_end=t_end)
    taken = [0]
    sampled = [0]
    for name, box in (("extrapolate", taken), ("phase", taken), ("sampler", sampled)):
        if getattr(run, name) is not None:
            setattr(run, name, _counted(getattr(run, name), box))
    try:
        traj = drive(run, model, data, grid=grid, capacity=len(grid))
    except Exception as exc:  # a run that fails fails alike both ways, up to the same sample
        traj = getattr(exc, "trajectory", None)
        if traj is None:
            raise
    return traj.arrays, taken[0], sampled[0]


def test_the_compiled_extrapolated_step_is_available():
    assert compiled.available(), compiled.unavailable_reason()
    model = build_model(load_scene(SCENES[0].parent / "bouncing_ball.toml"))
    assert compiled_events.unsupported(model) is None
    assert compiled_events.unsupported(build_model(load_scene(SCENES[0].parent / "bouncing_ball.toml").with_options(
        step_impl="python"))) == "step_impl python"


@pytest.mark.parametrize("path", slow_cases(SCENES, {"column_of_beads", "column_of_beads_100", "block_on_step"},
                                           [p.stem for p in SCENES]))
def test_same_adaptive_run_both_ways(path):
    scene = load_scene(path)
    duration = min(scene.options.duration, 0.3 if any(h in path.stem for h in HEAVY) else 1.0)
    scene = scene.with_options(duration=duration)
    try:
        ref, none, none_sampled = _run(scene, StepImpl.PYTHON)
    except SceneError as exc:  # a driven or actuated scene: the adaptive integrator refuses it, both ways alike
        with pytest.raises(SceneError) as again:
            _run(scene, StepImpl.COMPILED)
        assert str(again.value) == str(exc) and "use integrator = \"time-stepping\"" in str(exc)
        return
    got, taken, sampled = _run(scene, StepImpl.COMPILED)
    assert none == 0 and none_sampled == 0
    print(f"{scene.name}: {taken} compiled extrapolated steps, {sampled} compiled sample calls")
    if scene.name in MUST_COMPILE:
        assert taken > 0
    if scene.name in MUST_SAMPLE:
        assert sampled > 0
    assert set(ref) == set(got)
    for key in ref:
        x, y = np.asarray(ref[key]), np.asarray(got[key])
        assert x.shape == y.shape and x.tobytes() == y.tobytes(), (key, x.shape, y.shape)


@pytest.mark.parametrize("order", [4, 6, 8])
@pytest.mark.parametrize("H", [1e-3, 0.05])
@pytest.mark.parametrize("name", ["spinning_box", "pendulum_wall", "newton_cradle_5"])
def test_one_step_is_bit_identical(name, H, order):
    """One free extrapolated step, on a Lie group with a velocity-dependent bias (spinning_box: the
    midpoint's fixed point), a pendulum and five trees, at every order: (q1, u1, d) the same floats."""
    model = build_model(load_scene(SCENES[0].parent / f"{name}.toml"))
    data = make_data(model)
    state = initial_state(model, data)
    o = model.options
    run = AdaptiveRun(model, data, o.restitution, 1e-10, 1e-12, order, 1.0, 10 ** 6, state=state, t_end=1.0)
    assert run.extrapolate is not None
    fast = run.extrapolate
    run.extrapolate = None  # the Python step
    u = state.u + np.linspace(0.3, 1.7, model.nv)  # moving in every coordinate
    a, b = run._step(state.q, u, H, ()), fast(state.q, u, H)
    for x, y in zip(a, b):
        assert x.tobytes() == np.asarray(y).tobytes()
    assert FIXED_POINT < 1.0


@pytest.mark.parametrize("e", [0.5, 0.8, 1.0])
def test_ball_through_simulate_both_ways(e):
    """The ball through ms.simulate at rtol 1e-10, samples every 0.025 s (the benchmark's run), with restitution e:
    the compiled samples give the Python run's arrays bit for bit; the impact times are the closed form's
    t_k = t0 (1 + 2 e + ... + 2 e^k) (docs/theory.md §4.1) and the energy never rises."""
    base = load_scene(SCENES[0].parent / "bouncing_ball.toml").with_options(
        integrator="adaptive", restitution=e, rtol=1e-10, save_every=25, duration=2.0)
    runs = {}
    for impl in StepImpl:
        model = build_model(base.with_options(step_impl=impl.value))
        if impl is StepImpl.COMPILED:
            assert compiled_events.sampler_unsupported(model, make_data(model), lie=False) is None
        runs[impl] = ms.simulate(model).arrays
    ref, got = runs[StepImpl.PYTHON], runs[StepImpl.COMPILED]
    assert set(ref) == set(got)
    for key in ref:
        assert np.asarray(ref[key]).tobytes() == np.asarray(got[key]).tobytes(), key
    t0 = np.sqrt(2 * D0 / G)
    tn = np.array([t0 * (1 + 2 * sum(e ** j for j in range(1, k + 1))) for k in range(6)])
    tn = tn[tn < 1.9]  # the impacts in the run (e = 0.5: six, well before the accumulation at 3 t0)
    n = len(tn)
    assert np.abs(got["log_t"][:n] - tn).max() < 1e-9
    E = got["kinetic_energy"] + got["potential_energy"]
    assert (np.diff(E) <= 1e-9 * E[0]).all()


@pytest.mark.parametrize("rows", [True, False])
@pytest.mark.parametrize("name", ["bouncing_ball", "zeno_ball", "box_drop", "rocking_block", "newton_cradle_5",
                                  "cradle_rounding_perturbed", "column_of_beads", "heavy_on_light_ball_100"])
def test_compiled_gaps_are_bit_identical(name, rows):
    """The gaps of points on static planes (a sphere's centre, a box's vertices on a half-space) and of sphere pairs
    (the cradles, the beads) with their rows, drift and rates: the compiled ones are the Python Gaps.features's
    floats, at states moving in every coordinate."""
    model = build_model(load_scene(SCENES[0].parent / f"{name}.toml"))
    data = make_data(model)
    gaps = make_rules(model, data, model.options.restitution).gaps
    assert gaps.compiled is not None
    state = initial_state(model, data)
    rng = np.random.default_rng(7)
    for _ in range(5):
        q = pin.integrate(model.pin, state.q, rng.normal(0.0, 0.3, model.nv))
        u = rng.normal(0.0, 2.0, model.nv)
        idx = sorted(rng.choice(len(gaps.feats), size=max(1, len(gaps.feats) // 2), replace=False).tolist())
        for which in (None, idx):
            fast = gaps.features(q, u, which, rows)
            compiled_gaps, gaps.compiled = gaps.compiled, None
            ref = gaps.features(q, u, which, rows)
            gaps.compiled = compiled_gaps
            for key in ("g", "W", "drift", "gamma", "margin", "smooth"):
                x, y = np.asarray(getattr(ref, key)), np.asarray(getattr(fast, key))
                assert x.shape == y.shape and x.tobytes() == y.tobytes(), key
            if rows and which is not None:  # a free step end (AdaptiveRun._end): a, g, gamma, gdd = W'a + drift
                a = pin.aba(model.pin, data.pin, q, u, np.zeros(model.nv)).copy()
                end = gaps.compiled.end(q, u, which)
                for x, y in zip((a, ref.g, ref.gamma, ordered(ref.W.T, a) + ref.drift), end):
                    assert x.tobytes() == np.asarray(y).tobytes()


def test_compiled_results_are_arrays_of_their_own():
    """What the adaptive integrator's compiled calls return (src/owned.hpp: arrays over the storage the C++ computed
    them in, not numpy.copy's copies) are ordinary arrays: float64, writable, C order, each call's its own storage,
    alive after the objects that made them are gone; the values are tested bit for bit above."""
    import gc

    model = build_model(load_scene(SCENES[0].parent / "newton_cradle_5.toml"))
    data = make_data(model)
    gaps = make_rules(model, data, model.options.restitution).gaps
    state = initial_state(model, data)
    idx = list(range(len(gaps.feats)))
    first = gaps.compiled.features(state.q, state.u, idx, True)
    second = gaps.compiled.features(state.q, state.u, idx, True)
    for x, y in zip(first, second):
        assert x.dtype == np.float64 and x.flags.writeable and x.flags.c_contiguous and x.tobytes() == y.tobytes()
        x += 1.0  # its own storage: the other call's is untouched
        assert not np.shares_memory(x, y) and x.tobytes() != y.tobytes()
    assert first[1].shape == (model.nv, len(idx))  # W (nv, k)
    seq = (1, 2, 3)
    ratios = tuple(tuple((seq[j] / seq[j - m]) ** 2 - 1.0 for m in range(1, j + 1)) for j in range(len(seq)))
    ex = compiled_events.extrapolator(model, seq=seq, ratios=ratios, lie=False, rtol=1e-8, atol=1e-10,
                                      fixed_point=FIXED_POINT)
    q1, u1, err = ex(state.q, state.u, 1e-3)
    kept = [a.copy() for a in (q1, u1, err)]
    del ex, gaps, data
    gc.collect()
    np.ones(10_000)  # (storage freed with its owner would be reused here)
    assert all(a.tobytes() == b.tobytes() and a.shape == (n,) for a, b, n in
               zip((q1, u1, err), kept, (model.nq, model.nv, model.nq + model.nv)))


GAP_SCENES = ["bouncing_ball", "zeno_ball", "box_drop", "rocking_block", "newton_cradle_5", "newton_cradle_5_gapped",
              "cradle_rounding_perturbed", "column_of_beads", "heavy_on_light_ball_100"]


@pytest.mark.parametrize("name", GAP_SCENES)
def test_event_driven_run_both_ways(name):
    """The event-driven integrator reads the same gaps (event_rules.make_rules): on the bundled scenes whose features
    the compiled gaps take (points on static planes, sphere pairs), its run with them and its run in Python
    (step_impl = "python") give the same arrays bit for bit."""
    scene = load_scene(SCENES[0].parent / f"{name}.toml").with_options(duration=0.5, integrator="event-driven")
    runs = {}
    for impl in StepImpl:
        model = build_model(scene.with_options(step_impl=impl.value))
        gaps = make_rules(model, make_data(model), model.options.restitution).gaps
        assert (gaps.compiled is not None) is (impl is StepImpl.COMPILED)
        runs[impl] = ms.simulate(model, progress=False).arrays
    ref, got = runs[StepImpl.PYTHON], runs[StepImpl.COMPILED]
    assert set(ref) == set(got)
    for key in ref:
        x, y = np.asarray(ref[key]), np.asarray(got[key])
        assert x.shape == y.shape and x.tobytes() == y.tobytes(), key


@pytest.mark.parametrize("name, duration", [("box_drop", 0.3), ("newton_cradle_5", 0.3), ("rocking_block", 0.3),
                                            ("quadruped_drop", 0.06)])
def test_event_driven_samples_recorded_at_once_are_the_ones_recorded_one_by_one(name, duration, monkeypatch):
    """The event-driven integrator's samples: their states one by one on scipy's dense output, what they record (T,
    V, the pairs' distances) in one compiled call (compiled_events.figures, DenseSampler.figures) and recorded at once
    (Recorder.block): the arrays of the same run recorded sample by sample (Recorder.sample), bit for bit, a free
    body (a Lie group: nq != nv) included; a scene the compiled gaps do not take (quadruped_drop) too."""
    model = build_model(load_scene(SCENES[0].parent / f"{name}.toml").with_options(duration=duration,
                                                                                   integrator="event-driven"))
    made = []
    real = compiled_events.figures
    monkeypatch.setattr(compiled_events, "figures", lambda m, d: made.append(real(m, d)) or made[-1])
    at_once = ms.simulate(model, progress=False).arrays
    assert made and made[-1] is not None
    monkeypatch.setattr(compiled_events, "figures", lambda m, d: None)
    one_by_one = ms.simulate(model, progress=False).arrays
    assert set(at_once) == set(one_by_one) and len(at_once["t"]) > 50
    for key in at_once:
        x, y = np.asarray(at_once[key]), np.asarray(one_by_one[key])
        assert x.shape == y.shape and x.tobytes() == y.tobytes(), key


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_touching_cradle_through_simulate_both_ways(e):
    """The touching cradle struck at 1 m/s through ms.simulate (adaptive, rtol 1e-10): the compiled sphere gaps give
    the Python run's arrays bit for bit, and the velocities after the one impact are the simultaneous law's closed
    form (docs/theory.md §4.2): u_1 = (1 + e)/5 - e, u_2..5 = (1 + e)/5 [m/s]; momentum 1 kg m/s is kept."""
    base = load_scene(SCENES[0].parent / "newton_cradle_5.toml").with_options(
        integrator="adaptive", restitution=e, rtol=1e-10, atol=1e-12, save_every=25, duration=0.5)
    runs = {impl: ms.simulate(build_model(base.with_options(step_impl=impl.value)), progress=False).arrays
            for impl in StepImpl}
    ref, got = runs[StepImpl.PYTHON], runs[StepImpl.COMPILED]
    for key in ref:
        assert np.asarray(ref[key]).tobytes() == np.asarray(got[key]).tobytes(), key
    expected = np.r_[(1 + e) / 5 - e, np.full(4, (1 + e) / 5)]
    assert np.abs(got["u"][-1] - expected).max() < 1e-12
    assert abs(got["u"][-1].sum() - 1.0) < 1e-12
