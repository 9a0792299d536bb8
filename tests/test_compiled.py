"""Two implementations, one truth: the compiled step (moreau_sim._step) against the Python step.

Every bundled scene runs both ways (step_impl = "compiled" and "python", CI-sized durations) and must
give the same trajectory (t, q, u, energies, contact work, gaps, the percussion log's steps). How many
steps actually ran compiled is printed and, for the scenes the compiled step is meant to cover,
asserted > 0 (so "equal because every step fell back" shows).

Required bit-identical, for every scene. The C++ step makes the Python step's floating-point operations
in the same order (docs/theory.md §2.8): Pinocchio and coal are the same libraries; every product of the
step's stages (the rows, gamma, the contact work, the restitution rules, the projection: sums.ordered) sums in
index order with one rounding each, and the active set's solves are one elimination written out alike
(qp._lu_solve, src/step.cpp lu_solve): no BLAS or LAPACK kernel, no FMA, so the same on any CPU, at any size
and memory alignment (tested below against OpenBLAS's other CPU kernels). What is left of numpy's kernels are
the 3-vector products of contacts._vertex_contacts, reproduced as numpy's OpenBLAS computes them at that size
on an FMA machine (src/step.cpp gemv_dot). Within 1e-12 would not be enough: the correction's energy test
(dE > budget) and the active set of dependent rows are ties decided at round-off, and one flipped tie
moves box_drop by 1e-5 m. The constants both steps use are passed from Python
(compiled.CONSTANTS), and the step's result crosses by name (src/step.cpp StepOut).

A scene none of whose steps the compiled step takes runs the Python step both
ways; its detection (contacts.py's polytope paths, corners) still has
numpy products of its own, and two runs of heavy_on_light_box_10000 in one pytest process have been seen
to differ by 5e-27 m (alone they do not: the arrays' alignment). There, within 1e-12 is required. So it is
for heavy_on_light_box_10000 compiled (PYTHON_VARIES): the compiled step gives the same bits in every run, the
Python step's own run varies by 1.4e-48 m with what ran before it in the process (tests/test_compiled_boxes.py
holds the 100:1 stack bit-identical).
"""

from __future__ import annotations

import functools
import warnings
from pathlib import Path

import numpy as np
import pytest

import moreau_sim as ms
import moreau_sim.compiled as compiled
from moreau_sim import qp, sums
from moreau_sim.contacts import FeatureKind
from moreau_sim.data import make_data
from moreau_sim.errors import SceneError
from moreau_sim.model import build_model
from moreau_sim.options import StepImpl
from moreau_sim.scene import load_scene, parse_scene
from moreau_sim.simulate import simulate

from helpers import pile_projection, slow_cases

SCENES = sorted((Path(__file__).resolve().parent.parent / "scenes").glob("*.toml"))
MUST_COMPILE = {"bouncing_ball", "zeno_ball", "newton_cradle_5", "box_drop", "column_of_beads_100", "quadruped_drop",
                "solo_drop", "box_stack_10", "panda_table", "vibrating_paddle", "driven_paddle"}
# CI-sized durations [s]: long enough for the first impacts (and box_drop to settle on a face)
DURATION = {"bouncing_ball": 1.0, "zeno_ball": 1.5, "box_drop": 1.5, "newton_cradle_5": 0.3, "vibrating_paddle": 0.6,
            "driven_paddle": 0.6}
MAX_STEPS = 300  # other scenes: at most this many steps
PYTHON_VARIES = {"heavy_on_light_box_10000"}  # the Python step's own runs differ in one process (module docstring)
COMPARED = ("t", "q", "u", "kinetic_energy", "potential_energy", "contact_work", "correction_energy", "gap",
            "n_contacts", "smooth_error", "dissipation", "law_dissipation", "impact_t", "impact_dissipation")


def _run(scene, impl: StepImpl):
    sc = scene.with_options(step_impl=impl.value)
    model = build_model(sc)
    data = make_data(model)
    traj = simulate(model, data=data, progress=False)
    return traj, compiled.counts(data)


