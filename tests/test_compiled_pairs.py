"""The compiled step on every pair (src/step.cpp detect): pairs coal resolves by GJK/EPA (panda_table's and
panda_tapping's cylinders on a box, two convex meshes: coal's warm start runs on the same GeometryData both ways,
saved before the detection and restored where a step is handed back) and models of more than
broad_phase.MIN_PAIRS pairs (the compiled step queries the broad phase's candidates, the same pairs as the Python
step, so that the GJK warm starts of the pairs it skips age alike). Each scene's compiled run takes its steps
(the run's meta and compiled.counts say so) and gives the Python step's run bit for bit: every array of the
trajectory, the ledger's included (docs/theory.md §2.8)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
import moreau_sim.compiled as compiled
from moreau_sim import broad_phase
from moreau_sim.data import GATE_MARGIN, make_data
from moreau_sim.ledger import ledger

SCENES = Path(__file__).resolve().parent.parent / "scenes"


@pytest.fixture(scope="module", autouse=True)
def _compiled():
    assert compiled.available(), compiled.unavailable_reason()


def _pile(n: int, **options) -> ms.Scene:
    from benchmarks.scaling import pile

    return pile(n).with_options(step_impl="compiled", **options)


def _scene(name: str, **options) -> ms.Scene:
    return ms.load_scene(SCENES / f"{name}.toml").with_options(**options)


def _arrays_differ(a, b) -> list[str]:
    def same(x, y):
        return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
    keys = set(a.arrays) | set(b.arrays)
    return sorted(k for k in keys if k not in a.arrays or k not in b.arrays or not same(a.arrays[k], b.arrays[k]))


def _both(sc: ms.Scene):
    """(the Python step's run, the compiled run, the compiled run's step counts)."""
    ref = ms.simulate(ms.build_model(sc.with_options(step_impl="python")), progress=False)
    model = ms.build_model(sc.with_options(step_impl="compiled"))
    data = make_data(model)
    new = ms.simulate(model, data=data, progress=False)
    return ref, new, compiled.counts(data)


@pytest.mark.parametrize("name", ["panda_tapping", "panda_table", "box_stack_10"])
def test_the_scenes_are_compiled(name):
    """No pair hands these scenes' steps to Python any more."""
    assert compiled.unsupported(ms.build_model(_scene(name))) is None


def test_a_pile_under_the_broad_phase_is_compiled():
    model = ms.build_model(_pile(27))
    assert broad_phase.of(model, max(model.options.contact_tolerance, GATE_MARGIN)) is not None
    assert compiled.unsupported(model) is None


def _check(ref, new, counts, *, compiled_share: float):
    assert ref.meta["run"]["loop"] == "python" and new.meta["run"]["loop"] == "compiled"
    steps = new.meta["run"]["steps"]
    taken = counts["flight"] + counts["contact"]
    assert counts["contact"] > 0 and taken >= compiled_share * steps, dict(counts)
    assert _arrays_differ(ref, new) == []
    a, b = ledger(ref), ledger(new)
    for f in dataclasses.fields(a):  # floats and arrays by their bytes, the impact rows by their exact repr
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray) and x.dtype != object:
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), f.name
        else:
            assert repr(x if not isinstance(x, np.ndarray) else x.tolist()) == repr(
                y if not isinstance(y, np.ndarray) else y.tolist()), f.name


@pytest.mark.parametrize("e", [0.0, 0.5])
@pytest.mark.parametrize("h", [1e-3, 5e-4])
def test_panda_tapping_compiled_and_identical(e, h):
    """The arm's first tap on the table (0.45 s: the hand's spheres strike and rest; its cylinders' pairs are
    queried by GJK every step): every step compiled, the Python step's run bit for bit."""
    ref, new, counts = _both(_scene("panda_tapping", restitution=e, dt=h, duration=0.45))
    _check(ref, new, counts, compiled_share=1.0)


