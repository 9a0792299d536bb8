"""The compiled step on pairs of two boxes (src/step.cpp detect, src/box_box.hpp): it takes the steps of a resting
stack of boxes itself, and its trajectory is the Python step's bit for bit (docs/theory.md §2.8); the steps it
hands back (a vertex at a box's corner, edge contacts, a paid position lift) leave coal's warm start and the
detection's warm start (data.warm_start_pairs) as the Python step finds them, so the Python step that takes them
continues the same trajectory."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import moreau_sim as ms
import moreau_sim.compiled as compiled
from moreau_sim.data import make_data
from moreau_sim.model import build_model
from moreau_sim.options import StepImpl
from moreau_sim.scene import load_scene

SCENES = Path(__file__).resolve().parent.parent / "scenes"


def _model(name: str, impl: StepImpl, **options):
    return build_model(load_scene(SCENES / f"{name}.toml").with_options(step_impl=impl.value, **options))


def _steps(name: str, impl: StepImpl, n: int, **options):
    """n steps from the scene's start: (states, the detection's warm start after each step, counts)."""
    model = _model(name, impl, **options)
    data = make_data(model)
    st = ms.initial_state(model)
    states, warm = [], []
    for _ in range(n):
        st = ms.step(model, data, st).state
        states.append(st)
        warm.append(sorted(data.warm_start_pairs))
    return states, warm, compiled.counts(data)


def test_box_models_are_compiled():
    """Two boxes are no reason to hand a model to Python any more (coal's GJK/EPA on them runs on the same
    GeometryData both ways)."""
    assert compiled.unsupported(_model("box_stack_5", StepImpl.COMPILED)) is None


@pytest.mark.parametrize("turned_static", [False, True])
def test_a_moving_box_turned_in_its_joint_frame_is_handed_to_python(tmp_path, turned_static):
    """A box turned in the frame of a moving joint has face normals whose turn into the world is no exact product in
    any order of the sums: the compiled step does not take such a model (compiled.unsupported names it), whether or
    not a static box turned in the world (compiled since they sum alike, test_impact_energy) is beside it."""
    urdf = tmp_path / "turned.urdf"
    urdf.write_text((SCENES.parent / "models" / "cube.urdf").read_text().replace(
        '<collision><origin xyz="0 0 0"/>', '<collision><origin xyz="0 0 0" rpy="0 0.3 0"/>'))
    b = ms.SceneBuilder("turned", dt=1e-3, duration=0.01)
    if turned_static:
        b.add_box("slab", [2.0, 1.0, 0.1], position=[0.0, 0.0, 0.5], rpy=[0.0, 0.25, 0.0])
    b.add_body("turned", urdf, root_joint="free", position=[0.0, 0.0, 1.0])
    b.add_body("cube", SCENES.parent / "models" / "cube.urdf", root_joint="free", position=[0.0, 0.0, 1.3])
    model = build_model(b.build())
    assert compiled.unsupported(model) == "a moving box turned in its joint frame (pairs of two polytopes)"


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("h", [1e-2, 1e-3])
def test_resting_stack_every_step_compiled_and_identical(e, h):
    """box_stack_5 at rest (32 patch corners and 4 ground vertices a step, m = 36): every step
    compiled, and q, u and the detection's warm start equal to the Python step's, bit for bit."""
    n = 20
    ref, ref_warm, py = _steps("box_stack_5", StepImpl.PYTHON, n, restitution=e, dt=h)
    got, got_warm, counts = _steps("box_stack_5", StepImpl.COMPILED, n, restitution=e, dt=h)
    assert not py
    assert counts["contact"] == n, dict(counts)
    assert got_warm == ref_warm
    for a, b in zip(ref, got):
        assert np.array_equal(a.q, b.q) and np.array_equal(a.u, b.u)


@pytest.mark.parametrize("name, n", [
    # box_stack_10 at rest has 76 contacts (above the former 64-row limit; up to qp.COLD_START_ROWS = 200 rows the
    # cold active set on both sides)
    ("box_stack_10", 5),
    # heavy_on_light_box_100: equal boxes face on face, each vertex of the top one at an edge of the one below
    # (three face planes within the margin, one of them separating: a smooth contact with that face's normal,
    # contacts._corner_normals) and a face axis tied between the two boxes (contacts._face_axis: broken alike
    # by sums.ordered's products on both sides)
    ("heavy_on_light_box_100", 30),
])
def test_every_step_compiled_and_identical(name, n):
    """Every step of the scene compiled, bit for bit the Python step, the warm start alike."""
    ref, ref_warm, _ = _steps(name, StepImpl.PYTHON, n)
    got, got_warm, counts = _steps(name, StepImpl.COMPILED, n)
    assert counts["contact"] == n, dict(counts)
    assert got_warm == ref_warm
    for a, b in zip(ref, got):
        assert np.array_equal(a.q, b.q) and np.array_equal(a.u, b.u)


