"""The event path's floating-point order (docs/theory.md §2.8): the per-feature gaps, rows, drifts and rates
(gaps.py, box_gaps.py, kinematics.py) and the event rules' products (event_rules.py) are sums in index order,
as sums.py states them: the 3-vector sums against a Python float loop and an exact (fsum) reference, the
features' rates against the loop, and the whole event state (features, constrained accelerations, the
decisions at an event) bit for bit the same under OpenBLAS's other CPU kernels."""

import math
import os
import subprocess
import sys

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim.event_rules import EventState, dynamics, features, make_rules, resolve
from moreau_sim.sums import dot3, dots, ordered

from helpers import scene

EPS = np.finfo(float).eps


def bits(v):
    return np.asarray(v, float).view(np.int64).tolist()


def loop(a, x) -> float:
    """sum_k a_k x_k left to right from the first product, one rounding each, then + 0.0 (Python floats)."""
    s = float(a[0]) * float(x[0])
    for k in range(1, len(a)):
        s = s + float(a[k]) * float(x[k])
    return s + 0.0


@pytest.mark.parametrize("seed", range(4))
def test_three_vector_sums_are_the_index_order_loop(seed):
    """dot3 and dots (R x, the rows of X R', row-wise products, broadcasting) give the loop's bits, -0.0 sums
    as +0.0, and lie within the loop's error bound 2 eps sum|a_k x_k| of the exact sum (math.fsum)."""
    rng = np.random.default_rng(seed)
    for _ in range(50):
        a, b = (rng.standard_normal(3) * 10.0 ** rng.integers(-8, 8, 3) for _ in range(2))
        R, X = rng.standard_normal((3, 3)), rng.standard_normal((7, 3))
        assert bits(dot3(a, b)) == bits(loop(a, b)) == bits(ordered(a, b))
        assert bits(dots(a, b)) == bits(loop(a, b))
        assert bits(dots(R, a)) == bits([loop(r, a) for r in R])
        assert bits(dots(X[:, None], R)) == bits([[loop(x, r) for r in R] for x in X])
        assert bits(dots(X, X[::-1])) == bits([loop(x, y) for x, y in zip(X, X[::-1])])
        exact = math.fsum(a * b)
        assert abs(dot3(a, b) - exact) <= 2.0 * EPS * math.fsum(np.abs(a * b))
    assert bits(dot3(np.array([-0.0, 1.0, 0.0]), np.array([1.0, 0.0, -0.0]))) == bits(0.0)


def test_many_short_sums_are_the_index_order_loop():
    """ordered(W', u) with many more rows than terms (the features' rates: 7280 features of 60 velocities in
    box_stack_10) sums a pass per term: the loop's bits, rows of zeros (+0.0) included, C- or F-ordered."""
    rng = np.random.default_rng(3)
    for nv, k in ((6, 5000), (30, 1640), (60, 7280)):
        W = np.where(rng.random((nv, k)) < 0.8, 0.0, rng.standard_normal((nv, k)))
        W[:, 0] = -0.0
        u = rng.standard_normal(nv)
        expect = bits([loop(w, u) for w in W.T])
        assert bits(ordered(W.T, u)) == bits(ordered(np.ascontiguousarray(W.T), u)) == expect


# one scene per group of feature kinds: box-box vertices and edge pairs (30 velocities), spheres, a free
# trunk's points, cylinder rims and sphere-cylinder pairs with joint limits, cylinders against static boxes
SCENES = ["box_stack_5", "newton_cradle_5", "quadruped_drop", "panda_table"]


def event_state(name: str) -> dict:
    """What the event path computes at a scene's initial q with a seeded velocity: all features (g, W,
    drift, gamma, margin), the constrained accelerations of the three closest features, and the decisions
    at an event (resolve) from the scene's own initial state."""
    model = ms.build_model(scene(name))
    st0 = ms.initial_state(model)
    r = make_rules(model, ms.make_data(model), model.options.restitution)
    u = np.random.default_rng(7).standard_normal(model.nv)
    ev = EventState()
    fs = features(r, ev, st0.q, u)
    C = ()  # the closest three features with independent rows (dependent ones: lstsq, LAPACK's bits)
    for i in np.argsort(fs.g, kind="stable"):
        if len(C) < 3 and np.linalg.matrix_rank(fs.W[:, list(C) + [i]]) > len(C):
            C += (int(i),)
    a, lam, _ = dynamics(r, ev, st0.q, u, C)
    res = resolve(r, EventState(), 0.0, st0.q, st0.u, frozenset())
    return dict(g=fs.g, W=fs.W, drift=fs.drift, gamma=fs.gamma, margin=fs.margin, a=a, lam=lam, C=np.array(C),
                u_event=res.u, C_event=np.array(res.C, float), work=np.array(res.work))


@pytest.mark.parametrize("name", SCENES)
def test_feature_rates_are_index_order_sums(name):
    """gamma = W'u of every feature is the loop over the velocities in index order, bit for bit; the
    constrained accelerations hold their rows (W_C'a + drift_C = 0, to round-off of the terms)."""
    s = event_state(name)
    u = np.random.default_rng(7).standard_normal(s["W"].shape[0])
    assert bits(s["gamma"]) == bits([loop(w, u) for w in s["W"].T])
    C = s["C"]
    Wc = s["W"][:, C]
    rel = ordered(Wc.T, s["a"]) + s["drift"][C]
    scale = ordered(np.abs(Wc.T), np.abs(s["a"])) + np.abs(s["drift"][C]) + 1.0
    assert np.all(np.abs(rel) <= 1e-12 * scale), rel


_CORETYPE_RUN = """
import sys
sys.path.insert(0, sys.argv[1])
import numpy as np
from test_event_sums import event_state
np.savez(sys.argv[3], **event_state(sys.argv[2]))
"""


@pytest.mark.slow
@pytest.mark.parametrize("name", SCENES)
def test_event_state_same_bits_whatever_blas_kernel(name, tmp_path):
    """OpenBLAS picks its kernels by the CPU (OPENBLAS_CORETYPE takes another's: Sandybridge without FMA,
    Haswell, SkylakeX), and numpy's @ follows them: the event path's values do not (§2.8). Its remaining
    LAPACK calls (matrix_rank's decision, lstsq of dependent rows) are not reached here or keep their bits."""
    out = {}
    for core in ("SkylakeX", "Sandybridge", "Haswell"):
        f = tmp_path / f"{core}.npz"
        env = dict(os.environ, OPENBLAS_CORETYPE=core)
        subprocess.run([sys.executable, "-c", _CORETYPE_RUN, os.path.dirname(__file__), name, str(f)], env=env,
                       check=True)
        out[core] = np.load(f)
    ref = out["SkylakeX"]
    for core, arrays in out.items():
        for key in ref.files:
            assert bits(arrays[key]) == bits(ref[key]), (core, key)
