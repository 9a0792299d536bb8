"""Two implementations, one truth: the adaptive integrator's compiled extrapolated step (src/events.hpp,
moreau_sim/compiled_events.py) against its Python one (adaptive.AdaptiveRun._step).

Every bundled scene the adaptive integrator accepts runs both ways (step_impl = "python" and "compiled", the
durations of the byte-identity runs: 1 s, 0.3 s for the large models) and must give the same arrays bit for bit:
the C++ step makes the Python step's floating-point operations in the same order (docs/theory.md §2.8), and an
error estimate one ulp apart would move the next step size and so every later sample. How many steps ran
compiled is counted and, for the scenes with free flights between events, asserted > 0 (so that "equal because
nothing ran compiled" shows); the scenes whose extrapolated steps are all constrained or fixed show their
fallback by a count of 0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import moreau_sim.compiled as compiled
from moreau_sim import compiled_events
from moreau_sim.actuation import refuse_driven
from moreau_sim.adaptive import FIXED_POINT, AdaptiveRun
from moreau_sim.data import make_data
from moreau_sim.drive import refuse as refuse_drives
from moreau_sim.driver import drive
from moreau_sim.errors import SceneError
from moreau_sim.event_rules import sample_grid
from moreau_sim.model import build_model, initial_state
from moreau_sim.options import StepImpl
from moreau_sim.scene import load_scene

SCENES = sorted((Path(__file__).resolve().parent.parent / "scenes").glob("*.toml"))
HEAVY = ("quadruped", "solo", "panda", "column_of_beads_100", "box_stack_10", "heavy_on_light_box_10000")
MUST_COMPILE = {"bouncing_ball", "zeno_ball", "newton_cradle_5", "newton_cradle_5_gapped", "fast_impact",
                "pendulum_wall", "box_drop", "spinning_box"}


def _run(scene, impl: StepImpl):
    """The adaptive run of `scene` with step_impl `impl`: (arrays, compiled extrapolated steps taken)."""
    model = build_model(scene.with_options(step_impl=impl.value, integrator="adaptive"))
    refuse_driven(model, "adaptive")  # as simulate_adaptive refuses them
    refuse_drives(model, "adaptive")
    data = make_data(model)
    state = initial_state(model, data)
    t_end, grid = sample_grid(model, state, None, None)
    o = model.options
    run = AdaptiveRun(model, data, o.restitution, o.rtol, o.atol, 6, 1.0, 10 ** 6, state=state, t_end=t_end)
    taken = [0]
    if run.extrapolate is not None:
        inner = run.extrapolate

        def counted(q0, u0, H):
            taken[0] += 1
            return inner(q0, u0, H)
        run.extrapolate = counted
    try:
        traj = drive(run, model, data, grid=grid, capacity=len(grid))
    except Exception as exc:  # a run that fails fails alike both ways, up to the same sample
        traj = getattr(exc, "trajectory", None)
        if traj is None:
            raise
    return traj.arrays, taken[0]


def test_the_compiled_extrapolated_step_is_available():
    assert compiled.available(), compiled.unavailable_reason()
    model = build_model(load_scene(SCENES[0].parent / "bouncing_ball.toml"))
    assert compiled_events.unsupported(model) is None
    assert compiled_events.unsupported(build_model(load_scene(SCENES[0].parent / "bouncing_ball.toml").with_options(
        step_impl="python"))) == "step_impl python"


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_same_adaptive_run_both_ways(path):
    scene = load_scene(path)
    duration = min(scene.options.duration, 0.3 if any(h in path.stem for h in HEAVY) else 1.0)
    scene = scene.with_options(duration=duration)
    try:
        ref, none = _run(scene, StepImpl.PYTHON)
    except SceneError as exc:  # a driven or actuated scene: the adaptive integrator refuses it, both ways alike
        with pytest.raises(SceneError) as again:
            _run(scene, StepImpl.COMPILED)
        assert str(again.value) == str(exc) and "use integrator = \"time-stepping\"" in str(exc)
        return
    got, taken = _run(scene, StepImpl.COMPILED)
    assert none == 0
    print(f"{scene.name}: {taken} compiled extrapolated steps")
    if scene.name in MUST_COMPILE:
        assert taken > 0
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
