"""The rheonomic cases in the compiled step and the compiled run (src/step.cpp, src/rheonomic.hpp, src/run.cpp;
docs/theory.md §2.9, §2.13, §5.5): a static with prescribed motion and a driven joint are stepped in C++ from
their schedules handed over once (no Python call per step), and give the Python step's trajectory, percussion
log and ledger (the work of prescribed motion included) bit for bit, over e and h and every schedule kind
(sine, constant velocity, table)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import compiled, compiled_run
from moreau_sim.data import make_data
from moreau_sim.options import StepImpl

from helpers import MODELS, SCENES, inline_scene, slow_cases

RHEONOMIC = ("vibrating_paddle", "driven_paddle")

STATIC = """
[scene]
name = "moving_static"
[simulation]
restitution = 0.8
dt = 1e-3
duration = 1.0
[[bodies]]
name = "ball"
urdf = "{models}/ball.urdf"
root_joint = "prismatic"
axis = [0, 0, 1]
q0 = [0.4]
[[statics]]
name = "paddle"
shape = "halfspace"
motion = {motion}
"""

DRIVEN = (SCENES / "driven_paddle.toml").read_text().replace('"../models/', '"{models}/').rsplit("[[drives]]", 1)[0]
DRIVEN = DRIVEN.replace("u0 = [0.5654866776461628]", "u0 = [{u0}]") + """
[[drives]]
body = "paddle"
joint = "root"
motion = {motion}
"""

MOTIONS = {  # every kind of prescribed.Schedule: a static's (3 components) and a drive's (1)
    "static-velocity": (STATIC, "{ velocity = [0, 0, 0.2] }", 0.0),
    "static-table": (STATIC, "{ t = [0.0, 0.3, 0.45, 0.7], position = [[0, 0, 0], [0, 0, 0.05], [0, 0, -0.02], "
                             "[0, 0, 0]] }", 0.0),
    "static-sine-phase": (STATIC, "{ sine = { amplitude = [0, 0, 0.02], frequency = 5.0, phase = 0.7 } }", 0.0),
    "drive-table": (DRIVEN, "{ t = [0.0, 0.2, 0.5, 0.8], q = [0.0, 0.04, -0.03, 0.0] }", 0.2),  # u0: the slope at 0
    "drive-velocity": (DRIVEN, "{ velocity = 0.1 }", 0.1),
}


def _run(sc, impl: StepImpl, *, python_run: bool = True):
    """The run of scene sc with the step impl (python_run: the Python loop, which asks the step each step) and the
    counts of its steps by the way they went."""
    model = ms.build_model(sc.with_options(step_impl=impl.value))
    data = make_data(model)
    return ms.simulate(model, data=data, progress=False, python_run=python_run), compiled.counts(data)


def _same(ref, new) -> None:
    """The same arrays (every one, bytes), ledger figures and status."""
    keys = set(ref.arrays) | set(new.arrays)
    differ = sorted(k for k in keys if k not in ref.arrays or k not in new.arrays
                    or np.asarray(ref.arrays[k]).tobytes() != np.asarray(new.arrays[k]).tobytes())
    assert differ == []
    assert ref.meta["ledger"] == new.meta["ledger"] and ref.meta["status"] == new.meta["status"]
    assert ref.meta.get("invariants") == new.meta.get("invariants")
    assert ms.ledger(ref).totals() == ms.ledger(new).totals()


@pytest.fixture(scope="module", autouse=True)
def _compiled():
    assert compiled.available(), compiled.unavailable_reason()


@pytest.mark.parametrize("name", RHEONOMIC)
def test_the_compiled_step_and_run_take_rheonomic_scenes(name):
    model = ms.build_model(ms.load_scene(SCENES / f"{name}.toml"))
    assert compiled.unsupported(model) is None
    assert compiled_run.unsupported(model, None) is None


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("h", [5e-4, 1e-3])
@pytest.mark.parametrize("name", RHEONOMIC)
def test_compiled_step_is_the_python_step(name, e, h):
    """Every step of the bundled rheonomic scenes (1 s) taken by the compiled step, contact steps included: the
    trajectory, the log and the ledger (obstacle work: the paddle's W_o, the drive's W_p) are the Python step's."""
    sc = ms.load_scene(SCENES / f"{name}.toml").with_options(restitution=e, dt=h, duration=1.0)
    ref, py = _run(sc, StepImpl.PYTHON)
    new, counts = _run(sc, StepImpl.COMPILED)
    assert not py and set(counts) == {"flight", "contact"} and counts["contact"] > 0, counts
    assert ref.impacts > 0 and ms.ledger(ref).obstacle_work != 0.0
    _same(ref, new)


