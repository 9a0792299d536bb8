"""The set-valued impact law at re-entrant corners (moreau_sim.corners; docs/theory.md §3)."""

import re
from pathlib import Path

import numpy as np
import piqp
import pytest

import moreau_sim as ms
from moreau_sim.corners import MAX_PIECES, CornerSolution, Selection, impact_outcomes, select, stationary_points

from helpers import scene

# note §3: point mass, M = I, obstacle x > 0, y > 0 near the corner: K = {v_x <= 0} ∪ {v_y <= 0}
I2 = np.eye(2)
CORNER = [np.array([[-1.0, 0.0]]), np.array([[0.0, -1.0]])]


def as_set(vs, digits=8):
    return {tuple(np.round(np.asarray(v, float), digits) + 0.0) for v in vs}


def direct_qp(M, v0, G):
    s = piqp.DenseSolver()
    s.settings.verbose = False
    s.settings.eps_abs = s.settings.eps_rel = 1e-10
    s.settings.eps_duality_gap_abs = s.settings.eps_duality_gap_rel = 1e-10   # default 1e-8: ~1e-7 in v
    s.setup(M, -M @ v0, None, None, G, np.zeros(G.shape[0]), None)
    assert s.solve() == piqp.PIQP_SOLVED
    return s.result.x.copy()


def check_energy(M, u_minus, e, outcomes):
    """2T+ = |v|_M^2 + e^2 |v_perp|_M^2 (note §1) for every outcome; exact for e = 1, no gain."""
    T_minus = 0.5 * u_minus @ M @ u_minus
    for c, u_plus in outcomes:
        v_perp = u_minus - c.v
        T_plus = 0.5 * u_plus @ M @ u_plus
        assert T_plus == pytest.approx(T_minus - 0.5 * (1 - e * e) * (v_perp @ M @ v_perp), abs=1e-9)
        assert T_plus <= T_minus + 1e-9
        if e == 1.0:
            assert abs(T_plus - T_minus) <= 1e-9


# 1. the note's references ---------------------------------------------------------------------

def test_point_mass_symmetric_corner():
    sol = stationary_points(I2, np.array([1.0, 1.0]), CORNER)
    assert isinstance(sol, CornerSolution) and not sol.unique and sol.qp_solves == 3
    assert as_set(c.v for c in sol.candidates) == {(0.0, 1.0), (1.0, 0.0), (0.0, 0.0)}
    by_v = {tuple(np.round(c.v, 8) + 0.0): c for c in sol.candidates}
    assert as_set(c.v for c in sol.candidates if c.global_min) == {(0.0, 1.0), (1.0, 0.0)}
    for v in [(0.0, 1.0), (1.0, 0.0)]:
        assert by_v[v].distance == pytest.approx(0.5, abs=1e-12) and by_v[v].kind == "projection"
    corner = by_v[(0.0, 0.0)]
    assert corner.distance == pytest.approx(1.0, abs=1e-12) and not corner.global_min
    assert corner.kind == "corner" and corner.pieces == (0, 1)
    np.testing.assert_allclose(corner.multipliers, [1.0, 1.0], atol=1e-10)   # M(v - u-) = A' lam
    assert [c.pieces for c in sol.candidates] == [(0,), (1,), (0, 1)]        # sorted: distance, pieces
    for e, expected in [(1.0, {(-1.0, 1.0), (1.0, -1.0), (-1.0, -1.0)}), (0.0, {(0.0, 1.0), (1.0, 0.0), (0.0, 0.0)})]:
        out = impact_outcomes(I2, np.array([1.0, 1.0]), e, CORNER)
        assert as_set(u for _, u in out) == expected
        check_energy(I2, np.array([1.0, 1.0]), e, out)


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_point_mass_asymmetric_corner(e):
    u_minus = np.array([1.0, 0.5])
    sol = stationary_points(I2, u_minus, CORNER)
    assert as_set(c.v for c in sol.candidates) == {(1.0, 0.0), (0.0, 0.5), (0.0, 0.0)}
    assert [c.global_min for c in sol.candidates] == [True, False, False]
    np.testing.assert_allclose(sol.candidates[0].v, [1.0, 0.0], atol=1e-12)
    assert [c.distance for c in sol.candidates] == pytest.approx([0.125, 0.5, 0.625], abs=1e-12)
    out = impact_outcomes(I2, u_minus, e, CORNER)
    np.testing.assert_allclose(out[select(sol)][1], [1.0, -0.5 * e], atol=1e-12)
    check_energy(I2, u_minus, e, out)


