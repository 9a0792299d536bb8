"""The compiled run loop (src/run.cpp) on scenes with pairs of two boxes: their detection carries state from one
step to the next (coal's cached GJK guesses, the pairs with contacts: data.Data.warm_start), which a step the
Runner undoes (a check that fires) must leave as it found it, so that the Python step retaking it starts where
the Python run would. The same arrays, ledger and status bit for bit as the Python run (docs/theory.md §2.8, §9),
with the Runner taking steps, and through a run whose checks fire (steps undone and handed back)."""

from __future__ import annotations

from pathlib import Path

import pytest

import moreau_sim as ms
import moreau_sim.compiled as compiled
from moreau_sim import compiled_run
from moreau_sim.checkpoint import Checkpoint
from moreau_sim.invariants import Invariants

from helpers import slow_cases

SCENES = Path(__file__).resolve().parent.parent / "scenes"
# scene: steps (the scene's whole run where it is short)
RUNS = {"box_stack_5": None, "box_stack_10": None, "alternating_stack_10": None, "heavy_on_light_box_100": 300,
        "heavy_on_light_box_1000": 300, "blocks_corner": None, "spinning_box": 1500}
# every step of alternating_stack_10 goes to the Python step (a vertex on a box's surface: the compiled step hands it
# back), so its compiled run is the Python run's steps between the Runner's tries
PYTHON_STEPS = {"alternating_stack_10"}


def _arrays_differ(a, b) -> list[str]:
    def same(x, y):
        return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
    keys = set(a.arrays) | set(b.arrays)
    return sorted(k for k in keys if k not in a.arrays or k not in b.arrays or not same(a.arrays[k], b.arrays[k]))


def _scene(name: str, steps: int | None, **options) -> ms.Scene:
    sc = ms.load_scene(SCENES / f"{name}.toml")
    if steps is not None:
        sc = sc.with_options(duration=steps * sc.options.dt)
    return sc.with_options(**options) if options else sc


def _both(sc, check=None):
    """The Python run and the compiled run of the scene (each with a check of its own: check(model) or the
    default invariants)."""
    out = []
    for python_run in (True, False):
        model = ms.build_model(sc)
        out.append(ms.simulate(model, progress=False, python_run=python_run,
                               check=None if check is None else check(model)))
    return out


@pytest.fixture(scope="module", autouse=True)
def _compiled():
    assert compiled.available(), compiled.unavailable_reason()


@pytest.mark.parametrize("name", slow_cases(list(RUNS), {"alternating_stack_10"}))
def test_box_scenes_run_compiled_and_identical(name):
    """Each scene's run (its whole run where short) gives the Python run's arrays, ledger and status bit for bit,
    and the compiled loop took most of its steps (where the compiled step takes them)."""
    sc = _scene(name, RUNS[name])
    assert compiled_run.unsupported(ms.build_model(sc), None) is None
    ref, new = _both(sc)
    assert ref.meta["run"]["loop"] == "python" and new.meta["run"]["loop"] == "compiled"
    assert _arrays_differ(ref, new) == []
    assert ref.meta["ledger"] == new.meta["ledger"]
    assert ref.meta["status"] == new.meta["status"] and ref.meta.get("invariants") == new.meta.get("invariants")
    run = new.meta["run"]
    if name not in PYTHON_STEPS:
        assert run["python_steps"] < run["steps"] // 2, run


def _touchy(model):
    """The run's invariants with no tolerance on the energy's gain and the ledger's residual: they fire at the
    first round-off, and the Runner undoes those steps and hands them to the Python run."""
    check = Invariants(model, rtol=0.0)
    check.rel = check.rel_ledger = 0.0
    return check


@pytest.mark.parametrize("name,steps", [("box_stack_5", None), ("box_stack_10", 100), ("heavy_on_light_box_100", 300),
                                        ("blocks_corner", None)])
def test_undone_steps_leave_the_detection_as_it_was(name, steps):
    """Checks that fire on box scenes: each step where one reports is taken by the Stepper, undone (the GJK
    guesses, the warm start of the box pairs' detection restored) and retaken by the Python run; the arrays, the
    violations and the ledger are the Python run's bit for bit."""
    sc = _scene(name, steps)
    ref, new = _both(sc, _touchy)
    assert new.meta["run"]["loop"] == "compiled"
    assert ref.meta["status"] == new.meta["status"] == "flagged"
    assert ref.meta["invariants"] == new.meta["invariants"]
    # every step of these runs is the compiled step's (test_box_scenes_run_compiled_and_identical): the Python run's
    # steps are the ones undone (a report) and those it takes before the Runner tries again
    assert new.meta["run"]["python_steps"] > 0 and len(new.meta["invariants"]) > 0
    assert _arrays_differ(ref, new) == [] and ref.meta["ledger"] == new.meta["ledger"]


@pytest.mark.parametrize("name,steps", [("box_stack_5", None), ("heavy_on_light_box_100", 300)])
def test_resume_in_a_compiled_box_run(tmp_path, name, steps):
    """A checkpoint in the middle of a compiled run of boxes saves the detection's warm start as the Runner left it
    (data.Data.warm_start); the resume from it gives the uninterrupted Python run's arrays and ledger."""
    sc = _scene(name, steps)
    n = round(sc.options.duration / sc.options.dt)
    ref = ms.simulate(ms.build_model(sc), progress=False, python_run=True)
    path = tmp_path / "c.npz"
    every = (n // 3 + 1) * sc.options.dt
    full = ms.simulate(ms.build_model(sc), progress=False, checkpoint=Checkpoint(path=path, every=every, keep=True))
    ck = ms.load_trajectory(path).meta["checkpoint"]
    assert 0 < ck["steps"] < n and ck["warm_start"]["pairs"]
    resumed = ms.simulate(ms.build_model(sc), progress=False, checkpoint=Checkpoint(path=path, resume=True))
    assert full.meta["run"]["loop"] == resumed.meta["run"]["loop"] == "compiled"
    for run in (full, resumed):
        assert _arrays_differ(ref, run) == [] and run.meta["ledger"] == ref.meta["ledger"]