def _ext():
    """The extension module (loaded on first use)."""
    assert compiled.available(), compiled.unavailable_reason()
    return compiled._module


def test_compiled_step_is_available():
    """A normal install builds the extension against the installed Pinocchio and coal."""
    assert compiled.available(), compiled.unavailable_reason()


@pytest.mark.parametrize("path", slow_cases(SCENES, {"alternating_stack_10"}, [p.stem for p in SCENES]))
def test_same_trajectory_both_ways(path):
    scene = load_scene(path)
    o = scene.options
    duration = DURATION.get(scene.name, min(o.duration, MAX_STEPS * o.dt))
    scene = scene.with_options(duration=duration)
    ref, py_counts = _run(scene, StepImpl.PYTHON)
    got, counts = _run(scene, StepImpl.COMPILED)
    assert not py_counts  # the Python run never asks the compiled step
    steps = sum(counts.values())
    done = counts["flight"] + counts["contact"]
    print(f"{scene.name}: {done}/{steps} steps compiled ({counts['contact']} with contacts); "
          f"Python: {dict((k, v) for k, v in counts.items() if k.startswith('python'))}")
    if scene.name in MUST_COMPILE:
        assert done > 0 and counts["contact"] > 0, counts
    a, b = ref.arrays, got.arrays
    diff = {k: float(np.abs(np.asarray(a[k]) - np.asarray(b[k])).max(initial=0.0)) for k in ("q", "u")}
    print(f"    max |dq| = {diff['q']:.3g}, max |du| = {diff['u']:.3g}")
    for key in COMPARED:
        x, y = np.asarray(a[key]), np.asarray(b[key])
        assert x.shape == y.shape, key
        if (done and scene.name not in PYTHON_VARIES) or key in ("t", "n_contacts"):
            assert np.array_equal(x, y), (key, float(np.abs(x - y).max(initial=0.0)))
        else:  # Python both ways: as reproducible as the Python step itself (module docstring)
            # the ledger's energy differences (smooth_error, dissipation, ...) are at the round-off of T + V
            energy = 1.0 + np.abs(np.asarray(a["kinetic_energy"]) + np.asarray(a["potential_energy"])).max()
            scale = 1.0 if key in ("q", "u", "gap") else max(1.0 + np.abs(x).max(initial=0.0), energy)
            assert np.abs(x - y).max(initial=0.0) <= 1e-12 * scale, (key, float(np.abs(x - y).max()))
    assert len(a["log_step"]) == len(b["log_step"]) and np.array_equal(a["log_step"], b["log_step"])


def test_step_impl_is_a_scene_key(tmp_path):
    text = (Path(__file__).resolve().parent.parent / "scenes" / "bouncing_ball.toml").read_text()
    ball = Path(__file__).resolve().parent.parent / "scenes" / "bouncing_ball.toml"
    sc = parse_scene(text.replace("duration = 3.0", 'duration = 3.0\nstep_impl = "compiled"'), path=ball)
    assert sc.options.step_impl is StepImpl.COMPILED
    assert load_scene(ball).options.step_impl is StepImpl.COMPILED  # the default
    sc = parse_scene(text.replace("duration = 3.0", 'duration = 3.0\nstep_impl = "python"'), path=ball)
    assert sc.options.step_impl is StepImpl.PYTHON
    with pytest.raises(SceneError, match="step_impl"):
        parse_scene(text.replace("duration = 3.0", 'duration = 3.0\nstep_impl = "fortran"'), path=ball)