# 2. two unit squares, vertex to vertex --------------------------------------------------------

def test_two_squares_vertex_to_vertex():
    """Fixed square F = [-1, 0]^2; moving square A = [0, 1]^2 (mass 1, inertia of a unit square
    m (1 + 1)/12 = 1/6), centre c = (1/2, 1/2), theta = 0, touching F corner to corner at the
    origin and approaching along the diagonal: u- = (x', y', theta') = (-1, -1, 0), M = diag(1, 1, 1/6).

    A's corner p = c + R(theta) r, r = (-1/2, -1/2): p' = (x', y') + theta' (-r_y, r_x)
    = (x' + theta'/2, y' - theta'/2). The two faces of F at its corner give the two ways of
    staying apart: A's corner right of F's right face (g1 = p_x >= 0) or above F's top face
    (g2 = p_y >= 0), so w1 = (1, 0, 1/2), w2 = (0, 1, -1/2) and K = {w1'u >= 0} ∪ {w2'u >= 0}.
    (A's own faces at the corner are collinear with F's at theta = 0 and give the same rows.)

    Stationary points (M^-1 = diag(1, 1, 6); w_i' M^-1 w_i = 5/2, w1' M^-1 w2 = -3/2, w_i'u- = -1):
      piece 1 alone: lam = 1/(5/2) = 0.4, v = u- + 0.4 M^-1 w1 = (-0.6, -1, 1.2), distance
        1/2 lam^2 w1'M^-1 w1 = 0.2; w2'v = -1.6 < 0 so only piece 1 is active: stationary.
      piece 2 alone: by symmetry v = (-1, -0.6, -1.2), distance 0.2.
      both: [[5/2, -3/2], [-3/2, 5/2]] lam = (1, 1) -> lam = (1, 1) >= 0, v = (0, 0, 0), distance
        1/2 u-'M u- = 1; Clarke-stationary since M(u- - v) = (-1, -1, 0) = -(w1 + w2) and neither
        face of the corner is covered by the other piece (note §3 corner point).
    e = 1: u+ = 2v - u- in {(-0.2, -1, 2.4), (-1, -0.2, -2.4), (1, 1, 0)}, each with T = 1.
    """
    M = np.diag([1.0, 1.0, 1.0 / 6.0])
    pieces = [np.array([[1.0, 0.0, 0.5]]), np.array([[0.0, 1.0, -0.5]])]
    u_minus = np.array([-1.0, -1.0, 0.0])
    sol = stationary_points(M, u_minus, pieces)
    got = {c.pieces: c for c in sol.candidates}
    assert set(got) == {(0,), (1,), (0, 1)}
    np.testing.assert_allclose(got[(0,)].v, [-0.6, -1.0, 1.2], atol=1e-12)
    np.testing.assert_allclose(got[(1,)].v, [-1.0, -0.6, -1.2], atol=1e-12)
    np.testing.assert_allclose(got[(0, 1)].v, [0.0, 0.0, 0.0], atol=1e-12)
    assert [got[k].distance for k in [(0,), (1,), (0, 1)]] == pytest.approx([0.2, 0.2, 1.0], abs=1e-12)
    np.testing.assert_allclose(got[(0, 1)].multipliers, [1.0, 1.0], atol=1e-12)
    assert [c.global_min for c in sol.candidates] == [True, True, False]
    out = impact_outcomes(M, u_minus, 1.0, pieces)
    assert as_set(u for _, u in out) == {(-0.2, -1.0, 2.4), (-1.0, -0.2, -2.4), (1.0, 1.0, 0.0)}
    for e in [0.0, 0.3, 1.0]:
        check_energy(M, u_minus, e, impact_outcomes(M, u_minus, e, pieces))


