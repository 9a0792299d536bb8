"""A projection's islands (moreau_sim/islands.py, qp._by_islands, src/step.cpp by_islands; docs/theory.md §1.3,
islands): the partition against scipy's connected components of the graph of rows and trees, the projection island
by island against the whole one (the same v: the projection is unique), and scenes of several islands above
qp.SPARSE_ROWS rows, the compiled and the Python step bit for bit, holding a resting column at rest."""

import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.csgraph

import moreau_sim as ms
from moreau_sim import qp
from moreau_sim.islands import islands

from helpers import ROOT


def _problem(rng, trees: int, rows: int, size=(1, 6)):
    """M block diagonal over `trees` trees of random sizes (SPD blocks), W (nv, rows) each row touching one or two
    random trees (random entries on their velocities), v0: the blocks, M, M^-1, W, v0."""
    sizes = rng.integers(size[0], size[1] + 1, trees)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    blocks = tuple((int(a), int(n)) for a, n in zip(starts, sizes))
    nv = int(sizes.sum())
    M = np.zeros((nv, nv))
    for a, n in blocks:
        A = rng.standard_normal((n, n))
        M[a:a + n, a:a + n] = A @ A.T + n * np.eye(n)
    W = np.zeros((nv, rows))
    for j in range(rows):
        for t in rng.choice(trees, size=rng.integers(1, 3), replace=False):
            a, n = blocks[t]
            W[a:a + n, j] = rng.standard_normal(n)
    Minv = np.zeros_like(M)
    for a, n in blocks:
        Minv[a:a + n, a:a + n] = np.linalg.inv(M[a:a + n, a:a + n])
    return blocks, M, Minv, W, rng.standard_normal(nv)


def _components(W, blocks):
    """The reference partition: scipy's connected components of the bipartite graph rows - trees."""
    nv, m = W.shape
    tree = np.concatenate([np.full(n, t) for t, (a, n) in enumerate(blocks)])
    dof, row = np.nonzero(W)
    nt = len(blocks)
    A = scipy.sparse.coo_matrix((np.ones(len(dof)), (row, m + tree[dof])), shape=(m + nt, m + nt))
    _, label = scipy.sparse.csgraph.connected_components(A, directed=False)
    return {frozenset(np.flatnonzero(label[:m] == c).tolist()) for c in set(label[:m].tolist())}


@pytest.mark.parametrize("seed", range(20))
def test_the_islands_are_the_connected_components_of_rows_and_trees(seed):
    rng = np.random.default_rng(seed)
    blocks, _, _, W, _ = _problem(rng, trees=int(rng.integers(2, 60)), rows=int(rng.integers(2, 80)))
    parts = islands(W, blocks)
    ref = _components(W, blocks)
    if len(ref) == 1:
        assert parts is None
        return
    assert {frozenset(r.tolist()) for _, r in parts} == ref
    firsts = [int(r[0]) for _, r in parts]
    assert firsts == sorted(firsts)  # numbered by their first rows
    tree = np.concatenate([np.full(n, t) for t, (a, n) in enumerate(blocks)])
    for dofs, rows in parts:  # an island's velocities: whole trees, those its rows touch, ascending
        touched = set(tree[np.flatnonzero((W[:, rows] != 0.0).any(axis=1))].tolist())
        assert set(tree[dofs].tolist()) == touched and np.all(np.diff(dofs) > 0)


def test_one_island_a_row_on_nothing_or_a_non_finite_row_is_no_split():
    blocks = ((0, 2), (2, 1))
    W = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
    assert islands(W, blocks) is None  # both rows on tree 0
    W2 = np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0]])
    assert [r.tolist() for _, r in islands(W2, blocks)] == [[0], [1]]
    assert islands(np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 0.0]]), blocks) is None
    assert islands(np.array([[1.0, 0.0], [0.0, 0.0], [0.0, np.nan]]), blocks) is None


