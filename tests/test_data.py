"""A run starts from a fresh Data (data.Data.reset, driver.run_data; docs/theory.md §2.8): on a Data that an
earlier run used, or on one of the model's spares, a run takes the steps of a run on a new Data, bit for bit,
under every integrator, on every bundled scene; without the reset, the warm starts an earlier run left part it
from that run (the edge); a Data counts the steps of all its runs; a model keeps its runs' Datas up to SPARE_NV
velocities."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import compiled
from moreau_sim.data import make_data, spares
from moreau_sim.driver import SPARE_NV, drive, run_data
from moreau_sim.time_stepping import TimeStepping

from helpers import REFUSED, ROOT, scene

_spec = importlib.util.spec_from_file_location("invariant_table", ROOT / "scripts" / "invariant_table.py")
table = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(table)

SHORT = {"time-stepping": 0.05, "adaptive": 0.03, "event-driven": 0.03}  # [s] the longest runs here (capped table runs)
SLOW = ("column_of_beads", "alternating_stack_10", "quadruped", "solo", "panda", "box_stack_10",
        "heavy_on_light_box_10000")


def _same(a: ms.Trajectory, b: ms.Trajectory) -> None:
    assert a.meta["status"] == b.meta["status"]
    assert a.arrays.keys() == b.arrays.keys()
    for k in a.arrays:
        x, y = np.asarray(a.arrays[k]), np.asarray(b.arrays[k])
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), k


def _model(path, integ):
    sc = ms.load_scene(path)
    return ms.build_model(sc.with_options(integrator=integ, duration=min(table.duration(path, integ), SHORT[integ])))


def _case(path, integ):
    marks = [pytest.mark.slow] if integ != "time-stepping" and any(s in path.stem for s in SLOW) else []
    return pytest.param(path, integ, marks=marks, id=f"{path.stem}-{integ}")


@pytest.mark.parametrize("path, integ", [_case(p, i) for p in table.SCENES for i in table.INTEGRATORS
                                         if i == "time-stepping" or p.stem not in REFUSED])
def test_a_run_on_a_used_data_or_a_spare_takes_the_steps_of_a_run_on_a_new_data(path, integ):
    model = _model(path, integ)
    new = ms.simulate(model, data=make_data(model), progress=False)
    used = make_data(model)
    ms.simulate(model, data=used, progress=False)  # leaves its warm starts, guesses and Stepper in `used`
    _same(ms.simulate(model, data=used, progress=False), new)
    for _ in range(2):  # the model's spares (the runs' and their checks'), reset
        _same(ms.simulate(model, progress=False), new)


@pytest.mark.parametrize("name", ["box_stack_5", "panda_table"])
def test_without_the_reset_a_used_data_parts_the_run_from_a_new_datas(name):
    """The edge: the same time-stepping run driven on a used Data (driver.drive, no run_data) takes other steps
    (the detection's and the projection's warm starts, coal's guesses), and the same once the Data is reset."""
    model = ms.build_model(scene(name, duration=0.2))
    st = ms.initial_state(model)

    def run(data):
        return drive(TimeStepping(model, data, st), model, data, capacity=1 + model.options.n_steps)

    new = run(make_data(model))
    used = make_data(model)
    run(used)
    parted = run(used).arrays
    assert any(np.asarray(parted[k]).tobytes() != np.asarray(new.arrays[k]).tobytes() for k in new.arrays)
    run(used)
    _same(run(used.reset(compiled.guess_reset())), new)
    run(used)
    _same(run(used.reset()), new)  # Python's reset of coal's guesses (the extension absent): the same


def test_a_data_counts_the_steps_of_all_its_runs():
    model = ms.build_model(scene("bouncing_ball", duration=0.3, step_impl="compiled"))
    data = make_data(model)
    ms.simulate(model, data=data, progress=False)
    once = dict(compiled.counts(data))
    assert sum(once.values()) == model.options.n_steps
    ms.simulate(model, data=data, progress=False)
    assert dict(compiled.counts(data)) == {k: 2 * v for k, v in once.items()}


@pytest.mark.parametrize("n, kept", [(SPARE_NV, True), (SPARE_NV + 1, False)])
def test_a_model_keeps_its_runs_datas_up_to_spare_nv_velocities(n, kept):
    """A column of n beads (one velocity each): its run's Data goes to its spares up to SPARE_NV velocities."""
    b = ms.SceneBuilder(f"column_{n}", folder=ROOT / "scenes", dt=1e-3, duration=0.002)
    for k in range(n):
        b.add_body(f"bead{k}", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1), q0=[0.1 + 0.2 * k])
    b.add_halfspace("ground")
    model = ms.build_model(b.build())
    with run_data(model) as data:
        pass
    assert model.nv == n and (data in spares(model)) is kept


def test_runs_of_one_model_in_threads_each_take_their_own_data_and_the_same_steps():
    """Four runs of one model at once, in two threads (the spares: pop and append, one Data a run)."""
    import threading

    model = ms.build_model(scene("box_stack_5", duration=0.1))
    new = ms.simulate(model, data=make_data(model), progress=False)
    got, errors = [], []

    def work():
        try:
            for _ in range(2):
                got.append(ms.simulate(model, progress=False))
        except Exception as exc:  # (raised again below, in the test's thread)
            errors.append(exc)

    threads = [threading.Thread(target=work) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(got) == 4
    for traj in got:
        _same(traj, new)
    assert len({id(d) for d in spares(model)}) == len(spares(model))  # no Data handed back twice


def test_a_run_after_one_that_failed_midway_on_the_same_data_takes_the_steps_of_a_new_one():
    """A run stopped by an error leaves its Data as the error found it (a phase under way, warm starts, the Stepper's
    sets); the next run on it, given or kept by the model, resets it all the same."""
    from moreau_sim.adaptive import simulate_adaptive
    from moreau_sim.errors import SimulationError

    model = ms.build_model(scene("rocking_block", integrator="adaptive", duration=0.5))
    new = ms.simulate(model, data=make_data(model), progress=False)
    used = make_data(model)
    for data in (used, None):
        with pytest.raises(SimulationError, match="more than 20 events"):
            simulate_adaptive(model, data=data, max_events=20)
        _same(ms.simulate(model, data=data, progress=False), new)