# 3. reduction to the convex case --------------------------------------------------------------

def test_single_piece_is_the_ordinary_projection():
    rng = np.random.default_rng(0)
    B = rng.normal(size=(4, 4))
    M = B @ B.T + 4 * np.eye(4)
    A = rng.normal(size=(3, 4))
    u_minus = rng.normal(size=4)
    u_minus -= 2 * A[0] * (A[0] @ u_minus) / (A[0] @ A[0]) if A[0] @ u_minus > 0 else 0.0
    sol = stationary_points(M, u_minus, [A])
    assert sol.unique and sol.candidates[0].global_min and sol.qp_solves == 1
    np.testing.assert_allclose(sol.candidates[0].v, direct_qp(M, u_minus, A), atol=1e-8)
    c = sol.candidates[0]
    np.testing.assert_allclose(M @ (c.v - u_minus), A.T @ c.multipliers, atol=1e-9)


@pytest.mark.parametrize("pieces, v_expected", [
    ([CORNER[0], CORNER[0].copy(), CORNER[0].copy()], (0.0, 1.0)),                       # identical
    ([np.array([[-1.0, 0.0], [0.0, -1.0]]), np.array([[0.0, -1.0]])], (1.0, 0.0)),       # nested
    ([np.array([[-1.0, 0.0], [0.0, -1.0]]), np.array([[1.0, 0.0], [0.0, -1.0]])], (1.0, 0.0)),  # split half-plane
])
def test_convex_union_has_one_candidate(pieces, v_expected):
    """The sum of the pieces' normal cones would keep (0, 0) for the nested and split unions;
    the Clarke cone of their (convex) union {v_y <= 0} does not."""
    sol = stationary_points(I2, np.array([1.0, 1.0]), pieces)
    assert sol.unique
    np.testing.assert_allclose(sol.candidates[0].v, v_expected, atol=1e-12)
    np.testing.assert_allclose(sol.candidates[0].v, direct_qp(I2, np.array([1.0, 1.0]), np.array([[0.0, -1.0]]))
                               if v_expected == (1.0, 0.0) else v_expected, atol=1e-8)


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_admissible_u_minus_is_unchanged(e):
    for pieces, u_minus in [([CORNER[0]], np.array([-0.3, 2.0])),        # convex, inside
                            (CORNER, np.array([-1.0, -1.0])),            # both pieces
                            (CORNER, np.array([-0.5, 0.25]))]:           # one piece of the union
        out = impact_outcomes(I2, u_minus, e, pieces)
        assert len(out) == 1 and out[0][0].distance == 0.0
        assert np.array_equal(out[0][1], u_minus)
    assert stationary_points(I2, np.array([-1.0, -1.0]), CORNER).qp_solves == 0


# 4. smooth contacts S intersect every piece ---------------------------------------------------

def test_smooth_contact_floor():
    """3-D point mass at the corner edge, also on a floor (v_z >= 0) and falling."""
    pieces = [np.array([[-1.0, 0.0, 0.0]]), np.array([[0.0, -1.0, 0.0]])]
    W = np.array([[0.0], [0.0], [1.0]])
    u_minus = np.array([1.0, 1.0, -2.0])
    sol = stationary_points(np.eye(3), u_minus, pieces, W)
    assert as_set(c.v for c in sol.candidates) == {(0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 0.0)}
    for c in sol.candidates:
        assert np.all(W.T @ c.v >= -1e-9)
        assert c.multipliers[-1] == pytest.approx(2.0, abs=1e-10)   # the floor's lam


def test_smooth_contacts_respected_random():
    rng = np.random.default_rng(5)
    for _ in range(5):
        B = rng.normal(size=(4, 4))
        M = B @ B.T + np.eye(4)
        pieces = [rng.normal(size=(int(rng.integers(1, 3)), 4)) for _ in range(3)]
        W = rng.normal(size=(4, 2))
        u_minus = rng.normal(size=4) * 3
        sol = stationary_points(M, u_minus, pieces, W)
        assert sol.candidates[0].global_min
        for c in sol.candidates:
            assert np.all(W.T @ c.v >= -1e-9)
            assert all(np.all(pieces[j] @ c.v >= -1e-9) for j in c.pieces)
            rows = np.vstack([pieces[j] for j in c.pieces] + [W.T])
            np.testing.assert_allclose(M @ (c.v - u_minus), rows.T @ c.multipliers, atol=1e-8)
            assert np.all(c.multipliers >= -1e-9)


