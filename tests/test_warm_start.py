"""The projection above qp.SPARSE_ROWS rows (issue 24, docs/theory.md §1.3): the dual active set warm-started from
the previous step's final active set (rows matched by their contact's identity: pair, kind, feature; a row without
a match starts inactive), piqp + SuperLU (qp._solve_sparse) only where it fails. Where the projection is unique
(independent rows) the start changes the moves, not the answer: the final set, hence every bit, is the cold start's."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import qp, stepper
from moreau_sim.contacts import Contacts
from moreau_sim.data import make_data


def _bits(x) -> list:
    return np.ascontiguousarray(x, float).view(np.int64).tolist()


def _column_problem(n: int, h: float, up: int = 0, speed: float = 1.0):
    """n beads of 1 kg on vertical prismatic joints resting on each other and the ground (row k: bead k over bead
    k - 1 or the ground), v0 their free velocity -g h; the top `up` beads moving up at `speed` [m/s] (their rows
    separate)."""
    W = np.zeros((n, n))
    W[0, 0] = 1.0
    for k in range(1, n):
        W[k, k], W[k - 1, k] = 1.0, -1.0
    gh = 9.81 * h
    v0 = np.full(n, -gh)
    if up:
        v0[n - up:] = speed
    return np.eye(n), W, v0, gh


def _rows(r) -> np.ndarray:
    return r.lam > 0.0


@pytest.mark.parametrize("h", [5e-4, 2e-3])
@pytest.mark.parametrize("n", [qp.SPARSE_ROWS + 1, 300, 500])
def test_the_warm_start_gives_the_cold_bits_where_the_projection_is_unique(n, h):
    """A resting column above SPARSE_ROWS rows from nothing, from its own final set, from half of it and from a set
    with rows that must leave (the top beads separate): the active set (no piqp), the same bits each time, the
    closed form lam_k = (n_k) g h of the beads resting above row k, the KKT conditions to round-off; from its own
    set the start takes no move in the first pass."""
    up = 7
    M, W, v0, gh = _column_problem(n, h, up)
    cold = qp.solve(M, W, v0, Minv=M)
    assert cold.ok and cold.status == "ACTIVE_SET" and cold.polished
    rest = n - up
    np.testing.assert_allclose(cold.lam[:rest], gh * (rest - np.arange(rest)), rtol=1e-13, atol=0)
    assert not cold.lam[rest:].any()
    assert cold.residual <= 1e-15 * n
    half = _rows(cold).copy()
    half[::2] = False
    wrong = np.ones(n, bool)  # the separating rows taken as active: the start's multipliers there are negative
    for start in (_rows(cold), half, wrong, np.zeros(n, bool)):
        warm = qp.solve(M, W, v0, Minv=M, start=start)
        assert warm.status == "ACTIVE_SET" and warm.polished
        assert _bits(warm.v) == _bits(cold.v) and _bits(warm.lam) == _bits(cold.lam)
    assert qp.solve(M, W, v0, Minv=M, start=_rows(cold)).iterations < cold.iterations


def test_a_start_s_negative_rows_are_dropped_up_to_start_passes_solves(monkeypatch):
    """A start of the final set and one row that must leave (the top beads separate slowly): its first solve has a
    negative multiplier there; that row is dropped and the rest solved again. With START_PASSES = 1 the start is
    refused (from nothing: the cold start's moves), with 2 or more it is kept (no move in the first pass); the same
    bits either way."""
    n, up = 260, 9
    M, W, v0, _ = _column_problem(n, 1e-3, up, speed=1e-6)
    cold = qp.solve(M, W, v0, Minv=M)
    start = _rows(cold).copy()
    assert not start[n - up]
    start[n - up] = True  # the row under the separating beads
    moves = {}
    for passes in range(1, 4):
        monkeypatch.setattr(qp, "START_PASSES", passes)
        r = qp.solve(M, W, v0, Minv=M, start=start)
        assert r.status == "ACTIVE_SET" and _bits(r.v) == _bits(cold.v) and _bits(r.lam) == _bits(cold.lam)
        moves[passes] = r.iterations
    assert moves[1] == cold.iterations > moves[2] == moves[3]


def test_at_or_below_sparse_rows_the_start_is_not_read():
    """At SPARSE_ROWS rows the cold start whatever `start` says (the bundled scenes' bits)."""
    n = qp.SPARSE_ROWS
    M, W, v0, _ = _column_problem(n, 1e-3, 3)
    cold = qp.solve(M, W, v0, Minv=M)
    for start in (np.ones(n, bool), _rows(cold)):
        r = qp.solve(M, W, v0, Minv=M, start=start)
        assert r.iterations == cold.iterations and _bits(r.v) == _bits(cold.v) and _bits(r.lam) == _bits(cold.lam)


def _first_pass_moves(monkeypatch, *args) -> int:
    moves = []
    orig = qp._active_set

    def spy(G, r, tol, act=None, mul=np.matmul):
        s = orig(G, r, tol, act, mul)
        moves.append(None if s is None else s[2])
        return s

    monkeypatch.setattr(qp, "_active_set", spy)
    qp.solve(*args[:3], Minv=args[3], start=args[4])
    monkeypatch.setattr(qp, "_active_set", orig)
    return moves[0]


@pytest.mark.parametrize("from_set", [False, True])
def test_the_move_limit_hands_the_projection_to_the_sparse_path(from_set, monkeypatch):
    """The active set's move limit at its edge: with MOVES_PER_ROW m + MOVES_EXTRA equal to the first pass's moves
    the warm start answers; one move fewer and qp.solve answers as the sparse path (_solve_sparse: piqp, SuperLU)
    does, bit for bit, still the projection (KKT to round-off)."""
    n = 260
    M, W, v0, gh = _column_problem(n, 1e-3, 5)
    cold = qp.solve(M, W, v0, Minv=M)
    start = _rows(cold).copy()
    start[-40:-5] = False  # 35 rows to add again
    start = start if from_set else None
    k = _first_pass_moves(monkeypatch, M, W, v0, M, start)
    assert k >= 35
    monkeypatch.setattr(qp, "MOVES_PER_ROW", 0)
    monkeypatch.setattr(qp, "MOVES_EXTRA", k)
    r = qp.solve(M, W, v0, Minv=M, start=start)
    assert r.status == "ACTIVE_SET" and _bits(r.v) == _bits(cold.v)
    monkeypatch.setattr(qp, "MOVES_EXTRA", k - 1)
    r = qp.solve(M, W, v0, Minv=M, start=start)
    ref = qp._solve_sparse(M, W, v0, np.zeros(n), M, ms.QPForm.PRIMAL, 1e-10, 250, True)
    assert r.status == ref.status == "PIQP_SOLVED"
    assert _bits(r.v) == _bits(ref.v) and _bits(r.lam) == _bits(ref.lam)
    assert r.residual <= 1e-14 * n
    np.testing.assert_allclose(r.v, cold.v, rtol=0, atol=1e-14)


def _contacts(keys) -> Contacts:
    m = len(keys)
    pair, kind, feature = (np.array([k[i] for k in keys], int) for i in range(3))
    z3 = np.zeros((m, 3))
    return Contacts(np.zeros(m), z3, z3, z3, pair, kind, feature, np.zeros(m, int), np.zeros(m, int))


def test_rows_are_matched_by_their_contacts_identity():
    """warm_start: a row starts active iff its contact (pair, kind, feature) pushed at the last step, wherever it
    sits in the list; a contact that disappeared is dropped, one that appeared (or the same pair with another
    feature or kind) starts inactive; at or below SPARSE_ROWS rows, or with no kept set, no start."""
    m = qp.SPARSE_ROWS + 3
    keys = [(p, 1, 0) for p in range(m)]
    data = SimpleNamespace(active_rows=frozenset({(5, 1, 0), (7, 1, 0), (9999, 1, 0), (11, 1, 0)}))
    keys[3] = (7, 1, 0)  # moved in the list
    keys[7] = (3, 1, 0)
    keys[11] = (11, 2, 0)  # the same pair, another kind
    keys[12] = (11, 1, 1)  # ... another feature
    start = stepper.warm_start(data, _contacts(keys))
    assert start.dtype == bool and np.flatnonzero(start).tolist() == [3, 5]
    assert stepper.warm_start(data, _contacts(keys[:qp.SPARSE_ROWS])) is None
    assert stepper.warm_start(SimpleNamespace(active_rows=frozenset()), _contacts(keys)) is None


def test_the_kept_set_is_the_final_active_set_above_sparse_rows():
    """keep_active: the identities of the active set's final rows (its first pass's), or of piqp's rows with
    lam > 0 (a zero multiplier is not kept), above SPARSE_ROWS rows; none at or below, none after a failed
    projection."""
    m = qp.SPARSE_ROWS + 1
    keys = [(p, 0, p % 3) for p in range(m)]
    lam = np.zeros(m)
    lam[[0, 4, m - 1]] = [1.0, 5e-324, 2.0]

    def imp(c, lam, ok=True):
        res = qp.QPResult("ACTIVE_SET" if ok else "PIQP_MAX_ITER_REACHED", ok, 0, ok, np.zeros(1), lam)
        return SimpleNamespace(contacts=c, qp=res)

    data = SimpleNamespace(active_rows=frozenset({(1, 2, 3)}))
    stepper.keep_active(data, imp(_contacts(keys), lam))  # piqp's answer (no active set): its rows with lam > 0
    assert data.active_rows == {keys[0], keys[4], keys[m - 1]}
    first = np.zeros(m, bool)
    first[[2, 4]] = True  # the active set's answer: its first pass's final set, whatever lam
    res = qp.QPResult("ACTIVE_SET", True, 0, True, np.zeros(1), lam, active=first)
    stepper.keep_active(data, SimpleNamespace(contacts=_contacts(keys), qp=res))
    assert data.active_rows == {keys[2], keys[4]}
    stepper.keep_active(data, imp(_contacts(keys), lam, ok=False))
    assert data.active_rows == frozenset()
    data.active_rows = frozenset({(1, 2, 3)})
    stepper.keep_active(data, imp(_contacts(keys[:-1]), lam[:-1]))
    assert data.active_rows == frozenset()


def _hit(n: int, V: float, e: float, h: float) -> ms.Scene:
    """benchmarks.scaling.column's n touching beads, the top one 6 mm above the column and moving down at V [m/s]."""
    from benchmarks.scaling import REPO

    b = ms.SceneBuilder(f"column_hit_{n}", folder=REPO / "scenes", restitution=e, dt=h, duration=0.01,
                        step_impl="python")
    for k in range(n):
        b.add_body(f"bead{k}", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1),
                   q0=[0.1 + 0.2 * k + (6e-3 if k == n - 1 else 0.0)], u0=[-V if k == n - 1 else 0.0])
    b.add_halfspace("ground")
    return b.build()


@pytest.mark.parametrize("h", [5e-4, 1e-3])
@pytest.mark.parametrize("e", [0.0, 0.9])
def test_a_column_above_sparse_rows_steps_with_the_cold_bits(e, h, monkeypatch):
    """A column of 240 beads (above SPARSE_ROWS rows), its top bead falling onto it at 2 m/s, stepped by the Python
    step with the warm start and with the cold start (stepper.warm_start disabled): the same bits every step while
    the top contact appears, pushes and (e > 0) opens again; every projection the active set's, the kept set its
    final active set; the top bead leaves with e times its speed, the column stays at rest (the ground takes
    the blow), no energy gained."""
    n, V = 240, 2.0
    sc = _hit(n, V, e, h)
    runs = {}
    for mode in ("warm", "cold"):
        if mode == "cold":
            monkeypatch.setattr(stepper, "warm_start", lambda data, contacts: None)
        model = ms.build_model(sc)
        data = make_data(model)
        st, out = ms.initial_state(model, data), []
        for _ in range(10):
            r = ms.step(model, data, st)
            out.append((r, data.active_rows))
            st = r.state
        runs[mode] = out
    ms_ = [r.contacts.m for r, _ in runs["warm"]]
    assert min(ms_) == n - 1 and max(ms_) == n  # the top contact appears (and with e > 0 opens again)
    model = ms.build_model(sc)
    data = make_data(model)
    st0 = ms.initial_state(model, data)
    E0 = ms.energy.total(model, data, st0.q, st0.u)
    for (a, kept), (b, _) in zip(runs["warm"], runs["cold"]):
        assert a.qp.status == b.qp.status == "ACTIVE_SET"
        for x, y in ((a.state.q, b.state.q), (a.state.u, b.state.u), (a.P, b.P)):
            assert _bits(x) == _bits(y)
        c = a.contacts
        assert kept == {(p, k, f) for p, k, f, x in zip(c.pair, c.kind, c.feature, a.qp.active) if x}
        E = ms.energy.total(model, data, a.state.q, a.state.u)
        assert E <= E0 * (1 + 1e-12)
        E0 = E
    i = next(i for i, (r, _) in enumerate(runs["warm"]) if r.contacts.m == n)
    u, u_k = runs["warm"][i][0].state.u, runs["warm"][i - 1][0].state.u
    assert u_k[-1] < -V and abs(u[-1] + e * u_k[-1]) <= 1e-12  # u+ = -e u_k: v = 0 on the resting column
    assert np.abs(u[:-1]).max() <= 1e-12


def _stepped(model: ms.Model, n: int) -> tuple:
    """(data, the StepResults of n steps by ms.step from the scene's initial state)."""
    data = make_data(model)
    st, out = ms.initial_state(model, data), []
    for _ in range(n):
        out.append(ms.step(model, data, st))
        st = out[-1].state
    return data, out


def _compiled_or_fail():
    from moreau_sim import compiled

    assert compiled.available(), compiled.unavailable_reason()
    return compiled


@pytest.mark.parametrize("e", [0.0, 0.9])
def test_both_steps_take_a_column_above_sparse_rows_with_the_same_bits(e):
    """The hit column of 240 beads by the Python step and by the compiled step (src/step.cpp: the same warm start,
    the same matching, no hand-back above SPARSE_ROWS rows): the same bits every step, the same kept set; one step in
    the middle taken by the Python step (eps given) keeps the two in step (the kept set crosses both ways)."""
    compiled = _compiled_or_fail()
    n, h = 240, 5e-4
    sc = _hit(n, 2.0, e, h)
    out = {}
    for impl in ("python", "compiled", "mixed"):
        model = ms.build_model(sc.with_options(step_impl="python" if impl == "python" else "compiled"))
        data = make_data(model)
        st, rs = ms.initial_state(model, data), []
        for k in range(10):
            eps = model.options.qp_tolerance if impl == "mixed" and k in (4, 5) else None
            r = ms.step(model, data, st, eps=eps)
            rs.append((r, data.active_rows))
            st = r.state
        out[impl] = (rs, compiled.counts(data))
    assert set(out["compiled"][1]) <= {"flight", "contact"} and out["compiled"][1]["contact"] == 10
    assert out["mixed"][1]["contact"] == 8
    for impl in ("compiled", "mixed"):
        for (a, ka), (b, kb) in zip(out["python"][0], out[impl][0]):
            assert a.contacts.m == b.contacts.m > qp.SPARSE_ROWS and a.qp.status == b.qp.status == "ACTIVE_SET"
            for x, y in ((a.state.q, b.state.q), (a.state.u, b.state.u), (a.P, b.P), (a.qp.lam, b.qp.lam)):
                assert _bits(x) == _bits(y)
            assert ka == kb and len(ka) >= n - 1


def test_a_compiled_run_above_sparse_rows_records_the_python_runs_bits(monkeypatch):
    """simulate() of the hit column (240 beads) by the Python step, by the compiled step in the Python loop and by
    the compiled run loop (src/run.cpp's Runner over the Stepper): every recorded array the same bits; the compiled
    loop takes every step. (Its 28,920 pairs listed: the run loops refuse a scene without a pair list,
    compiled.loop_refusal.)"""
    _compiled_or_fail()
    monkeypatch.setattr(ms.model, "LAZY_PAIRS", 10 ** 5)
    sc = _hit(240, 2.0, 0.5, 5e-4).with_options(duration=4e-3)
    runs = [ms.simulate(ms.build_model(sc.with_options(step_impl=impl)), progress=False, python_run=python_run)
            for impl, python_run in (("python", True), ("compiled", True), ("compiled", False))]
    ref = runs[0]
    for new in runs[1:]:
        assert set(new.arrays) == set(ref.arrays)
        assert [k for k in ref.arrays if ref.arrays[k].tobytes() != new.arrays[k].tobytes()] == []
    assert runs[2].meta["run"]["loop"] == "compiled" and runs[2].meta["run"]["python_steps"] == 0


def test_above_warm_rows_a_projection_without_a_start_takes_the_sparse_path_alone(monkeypatch):
    """Above qp.WARM_ROWS rows a projection without a start (none given, or none of its rows set) goes to the sparse
    path alone (piqp + SuperLU: the cold start's moves cost too much there); with a start the warm-started active
    set solves at any size. At the edge (WARM_ROWS = m) the cold active set still solves. Every answer the same
    projection to its tolerance and the column's closed form lam_k = (n - k) g h."""
    n = qp.SPARSE_ROWS + 20
    M, W, v0, gh = _column_problem(n, 1e-3)
    monkeypatch.setattr(qp, "WARM_ROWS", n)
    at = qp.solve(M, W, v0, Minv=M)
    assert at.status == "ACTIVE_SET"
    monkeypatch.setattr(qp, "WARM_ROWS", n - 1)
    for start in (None, np.zeros(n, bool)):
        above = qp.solve(M, W, v0, Minv=M, start=start)
        assert above.ok and above.status == "PIQP_SOLVED"
        np.testing.assert_allclose(above.lam, gh * (n - np.arange(n)), rtol=1e-9, atol=0)
        np.testing.assert_allclose(above.v, at.v, rtol=0, atol=1e-12)
    warm = qp.solve(M, W, v0, Minv=M, start=np.arange(n) % 2 == 0)
    assert warm.status == "ACTIVE_SET"
    np.testing.assert_allclose(warm.lam, gh * (n - np.arange(n)), rtol=1e-12, atol=0)


def test_above_warm_rows_a_cold_step_is_handed_back_and_the_warm_ones_stay_compiled(monkeypatch):
    """qp.WARM_ROWS lowered to 230, under the hit column's 240 rows: its first step has no start, so the Python
    step takes the sparse path alone and the compiled step hands that step back (src/step.cpp project); every later
    step starts from the last final set and stays compiled, by ms.step and in the compiled run loop. With
    compiled_run.LOG_ROWS lowered to 4 a step's log rows outgrow the room reserved: the Runner undoes that step and
    takes it again with them reserved (Runner.log_need). Every array the Python step's bits."""
    from moreau_sim import compiled_run

    compiled = _compiled_or_fail()
    monkeypatch.setattr(qp, "WARM_ROWS", 230)
    monkeypatch.setitem(compiled.CONSTANTS, "warm_rows", 230)
    monkeypatch.setattr(compiled_run, "LOG_ROWS", 4)
    monkeypatch.setattr(ms.model, "LAZY_PAIRS", 10 ** 5)  # a pair list: the run loop takes the scene
    sc = _hit(240, 2.0, 0.5, 5e-4).with_options(duration=4e-3)
    out = {}
    for impl in ("python", "compiled"):
        data, rs = _stepped(ms.build_model(sc.with_options(step_impl=impl)), 6)
        out[impl] = (rs, compiled.counts(data))
    assert out["compiled"][1] == {"python: more rows than the active set takes from nothing": 1, "contact": 5}
    for a, b in zip(*(out[i][0] for i in ("python", "compiled"))):
        assert a.contacts.m == b.contacts.m > qp.WARM_ROWS
        for x, y in ((a.state.q, b.state.q), (a.state.u, b.state.u), (a.P, b.P), (a.qp.lam, b.qp.lam)):
            assert _bits(x) == _bits(y)
    assert [r.qp.status for r in out["python"][0]] == ["PIQP_SOLVED"] + ["ACTIVE_SET"] * 5
    depth, deepest = [0], [0]  # advance's calls within a call: the Runner's retries
    real = compiled_run.CompiledRun.advance

    def spy(self, t_stop):
        depth[0] += 1
        deepest[0] = max(deepest[0], depth[0])
        try:
            return real(self, t_stop)
        finally:
            depth[0] -= 1
    monkeypatch.setattr(compiled_run.CompiledRun, "advance", spy)
    runs = [ms.simulate(ms.build_model(sc.with_options(step_impl=impl)), progress=False, python_run=python_run)
            for impl, python_run in (("python", True), ("compiled", False))]
    assert [k for k in runs[0].arrays if runs[0].arrays[k].tobytes() != runs[1].arrays[k].tobytes()] == []
    assert runs[1].meta["run"]["loop"] == "compiled" and runs[1].meta["run"]["python_steps"] == 1
    assert deepest[0] == 2  # one retry a call at most: the rows one step needs are reserved for the next


def _pressed(n: int, e: float, h: float, step_impl: str = "python") -> ms.Scene:
    """benchmarks.scaling.column's n touching beads, bead k moving down at 0.01 (k + 1) m/s: every contact closing
    at 0.01 m/s (the first step's midpoint gaps negative, the position correction on every row)."""
    from benchmarks.scaling import REPO

    b = ms.SceneBuilder(f"column_pressed_{n}", folder=REPO / "scenes", restitution=e, dt=h, duration=0.01,
                        step_impl=step_impl)
    for k in range(n):
        b.add_body(f"bead{k}", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1),
                   q0=[0.1 + 0.2 * k], u0=[-0.01 * (k + 1)])
    b.add_halfspace("ground")
    return b.build()