@pytest.mark.parametrize("e", [0.0, 0.8])
@pytest.mark.parametrize("h", [5e-4, 1e-3])
@pytest.mark.parametrize("name", RHEONOMIC)
def test_compiled_run_is_the_python_run(name, e, h):
    """The compiled run loop (src/run.cpp) takes every step and records the Python run's arrays and ledger."""
    sc = ms.load_scene(SCENES / f"{name}.toml").with_options(restitution=e, dt=h, duration=1.0)
    ref, _ = _run(sc, StepImpl.PYTHON, python_run=True)
    new, _ = _run(sc, StepImpl.COMPILED, python_run=False)
    run = new.meta["run"]
    # the Python loop takes only the steps whose invariant check fires, to report it (compiled_run.py)
    assert run["loop"] == "compiled" and "python_calls" not in run
    assert run["python_steps"] <= len(new.meta.get("invariants") or [])
    _same(ref, new)


@pytest.mark.parametrize("kind", slow_cases(sorted(MOTIONS), {"drive-table", "drive-velocity"}))
def test_every_schedule_kind_is_evaluated_alike(tmp_path, kind):
    """Tables (held before and after, the segment's slope), constant velocities and a sine with a phase: the
    compiled step and run evaluate them as prescribed.Schedule.at does, bit for bit."""
    text, motion, u0 = MOTIONS[kind]
    sc = inline_scene(text.format(models=MODELS, motion=motion, u0=u0), tmp_path)
    ref, _ = _run(sc, StepImpl.PYTHON)
    new, counts = _run(sc, StepImpl.COMPILED)
    assert set(counts) == {"flight", "contact"} and counts["contact"] > 0, counts
    _same(ref, new)
    run, _ = _run(sc, StepImpl.COMPILED, python_run=False)
    assert run.meta["run"]["loop"] == "compiled"
    assert run.meta["run"]["python_steps"] <= len(run.meta.get("invariants") or [])
    _same(ref, run)


def test_a_step_without_its_time_goes_to_python():
    """compiled.raw_step needs the step's start time where something moves with time: without it, the Python step."""
    model = ms.build_model(ms.load_scene(SCENES / "vibrating_paddle.toml"))
    data = make_data(model)
    assert compiled.raw_step(model, data, model.q0.copy(), model.u0.copy(), 1e-3, 0.5) is None
    assert list(compiled.counts(data)) == ["python: a moving static or a driven joint, and no time given"]
    assert compiled.raw_step(model, data, model.q0.copy(), model.u0.copy(), 1e-3, 0.5, t=0.0) is not None


def test_step_in_place_is_compiled_for_a_driven_joint():
    """stepper.step_in_place passes the step's time: the compiled step takes a driven scene's steps there too."""
    model = ms.build_model(ms.load_scene(SCENES / "driven_paddle.toml"))
    data = make_data(model)
    q, u = model.q0.copy(), model.u0.copy()
    t = 0.0
    for _ in range(800):  # 0.4 s: the first impacts
        t = ms.step_in_place(model, data, t, q, u).t
    assert set(compiled.counts(data)) == {"flight", "contact"}
    h, A, w = model.options.dt, 0.03, 2 * math.pi * 3.0
    assert abs(q[1] - A * math.sin(w * t)) <= h * h * A * w * w  # the trapezoid of §2.13


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("h", [5e-4, 1e-3])
def test_driven_double_pendulum_striking_a_wall(tmp_path, e, h):
    """pendulum_wall's double pendulum, its shoulder driven as pi/2 + 2 sin(pi t), its elbow free, striking the
    wall (3 s): M couples the free and driven rows (M_rd != 0) and the midpoint bias iterates (§2.13); the compiled
    step and run take every step, impacts included, and give the Python step's arrays and ledger."""
    text = (SCENES / "pendulum_wall.toml").read_text().replace(
        "q0 = [1.5707963267948966, 0.0]", "q0 = [1.5707963267948966, 0.0]\nu0 = [6.283185307179586, 0.0]")
    text = text.replace('urdf = "../models/', f'urdf = "{MODELS}/') + (
        '\n[[drives]]\nbody = "pendulum"\njoint = "shoulder"\n'
        'motion = { sine = { amplitude = 2.0, frequency = 0.5 } }\n')
    sc = inline_scene(text, tmp_path).with_options(restitution=e, dt=h, duration=3.0)
    ref, _ = _run(sc, StepImpl.PYTHON)
    new, counts = _run(sc, StepImpl.COMPILED)
    assert ref.impacts > 0 and set(counts) == {"flight", "contact"}, counts
    _same(ref, new)
    run, _ = _run(sc, StepImpl.COMPILED, python_run=False)
    assert run.meta["run"]["loop"] == "compiled"
    assert run.meta["run"]["python_steps"] <= len(run.meta.get("invariants") or [])
    _same(ref, run)
