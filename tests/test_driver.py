"""The one driver of every integrator (moreau_sim/driver.py): the invariant hook sees the start,
every accepted point and every sample, and keeps what it reports in meta; the progress bar moves
with wall time for every integrator."""

from __future__ import annotations

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import driver
from moreau_sim.protocol import Report

from helpers import scene

INTEGRATORS = ["time-stepping", "adaptive", "event-driven"]


@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("e", [0.0, 0.5, 0.9])
def test_the_invariant_hook_sees_every_point_and_records_violations(integrator, e):
    """A hook that flags nothing leaves meta alone (and the ball gains no energy); one that wants
    the ball never below its initial height flags every sample
    after the start, in meta["invariants"], and the run still ends with the same arrays, flagged."""
    model = ms.build_model(scene("bouncing_ball", duration=0.6, restitution=e, integrator=integrator))
    seen = {"start": 0, "point": 0, "sample": 0, "end": 0}

    def count(where, state, rep, rec):
        seen[where] += 1
        assert (rep is None) == (where != "point") and (rep is None or isinstance(rep, Report))
        return None

    quiet = ms.simulate(model, progress=False, check=count)
    assert seen["start"] == seen["end"] == 1 and seen["sample"] == len(quiet.t) and seen["point"] >= 1
    assert "invariants" not in quiet.meta
    E = quiet.arrays["kinetic_energy"] + quiet.arrays["potential_energy"]
    assert E.max() <= E[0] + 1e-9 * abs(E[0])  # the law never gains energy (docs/theory.md §1.4)

    h0 = float(quiet.q[0, -1])

    def never_below_start(where, state, rep, rec):
        if where == "sample" and state.q[-1] < h0:
            return {"t": state.t, "what": "below the initial height"}
        return None

    flagged = ms.simulate(model, progress=False, check=never_below_start)
    below = np.flatnonzero(quiet.q[:, -1] < h0)
    assert [v["t"] for v in flagged.meta["invariants"]] == quiet.t[below].tolist()
    assert quiet.complete and flagged.meta["status"] == "flagged" and np.array_equal(flagged.q, quiet.q)


@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_progress_moves_with_wall_time(monkeypatch, capsys, integrator):
    """Refreshed at most every PROGRESS_EVERY of wall time (0 here: at every step), whatever a step costs;
    time-stepping counts steps, the event integrators simulated seconds."""
    monkeypatch.setattr(driver, "_PROGRESS_DELAY", 0.0)
    monkeypatch.setattr(driver, "PROGRESS_EVERY", 0.0)
    model = ms.build_model(scene("bouncing_ball", duration=0.5, integrator=integrator))
    ms.simulate(model, progress=True)
    err = capsys.readouterr().err
    total = f"/{model.options.n_steps} step" if integrator == "time-stepping" else "/0.5 s"
    assert total in err and "100%" in err


@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_state_dict_round_trips_through_json(integrator):
    """Every integrator's state after some steps survives JSON and load_state_dict unchanged (what a
    checkpoint stores; the bit-identical resume itself is tests/test_checkpoint.py's)."""
    import json

    from moreau_sim.adaptive import AdaptiveRun
    from moreau_sim.event_driven import EventDrivenRun
    from moreau_sim.time_stepping import TimeStepping

    model = ms.build_model(scene("rocking_block", duration=0.3, restitution=0.5, integrator=integrator))

    def make():
        data, st = ms.make_data(model), ms.initial_state(model)
        if integrator == "time-stepping":
            return TimeStepping(model, data, st)
        if integrator == "adaptive":
            return AdaptiveRun(model, data, 0.5, 1e-8, 1e-10, 6, 1.0, 10 ** 6, state=st, t_end=0.3)
        return EventDrivenRun(model, data, 0.5, 1e-12, 1e-12, "DOP853", 1e-2, 10 ** 5, state=st, t_end=0.3)

    a = make()
    for _ in range(5):
        a.step()
    d = json.loads(json.dumps(a.state_dict()))
    b = make()
    b.load_state_dict(d)
    assert b.state_dict() == a.state_dict() and b.position() == a.position()
    assert np.array_equal(b.state.q, a.state.q) and np.array_equal(b.state.u, a.state.u)


@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_the_run_loop_cpu_time_is_in_meta_and_the_summary(integrator):
    """meta["run"]["cpu_seconds"]: the run loop's CPU time, within the CPU time of the whole ms.simulate call (which
    also builds the run and assembles the trajectory), and no more than the process used; the summary carries it."""
    import time

    model = ms.build_model(scene("bouncing_ball", duration=1.0, restitution=0.8, integrator=integrator))
    c0 = time.process_time()
    traj = ms.simulate(model, progress=False)
    whole = time.process_time() - c0
    cpu = traj.meta["run"]["cpu_seconds"]
    assert isinstance(cpu, float) and 0.0 < cpu <= whole
    assert ms.summary(traj)["cpu_seconds"] == cpu and "CPU" in str(ms.summary(traj))