@pytest.mark.parametrize("h", [5e-4, 1e-3])
@pytest.mark.parametrize("e", [0.0, 0.9])
def test_the_position_correction_above_sparse_rows_starts_from_the_law_s_final_set(e, h, monkeypatch):
    """A column of 240 beads closing on each other: the position correction's QP (240 rows, above
    SPARSE_ROWS) starts from the law's final active set (stepper.correct_positions, docs/theory.md §2.5). Where it
    is unique (independent rows) that changes the moves, not the answer: the same bits as the cold start (its start
    dropped) every step; the compiled step gives the same bits; no contact ends deeper than the contact tolerance
    + 2 h max|u| and T + V never grows beyond what the correction books."""
    n = 240
    seen = []
    real = qp.solve

    def spy(*args, start=None, **kw):
        seen.append(start is not None and len(start) > qp.SPARSE_ROWS and bool(np.any(start)))
        return real(*args, start=start, **kw)

    runs = {}
    for mode in ("warm", "cold", "compiled"):
        model = ms.build_model(_pressed(n, e, h, "compiled" if mode == "compiled" else "python"))
        if mode == "cold":
            monkeypatch.setattr(stepper.qp, "solve", lambda *a, start=None, **kw: real(*a, **kw))
        else:
            monkeypatch.setattr(stepper.qp, "solve", spy)
        data, out = _stepped(model, 6)
        runs[mode] = (model, data, out)
    assert any(seen)  # a correction QP warm-started above SPARSE_ROWS (the Python step's)
    model, data, warm = runs["warm"]
    tol = model.options.contact_tolerance
    assert warm[0].contacts.m == n and warm[0].correction_energy != 0.0  # every contact closed and corrected
    for a, b, c in zip(warm, runs["cold"][2], runs["compiled"][2]):
        for x, y, z in ((a.state.q, b.state.q, c.state.q), (a.state.u, b.state.u, c.state.u)):
            assert _bits(x) == _bits(y) == _bits(z)
        g = np.diff(np.concatenate(([0.0], a.state.q))) - np.concatenate(([0.1], np.full(n - 1, 0.2)))
        assert g.min() >= -(tol + 2 * h * np.abs(a.state.u).max())  # deeper only by what a step's approach makes
    st0 = ms.initial_state(model, data)
    E = [ms.energy.total(model, data, st0.q, st0.u)] + [ms.energy.total(model, data, r.state.q, r.state.u)
                                                       for r in warm]
    for k, r in enumerate(warm):  # E_{k+1} - E_k = W_c + correction_energy, W_c <= 0
        assert E[k + 1] - E[k] - r.correction_energy <= 1e-12 * abs(E[0])