@pytest.mark.parametrize("e", [0.0, 0.3, 1.0])
def test_panda_table_compiled_and_identical(e):
    """The falling arm lands with its cylinders on the table (coal's GJK/EPA witness contacts, the patch about the
    box's face normal nearest to coal's, contacts._snap): the compiled run takes its steps, those it hands back
    (corners) retaken by the Python step from the same warm start, the Python step's run bit for bit."""
    ref, new, counts = _both(_scene("panda_table", restitution=e, duration=0.4))
    _check(ref, new, counts, compiled_share=0.9)


@pytest.mark.slow
@pytest.mark.parametrize("e", [0.1, 0.5])
def test_a_27_cube_pile_compiled_and_identical(e):
    """benchmarks.scaling's pile of 27 cubes in a bin (486 pairs: the broad phase) falling and landing: the compiled
    step queries the broad phase's candidates and takes the steps with edge contacts itself (test_compiled_edges), the
    hand-backs (corners, more rows than compiled.MAX_CONTACTS) retaken by the Python step, the Python
    step's run bit for bit."""
    ref, new, counts = _both(_pile(27, restitution=e, duration=0.25))
    assert "python: edge contacts of two boxes" not in counts, dict(counts)
    _check(ref, new, counts, compiled_share=0.3)


def test_the_candidates_are_the_broad_phase_s():
    """The compiled step's broad phase (src/step.cpp candidates) names the pairs broad_phase.candidates_at names at
    the step's midpoint, on every step of a pile falling onto the ground and onto itself (0.16 s)."""
    model = ms.build_model(_pile(27))
    data, probe = make_data(model), make_data(model)
    bp = broad_phase.of(model, max(model.options.contact_tolerance, GATE_MARGIN))
    st = ms.initial_state(model)
    h = model.options.dt
    most = 0
    for _ in range(160):
        r = ms.step(model, data, st)
        q_m = pin.integrate(model.pin, st.q, 0.5 * h * st.u)
        model.forest.place(probe.kinematics, q_m, model.geometries, probe.oMg)
        got = data._compiled_step.stepper.candidates
        assert got == bp.candidates(probe).tolist()
        most = max(most, len(got))
        st = r.state
    assert most >= 10 and compiled.counts(data)["contact"] > 40


def _mesh_stack(e: float, h: float, duration: float) -> ms.Scene:
    """Two convex meshes (models/box_mesh.urdf: coal's ConvexBase) dropped onto a cube on the ground, the top one
    tilted so that it lands on an edge."""
    b = ms.SceneBuilder("mesh_stack", folder=SCENES, restitution=e, dt=h, duration=duration,
                        description="two box meshes dropped on a cube")
    b.add_body("bottom", "../models/cube.urdf", root_joint="free", position=(0.0, 0.0, 0.05))
    b.add_body("mid", "../models/box_mesh.urdf", root_joint="free", position=(0.01, 0.0, 0.35), rpy=(0.0, 0.0, 0.2))
    b.add_body("top", "../models/box_mesh.urdf", root_joint="free", position=(0.0, 0.02, 0.85), rpy=(0.4, 0.3, -0.3))
    b.add_halfspace("ground")
    return b.build()


@pytest.mark.parametrize("e", [0.0, 0.5])
@pytest.mark.parametrize("h", [1e-3, 2e-3])
def test_two_convex_meshes_compiled_and_identical(e, h):
    """Pairs of two polytopes other than two boxes (mesh on mesh, mesh on box: vertex point queries, the face axis,
    coal's patch): compiled, the Python step's run bit for bit (a paid position lift is handed back: at e = 0 the
    cube under the meshes takes one in about 4 of 5 steps, theory §2.5)."""
    sc = _mesh_stack(e, h, 0.6)
    assert len(ms.build_model(sc).polytope_pair_set) == 3
    ref, new, counts = _both(sc)
    _check(ref, new, counts, compiled_share=0.15)
