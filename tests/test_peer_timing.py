"""The peers' per-step timers (timing_repeats, what benchmarks.compiled_costs reads): the timed
runs leave the trajectory bit for bit as it is, and each step's contact count is the peer's own
physics: a step with no contact is free flight (u' = u + h g), a step with one is not. Never timings."""

import numpy as np
import pytest

import moreau_sim as ms

from benchmarks import compiled_costs, scene_path
from benchmarks.peers import available, run
from benchmarks.spec import make_spec

PEERS = [pytest.param(p, marks=pytest.mark.skipif(why is not None, reason=str(why)))
         for p, why in available().items() if p in compiled_costs.PEERS]


@pytest.mark.parametrize("peer", PEERS)
@pytest.mark.parametrize("e, h", [(0.8, 1e-3), (0.5, 2e-3)])
def test_timed_run_is_the_run_and_its_contact_steps_are_the_impacts(peer, e, h):
    spec = make_spec(ms.build_model(ms.load_scene(scene_path("bouncing_ball"))), e=e, h=h, T=1.2)
    plain = run(peer, spec)
    timed = run(peer, spec, timing_repeats=1)
    u = plain["bodies"][0]["u"]
    assert np.array_equal(u, timed["bodies"][0]["u"]) and np.array_equal(plain["bodies"][0]["q"],
                                                                         timed["bodies"][0]["q"])
    tm = timed["timing"]
    n = len(u) - 1
    contacts = np.asarray(tm["contacts"])
    assert len(tm["step_us"]) == n == len(contacts) and np.all(np.asarray(tm["step_us"]) > 0)
    assert tm["wall_seconds"] > 0
    g = float(np.dot(spec["gravity"], spec["bodies"][0]["axis"]))
    jump = np.abs(np.diff(u) - g * h)
    assert jump[contacts == 0].max() < 1e-12  # free flight
    assert (contacts > 0).any() and jump[contacts > 0].max() > 0.1  # the impact acts in a contact step


def test_phases_of_a_run():
    c = [0, 0, 1, 2, 0, 1, 1, 1, 0, 3]
    assert np.flatnonzero(compiled_costs.phase(c, "flight")).tolist() == [0, 1, 4, 8]
    assert np.flatnonzero(compiled_costs.phase(c, "contact")).tolist() == [2, 3, 5, 6, 7, 9]
    assert np.flatnonzero(compiled_costs.phase(c, "late-contact")).tolist() == [7, 9]  # the last third