def test_the_kept_set_stays_in_the_compiled_stepper_until_read():
    """The compiled step leaves the set it kept in its Stepper (data.hold_active: not read back each step, m rows);
    read after six steps it is the Python step's kept set, bit for bit the same run; after the read the set is
    data's own again and is sent back, and the next steps still match the Python step's bits."""
    compiled = _compiled_or_fail()
    sc = _hit(240, 2.0, 0.5, 5e-4)
    runs = {}
    for impl in ("python", "compiled"):
        model = ms.build_model(sc.with_options(step_impl=impl))
        data = make_data(model)
        st, rs, kept = ms.initial_state(model, data), [], []
        for k in range(9):
            r = ms.step(model, data, st)
            st = r.state
            rs.append(r)
            if impl == "compiled" and k < 5:
                assert data.active_holder is not None  # not read back
            if k == 5:
                kept = data.active_rows
                assert data.active_holder is None
        runs[impl] = (rs, kept, compiled.counts(data))
    assert runs["compiled"][2]["contact"] == 9
    assert len(runs["python"][1]) >= 239 and runs["python"][1] == runs["compiled"][1]
    for a, b in zip(runs["python"][0], runs["compiled"][0]):
        assert _bits(a.state.q) == _bits(b.state.q) and _bits(a.state.u) == _bits(b.state.u)


@pytest.mark.parametrize("n", [256, 257])
def test_contact_space_below_and_above_its_scan_size_gives_the_python_bits(n):
    """src/step.cpp contact_space passes over every entry of M^-1 W and W'M^-1 W up to kScanEntries = 2^16 (nv m
    and m^2) and over their nonzeros, listed and sorted, above: the hit column of 256 beads (255 and 256 rows: 65,280
    and 65,536 entries, scanned) and of 257 (65,792: listed), compiled, gives the Python step's bits every step."""
    compiled = _compiled_or_fail()
    sc = _hit(n, 2.0, 0.5, 5e-4)
    runs = {}
    for impl in ("python", "compiled"):
        model = ms.build_model(sc.with_options(step_impl=impl))
        data, rs = _stepped(model, 8)
        runs[impl] = (rs, compiled.counts(data))
    assert runs["compiled"][1]["contact"] == 8
    assert {r.contacts.m for r in runs["python"][0]} == {n - 1, n}
    for a, b in zip(runs["python"][0], runs["compiled"][0]):
        for x, y in ((a.state.q, b.state.q), (a.state.u, b.state.u), (a.P, b.P), (a.qp.lam, b.qp.lam)):
            assert _bits(x) == _bits(y)