@pytest.mark.parametrize("seed", range(6))
def test_the_projection_island_by_island_is_the_whole_projection(seed):
    """Above qp.SPARSE_ROWS rows: with blocks, island by island; without, as one. The projection's v is unique (M
    positive definite): the two agree to 1e-12 of its scale, both meet the law (KKT) to 1e-12, and each island's
    rows are a problem of their own (the velocities of trees no row touches keep v0 exactly)."""
    rng = np.random.default_rng(100 + seed)
    blocks, M, Minv, W, v0 = _problem(rng, trees=400, rows=260)
    b = np.zeros(W.shape[1])
    parts = islands(W, blocks)
    assert parts is not None and len(parts) > 1
    split = qp.solve(M, W, v0, b=b, Minv=Minv, blocks=blocks)
    whole = qp.solve(M, W, v0, b=b, Minv=Minv)
    assert split.ok and whole.ok
    scale = 1.0 + np.abs(v0).max()
    assert np.abs(split.v - whole.v).max() <= 1e-12 * scale
    for r in (split, whole):
        assert r.residual <= 1e-12 * scale * max(1.0, np.abs(r.lam).max())
    untouched = np.setdiff1d(np.arange(len(v0)), np.concatenate([d for d, _ in parts]))
    assert np.array_equal(split.v[untouched], v0[untouched])


def _columns(sizes, impl: str):
    """Columns of touching beads (column_of_beads_100's construction), one per size, 1 m apart, from rest."""
    b = ms.SceneBuilder("columns", folder=ROOT / "scenes", restitution=0.5, dt=5e-4, duration=0.01, step_impl=impl)
    for c, n in enumerate(sizes):
        for k in range(n):
            b.add_body(f"c{c}b{k}", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1),
                       position=(float(c), 0.0, 0.0), q0=[0.1 + 0.2 * k])
    b.add_halfspace("ground")
    return ms.build_model(b.build())


@pytest.mark.parametrize("sizes", [(100, 100), (101, 100), (120, 100), (230, 30)])
def test_columns_side_by_side_rest_island_by_island_bit_for_bit(sizes, monkeypatch):
    """Two columns of touching beads (200 rows: one problem, qp.SPARSE_ROWS' edge; 201 and 220 rows: islands of 101 or
    120 and 100 rows, from nothing at the first step, then from the kept set; 260 rows: islands of 230 and 30): 40
    steps from rest. The compiled step and the Python step give the same bits, and the columns rest: every velocity
    within 1e-12 m/s of 0 (the contacts hold the weight of each bead above exactly), no gap below
    -contact_tolerance."""
    split = []  # the Python step's projections that went island by island
    whole = qp._by_islands
    monkeypatch.setattr(qp, "_by_islands", lambda *a, **k: split.append(1) or whole(*a, **k))
    ends = {}
    for impl in ("compiled", "python"):
        model = _columns(sizes, impl)
        data, st = ms.make_data(model), ms.initial_state(model)
        for _ in range(40):
            r = ms.step(model, data, st)
            st = r.state
            assert r.contacts.m == sum(sizes) and r.qp.ok
            if impl == "python":  # (islands finds them at any size; solve splits above SPARSE_ROWS rows only)
                assert [len(rows) for _, rows in islands(r.qp.W, model.forest.blocks)] == list(sizes)
            assert np.abs(st.u).max() <= 1e-12
        assert ms.pair_distances(model, data, st.q).min() >= -model.options.contact_tolerance
        ends[impl] = st
        if impl == "python":
            assert len(split) == (40 if sum(sizes) > qp.SPARSE_ROWS else 0)
        if impl == "compiled":
            assert set(ms.compiled.counts(data)) == {"contact"}, ms.compiled.counts(data)
    assert np.array_equal(ends["compiled"].q, ends["python"].q) and np.array_equal(ends["compiled"].u, ends["python"].u)
