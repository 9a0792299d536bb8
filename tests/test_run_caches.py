"""What a run keeps per model for the next run of it (model._STARTS: the start checks passed; data.spares:
the runs' and their checks' Datas) changes no bit: two runs of one model, and runs of two models interleaved, give the
arrays and meta (but the timings) of runs of freshly built models, under each integrator; a start the checks refuse
is refused again (nothing is kept for it)."""

from __future__ import annotations

import dataclasses
import gc
import weakref

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import model as model_module
from moreau_sim.data import make_data, spares
from moreau_sim.errors import SceneError

from helpers import scene

INTEGRATORS = ["adaptive", "event-driven", "time-stepping"]
TIMINGS = {"wall_seconds", "cpu_seconds", "us_per_step", "created"}  # the meta that says when and how long


def _model(name: str, integrator: str, **options):
    return ms.build_model(scene(name, integrator=integrator, **options))


def _untimed(meta):
    if isinstance(meta, dict):
        return {k: _untimed(v) for k, v in meta.items() if k not in TIMINGS}
    return meta


def _same(a: ms.Trajectory, b: ms.Trajectory) -> None:
    assert a.arrays.keys() == b.arrays.keys()
    for k in a.arrays:
        assert a.arrays[k].dtype == b.arrays[k].dtype and a.arrays[k].tobytes() == b.arrays[k].tobytes(), k
    assert _untimed(a.meta) == _untimed(b.meta)


@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("e", [0.5, 1.0])
def test_runs_of_one_model_and_of_two_interleaved_give_the_bits_of_fresh_runs(integrator, e):
    names = ("bouncing_ball", "newton_cradle_5")
    fresh = {n: ms.simulate(_model(n, integrator, restitution=e, duration=0.3), progress=False) for n in names}
    kept = {n: _model(n, integrator, restitution=e, duration=0.3) for n in names}
    for _ in range(2):  # the second round takes what the first kept
        for n in names:
            _same(ms.simulate(kept[n], progress=False), fresh[n])
    for n in names:
        assert model_module._STARTS.get(kept[n]) == kept[n].q0.tobytes()
    if integrator != "time-stepping":  # the event integrators' smooth points need the checks' own Data
        assert spares(kept["bouncing_ball"])


def test_a_start_the_checks_refuse_is_refused_at_every_run():
    ok = _model("bouncing_ball", "adaptive", contact_tolerance=1e-6)
    inside = dataclasses.replace(ok, q0=np.zeros(ok.nq))  # the ball's centre on the ground: a radius inside
    for _ in range(2):
        with pytest.raises(SceneError, match="inside"):
            ms.initial_state(inside, make_data(inside))
    assert model_module._STARTS.get(inside) is None


@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_a_model_a_run_kept_caches_of_goes_when_dropped(integrator):
    """What a run keeps for the next run of a model (the checks' spare Data, the start checks, the per-model tables
    of the event integrators) does not keep the model alive: dropped, it is collected (a Data refers to its model,
    so a table keyed weakly by the model but holding its Data would keep every model ever run)."""
    m = _model("newton_cradle_5", integrator, duration=0.2)
    assert ms.simulate(m, progress=False).meta["status"] == "complete"
    assert integrator == "time-stepping" or spares(m)
    gone = weakref.ref(m)
    del m
    gc.collect()
    assert gone() is None