def _random_projection(seed):
    rng = np.random.default_rng(seed)
    nv, m = int(rng.integers(1, 31)), int(rng.integers(1, 41))
    A = rng.standard_normal((nv, nv))
    M = A @ A.T + nv * np.eye(nv)
    W = np.asfortranarray(rng.standard_normal((nv, m)))  # Fortran-ordered, as constraints.contact_rows makes W
    if m >= 4 and seed % 2:
        W[:, 3] = W[:, 0] + W[:, 1] - W[:, 2]  # dependent rows (a face on a plane)
    b = 0.1 * rng.standard_normal(m) if seed % 3 == 0 else np.zeros(m)
    return M, W, rng.standard_normal(nv), b


def test_projection_is_bit_identical_to_qp_solve():
    """The C++ projection (src/step.cpp project: the screen, the closed form, the dual active set) against
    qp.solve on random problems of 1-40 rows in 1-30 velocities, dependent rows and bounds included: the same
    v and multipliers bit for bit, or a hand-back exactly where qp.solve turns to piqp."""
    solved = 0
    for seed in range(300):
        M, W, v0, b = _random_projection(seed)
        Minv = np.linalg.inv(M)
        ref = qp.solve(M, W, v0, b=b, Minv=Minv)
        status, v, lam = _ext().project(W, v0, b, Minv, compiled.CONSTANTS)
        if status is None:  # handed back, with its reason in v
            assert ref.status not in ("ACTIVE_SET", "ADMISSIBLE"), (seed, v)
            continue
        assert ref.status == status.name, seed
        assert np.array_equal(v, ref.v) and np.array_equal(lam, ref.lam), seed
        solved += status is _ext().Projection.ACTIVE_SET
    assert solved >= 200


