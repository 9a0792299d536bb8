"""The compiled run loop (moreau_sim/compiled_run.py, src/run.cpp) against the Python run: the same arrays and
ledger figures bit for bit on every bundled scene (short runs), through checkpoints and resumes, and a metadata
entry saying which loop ran.

The Runner records what driver._Loop.account records per step, operation by operation: the ledger's
products (ledger.impact_terms's x'Mx and P.b) are summed in index order on both sides (sums.ordered, src/run.cpp
quad / odot; docs/theory.md §2.8), so that the sums are the same at every size on any CPU
(test_ledger_products_are_ordered).
A scene the compiled step does not take (compiled.unsupported) runs the Python loop; its meta says so and why.
Drives and prescribed motion run compiled (tests/test_compiled_rheonomic.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import moreau_sim as ms
import moreau_sim.compiled as compiled
from moreau_sim import compiled_run
from moreau_sim.checkpoint import Checkpoint
from moreau_sim.errors import SimulationInterrupted
from moreau_sim.trajectory import ARRAYS

from helpers import slow_cases

SCENES = sorted((Path(__file__).resolve().parent.parent / "scenes").glob("*.toml"))
MAX_STEPS = 400  # every scene: at most this many steps (the first impacts of the balls and the cradles)
DURATION = {"bouncing_ball": 1.0, "zeno_ball": 1.5, "newton_cradle_5": 0.3, "box_drop": 1.0, "vibrating_paddle": 0.6,
            "driven_paddle": 0.6}
MUST_RUN_COMPILED = {"bouncing_ball", "zeno_ball", "newton_cradle_5", "box_drop", "vibrating_paddle", "driven_paddle"}


def _arrays_differ(a, b) -> list[str]:
    def same(x, y):
        return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
    keys = set(a.arrays) | set(b.arrays)
    return sorted(k for k in keys if k not in a.arrays or k not in b.arrays or not same(a.arrays[k], b.arrays[k]))


def _run(sc, python_run: bool, **kw):
    return ms.simulate(ms.build_model(sc), progress=False, python_run=python_run, **kw)


@pytest.fixture(scope="module", autouse=True)
def _compiled():
    """The compiled step is built at install (test_compiled.py asserts it): missing, these tests fail."""
    assert compiled.available(), compiled.unavailable_reason()


def _short(path: Path, **options):
    sc = ms.load_scene(path)
    o = sc.options
    return sc.with_options(duration=DURATION.get(sc.name, min(o.duration, MAX_STEPS * o.dt)), **options)


@pytest.mark.parametrize("path", slow_cases(SCENES, {"alternating_stack_10"}, [p.stem for p in SCENES]))
def test_same_run_both_loops(path):
    """Every bundled scene the compiled loop takes gives the Python loop's arrays, status and ledger figures bit
    for bit; every other runs the Python loop, and its meta says why (its two runs would be the Python loop twice:
    tests/test_compiled.py compares those)."""
    sc = _short(path)
    why = compiled_run.unsupported(ms.build_model(sc), None)
    if why is not None:
        assert sc.name not in MUST_RUN_COMPILED
        run = _run(sc.with_options(duration=2 * sc.options.dt), False).meta["run"]
        assert run["loop"] == "python" and run["why"] == why
        return
    got = []
    for python_run in (True, False):
        try:
            got.append(_run(sc, python_run))
        except ms.SimulationError as exc:
            got.append(exc)
    ref, new = got
    assert type(ref) is type(new)
    if isinstance(ref, Exception):
        assert str(ref) == str(new)
        ref, new = ref.trajectory, new.trajectory
    assert ref.meta["run"]["loop"] == "python" and new.meta["run"]["loop"] == "compiled"
    assert _arrays_differ(ref, new) == []
    assert ref.meta["ledger"] == new.meta["ledger"]
    assert ref.meta["status"] == new.meta["status"] and ref.meta.get("invariants") == new.meta.get("invariants")
    if sc.name in MUST_RUN_COMPILED:
        assert new.meta["run"]["python_steps"] < new.meta["run"]["steps"]
    print(sc.name, new.meta["run"])


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("h", [1e-3, 2e-3])
@pytest.mark.parametrize("name,save_every", [("zeno_ball", 1), ("newton_cradle_5", 3), ("box_drop", 7)])
def test_same_run_over_e_and_h(name, save_every, e, h):
    """The same runs bit for bit over restitution, step size and sampling (save_every > 1: the ledger's terms
    accumulate between samples)."""
    sc = ms.load_scene(Path(__file__).resolve().parent.parent / "scenes" / f"{name}.toml")
    sc = sc.with_options(restitution=e, dt=h, duration=min(sc.options.duration, 500 * h), save_every=save_every)
    ref, new = _run(sc, True), _run(sc, False)
    assert new.meta["run"]["loop"] == "compiled"
    assert _arrays_differ(ref, new) == [] and ref.meta["ledger"] == new.meta["ledger"]
    assert ref.meta["status"] == new.meta["status"]


@pytest.mark.parametrize("name,steps", [("zeno_ball", 900), ("newton_cradle_5", 300)])
def test_resume_in_a_compiled_run(tmp_path, name, steps):
    """A checkpoint in the middle of a compiled run and a resume from it give the uninterrupted Python run's
    arrays and ledger."""
    sc = ms.load_scene(Path(__file__).resolve().parent.parent / "scenes" / f"{name}.toml")
    h = sc.options.dt
    sc = sc.with_options(duration=steps * h, save_every=2)
    ref = _run(sc, True)
    path = tmp_path / "c.npz"
    full = _run(sc, False, checkpoint=Checkpoint(path=path, every=(steps // 3 + 1) * h, keep=True))
    ck = ms.load_trajectory(path).meta["checkpoint"]
    assert 0 < ck["steps"] < steps
    resumed = _run(sc, False, checkpoint=Checkpoint(path=path, resume=True))
    assert full.meta["run"]["loop"] == resumed.meta["run"]["loop"] == "compiled"
    for run in (full, resumed):
        assert _arrays_differ(ref, run) == [] and run.meta["ledger"] == ref.meta["ledger"]


def test_an_interrupt_in_a_compiled_run_resumes_bitwise(tmp_path, monkeypatch):
    """Ctrl-C in the middle of a compiled run (at one of its polls) stops it with the samples so far; the
    resume from its last checkpoint gives the uninterrupted Python run's arrays and ledger."""
    sc = ms.load_scene(Path(__file__).resolve().parent.parent / "scenes" / "zeno_ball.toml")
    h = sc.options.dt
    sc = sc.with_options(duration=1000 * h)
    ref = _run(sc, True)
    advance = compiled_run.CompiledRun.advance
    calls = [0]

    def interrupted(self, t_stop):
        calls[0] += 1
        if calls[0] == 9:
            raise KeyboardInterrupt
        return advance(self, t_stop)

    monkeypatch.setattr(compiled_run, "POLL_SECONDS", 0.0)  # a poll every 64 steps
    monkeypatch.setattr(compiled_run.CompiledRun, "advance", interrupted)
    path = tmp_path / "c.npz"
    with pytest.raises(SimulationInterrupted) as err:
        _run(sc, False, checkpoint=Checkpoint(path=path, every=100 * h))
    assert 0 < len(err.value.trajectory.arrays["t"]) < len(ref.arrays["t"]) and path.exists()
    monkeypatch.setattr(compiled_run.CompiledRun, "advance", advance)
    resumed = _run(sc, False, checkpoint=Checkpoint(path=path, resume=True))
    assert resumed.meta["run"]["loop"] == "compiled"
    assert _arrays_differ(ref, resumed) == [] and resumed.meta["ledger"] == ref.meta["ledger"]


