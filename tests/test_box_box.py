"""Edge-on-edge contacts of two boxes in the fixed step's detection (moreau_sim/box_box.py, docs/theory.md §6.2):
two cubes crossed at 90 degrees edge on edge against the closed form, and a cube dropped edge first onto
another's edge, which bounces with the law's ratio."""

import math

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim.contacts import FeatureKind
from moreau_sim.energy import total

from helpers import MODELS

S = 0.05  # [m] the cubes' half side
TOP = S * math.sqrt(2.0)  # [m] the height of an edge of a cube standing on it, above its centre


def crossed(z: float, *, e: float = 0.5, h: float = 1e-3) -> ms.Scene:
    """A static 0.1 m cube turned 45 deg about y (its top edge along y at z = TOP) and a free one turned 45 deg
    about x at height z (its bottom edge along x at z - TOP): the two edges cross at 90 deg above the origin."""
    b = ms.SceneBuilder("crossed_edges", restitution=e, dt=h, duration=0.2)
    b.add_box("edge", [2 * S] * 3, position=[0.0, 0.0, 0.0], rpy=[0.0, math.pi / 4, 0.0])
    b.add_body("cube", MODELS / "cube.urdf", root_joint="free", position=[0.0, 0.0, z], rpy=[math.pi / 4, 0.0, 0.0])
    return b.build()


@pytest.mark.parametrize("d", [-1e-3, -1e-6, 0.0, 5e-10])
def test_crossed_edges_gap_and_normal_are_exact(d):
    """Edges crossed at 90 deg a distance d apart along z (d < 0: crossed into each other): one contact, of kind
    EDGE, gap d, normal +z (from the static cube to the free one), its points on the two edges above the origin."""
    model = ms.build_model(crossed(2 * TOP + d))
    data = ms.make_data(model)
    c = ms.detect(model, data, model.q0)
    assert c.m == 1 and not c.corners and c.kind[0] == FeatureKind.EDGE
    assert abs(c.g[0] - d) <= 1e-15
    np.testing.assert_allclose(c.normal[0], [0.0, 0.0, 1.0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(c.point_a[0], [0.0, 0.0, TOP + d], rtol=0, atol=1e-15)
    np.testing.assert_allclose(c.point_b[0], [0.0, 0.0, TOP], rtol=0, atol=1e-15)


def test_crossed_edges_apart_are_no_contact():
    """2 um apart (beyond the contact tolerance): no contact at all."""
    model = ms.build_model(crossed(2 * TOP + 2e-6))
    assert ms.detect(model, ms.make_data(model), model.q0).m == 0


@pytest.mark.parametrize("h", [1e-3, 1e-4])
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_a_cube_dropped_edge_on_edge_bounces_with_the_law(e, h):
    """The free cube falls 2 cm onto the crossed edge: a central impact (the contact point under its centre of
    mass, the normal vertical), so the impact step gives gamma+ = -e gamma- on the edge contact, the cube does
    not turn, and T + V does not rise; it leaves with the approach speed times e (to the smooth forces' h g)."""
    scene = crossed(2 * TOP + 0.02, e=e, h=h)
    model = ms.build_model(scene)
    data = ms.make_data(model)
    state = ms.initial_state(model)
    for k in range(int(round(0.2 / h))):
        r = ms.step(model, data, state, t_next=(k + 1) * h)
        if r.contacts.m:
            assert r.contacts.m == 1 and r.contacts.kind[0] == FeatureKind.EDGE
            gm, gp = float(r.gamma_minus[0]), float(r.gamma_plus[0])
            assert gm < -0.5 and r.P[0] > 0.0
            assert abs(gp + e * gm) <= 1e-12 * abs(gm), (gp, gm)
            assert np.abs(r.state.u[3:]).max() <= 1e-12  # no turn
            assert np.abs(r.state.u[:2]).max() <= 1e-12  # no slide
            assert r.state.u[2] == pytest.approx(-e * state.u[2], abs=2 * h * 9.81)
            assert total(model, data, r.state.q, r.state.u) <= total(model, data, state.q, state.u) + 1e-15
            break
        state = r.state
    else:
        pytest.fail("no impact")


@pytest.mark.parametrize(("yaw", "tilt"), [(1e-4, 1e-14), (1e-5, -1e-15), (1e-6, 1e-16), (1e-8, 0.0)])
def test_nearly_parallel_edges_of_faces_on_faces_take_a_face_normal(yaw, tilt):
    """A cube resting face on face on another, yawed by `yaw` and tilted by `tilt` about x [rad]: their nearly
    parallel edges cross, and the lines' common normal is tilt / yaw off the faces' (1e-10 rad at 1e-14 / 1e-4),
    outside the upper cube's normal cone by less than box_box.CONE: under a heavy load it pushed a light cube
    sideways. Every crossing's
    normal is in both edges' cones: here a face normal of one of the two cubes (to round-off)."""
    import coal
    import pinocchio as pin

    from moreau_sim import box_box

    cube = coal.Box(2 * S, 2 * S, 2 * S)
    lower = pin.SE3.Identity()
    upper = pin.SE3(pin.rpy.rpyToMatrix(tilt, 0.0, yaw), np.array([0.0, 0.0, 2 * S]))
    edges = box_box.box_edges(cube, pin.SE3.Identity())
    box = [(M.rotation, M.translation, np.full(3, S)) for M in (upper, lower)]
    hits = box_box.edge_crossings(box_box.world(edges, upper), box_box.world(edges, lower), *box, 1e-9)
    assert hits  # the yawed square's edges cross the other's
    faces = np.array([upper.rotation[:, 2], [0.0, 0.0, 1.0]])
    for g, _, _, n, _, _ in hits:
        assert np.abs(faces - n).max(axis=1).min() <= 1e-15, n
        assert abs(g) <= 2 * S * (abs(tilt) + 1e-15)