@pytest.mark.parametrize("m", [150, 199, 201, 260])
def test_large_sparse_projection_is_bit_identical_to_qp_solve(m):
    """Above kWideRows (200) rows the compiled active set solves G_AA by its nonzeros (sparse_lu_solve, also in the
    final solves), and the final products run over the columns' nonzeros (otimes_cols): on pile-like problems of
    150-260 rows (M block diagonal, rows on two bodies, dependent corners) the same v and multipliers as qp.solve,
    bit for bit, on both sides of the threshold."""
    solved = 0
    for seed in range(3):
        M, W, v0, b, Minv = pile_projection(seed, m // 4, m)
        ref = qp.solve(M, W, v0, b=b, Minv=Minv)
        status, v, lam = _ext().project(W, v0, b, Minv, compiled.CONSTANTS)
        if status is None:
            assert ref.status not in ("ACTIVE_SET", "ADMISSIBLE"), (seed, v)
            continue
        assert ref.status == status.name, seed
        assert v.view(np.int64).tolist() == ref.v.view(np.int64).tolist(), seed
        assert lam.view(np.int64).tolist() == ref.lam.view(np.int64).tolist(), seed
        solved += status is _ext().Projection.ACTIVE_SET
    assert solved >= 2


def test_kernels_are_bit_identical_to_qp():
    """The two kernels of docs/theory.md §2.8 alone, C++ against Python: src/step.cpp omatmul against sums.ordered
    (every product of the projection) and lu_solve against qp._lu_solve (its solves), bit for bit on random
    inputs of 1-64 rows (both of _lu_solve's paths), and None on the same singular or NaN systems."""
    rng = np.random.default_rng(7)
    for _ in range(200):
        r, n, c = (int(k) for k in rng.integers(1, 65, 3))
        A = rng.standard_normal((r, n)) * 10.0 ** rng.integers(-6, 6, (r, n))
        X = np.where(rng.random((n, c)) < 0.5, 0.0, rng.standard_normal((n, c)))
        assert _ext().ordered(A, X).view(np.int64).tolist() == sums.ordered(A, X).view(np.int64).tolist()
    from test_qp import lu_systems
    for seed in range(20):
        for A, rhs in lu_systems(seed):
            x, ref = _ext().lu_solve(A, rhs), qp._lu_solve(A, rhs)
            assert (x is None) == (ref is None)
            assert ref is None or x.view(np.int64).tolist() == ref.view(np.int64).tolist()


def test_band_solve_is_bit_identical_to_qp():
    """The active set's solve of G_AA on its row-major band (src/step.cpp band_lu_solve: each pivot row's update run
    over the columns up to its last nonzero, zeros of that range included) against qp._lu_solve of A[sel][:, sel],
    bit for bit: the clean systems of test_qp.lu_systems (SPD, pivoting, banded, scattered, a row swap at every column,
    right-hand sides of signed zeros), random subsets of their rows as the active set takes them, ties in a pivot
    column, and None on the same singular systems."""
    from test_qp import lu_systems
    rng = np.random.default_rng(11)
    tie = np.array([[1.0, 2.0, 0.0], [0.0, 1.0, 3.0], [-1.0, 0.0, 5.0]])  # |a_00| = |a_20|: the first is the pivot
    cases = [(tie, np.array([1.0, -0.0, 2.0]))]
    for seed in range(6):
        cases += [(A, rhs) for A, rhs in lu_systems(seed)
                  if np.isfinite(A).all() and not (np.signbit(A) & (A == 0.0)).any()]
    checked = 0
    for A, rhs in cases:
        n = A.shape[0]
        for sel in (np.arange(n), np.flatnonzero(rng.random(n) < 0.6)):
            if not sel.size:
                continue
            r = rhs[sel].copy()
            x, ref = _ext().lu_solve_band(A, r, sel.tolist()), qp._lu_solve(A[np.ix_(sel, sel)], r)
            assert (x is None) == (ref is None), (n, sel)
            assert ref is None or x.view(np.int64).tolist() == ref.view(np.int64).tolist(), (n, sel)
            checked += ref is not None
    assert checked >= 150
    with pytest.raises(ValueError, match="without -0.0"):
        _ext().lu_solve_band(np.array([[1.0, -0.0], [0.0, 1.0]]), np.ones(2), [0, 1])


def _after(A, before, sel, rhs, sparse=False):
    """band_lu_solve (sparse: sub_lu_solve, sparse_lu_factor) of A[sel][:, sel] after one of A[before][:, before] on
    the same factor cache: (x, the steps it took from the first factor), x checked bit for bit against qp._lu_solve
    (None alike)."""
    x, reused = _ext().lu_solve_after(A, list(before), list(sel), rhs, sparse=sparse)
    ref = qp._lu_solve(A[np.ix_(sel, sel)], rhs)
    assert (x is None) == (ref is None), (before, sel)
    assert ref is None or x.view(np.int64).tolist() == ref.view(np.int64).tolist(), (before, sel)
    return x, reused


@pytest.mark.parametrize("sparse", [False, True], ids=["band", "sparse"])
def test_solve_prefix_kept_is_bit_identical_to_qp(sparse):
    """The factor prefix kept from one solve to the next (src/step.cpp band_lu_solve, and sub_lu_solve's
    sparse_lu_factor as nonzeros.lu_factor: a row added to or dropped from the rows at sorted place c keeps the first
    c elimination steps where they pick the same pivot rows; the same rows apply the last factor again), bit for bit
    against qp._lu_solve: the clean systems of test_qp.lu_systems with a row added, a row dropped, the same rows; and
    the condition at its edge: an added row whose |a_cj| equals the pivot's (it stays below the pivot row: kept; it
    sits above it: it is the first largest, so the whole elimination), one ulp below (kept) and above (not), a
    dropped row that was a pivot row (not kept) and one that was not (kept)."""

    from test_qp import check_prefix_rule

    check_prefix_rule(functools.partial(_after, sparse=sparse), same_rows=True)


def test_distinct_rows_are_python_ones():
    """Stepper::distinct (src/step.cpp distinct_rows: row j compared only with the earlier rows whose entry at its
    largest |entry| is within the tolerance of its own, found by binary search) keeps the columns constraints.distinct
    keeps: rows on blocks of velocities, repeats within the tolerance and beyond it, repeats whose largest entries
    differ by about the tolerance (either side of it), a repeat with one more entry at the tolerance (a repeat) or one
    ulp above it (not), either row first, zero rows."""
    from moreau_sim.constraints import DISTINCT, distinct
    from moreau_sim.contacts import Contacts
    rng = np.random.default_rng(5)

    def kept(W):
        m = W.shape[1]
        z3, zi = np.zeros((m, 3)), np.arange(m)
        return distinct(Contacts(np.zeros(m), z3, z3, z3, zi, zi, zi, zi, zi), W)[0].pair.tolist()

    checked = 0
    for trial in range(80):
        nv, m = int(rng.integers(4, 13)), int(rng.integers(3, 30))
        W = np.zeros((nv, m))
        for j in range(m):
            a = int(rng.integers(1, nv))
            W[a:int(rng.integers(a + 1, nv + 1)), j] = rng.normal(size=1)[0] + rng.normal(size=1)
            W[a, j] = 1.0 + rng.random()  # the first nonzero, > the tolerance
        W[-1, 0] = 100.0  # max |W|: the tolerance is thr throughout (the repeats below only shrink entries)
        W[:, 1] = 0.0 if trial % 7 == 0 else W[:, 1]
        thr = DISTINCT * (1.0 + np.abs(W).max())
        for j in range(1, m):
            i, kind = int(rng.integers(0, j)), int(rng.integers(0, 8))
            lo = int(np.flatnonzero(W[:, i])[0]) if W[:, i].any() else 0
            if kind == 0:
                W[:, j] = W[:, i] - 0.5 * thr * np.sign(W[:, i])
            elif kind == 1:
                W[:, j] = W[:, i] - 2.0 * thr * np.sign(W[:, i])
            elif kind in (2, 3) and lo > 0:  # j starts one velocity lower, at the tolerance (2) or one ulp above (3)
                W[:, j] = W[:, i]
                W[lo - 1, j] = thr if kind == 2 else np.nextafter(thr, 1.0)
            elif kind in (4, 5) and lo > 0:  # i does (i weak or not), j is i's row without it
                W[:, j] = W[:, i]
                W[lo - 1, i] = thr if kind == 4 else np.nextafter(thr, 1.0)
            elif kind in (6, 7):  # the largest entries differ by about the tolerance (by its round-off: either side)
                W[:, j] = W[:, i]
                top = int(np.argmax(np.abs(W[:, i])))
                W[top, j] = W[top, i] - (thr if kind == 6 else np.nextafter(thr, 1.0)) * np.sign(W[top, i])
        assert DISTINCT * (1.0 + np.abs(W).max()) == thr
        assert list(_ext().distinct_rows(W, DISTINCT)) == kept(W), trial
        checked += len(kept(W)) < m
    assert checked >= 40


def test_the_build_does_not_contract():
    """The extension is compiled as §2.8 requires: with -ffp-contract=off (reported by the build, CMakeLists.txt),
    doubles rounded at each operation (FLT_EVAL_METHOD 0, no x87 excess precision), and its probe a * b + c on
    run-time values rounds twice: (1 + 2^-30)(1 - 2^-30) = 1 - 2^-60 rounds to 1, so the sum is 0, where one fused
    rounding would give -2^-60."""
    fp = _ext().fp_build()
    assert "-ffp-contract=off" in fp["options"].split() and "fast-math" not in fp["options"].replace("-fno-fast", "")
    assert fp["flt_eval_method"] == "0"
    a, b = 1.0 + 2.0**-30, 1.0 - 2.0**-30
    assert _ext().fp_probe(a, b, -1.0) == 0.0


# what the step computes (the energies are Pinocchio's); the ledger's other columns (dissipation, ...) are
# recording.py's numpy products, which the rule of §2.8 does not cover
STEP_KEYS = ("t", "q", "u", "kinetic_energy", "potential_energy", "contact_work", "correction_energy", "gap",
             "n_contacts", "log_step")
_CORETYPE_RUN = """
import sys, numpy as np, moreau_sim as ms
sc = ms.load_scene(sys.argv[1]).with_options(duration=float(sys.argv[2]), step_impl=sys.argv[3])
tr = ms.simulate(ms.build_model(sc), progress=False)
np.savez(sys.argv[4], **{k: np.asarray(tr.arrays[k]) for k in sys.argv[5].split(",")})
"""


@pytest.mark.slow
@pytest.mark.parametrize("name,duration", [
    ("newton_cradle_5", 0.3), ("box_stack_5", 0.3),
    ("box_drop", 1.5)])
def test_same_bits_whatever_blas_kernel(name, duration, tmp_path):
    """The rule of §2.8 does not lean on one machine's BLAS: OpenBLAS (DYNAMIC_ARCH) picks its kernels by the CPU,
    and OPENBLAS_CORETYPE makes it take another's (Sandybridge: no FMA; Haswell; SkylakeX) - dgesv's answers and
    numpy's small products change with it. The Python step under each and the compiled step: the same trajectory
    bit for bit (newton_cradle_5: spheres, 1-4 row solves; box_stack_5: 30 velocities, solves of 1-14 rows;
    box_drop: a cube's vertices on the ground, not yet: see its mark)."""
    import os
    import subprocess
    import sys

    keys = ",".join(STEP_KEYS)
    out = {}
    for core, impl in (("SkylakeX", "python"), ("Sandybridge", "python"), ("Haswell", "python"),
                       ("Sandybridge", "compiled")):
        f = tmp_path / f"{core}-{impl}.npz"
        env = dict(os.environ, OPENBLAS_CORETYPE=core)
        subprocess.run([sys.executable, "-c", _CORETYPE_RUN, str(SCENES[0].parent / f"{name}.toml"), str(duration),
                        impl, str(f), keys], env=env, check=True)
        out[core, impl] = np.load(f)
    ref = out["SkylakeX", "python"]
    for run, arrays in out.items():
        for key in STEP_KEYS:
            assert np.array_equal(arrays[key], ref[key]), (run, key)


def test_constants_are_passed_from_python():
    """Every constant the two steps share crosses at construction from its Python home (compiled.CONSTANTS):
    the extension asks for exactly these names (a missing or an unknown one is an error, so none can be left
    to a value of its own) and reads back the same values."""
    from moreau_sim import constraints, results, stepper
    C = compiled.CONSTANTS
    assert sorted(_ext().constant_names()) == sorted(C)
    assert _ext().read_constants(C) == {k: float(v) for k, v in C.items()}
    for k in C:
        with pytest.raises(ValueError, match=k):
            _ext().read_constants({j: v for j, v in C.items() if j != k})
    with pytest.raises(ValueError, match="unknown"):
        _ext().read_constants({**C, "spare": 1.0})
    # their homes, by name
    assert (C["midpoint_iterations"], C["resting"]) == (stepper.MIDPOINT_ITERATIONS, results.RESTING)
    assert (C["vertex"], C["witness"]) == (FeatureKind.VERTEX, FeatureKind.WITNESS)
    assert (C["warm_rows"], C["sparse_rows"]) == (qp.WARM_ROWS, qp.SPARSE_ROWS)
    assert (C["screen"], C["distinct"]) == (qp.SCREEN, constraints.DISTINCT)
    # and the stepper of a model holds them
    model = build_model(load_scene(SCENES[0].parent / "box_drop.toml"))
    data = make_data(model)
    ctx = compiled._context(model, data)
    assert ctx.stepper.constants == {k: float(v) for k, v in C.items()}


def test_the_result_crosses_by_name():
    """The compiled step's result is a typed object with an enum outcome whose arrays are named by the
    extension's own layout (StepOut.layout: no positional slicing in Python): the contact steps of box_drop
    give the Python step's contacts, impact and projection problem, by name and bit for bit (each one compiled but
    those that pay a position lift, which the compiled step hands to the Python step, docs/theory.md §2.5)."""
    scene = load_scene(SCENES[0].parent / "box_drop.toml")
    assert {m.name for m in _ext().Outcome} == {"FLIGHT", "CONTACT", "FALLBACK"}
    names = ["q_next", "u_next", "u_free", *ms.Contacts.ARRAYS, "P", "gamma_minus", "gamma_plus", "v_free", "b", "v",
             "lam", "M", "W"]
    models = {impl: build_model(scene.with_options(step_impl=impl.value)) for impl in StepImpl}
    datas = {impl: make_data(m) for impl, m in models.items()}
    state = {impl: None for impl in StepImpl}
    contact = 0
    for _ in range(1200):
        rs = {}
        before = state[StepImpl.COMPILED] or ms.initial_state(models[StepImpl.COMPILED])
        for impl in StepImpl:
            m = models[impl]
            s = state[impl] or ms.initial_state(m)
            rs[impl] = ms.step(m, datas[impl], s)
            state[impl] = rs[impl].state
        a, b = rs[StepImpl.PYTHON], rs[StepImpl.COMPILED]
        if a.qp is not None and not contact:  # the first contact step: the extension's own names
            ctx = compiled._context(models[StepImpl.COMPILED], datas[StepImpl.COMPILED])
            o = models[StepImpl.COMPILED].options
            out = ctx.stepper.step(before.q, before.u, o.dt, o.restitution)
            assert out.outcome is _ext().Outcome.CONTACT and out.m == a.contacts.m
            assert sorted(n for n, *_ in out.layout()) == sorted(names)
        assert np.array_equal(a.u_free, b.u_free)
        for key in ("g", "point_a", "point_b", "normal", "pair", "kind", "feature", "joint_a", "joint_b"):
            x, y = getattr(a.contacts, key), getattr(b.contacts, key)
            assert x.dtype.kind == y.dtype.kind and np.array_equal(x, y), key
        if a.qp is not None:
            contact += 1
            for key in ("M", "W", "v0", "b", "v", "lam"):
                assert np.array_equal(getattr(a.qp, key), getattr(b.qp, key)), key
            assert (a.qp.status, a.qp.polished) == (b.qp.status, b.qp.polished)
    counts = compiled.counts(datas[StepImpl.COMPILED])  # a step that pays a position lift is the Python step's (§2.5)
    assert contact > 50 and counts["contact"] + counts["python: a paid position lift"] == contact, dict(counts)


def test_kept_buffers_give_python_bits_as_the_rows_come_and_go():
    """The compiled step keeps its large buffers (M, M^-1, the projection's MiW and G) from one step to the next,
    resized only where the rows' count changes, and hands M and W to Python as views of the step's own arrays: on
    column_of_beads (its contact count rising and falling from step to step) every contact step gives the Python
    step's contacts, impact and projection problem bit for bit (M made from the trees' blocks, W +0.0 off the two
    bodies' velocities, read-only), and a result kept from an earlier step still holds its own M and W after later
    steps (the storage of a dropped step's W cleared where it was written and reused: Spare::take_zero)."""
    scene = load_scene(SCENES[0].parent / "column_of_beads.toml")
    models = {impl: build_model(scene.with_options(step_impl=impl.value)) for impl in StepImpl}
    datas = {impl: make_data(m) for impl, m in models.items()}
    state = {impl: ms.initial_state(m) for impl, m in models.items()}
    kept, ms_seen = [], []
    for _ in range(1500):
        rs = {impl: ms.step(models[impl], datas[impl], state[impl]) for impl in StepImpl}
        for impl in StepImpl:
            state[impl] = rs[impl].state
        a, b = rs[StepImpl.PYTHON], rs[StepImpl.COMPILED]
        assert np.array_equal(a.state.q, b.state.q) and np.array_equal(a.state.u, b.state.u)
        if a.qp is None:
            continue
        ms_seen.append(a.contacts.m)
        for key in ("M", "W", "v0", "b", "v", "lam"):  # every bit, a zero's sign included
            assert getattr(a.qp, key).tobytes() == getattr(b.qp, key).tobytes(), key
        for key in ("P", "gamma_minus", "gamma_plus"):
            assert np.array_equal(getattr(a, key), getattr(b, key)), key
        # a row is +0.0 on the velocities that move neither body (constraints.contact_rows), and W read-only (the
        # extension reuses its storage)
        moved = (models[StepImpl.PYTHON].support_mask[a.contacts.joint_a]
                 + models[StepImpl.PYTHON].support_mask[a.contacts.joint_b]).T != 0.0
        assert not np.signbit(a.qp.W[~moved]).any() and not (a.qp.W[~moved] != 0.0).any()
        assert not b.qp.W.flags.writeable
        kept.append((b, b.qp.M.copy(), b.qp.W.copy()))
    steps = np.diff(ms_seen)
    assert (steps > 0).any() and (steps < 0).any(), ms_seen  # the rows came and went
    assert compiled.counts(datas[StepImpl.COMPILED])["contact"] > 100
    for b, M, W in kept:
        assert b.qp.M.tobytes() == M.tobytes() and b.qp.W.tobytes() == W.tobytes()


@pytest.mark.parametrize("name", [pytest.param("column_of_beads_100", marks=pytest.mark.slow), "quadruped_drop"])
def test_python_step_is_bit_reproducible(name):
    """The Python step alone, twice in one process (other arrays allocated in between, so numpy's land at other
    addresses): the same trajectory bit for bit, on the larger models (100 and 18 velocities, 16-76 rows) whose
    products BLAS would sum in a size- and alignment-dependent order (sums.ordered)."""
    scene = load_scene(SCENES[0].parent / f"{name}.toml").with_options(duration=0.3)
    a, _ = _run(scene, StepImpl.PYTHON)
    junk = [np.ones(k) for k in range(1, 50)]  # noqa: F841 (shifts the allocator)
    b, _ = _run(scene, StepImpl.PYTHON)
    for key in COMPARED:
        assert np.array_equal(np.asarray(a.arrays[key]), np.asarray(b.arrays[key])), key


def test_column_of_beads_past_the_old_parting_is_identical():
    """Over its full length column_of_beads used to part between the two steps at step 1292 (t = 0.646 s;
    the Python step kept piqp's answer to a correction QP). Run past it both ways: identical."""
    scene = load_scene(SCENES[0].parent / "column_of_beads.toml").with_options(duration=0.7)
    ref, _ = _run(scene, StepImpl.PYTHON)
    got, counts = _run(scene, StepImpl.COMPILED)
    assert counts["contact"] > 300 and not any(k.startswith("python") for k in counts), counts
    for key in COMPARED:
        assert np.array_equal(np.asarray(ref.arrays[key]), np.asarray(got.arrays[key])), key


def test_version_mismatch_falls_back_with_one_warning(monkeypatch):
    """A Pinocchio other than the build's: the Python step, one warning, the same trajectory."""
    import pinocchio
    monkeypatch.setattr(compiled, "_loaded", False)
    monkeypatch.setattr(compiled, "_module", None)
    monkeypatch.setattr(compiled, "_reason", None)
    monkeypatch.setattr(pinocchio, "__version__", "0.0.0")
    scene = load_scene(SCENES[0].parent / "bouncing_ball.toml").with_options(duration=0.6)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        traj, counts = _run(scene, StepImpl.COMPILED)
        _run(scene, StepImpl.COMPILED)
    mine = [w for w in caught if "compiled step is unavailable" in str(w.message)]
    assert len(mine) == 1 and "pinocchio 0.0.0" in str(mine[0].message)
    assert not compiled.available() and not counts
    ref, _ = _run(scene, StepImpl.PYTHON)
    assert np.array_equal(ref.arrays["q"], traj.arrays["q"])