def test_spilled_compiled_run(tmp_path, monkeypatch):
    """Spilling to disk (a small block: the columns spill many times) leaves the arrays unchanged."""
    from moreau_sim import columns

    sc = ms.load_scene(Path(__file__).resolve().parent.parent / "scenes" / "newton_cradle_5.toml")
    sc = sc.with_options(duration=0.4)
    ref = _run(sc, True)
    monkeypatch.setattr(columns, "SPILL_BYTES", 4096)
    new = _run(sc, False, spill=tmp_path)
    assert new.meta["run"]["loop"] == "compiled"
    assert _arrays_differ(ref, new) == [] and ref.meta["ledger"] == new.meta["ledger"]


@pytest.mark.parametrize("strict", [False, True])
def test_a_run_that_breaks_an_invariant(strict):
    """slider_crank_clearance without position correction breaks the penetration invariant (flagged: its sliding
    corner drifts into the guide each step, docs/theory.md §2.5): the step where a check reports goes to the Python
    loop (its message, its strict error), the rest stay compiled; the same arrays, violations, status."""
    sc = ms.load_scene(Path(__file__).resolve().parent.parent / "scenes" / "slider_crank_clearance.toml")
    sc = sc.with_options(position_correction="none")
    got = []
    for python_run in (True, False):
        try:
            got.append(_run(sc, python_run, strict=strict))
        except ms.SimulationError as exc:
            assert strict
            got.append(exc)
    ref, new = got
    if strict:
        assert str(ref) == str(new)
        ref, new = ref.trajectory, new.trajectory
    else:
        assert ref.meta["status"] == new.meta["status"] == "flagged"
        assert ref.meta["invariants"] == new.meta["invariants"]
        assert new.meta["run"]["python_steps"] <= 2 * len(new.meta["invariants"])
    assert _arrays_differ(ref, new) == [] and ref.meta["ledger"] == new.meta["ledger"]
    assert new.meta["run"]["loop"] == "compiled" and ref.meta["status"] == new.meta["status"]


