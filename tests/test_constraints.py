"""The constraints of the closed contacts (moreau_sim.constraints, docs/theory.md §1, §3, §6): the rows
w_i against finite differences of the gaps, duplicate rows merged, the pieces of the cone at corners."""

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
from moreau_sim.constraints import corner_pieces, distinct

from helpers import FREE_BOX, GROUND, box_body, lowest_corner_height, scene


def gaps_by_feature(model, data, q):
    c = ms.detect(model, data, q)
    return {(int(p), int(f)): g for p, f, g in zip(c.pair, c.feature, c.g)}


def check_rows_by_finite_differences(model, q, eps=1e-7, n_dirs=4, expect_min=1):
    data = ms.make_data(model)
    c = ms.detect(model, data, q)
    assert c.m >= expect_min
    model.forest.mass_matrix(data.kinematics, q)  # fills the WORLD joint Jacobians the rows use
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
    # below its centre by 3r. Crossed edges, 1 mm deep, no vertex near: the edge crossing (box_box.py).
    r = 0.1 / np.sqrt(2)
    q[:7] = np.r_[[0, 0, 0], pin.Quaternion(pin.rpy.rpyToMatrix(0, np.pi / 4, 0)).coeffs()]
    q[7:14] = np.r_[[0, -r, 6 * r - 1e-3], pin.Quaternion(pin.rpy.rpyToMatrix(np.pi / 4, 0, 0)).coeffs()]
    c = check_rows_by_finite_differences(model, q)
    assert c.kind.tolist() == [ms.FeatureKind.EDGE] and abs(c.g[0] + 1e-3) <= 1e-15




def test_distinct_drops_repeated_rows_and_keeps_the_first():
    """The front and back corners of a planar block resting on an edge give the same row twice."""
    model = ms.build_model(scene("rocking_block"))
    data = ms.make_data(model)
    q = model.q0.copy()
    q[2] = 0.0  # flat on its bottom face: 4 vertices (2 front, 2 back) at exactly zero gap
    q[1] = 0.2
    c = ms.detect(model, data, q)
    model.forest.mass_matrix(data.kinematics, q)  # fills the WORLD joint Jacobians the rows use
    W = ms.contact_rows(model, data, c)
    kept, Wk = distinct(c, W)
    assert c.m == 4 and kept.m == 2  # one row per bottom edge end (x = -0.1 and x = +0.1)
    for i in range(c.m):  # every dropped row equals a kept one, and the kept ones differ
        assert np.abs(Wk - W[:, [i]]).max(axis=0).min() <= 1e-15
    assert np.abs(Wk[:, 0] - Wk[:, 1]).max() > 0.1
    np.testing.assert_array_equal(Wk[:, 0], W[:, 0])  # the first of a repeated pair is the one kept


def test_assemble_constraints_is_crba_and_the_rows():
    model = ms.build_model(scene("newton_cradle_5"))
    data = ms.make_data(model)
    q = model.q0
    c = ms.detect(model, data, q)
    cs = ms.assemble_constraints(model, data, q, c)
    np.testing.assert_array_equal(cs.M, pin.crba(model.pin, ms.make_data(model).pin, q))
    # ball i+1 right of ball i along x: gap_i = x_{i+1} - x_i - 2r, row e_{i+1} - e_i
    expected = np.zeros((5, 4))
    expected[np.arange(4), np.arange(4)], expected[np.arange(1, 5), np.arange(4)] = -1.0, 1.0
    np.testing.assert_array_equal(np.sort(cs.W, axis=1), np.sort(expected, axis=1))
    assert cs.pieces is None


def test_corner_pieces_of_a_point_at_an_edge():
    """corner_point: the particle (x, z) at the block's edge: one corner, two faces (x = 0 with
    outward normal -x, z = 0 with -z), each a piece of one row: -e_x and -e_z."""
    model = ms.build_model(scene("corner_point"))
    data = ms.make_data(model)
    q = model.q0
    cs = ms.assemble_constraints(model, data, q, ms.detect(model, data, q))
    assert cs.W.shape == (2, 0) and cs.pieces is not None
    assert cs.pieces.choice == ((0,), (1,))
    np.testing.assert_array_equal(np.concatenate(cs.pieces.pieces), [[-1.0, 0.0], [0.0, -1.0]])


def test_corner_pieces_of_two_squares_vertex_to_vertex():
    """blocks_corner: the free square's vertex r = (-1/2, -1/2) from its centre on the fixed square's
    vertex; the faces x = 0 and z = 0 (normals +x, +z) give rows d(c + R r)/dq: (1, 0, 1/2) and
    (0, 1, -1/2) (theta turns x towards z). The back corner repeats the front one and is dropped."""
    model = ms.build_model(scene("blocks_corner"))
    data = ms.make_data(model)
    q = model.q0
    c = ms.detect(model, data, q)
    assert len(c.corners) == 2
    model.forest.mass_matrix(data.kinematics, q)  # fills the WORLD joint Jacobians the rows use
    contacts, W, pieces = corner_pieces(model, data, c, np.zeros((3, 0)))
    assert len(pieces.corners) == 1 and W.shape == (3, 0)
    np.testing.assert_allclose(np.concatenate(pieces.pieces), [[1.0, 0.0, 0.5], [0.0, 1.0, -0.5]], atol=1e-15)


@pytest.mark.parametrize("seed", range(40))
def test_distinct_screen_finds_the_pairs_the_all_pairs_test_finds(seed):
    """Above SCREEN_ROWS rows distinct sorts by a key instead of comparing all pairs: the same rows are
    dropped as by the all-pairs test (repeats, near-repeats within and just beyond the tolerance, zero rows)."""
    from moreau_sim.constraints import SCREEN_ROWS, _duplicates_screened

    rng = np.random.default_rng(seed)
    nv, m = int(rng.integers(1, 20)), int(rng.integers(SCREEN_ROWS + 1, 80))
    W = rng.standard_normal((nv, m)) * rng.choice([1e-3, 1.0, 1e3])
    W[:, rng.integers(0, m, m // 4)] = 0.0
    src, dst = rng.integers(0, m, m // 2), rng.integers(0, m, m // 2)
    W[:, dst] = W[:, src]
    tol = 1e-12 * (1.0 + np.abs(W).max())
    W[:, dst[:4]] += rng.choice([0.5, 2.0]) * tol * rng.uniform(-1, 1, (nv, min(4, len(dst))))
    same = np.abs(W[:, :, None] - W[:, None, :]).max(axis=0) <= tol
    expect = (same & np.triu(np.ones((m, m), bool), 1)).any(axis=0)
    np.testing.assert_array_equal(_duplicates_screened(W, tol), expect)