def _random_corner_problems(seed):
    rng = np.random.default_rng(seed)
    for _ in range(5):
        B = rng.normal(size=(5, 5))
        yield (B @ B.T + np.eye(5), rng.normal(size=5) * 3,
               [rng.normal(size=(int(rng.integers(1, 3)), 5)) for _ in range(3)], rng.normal(size=(5, 2)))


def _slope_corner():
    """The corner problem of a step of the slope scene (tests/test_gjk_guess.slope, h = 2e-3, t = 1.174 s):
    three free cubes (nv = 18), 8 smooth rows and a cube's vertex at a slab's top-end edge (two pieces)."""
    d = np.load(Path(__file__).parent / "data" / "corner_slope.npz")
    yield d["M"], d["v0"], [d[f"p{j}"] for j in range(int(d["n"]))], d["W"]


@pytest.mark.parametrize("problems", [*(lambda s=s: _random_corner_problems(s) for s in range(4)), _slope_corner],
                         ids=["random0", "random1", "random2", "random3", "slope"])
def test_each_candidate_is_its_pieces_exact_projection(problems):
    """A candidate's v and multipliers meet the law to round-off, as the smooth law's projection does (§1.3):
    rows' v >= 0, lam >= 0, lam_i (rows' v)_i = 0 and M (v - v0) = rows lam, each to 1e-13 of its scale. Where
    the active set was not tried, piqp's answer (its least-squares polish failing on the slope's problem) met
    them to 1e-11 of |v0| only: that corner step booked D - L = -9.4e-10 J of an impact's 1.9e-4 J
    (docs/theory.md §3.3)."""
    for M, v0, pieces, W in problems():
        scale = float(np.abs(v0).max())
        for c in stationary_points(M, v0, pieces, W).candidates:
            rows = np.vstack([pieces[j] for j in c.pieces] + [W.T])
            g, lam = rows @ c.v, np.asarray(c.multipliers)
            force = float(np.abs(M @ (c.v - v0)).max()) + scale
            assert g.min() >= -1e-13 * scale and lam.min() >= 0.0
            assert float(np.abs(lam * g).max()) <= 1e-13 * scale * (1.0 + float(lam.max()))
            assert float(np.abs(M @ (c.v - v0) - rows.T @ lam).max()) <= 1e-13 * force


def test_squeezed_smooth_contacts_lower_dimensional_pieces():
    """W = (e_z, -e_z) pins v_z = 0: the pieces are flat, the corner law acts in the x-y plane."""
    pieces = [np.array([[-1.0, 0.0, 0.0]]), np.array([[0.0, -1.0, 0.0]])]
    W = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, -1.0]])
    sol = stationary_points(np.eye(3), np.array([1.0, 1.0, 5.0]), pieces, W)
    assert as_set(c.v for c in sol.candidates) == {(0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 0.0)}
    assert [c.global_min for c in sol.candidates] == [True, True, False]


# 5. determinism and selection -----------------------------------------------------------------