def test_the_python_step_in_between(monkeypatch):
    """Steps handed back to Python (here at every 3rd call of the Runner) leave the run unchanged."""
    sc = ms.load_scene(Path(__file__).resolve().parent.parent / "scenes" / "newton_cradle_5.toml")
    sc = sc.with_options(duration=0.6)
    ref = _run(sc, True)
    advance = compiled_run.CompiledRun.advance
    calls = [0]

    def sometimes(self, t_stop):
        calls[0] += 1
        return None if calls[0] % 3 == 0 else advance(self, t_stop)

    monkeypatch.setattr(compiled_run, "POLL_SECONDS", 0.0)  # return every 64 steps
    monkeypatch.setattr(compiled_run.CompiledRun, "advance", sometimes)
    new = _run(sc, False)
    assert new.meta["run"]["loop"] == "compiled" and new.meta["run"]["python_steps"] > 0
    assert _arrays_differ(ref, new) == [] and ref.meta["ledger"] == new.meta["ledger"]


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_ledger_products_are_ordered(e):
    """ledger.impact_terms's products, which src/run.cpp's quad and odot sum alike, are sums in index order with
    one rounding each, at every size (sums.ordered's small and large paths): x'Mx as (x'M)x, and P.b."""
    from moreau_sim.ledger import impact_terms

    def dot(a, b):
        s = a[0] * b[0]
        for k in range(1, len(a)):
            s = s + a[k] * b[k]
        return s + 0.0

    def quad(M, x):
        return dot([dot(x, M[:, j]) for j in range(len(x))], x)

    rng = np.random.default_rng(0)
    for n in [*range(1, 20), 63, 64, 65, 80, 120]:
        A = rng.standard_normal((n, n))
        M = A @ A.T
        if n > 64:  # a banded M (many bodies): sums.ordered's large path sums over the nonzero entries only
            i = np.arange(n)
            M = np.where(abs(i[:, None] - i[None, :]) < 6, M, 0.0)
        v_free, v, u_k, u_next = rng.standard_normal((4, n))
        P, b = rng.random(n), rng.standard_normal(n)
        u_plus = u_next - e * (v_free - u_k)
        T_minus, T_plus, law = impact_terms(M, v_free, v, u_k, u_next, e, P, b)
        assert T_minus == 0.5 * quad(M, v_free) and T_plus == 0.5 * quad(M, u_plus)
        assert law == 0.5 * (1.0 - e * e) * quad(M, v_free - v) - dot(P, b)


def test_the_meta_says_which_loop():
    sc = ms.load_scene(Path(__file__).resolve().parent.parent / "scenes" / "bouncing_ball.toml").with_options(
        duration=0.05)
    assert _run(sc, False).meta["run"]["loop"] == "compiled"
    py = _run(sc.with_options(step_impl="python"), False).meta["run"]
    assert py["loop"] == "python" and py["why"] == "step_impl python"
    assert set(ARRAYS) <= set(_run(sc, False).arrays)
