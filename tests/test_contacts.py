"""Contacts: gaps, rows w_i against finite differences, the active set, face-on-face rest."""

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms

from helpers import scene

FREE_BOX = """
[scene]
name = "fd"
[simulation]
gravity = [0, 0, {g}]
restitution = {e}
dt = 1e-3
duration = {T}
{bodies}
"""


def box_body(name, urdf="box.urdf", position=(0, 0, 0), rpy=(0, 0, 0)):
    return (f'[[bodies]]\nname = "{name}"\nurdf = "{{models}}/{urdf}"\nroot_joint = "free"\n'
            f"position = {list(position)}\nrpy = {list(rpy)}\n")


GROUND = '[[statics]]\nname = "ground"\nshape = "halfspace"\n'


def lowest_corner_height(rpy, half=(0.1, 0.1, 0.2)):
    R = pin.rpy.rpyToMatrix(*rpy)
    c = np.array([[sx * half[0], sy * half[1], sz * half[2]] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return -(c @ R.T)[:, 2].min()


def gaps_by_feature(model, data, q):
    c = ms.detect(model, data, q)
    return {(int(p), int(f)): g for p, f, g in zip(c.pair, c.feature, c.g)}


def check_rows_by_finite_differences(model, q, eps=1e-7, n_dirs=4, expect_min=1):
    data = ms.make_data(model)
    c = ms.detect(model, data, q)
    assert c.m >= expect_min
    pin.computeJointJacobians(model.pin, data.pin, q)
    W = ms.contact_rows(model, data, c)
    rng = np.random.default_rng(0)
    for _ in range(n_dirs):
        dv = rng.standard_normal(model.nv)
        gp = gaps_by_feature(model, data, pin.integrate(model.pin, q, eps * dv))
        gm = gaps_by_feature(model, data, pin.integrate(model.pin, q, -eps * dv))
        for i, key in enumerate(zip(c.pair.tolist(), c.feature.tolist())):
            fd = (gp[key] - gm[key]) / (2 * eps)
            assert abs(fd - W[:, i] @ dv) <= 1e-6 * (1 + abs(fd)), (key, fd, W[:, i] @ dv)
    return c


def test_rows_chain_sphere_against_box():
    """Double pendulum (revolute chain) with its tip bob 1 mm inside the wall."""
    model = ms.build_model(scene("pendulum_wall"))
    th1 = -0.3
    x1 = -0.5 * np.sin(th1)
    th12 = np.arcsin(-(0.401 - x1) / 0.5)
    q = np.array([th1, th12 - th1])
    c = check_rows_by_finite_differences(model, q)
    assert np.isclose(c.g.min(), -1e-3, atol=1e-9)


@pytest.mark.parametrize("rpy,expect", [((0.3, 0.2, 0.1), 1), ((0.3, 0.0, 0.0), 2), ((0.0, 0.0, 0.4), 4)])
def test_rows_box_vertices_on_ground(tmp_scene, rpy, expect):
    """Free box 1 mm into the ground on a corner, an edge (2 corners), a face (4 corners)."""
    model = ms.build_model(tmp_scene(FREE_BOX.format(g=-9.81, e=0.5, T=1, bodies=box_body("b") + GROUND)))
    q = model.q0.copy()
    q[:3] = [0.1, -0.2, lowest_corner_height(rpy) - 1e-3]
    q[3:7] = pin.Quaternion(pin.rpy.rpyToMatrix(*rpy)).coeffs()
    c = check_rows_by_finite_differences(model, q, expect_min=expect)
    assert c.m == expect  # the coal witness at a corner is dropped as a duplicate
    assert np.allclose(c.g, -1e-3, atol=1e-9)
    assert np.allclose(c.normal, [0, 0, 1])


def test_rows_box_on_box_vertex_and_edge(tmp_scene):
    """Two free boxes (both move: the J_B term), no gravity: a tilted box pressed into another."""
    bodies = box_body("lower") + box_body("upper")
    model = ms.build_model(tmp_scene(FREE_BOX.format(g=0, e=0.5, T=1, bodies=bodies)))
    q = model.q0.copy()
    R_low = pin.rpy.rpyToMatrix(0.05, -0.03, 0.2)
    rpy = (0.4, 0.3, 0.2)
    q[:7] = np.r_[[0.01, 0.02, 0.0], pin.Quaternion(R_low).coeffs()]
    # place the upper box so that its lowest corner is 1 mm below the lower box's top face
    q[7:10] = [0.0, 0.0, 0.2 + lowest_corner_height(rpy) - 1e-3]
    q[10:14] = pin.Quaternion(pin.rpy.rpyToMatrix(*rpy)).coeffs()
    check_rows_by_finite_differences(model, q)
    # edge on edge: the lower box turned pi/4 about y has a top edge along y at x = r, z = 3r
    # (r = 0.1/sqrt 2); the upper box turned pi/4 about x has a bottom edge along x at y = r
    # below its centre by 3r. Crossed edges, 1 mm deep, no vertex near: coal's witness only.
    r = 0.1 / np.sqrt(2)
    q[:7] = np.r_[[0, 0, 0], pin.Quaternion(pin.rpy.rpyToMatrix(0, np.pi / 4, 0)).coeffs()]
    q[7:14] = np.r_[[0, -r, 6 * r - 1e-3], pin.Quaternion(pin.rpy.rpyToMatrix(np.pi / 4, 0, 0)).coeffs()]
    c = check_rows_by_finite_differences(model, q)
    assert ms.FeatureKind.WITNESS in c.kind.tolist()


def test_active_set_counts_touching_bodies_despite_rounding():
    """Cradle balls at x = 0.2 i computed in floating point (0.6000000000000001): all 4 closed."""
    model = ms.build_model(scene("newton_cradle_5"))
    c = ms.detect(model, ms.make_data(model), model.q0)
    assert c.m == 4
    assert np.abs(c.g).max() <= 1e-15
    assert model.scene.options.contact_tolerance >= 1e6 * np.abs(c.g).max()


def test_separated_pairs_give_no_contact():
    model = ms.build_model(scene("newton_cradle_5_gapped"))
    assert ms.detect(model, ms.make_data(model), model.q0).m == 0


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_box_rests_flat_on_ground_and_on_box(tmp_scene, e):
    """Face on face with the exact height: a box on the ground, a box on a static box (yawed, so
    the faces overlap only partly), a free box on a free box. 1 s: no sinking, no rocking."""
    bodies = (box_body("on_ground", position=(0, 0, 0.2))
              + box_body("on_table", position=(1.0, 0.0, 0.6), rpy=(0, 0, 0.5))
              + box_body("bottom", position=(3.0, 0, 0.2))
              + box_body("top", position=(3.0, 0, 0.6), rpy=(0, 0, 0.3)))
    statics = GROUND + ('[[statics]]\nname = "table"\nshape = "box"\nsize = [0.3, 0.3, 0.4]\n'
                        'position = [1.0, 0.0, 0.2]\n')
    model = ms.build_model(tmp_scene(FREE_BOX.format(g=-9.81, e=e, T=1.0, bodies=bodies + statics)))
    traj = ms.simulate(model, progress=False)
    q0, q1 = traj.q[0], traj.q[-1]
    assert np.abs(q1 - q0).max() <= 1e-6  # exact height and orientation, to 1e-6
    assert np.abs(traj.u).max() <= 1e-9  # still: no rocking, no creeping
    assert traj.n_contacts[-1] >= 4 * 3  # every face rests on >= 4 points (box-box: 4 + 4 duplicates)
