"""The loop (moreau_sim.simulate): sample times without drift, save_every sampling with the ledger
summed over the skipped steps, run() as load + override + build + simulate, the run's metadata and
summary. (Errors naming the step and time: test_inputs.py.)"""

import numpy as np
import pytest

import moreau_sim as ms

from helpers import SCENES, run, scene


def test_sample_times_are_k_h_exactly():
    """t_k = k h computed from k (not summed), so 10000 steps of 1e-4 s end at exactly 1.0 s."""
    traj = run("bouncing_ball", dt=1e-4, duration=1.0)
    np.testing.assert_array_equal(traj.t, np.arange(10001) * 1e-4)
    assert traj.t[-1] == 1.0


@pytest.mark.parametrize("every", [7, 10])
def test_save_every_samples_the_same_run(every):
    """save_every = N: the samples of the N = 1 run at steps N, 2N, ... and the last step, bit for bit;
    contact work and correction energy summed over the steps since the previous sample."""
    full = run("bouncing_ball", restitution=0.0, dt=1e-2, duration=1.0)
    part = run("bouncing_ball", restitution=0.0, dt=1e-2, duration=1.0, save_every=every)
    n = len(full.t) - 1
    idx = np.r_[0:n + 1:every, n] if n % every else np.r_[0:n + 1:every]
    for k in ("t", "q", "u", "kinetic_energy", "gap", "n_contacts"):
        np.testing.assert_array_equal(part.arrays[k], full.arrays[k][idx], err_msg=k)
    for k in ("contact_work", "correction_energy"):
        sums = [full.arrays[k][a + 1:b + 1].sum() for a, b in zip(idx[:-1], idx[1:])]
        np.testing.assert_allclose(part.arrays[k][1:], sums, rtol=1e-14, atol=1e-15, err_msg=k)
    assert full.correction_energy.sum() > 0 and full.contact_work.sum() < 0
    np.testing.assert_array_equal(part.log_P, full.log_P)  # the log keeps every step


def test_run_is_load_override_build_simulate():
    a = ms.run(SCENES / "box_drop.toml", dt=2e-3, duration=0.5, restitution=0.3, bias="explicit")
    b = ms.simulate(ms.build_model(scene("box_drop", dt=2e-3, duration=0.5, restitution=0.3, bias="explicit")),
                    progress=False)
    for k in a.arrays:
        np.testing.assert_array_equal(a.arrays[k], b.arrays[k], err_msg=k)
    assert a.meta["options"] == b.meta["options"]
    assert a.meta["options"]["restitution"] == 0.3 and a.meta["options"]["bias"] == "explicit"


def test_metadata_and_summary_describe_the_run():
    traj = run("bouncing_ball", duration=1.5)
    meta = traj.meta
    assert meta["status"] == "complete" and meta["run"]["steps"] == 1500
    assert meta["scene"]["name"] == "bouncing_ball" and "[simulation]" in meta["scene"]["toml"]
    assert meta["options"] == scene("bouncing_ball", duration=1.5).options.to_dict()
    s = ms.summary(traj)
    E = traj.total_energy
    assert s["steps"] == 1500 and s["samples"] == 1501 and s["t_end"] == 1.5
    assert s["impacts"] == traj.impacts == int(traj.log_impact.sum()) >= 1
    assert s["energy_start"] == E[0] and s["energy_end"] == E[-1]
    assert s["energy_max_increase"] == np.max(E - E[0])
    assert s["contact_work_total"] == traj.contact_work.sum() and s["min_gap"] == traj.gap.min()
