"""The Recorder (moreau_sim.recording): columns grow past their first capacity, the arrays follow
trajectory.ARRAYS (names, order, dtypes, shapes), percussions are logged above LOG_RELATIVE with new
impacts flagged."""

import json
import subprocess
import sys

import numpy as np

import moreau_sim as ms
from moreau_sim import trajectory
from moreau_sim.recording import LOG_RELATIVE

from helpers import SCENES, scene


def test_columns_grow_and_keep_every_sample():
    model = ms.build_model(scene("bouncing_ball"))
    rec = ms.Recorder(model, ms.make_data(model), n_samples=1)
    for k in range(100):
        rec.sample(ms.State(0.01 * k, np.array([1.0 + k]), np.array([-k / 10])), work=-k, corr=k / 2, n_contacts=k % 3)
    a = rec.arrays()
    assert rec.n == 100 and len(a["t"]) == 100
    np.testing.assert_array_equal(a["q"][:, 0], 1.0 + np.arange(100))
    np.testing.assert_array_equal(a["contact_work"], -np.arange(100.0))
    np.testing.assert_array_equal(a["n_contacts"], np.arange(100) % 3)
    np.testing.assert_allclose(a["potential_energy"], 9.81 * (1.0 + np.arange(100)), rtol=1e-15)
    np.testing.assert_array_equal(a["gap"][:, 0], 0.9 + np.arange(100))


def test_arrays_follow_the_schema():
    model = ms.build_model(scene("box_drop"))
    rec = ms.Recorder(model, ms.make_data(model))
    rec.sample(ms.initial_state(model), 0.0, 0.0, 0)
    a = rec.arrays()
    assert tuple(a) == trajectory.ARRAYS
    sizes = {"nq": model.nq, "nv": model.nv, "pairs": len(model.pairs)}
    schema = {**trajectory.SAMPLES, **trajectory.LOG, **trajectory.BRANCHES, **trajectory.CANDIDATES,
              **trajectory.IMPACTS}
    for name, (dtype, shape) in schema.items():
        assert a[name].dtype == np.dtype(dtype), name
        assert a[name].shape[1:] == tuple(sizes.get(d, d) for d in shape), name
    assert len(a["t"]) == 1 and len(a["log_P"]) == 0 and len(a["branch_step"]) == 0


def test_percussions_are_logged_above_the_threshold_with_new_impacts_flagged():
    """The cradle's first step: 4 contacts; a percussion below LOG_RELATIVE of the step's largest is
    not logged; a contact already pushing in the previous step is not a new impact."""
    model = ms.build_model(scene("newton_cradle_5"))
    data = ms.make_data(model)
    r = ms.step(model, data, ms.initial_state(model))
    rec = ms.Recorder(model, data)
    P = r.P.copy()
    P[1] = 0.5 * LOG_RELATIVE * P.max()
    first = (int(r.contacts.pair[0]), int(r.contacts.kind[0]), int(r.contacts.feature[0]))
    keys = rec.log_percussions(1, 5e-4, r.contacts, P, r.gamma_minus, r.gamma_plus, previous={first})
    a = rec.arrays()
    assert keys == r.contacts.keys() and len(keys) == 4
    np.testing.assert_array_equal(a["log_pair"], r.contacts.pair[[0, 2, 3]])
    np.testing.assert_array_equal(a["log_impact"], [False, True, True])
    np.testing.assert_array_equal(a["log_P"], P[[0, 2, 3]])
    assert np.all(a["log_step"] == 1) and np.all(a["log_t"] == 5e-4)


MEMORY_PROBE = """
import json, resource, sys
import moreau_sim as ms
sc = ms.load_scene(sys.argv[1]).with_options(step_impl="compiled")
ms.simulate(ms.build_model(sc.with_options(duration=1.0)), progress=False)  # libraries loaded and warm
model = ms.build_model(sc.with_options(duration=float(sys.argv[2])))
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
traj = ms.simulate(model, progress=False)
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"growth": (peak - base) * 1024, "data": sum(a.nbytes for a in traj.arrays.values()),
                  "rows": len(traj.log_P), "samples": len(traj.t)}))
"""


def test_memory_is_proportional_to_the_data():
    """A resting ball over 10^5 steps (a percussion logged every step): the peak RSS grows by the
    recorded arrays and little more (the recorder copies nothing while recording; the issue's
    first recorder grew ~1 KB per logged percussion, 8x its 121-byte row). A byte bound on
    ru_maxrss, not a timing; run in a fresh process so that nothing else moves the peak."""
    r = subprocess.run([sys.executable, "-c", MEMORY_PROBE, str(SCENES / "zeno_ball.toml"), "100"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads(r.stdout)
    assert m["rows"] > 90_000 and m["samples"] == 100_001
    assert m["growth"] <= 1.5 * m["data"] + 8e6, m  # data: 19 MB; allocator slack and one joined column
