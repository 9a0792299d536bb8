"""The forest of models (moreau_sim/trees.py, docs/theory.md §2.12): one Pinocchio model per body.

- on every bundled scene, the forest's M(q), M(q)^-1, free acceleration, bias h(q, u), WORLD
  Jacobians, joint placements and kinetic energy equal the whole scene model's bit for bit, and its
  potential energy too except for bodies of several joints (another association of the same sum:
  within 1e-15 relative); the contact-space matrix W'M^-1W tree by tree equals the dense product;
- a column of 1000 touching beads builds and steps on the Python step (no persistent penetration,
  no energy gain);
- a scene whose whole-model Data is refused (the memory limit) runs on the Python step.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
from moreau_sim import energy
from moreau_sim.bodies import load_body
from moreau_sim.data import make_data
from moreau_sim.errors import SceneError
from moreau_sim.model import DATA_LIMIT_VARIABLE, build_model, initial_state
from moreau_sim.options import RootJoint
from moreau_sim.scene import load_scene
from moreau_sim.stepper import step

ROOT = Path(__file__).resolve().parent.parent
SCENES = sorted((ROOT / "scenes").glob("*.toml"))


def _states(model, n: int = 3):
    """The initial state and n random states (random q on each joint's manifold, random u)."""
    rng = np.random.default_rng(7)
    out = [(model.q0, model.u0 + 0.1)]
    for _ in range(n):
        q = pin.randomConfiguration(model.pin, -np.ones(model.nq), np.ones(model.nq))
        out.append((q, rng.standard_normal(model.nv)))
    return out


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_forest_equals_whole_model(path):
    model = build_model(load_scene(path))
    data = make_data(model)
    f, kin, pm, pd = model.forest, data.kinematics, model.pin, data.pin
    assert (f.nq, f.nv, f.njoints) == (model.nq, model.nv, pm.njoints)
    tau = np.linspace(-1.0, 1.0, model.nv)
    for q, u in _states(model):
        M = pin.crba(pm, pd, q, pin.Convention.WORLD).copy()
        J = pd.J.reshape(6, -1).copy()
        assert np.array_equal(f.mass_matrix(kin, q), M)
        assert np.array_equal(kin.J, J)
        assert np.array_equal(f.inverse_mass_matrix(kin, q), pin.computeMinverse(pm, pd, q))
        assert np.array_equal(f.acceleration(kin, q, u, tau), pin.aba(pm, pd, q, u, tau))
        assert np.array_equal(f.bias(kin, q, u), pin.nonLinearEffects(pm, pd, q, u))
        T = pin.computeKineticEnergy(pm, pd, q, u)
        assert f.kinetic(kin, q, u) == T
        V = pin.computePotentialEnergy(pm, pd, q)
        if all(t.single for t in f.trees):
            assert f.potential(kin, q) == V
        else:
            assert abs(f.potential(kin, q) - V) <= 1e-15 * (1.0 + abs(V)) * pm.njoints
        pin.updateGeometryPlacements(pm, pd, model.geom, data.geom, q)
        oMg = [np.array(o.homogeneous) for o in data.geom.oMg]
        oMi = [np.array(o.homogeneous) for o in pd.oMi]
        f.place(kin, q, model.geometries, data.geom.oMg)
        assert all(np.array_equal(a, o.homogeneous) for a, o in zip(oMi, kin.oMi))
        assert all(np.array_equal(a, o.homogeneous) for a, o in zip(oMg, data.geom.oMg))
        W = np.random.default_rng(1).standard_normal((model.nv, 4))
        W[: model.nv // 2] = 0.0
        G = W.T @ pin.computeMinverse(pm, pd, q) @ W
        assert np.allclose(f.delassus(kin, q, W), G, rtol=1e-12, atol=1e-12 * np.abs(G).max())


def column(n: int, **options) -> ms.Scene:
    """n touching beads (r = 0.1 m, 1 kg) on vertical prismatic joints over the ground."""
    b = ms.SceneBuilder(f"column_{n}", folder=ROOT / "scenes", restitution=0.5, dt=5e-4, duration=0.01,
                        step_impl="python", **options)
    for k in range(n):
        b.add_body(f"bead{k}", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1), q0=[0.1 + 0.2 * k])
    b.add_halfspace("ground")
    return b.build()


def _run_column(model, steps: int):
    data = make_data(model)
    state = initial_state(model, data)
    E0 = energy.total(model, data, state.q, state.u)
    tol = model.options.contact_tolerance
    for _ in range(steps):
        r = step(model, data, state)
        assert r.qp is None or r.qp.ok
        state = r.state
        assert energy.total(model, data, state.q, state.u) <= E0 + 1e-9 * (1.0 + abs(E0))  # no energy gain
    g = ms.contacts.pair_distances(model, data, state.q)
    assert np.nanmin(g) >= -10 * tol - 0.5 * model.options.dt * 9.81 * model.options.dt  # no persistent penetration
    return state


def test_refused_whole_data_runs_on_the_python_step(monkeypatch):
    """A scene whose whole-model Data exceeds the memory limit: the compiled step's Data is refused
    with one line, and the Python step runs it on the forest."""
    model = build_model(column(20).with_options(step_impl="compiled"))
    monkeypatch.setenv(DATA_LIMIT_VARIABLE, "1e-7")  # 107 bytes: no Data of nv = 20 fits (256 kB)
    data = make_data(model)
    with pytest.raises(SceneError, match="nv = 20 degrees of freedom"):
        data.pin  # noqa: B018
    assert not model.whole_data_fits()
    state = _run_column(model, 40)
    assert np.all(np.diff(state.q) > -1e-3)  # the beads stay in order


@pytest.mark.slow
def test_column_of_1000_beads():
    model = build_model(column(1000))
    assert model.nv == 1000 and len(model.forest.trees) == 1000
    _run_column(model, 5)


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_whole_model_as_appended_one_by_one(path):
    """model._whole (pairwise appends and one pass over the geometries) makes the scene's model and
    geometry that appending the bodies one by one with pin.appendModel makes (Pinocchio's ==)."""
    scene = load_scene(path)
    built = build_model(scene)
    model, geom = pin.Model(), pin.GeometryModel()
    for i, body in enumerate(scene.bodies):
        m, g, _, _ = load_body(body, f"[[bodies]][{i}]")
        placement = (pin.SE3.Identity() if body.root_joint is RootJoint.FREE else
                     pin.SE3(pin.rpy.rpyToMatrix(*body.rpy), np.array(body.position, float)))
        model, geom = pin.appendModel(model, m, geom, g, 0, placement)
    model.name = scene.name
    model.gravity.linear = np.array(scene.options.gravity, float)
    assert model == built.pin
    for a, b in zip(geom.geometryObjects, built.geom.geometryObjects):
        assert (a.name, a.parentJoint, a.parentFrame) == (b.name, b.parentJoint, b.parentFrame)
        assert np.array_equal(a.placement.homogeneous, b.placement.homogeneous)
    assert geom.ngeoms == built.geom.ngeoms - len(scene.statics)


@pytest.mark.parametrize("where", ["build", "run"])
def test_a_failed_allocation_is_one_line_naming_the_scene_and_its_size(where, monkeypatch):
    """A MemoryError (or std::bad_alloc as a RuntimeError) while the model is built or while it runs is
    a SceneError / SimulationError of one line naming the scene and its size, never a traceback."""
    import importlib

    model_module, simulate_module = (importlib.import_module(f"moreau_sim.{m}") for m in ("model", "simulate"))

    def fail(*a, **k):
        raise MemoryError

    sc = load_scene(ROOT / "scenes" / "column_of_beads.toml")
    if where == "build":
        monkeypatch.setattr(model_module, "whole_model", fail)
        with pytest.raises(SceneError) as ei:
            build_model(sc)
        assert "out of memory building its model" in str(ei.value)
    else:
        model = build_model(sc)
        def bad_alloc(*a, **k):
            raise RuntimeError("std::bad_alloc")

        monkeypatch.setattr(simulate_module, "drive", bad_alloc)
        with pytest.raises(ms.SimulationError) as ei:
            ms.simulate(model, progress=False)
        assert f"nv = {model.nv}" in str(ei.value) and f"{len(model.pairs)} collision pairs" in str(ei.value)
    msg = str(ei.value)
    assert "column_of_beads" in msg and "bodies" in msg and "\n" not in msg
    assert ei.value.__cause__ is None and ei.value.__suppress_context__
