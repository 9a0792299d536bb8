"""A cube resting on an equal one, tilted by round-off (docs/theory.md §6.2, item 1c): a vertex of the upper cube at
the lower cube's top corner lies on three face planes (top and two sides, to the corner margin); its edges dip below
the top plane by the tilt, so the cone test (unit edges, 1e-9) refused every face and the row took coal's point-query
normal, (0, 0.447, 0.894) at a tilt of 2e-9 or 5e-9 rad: 63 degrees off, a false way of staying apart (issue 23).
A face plane whose edges' crossing the cone test refuses still separates when the vertex's whole body lies outside it
to within the contact tolerance (contacts._corner_normals, src/step.cpp vertex_contacts): the top face does, the side
faces do not (the body reaches 0.1 m inside them). Checked against the closed form (every cube-cube row's normal is a
face normal: the lower cube's top, +z, or the upper cube's bottom, R z), both steps bit for bit, the stacks' rest over
e and h, and the rule at its edge."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
import moreau_sim.compiled as compiled
from moreau_sim.contacts import FeatureKind, _corner_normals
from moreau_sim.data import make_data

from helpers import MODELS

HALF = 0.05  # [m] the cubes' half side (tests/models/cube.urdf)
TILTS = [0.0, 5e-10, 2e-9, 5e-9, 1e-8, 1e-6]  # [rad]
AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "yawed": (1.0, 1.0, 0.3)}  # rpy = tilt * these


@pytest.fixture(scope="module", autouse=True)
def _compiled():
    assert compiled.available(), compiled.unavailable_reason()


def _stack(k: int, rpy, e: float = 0.0, h: float = 1e-3, duration: float = 0.01, impl: str = "python") -> ms.Scene:
    """k cubes on the ground, each resting on the one below, the top one rotated by rpy [rad] and lowered until its
    lowest vertex touches the cube below (the others exact)."""
    R = pin.rpy.rpyToMatrix(*rpy)
    c = np.array([[sx, sy, sz] for sx in (-HALF, HALF) for sy in (-HALF, HALF) for sz in (-HALF, HALF)])
    low = float((c @ R.T)[:, 2].min())
    b = ms.SceneBuilder("tilted_corners", restitution=e, dt=h, duration=duration, step_impl=impl)
    for j in range(k - 1):
        b.add_body(f"c{j}", MODELS / "cube.urdf", root_joint="free", position=[0.0, 0.0, HALF + 2 * HALF * j])
    b.add_body("top", MODELS / "cube.urdf", root_joint="free", position=[0.0, 0.0, 2 * HALF * (k - 1) - low],
               rpy=list(rpy))
    b.add_halfspace("ground")
    return b.build()


def _one_step(sc: ms.Scene, impl: str):
    model = ms.build_model(sc.with_options(step_impl=impl))
    data = make_data(model)
    r = ms.step(model, data, ms.initial_state(model, data))
    return r.contacts, r.state


@pytest.mark.parametrize("axis", list(AXES))
@pytest.mark.parametrize("tilt", TILTS)
def test_every_touching_row_has_a_face_normal(tilt, axis):
    """Every row between the two cubes (a vertex's, or a corner of coal's patch; one vertex only at 1e-6 rad) has the
    lower cube's top normal or the upper cube's bottom normal (to 1e-15 in every component: within 1e-15 rad of the
    closed form), so it is within the tilt of vertical; the ground's rows +z; no corner; both steps the same rows and
    bits after one step."""
    rpy = tuple(tilt * a for a in AXES[axis])
    sc = _stack(2, rpy)
    model = ms.build_model(sc)
    c = ms.detect(model, make_data(model), model.q0)
    assert not c.corners
    Rz = pin.rpy.rpyToMatrix(*rpy)[:, 2]
    ez = np.array([0.0, 0.0, 1.0])
    cubes = c.joint_b != 0
    assert np.isin(c.kind[cubes], [FeatureKind.VERTEX, FeatureKind.PATCH]).all() and cubes.any()
    for n in c.normal[cubes]:  # from B (the lower cube) to A (the upper one)
        assert min(np.abs(n - ez).max(), np.abs(n - Rz).max()) <= 1e-15, n
        assert np.hypot(n[0], n[1]) <= np.sqrt(2.0) * tilt + 1e-15  # the sine of its angle to vertical
    np.testing.assert_array_equal(c.normal[~cubes], np.tile(ez, ((~cubes).sum(), 1)))
    (cp, sp), (cc, sc_) = _one_step(sc, "python"), _one_step(sc, "compiled")
    assert cp.m == cc.m and cp.kind.tolist() == cc.kind.tolist() and cp.feature.tolist() == cc.feature.tolist()
    assert np.array_equal(cp.normal, cc.normal) and np.array_equal(cp.g, cc.g)
    assert np.array_equal(sp.q, sc_.q) and np.array_equal(sp.u, sc_.u)


@pytest.mark.parametrize("h", [1e-3, 1e-2])
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("k", [2, 3])
def test_a_stack_with_a_tilted_top_stays_put(k, e, h):
    """Two and three cubes, the top one tilted by 5e-9 rad about x (its high vertices 5e-10 m up, within the contact
    tolerance of the lower cube's top corners): over 0.2 s no cube moves by more than 1e-9 m, under both steps, with
    the same bits."""
    q = {}
    for impl in ("python", "compiled"):
        traj = ms.run(_stack(k, (5e-9, 0.0, 0.0), e, h, 0.2, impl))
        xyz = traj.q.reshape(len(traj.t), k, 7)[:, :, :3]
        assert float(np.abs(xyz - xyz[0]).max()) <= 1e-9, impl
        q[impl] = traj.q
    assert np.array_equal(q["python"], q["compiled"])


def test_the_rule_at_its_edge():
    """The upper cube's vertex (+x, +y, bottom) at the lower cube's top corner, its edge along -y dipping by 5e-9 rad
    (the cone test refuses the top face): the top face separates while the body's lowest vertex is within the contact
    tolerance below the top plane, the next double below it does not (no face: None); the side faces never do."""
    model = ms.build_model(_stack(2, (0.0, 0.0, 0.0)))
    pair = model.pairs[0]
    assert model.geometry_body[pair.first] == "top" and model.geometry_body[pair.second] == "c0"
    tol = model.options.contact_tolerance
    oMo = pin.SE3(np.eye(3), np.array([0.0, 0.0, HALF]))
    oMi = pin.SE3(pin.rpy.rpyToMatrix(5e-9, 0.0, 0.0), np.zeros(3))
    i = 6  # signs (+, +, -): shapes.vertex_edges' order
    p = np.array([HALF, HALF, 2 * HALF])

    def s_top(z):  # the body vertex's signed distance to the top plane, summed as the rule sums it
        n, d = model.face_planes[pair.second]
        return (n @ (oMo.rotation.T @ (np.array([-HALF, -HALF, z]) - oMo.translation)) - d)[2]

    z = 2 * HALF - tol
    while s_top(z) < -tol:
        z = np.nextafter(z, np.inf)
    while s_top(np.nextafter(z, -np.inf)) >= -tol:
        z = np.nextafter(z, -np.inf)
    assert s_top(z) >= -tol > s_top(np.nextafter(z, -np.inf))
    for zz, top in ((z, True), (np.nextafter(z, -np.inf), False)):
        body = np.array([p, [-HALF, -HALF, zz]])
        got = _corner_normals(model, pair.first, i, oMi, pair.second, oMo, p, tol, body, tol)
        if top:
            np.testing.assert_array_equal(got[0], [[0.0, 0.0, 1.0]])
        else:
            assert got is None
