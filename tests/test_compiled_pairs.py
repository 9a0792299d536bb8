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
    hand-backs (corners) retaken by the Python step, the Python
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


def _as_table(monkeypatch) -> None:
    """Scenes built from here on without a pair list (model.LAZY_PAIRS) and with the broad phase
    (broad_phase.MIN_PAIRS): the configuration of every scene above 20,000 pairs, on small scenes."""
    monkeypatch.setattr(ms.model, "LAZY_PAIRS", 0)
    monkeypatch.setattr(broad_phase, "MIN_PAIRS", 0)


def _steps(model, n: int) -> tuple[list, object]:
    """n steps of ms.step from the initial state: each step's (q, u, P bytes, correction energy), and the Data."""
    data = make_data(model)
    st, out = ms.initial_state(model, data), []
    for _ in range(n):
        r = ms.step(model, data, st)
        st = r.state
        out.append((st.q.tobytes(), st.u.tobytes(), r.P.tobytes(), r.correction_energy))
    return out, data


@pytest.mark.parametrize("name, steps, share", [
    ("box_stack_10", 120, 1.0), ("panda_table", 200, 0.9), ("block_on_step", 200, 0.9),
    ("column_of_beads_100", 200, 1.0), ("solo12_stand", 100, 1.0), ("alternating_stack_10", 20, 0.0)])
def test_a_table_of_pairs_compiled_and_identical(name, steps, share, monkeypatch):
    """A scene without a pair list: the compiled step holds nothing per pair (src/pair_table.hpp mirrors
    pair_table.PairTable) and queries coal on the broad phase's candidates through the objects the Python step
    makes per pair at first use (data.Data.pair_query), GJK warm starts included, restored where a step is handed
    back (alternating_stack_10 hands back every step, block_on_step its corner): every step is the Python step's
    on the same table bit for bit, and no GeometryData of every pair is made (docs/theory.md §2.12)."""
    _as_table(monkeypatch)
    sc = _scene(name)
    ref, _ = _steps(ms.build_model(sc.with_options(step_impl="python")), steps)
    model = ms.build_model(sc.with_options(step_impl="compiled"))
    assert not model.listed and compiled.unsupported(model) is None
    new, data = _steps(model, steps)
    counts = compiled.counts(data)
    assert counts["flight"] + counts["contact"] >= share * steps, dict(counts)
    assert share > 0 or counts["flight"] + counts["contact"] < steps
    assert new == ref
    assert data._geom is None and model.geometry_model is None


@pytest.mark.parametrize("e", [0.0, 0.9])
def test_the_correction_guard_on_a_table_of_pairs(e, monkeypatch):
    """column_of_beads_100 without a pair list: the position correction's guard (no other pair pushed deeper,
    contacts.pair_distances(near=True): the candidates' distances, +inf for the other pairs) runs on the coal
    distance objects the Python step makes per pair (data.Data.distance_query): the steps, corrected ones among them,
    are the Python step's bit for bit."""
    _as_table(monkeypatch)
    sc = _scene("column_of_beads_100", restitution=e)
    ref, _ = _steps(ms.build_model(sc.with_options(step_impl="python")), 200)
    model = ms.build_model(sc.with_options(step_impl="compiled"))
    new, data = _steps(model, 200)
    assert new == ref
    assert any(c != 0.0 for *_, c in new) and len(data._coal_distance) > 0
    assert compiled.counts(data)["contact"] > 0 and not any(k.startswith("python") for k in compiled.counts(data))


def test_a_table_with_left_out_pairs_names_the_python_candidates(monkeypatch):
    """A column whose scene leaves out the pairs that cannot touch (bead i with i + 2 and beyond, the upper beads with
    the ground: sorted keys removed from every row of the table) built without a pair list: the compiled step's pair
    indices (src/pair_table.hpp's index, geometries) are PairTable's, its candidates broad_phase's at every step's
    midpoint, and its steps the Python step's bit for bit."""
    _as_table(monkeypatch)
    b = ms.SceneBuilder("column_left_out", folder=str(SCENES), restitution=0.5, dt=5e-4, duration=0.05,
                        step_impl="compiled")
    n = 12
    for k in range(n):
        b.add_body(f"bead{k}", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1), q0=[0.1 + 0.2 * k])
    b.add_halfspace("ground")
    for i in range(n):
        for j in range(i + 2, n):
            b.exclude(f"bead{i}", f"bead{j}")
    for k in range(1, n, 2):
        b.exclude(f"bead{k}", "ground")
    model = ms.build_model(b.build())
    table = model.pair_table
    assert not model.listed and len(table.removed) > 0 and len(table) == n - 1 + (n + 1) // 2
    data, probe = make_data(model), make_data(model)
    bp = broad_phase.of(model, max(model.options.contact_tolerance, GATE_MARGIN))
    ref, _ = _steps(ms.build_model(b.build().with_options(step_impl="python")), 60)
    st, h = ms.initial_state(model, data), model.options.dt
    for k in range(60):
        r = ms.step(model, data, st)
        q_m = pin.integrate(model.pin, st.q, 0.5 * h * st.u)
        model.forest.place(probe.kinematics, q_m, model.geometries, probe.oMg)
        assert data._compiled_step.stepper.candidates == bp.candidates(probe).tolist()
        assert (r.state.q.tobytes(), r.state.u.tobytes()) == ref[k][:2]
        st = r.state
    assert compiled.counts(data)["contact"] == 60


def test_a_scene_above_the_pair_list_limit_gets_the_compiled_step():
    """A 250-bead column (31,125 pairs, above model.LAZY_PAIRS: no pair list) gets the compiled step with nothing
    made per pair but the broad phase's candidates' coal objects (about two a bead), where it used to build a
    GeometryData of every pair (quadratic in beads); the compiled time-stepping run loop takes its runs too,
    recording a gap per geometry (tests/test_record_gaps.py); the event loops record every pair's distance, so they
    refuse such a scene in one line."""
    from benchmarks.scaling import column

    model = ms.build_model(column(250).with_options(step_impl="compiled"))
    assert not model.listed and compiled.unsupported(model) is None
    data = make_data(model)
    ms.step(model, data, ms.initial_state(model, data))
    assert data._geom is None and 0 < len(data._coal) <= 2 * 250
    assert compiled.loop_refusal(model, "Runner", "the run loop", whole=False) is None
    why = compiled.loop_refusal(model, "Extrapolator", "the event loop")
    assert why is not None and why.startswith("a scene without a pair list") and "\n" not in why
    traj = ms.simulate(ms.build_model(model.scene.with_options(duration=10 * model.options.dt)), progress=False)
    assert traj.meta["run"]["loop"] == "compiled" and traj.gap.shape == (11, 251) and traj.meta["status"] == "complete"


def test_the_dense_matrices_limit_edge(monkeypatch):
    """The compiled step forms M and M^-1 dense (compiled.DENSE_COPIES of (nv, nv) doubles): a model gets it while they
    fit the memory limit, and is refused in one line one byte below (its steps then go to the Python step)."""
    from moreau_sim.memory import DATA_LIMIT_VARIABLE

    model = ms.build_model(_scene("box_stack_10", step_impl="compiled"))
    need = compiled.DENSE_COPIES * 8 * model.nv ** 2
    monkeypatch.setenv(DATA_LIMIT_VARIABLE, repr(need / 2 ** 30))
    assert compiled.unsupported(model) is None
    monkeypatch.setenv(DATA_LIMIT_VARIABLE, repr((need - 1) / 2 ** 30))
    why = compiled.unsupported(model)
    assert why is not None and why.startswith("its dense mass matrices") and "\n" not in why
