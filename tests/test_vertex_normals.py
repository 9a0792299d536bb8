"""A box vertex's contact normal against another box (contacts._corner_normals, src/step.cpp vertex_contacts,
docs/theory.md §6.2), against the closed form of a point's distance to a box: a vertex outside the box within the
corner margin of one face plane only lies over that face (its projection inside it, the other planes behind it)
and takes that face's normal, the exact one, not coal's (whose point query, warm-started from the previous
vertex's, gave a normal 0.45 rad off vertical to a vertex 1.4e-17 m over a face and 1.2e-9 m inside its edges).
Both steps take the same rows (the Python step's bits)."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
import moreau_sim.compiled as compiled
from moreau_sim.contacts import FeatureKind

from helpers import MODELS

TILT = (0.3, 0.2, 0.0)  # [rad] roll, pitch of the cube: one vertex lowest
TOP, EDGE = 0.05, 0.2  # [m] the slab's top face z = TOP, its side face x = EDGE


def _tilted_cube_over_a_slab_edge(dx: float, dz: float, h: float = 1e-3) -> ms.Scene:
    """A static slab 0.4 x 0.4 x 0.1 m (top face z = 0.05, side face x = 0.2) and a free 0.1 m cube tilted by TILT,
    its lowest vertex at (0.2 + dx, 0, 0.05 + dz): over the top face for dx < 0, beyond the side plane for dx > 0
    (q0; the scene starts it LIFT higher, as a start inside the slab is refused)."""
    R = pin.rpy.rpyToMatrix(*TILT)
    corners = np.array([[sx, sy, sz] for sx in (-0.05, 0.05) for sy in (-0.05, 0.05) for sz in (-0.05, 0.05)])
    low = (corners @ R.T)[np.argmin((corners @ R.T)[:, 2])]
    b = ms.SceneBuilder("vertex_over_an_edge", restitution=0.5, dt=h, duration=10 * h)
    b.add_box("slab", [0.4, 0.4, 0.1], position=[0.0, 0.0, 0.0])
    b.add_body("cube", MODELS / "cube.urdf", root_joint="free",
               position=(np.array([EDGE + dx, 0.0, TOP + dz + LIFT]) - low).tolist(), rpy=list(TILT))
    return b.build()


LIFT = 0.01  # [m]


def _point_to_box(p: np.ndarray, half: np.ndarray) -> tuple[float, np.ndarray]:
    """The signed distance [m] of point p to an axis-aligned box of half sides `half` at the origin, and its unit
    normal (out of the box towards p): outside, from the nearest point; inside, the nearest face's."""
    q = np.clip(p, -half, half)
    if (q != p).any():
        v = p - q
        d = float(np.sqrt(v @ v))
        return d, v / d
    s = np.abs(p) - half
    f = int(np.argmax(s))
    n = np.zeros(3)
    n[f] = np.sign(p[f])
    return float(s[f]), n


def _rows(sc: ms.Scene, impl: str, lift: float = 0.0):
    """The contacts and the state after one step under the step `impl` from the scene's start lowered by `lift` [m]."""
    model = ms.build_model(sc.with_options(step_impl=impl))
    data = ms.make_data(model)
    q = model.q0.copy()
    q[2] -= lift
    r = ms.step(model, data, ms.State(0.0, q, model.u0.copy()))
    if impl == "compiled":  # it took the step itself (no hand-back to the Python step)
        assert compiled.counts(data)["contact"] == 1, dict(compiled.counts(data))
    return r.contacts, r.state