def test_deterministic_and_selection_policies():
    rng = np.random.default_rng(2)
    B = rng.normal(size=(3, 3))
    args = (B @ B.T + np.eye(3), rng.normal(size=3), [rng.normal(size=(2, 3)) for _ in range(3)],
            rng.normal(size=(3, 1)))
    a, b = stationary_points(*args), stationary_points(*args)
    assert len(a.candidates) == len(b.candidates)
    for x, y in zip(a.candidates, b.candidates):
        assert np.array_equal(x.v, y.v) and np.array_equal(x.multipliers, y.multipliers)
        assert (x.distance, x.pieces, x.kind, x.global_min) == (y.distance, y.pieces, y.kind, y.global_min)
    assert all(select(a, p) == select(b, p) for p in Selection)

    sym = stationary_points(I2, np.array([1.0, 1.0]), CORNER)
    assert select(sym) == select(sym, Selection.GLOBAL_MIN) == select(sym, "global-min") == 0
    np.testing.assert_array_equal(sym.candidates[select(sym)].v, [0.0, 1.0])     # tie -> lowest piece
    np.testing.assert_array_equal(sym.candidates[select(sym, Selection.SYMMETRIC)].v, [0.0, 0.0])
    np.testing.assert_array_equal(sym.candidates[select(sym, Selection.FIRST)].v, [0.0, 1.0])
    asym = stationary_points(I2, np.array([1.0, 0.5]), CORNER)
    np.testing.assert_array_equal(asym.candidates[select(asym)].v, [1.0, 0.0])
    np.testing.assert_array_equal(asym.candidates[select(asym, Selection.SYMMETRIC)].v, [1.0, 0.0])
    np.testing.assert_array_equal(asym.candidates[select(asym, Selection.FIRST)].v, [0.0, 0.5])  # piece 0


# 6. input validation --------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, word", [
    (dict(M=np.eye(3)), "M"),
    (dict(M=np.array([[1.0, 0.5], [0.0, 1.0]])), "symmetric"),
    (dict(M=np.diag([1.0, -1.0])), "positive definite"),
    (dict(v0=np.ones(3)), "M"),
    (dict(v0=np.ones((2, 1))), "v0"),
    (dict(pieces=np.array([[-1.0, 0.0]])), "pieces"),
    (dict(pieces=[]), "pieces"),
    (dict(pieces=[np.array([[-1.0, 0.0]])] * (MAX_PIECES + 1)), "pieces"),
    (dict(pieces=[np.array([-1.0, 0.0])]), "pieces[0]"),
    (dict(pieces=[np.array([[-1.0, 0.0]]), np.array([[0.0, 0.0]])]), "pieces[1]"),
    (dict(W=np.ones((3, 1))), "W"),
    (dict(W=np.zeros((2, 1))), "W"),
    (dict(tol=0.0), "tol"),
])
def test_validation(kwargs, word):
    args = dict(M=I2, v0=np.array([1.0, 1.0]), pieces=CORNER, W=None, tol=1e-9) | kwargs
    with pytest.raises(ValueError, match=re.escape(word)):
        stationary_points(args["M"], args["v0"], args["pieces"], args["W"], tol=args["tol"])


@pytest.mark.parametrize("e", [-0.1, 1.5, float("nan"), "x"])
def test_validation_restitution(e):
    with pytest.raises(ValueError, match="e "):
        impact_outcomes(I2, np.array([1.0, 1.0]), e, CORNER)
    with pytest.raises(ValueError, match="u_minus"):
        impact_outcomes(I2, np.ones(2)[:, None], 0.5, CORNER)


# 5. the energy identity at every branch of the bundled corner scenes -------------------------

@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("name", ["corner_point", "corner_point_asymmetric", "blocks_corner"])
def test_energy_identity_at_each_corner_branch(name, e):
    """Every admissible outcome u+ = (1 + e) v - e u- of the scene's corner impact (three stationary
    points each) loses T(u-) - T(u+) = (1 - e^2)/2 |u- - v|_M^2, to 1e-12 J."""
    model = ms.build_model(scene(name))
    data = ms.make_data(model)
    state = ms.initial_state(model)
    M = ms.assemble_constraints(model, data, state.q, ms.detect(model, data, state.q)).M
    u = state.u
    outs = ms.impact_outcomes(model, state, e=e)
    assert len(outs) == 3 and sum(o.selected for o in outs) == 1
    for o in outs:
        dv = u - o.v
        loss = 0.5 * u @ M @ u - 0.5 * o.u_plus @ M @ o.u_plus
        assert abs(loss - 0.5 * (1 - e * e) * (dv @ M @ dv)) <= 1e-12
        assert abs(o.distance - 0.5 * dv @ M @ dv) <= 1e-12
        np.testing.assert_allclose(o.u_plus, (1 + e) * o.v - e * u, rtol=0, atol=1e-14)