@pytest.mark.parametrize(("dx", "dz"), [
    (-1.5e-9, 0.0), (-1.5e-9, 5e-10), (-1e-6, 0.0), (-0.1, 1e-10),  # over the top face, just inside its edge or not
    (1e-10, -1.5e-9), (5e-10, -2e-9),  # beyond the side plane, below the top one: over the side face
])
def test_a_vertex_over_one_face_takes_the_exact_normal(dx, dz):
    """The vertex within the margin (the contact tolerance, 1e-9 m) of one face plane only: its one vertex contact
    has the closed form's gap and normal, the face's (to round-off), in both steps alike."""
    sc = _tilted_cube_over_a_slab_edge(dx, dz)
    model = ms.build_model(sc)
    q = model.q0.copy()
    q[2] -= LIFT
    c = ms.detect(model, ms.make_data(model), q)
    vertex = np.flatnonzero(c.kind == FeatureKind.VERTEX)  # (beyond the side plane the slab's edge crosses too)
    assert len(vertex) == 1 and not c.corners
    c = c.select(vertex)
    d, n = _point_to_box(np.array([EDGE + dx, 0.0, TOP + dz]), np.array([0.2, 0.2, 0.05]))
    assert np.count_nonzero(n) == 1  # one face's region
    n_ba = n if c.joint_a[0] != 0 else -n  # from B to A: the cube is A or B
    assert abs(c.g[0] - d) <= 1e-15 * (1.0 + abs(dz) / 1e-9)
    np.testing.assert_allclose(c.normal[0], n_ba, rtol=0, atol=1e-15)
    (cp, sp), (cc, sc_) = _rows(sc, "python", LIFT), _rows(sc, "compiled", LIFT)
    assert np.array_equal(cp.normal, cc.normal) and np.array_equal(cp.g, cc.g)
    assert np.array_equal(sp.q, sc_.q) and np.array_equal(sp.u, sc_.u)


STACK_POSES = ([2.1904590197581883e-11, 2.1865706158418885e-11, 0.05],  # a resting stack's two lowest cubes
               [-9.883031108127316e-19, -3.418801318401898e-18, 6.154048403456417e-15],  # at step 50 (h = 1e-2, e = 0)
               [-1.0847480191594258e-09, 1.4912403134036772e-09, 0.15000000000000002],
               [0.0, 0.0, -5.7712510326268784e-09])


@pytest.mark.parametrize("poses", [
    STACK_POSES,
    ([0.0, 0.0, 0.05], [0.0, 0.0, 0.0], [1.5e-9, -1.2e-9, 0.15], [0.0, 0.0, 5.8e-9]),
    ([0.0, 0.0, 0.05], [0.0, 0.0, 0.0], [-2e-9, 2e-9, 0.15], [0.0, 0.0, 0.0]),
], ids=["stack", "shifted", "shifted_more"])
def test_a_cube_resting_a_nanometre_off_another_has_vertical_normals(poses):
    """A cube resting on an equal one, shifted and yawed by round-off (positions [m], rpy [rad]; the first: the two
    lowest cubes of test_stack_family's resting stack where it failed, issue 23): the vertices over the lower cube's
    top face (1.2e-9 m inside its edges and more) and the lower cube's under the upper one's bottom face touch face
    on face, every normal vertical (to the tilts, < 1e-17 rad), in both steps alike. With coal's normal a vertex of
    the first 1.4e-17 m over the face took one 0.45 rad off vertical."""
    low, low_rpy, top, top_rpy = poses
    b = ms.SceneBuilder("cubes_a_nanometre_off", restitution=0.0, dt=1e-2, duration=0.1)
    b.add_body("low", MODELS / "cube.urdf", root_joint="free", position=low, rpy=low_rpy)
    b.add_body("top", MODELS / "cube.urdf", root_joint="free", position=top, rpy=top_rpy)
    sc = b.build()
    model = ms.build_model(sc)
    c = ms.detect(model, ms.make_data(model), model.q0)
    assert (c.kind == FeatureKind.VERTEX).sum() >= 2
    assert np.hypot(c.normal[:, 0], c.normal[:, 1]).max() <= 1e-15
    (cp, sp), (cc, sc_) = _rows(sc, "python"), _rows(sc, "compiled")
    assert np.hypot(cp.normal[:, 0], cp.normal[:, 1]).max() <= 1e-15
    assert np.array_equal(cp.normal, cc.normal) and np.array_equal(cp.g, cc.g)
    assert np.array_equal(sp.q, sc_.q) and np.array_equal(sp.u, sc_.u)
