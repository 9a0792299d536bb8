"""Error metrics on hand-built trajectories with known errors."""

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
from moreau_sim.testing import metrics
from moreau_sim.trajectory import ARRAYS

from helpers import scene


def traj(t, q, u=None, gap=None, E=None, log=()) -> ms.Trajectory:
    """A Trajectory from arrays; log rows are (t, pair, gamma_minus)."""
    t = np.asarray(t, float)
    q = np.asarray(q, float).reshape(len(t), -1)
    u = np.zeros_like(q) if u is None else np.asarray(u, float).reshape(len(t), -1)
    n = len(t)
    arrays = {k: np.zeros(n) for k in ARRAYS}
    arrays.update(t=t, q=q, u=u, kinetic_energy=np.zeros(n) if E is None else np.asarray(E, float),
                  gap=np.zeros((n, 1)) if gap is None else np.asarray(gap, float).reshape(n, -1))
    lt, lp, lg = (np.array(c) for c in zip(*log)) if log else (np.zeros(0),) * 3
    arrays.update(log_t=lt.astype(float), log_pair=lp.astype(np.int64), log_gamma_minus=lg.astype(float),
                  log_impact=np.ones(len(lt), bool))
    return ms.Trajectory(arrays, {"status": "complete"})


def test_impact_times_matched_per_pair_in_order():
    ref = traj([0, 1], [0, 0], log=[(0.1, 0, -1), (0.3, 0, -1), (0.2, 1, -1), (0.5, 1, -1)])
    # pair 0: +1 ms and -2 ms; pair 1: one impact only (+0.5 ms), the second is missing; a row of
    # pair 0 repeated at the same instant (a second corner) counts once; pair 2 is extra
    run = traj([0, 1], [0, 0], log=[(0.101, 0, -1), (0.101, 0, -1), (0.298, 0, -1), (0.2005, 1, -1),
                                    (0.7, 2, -1)])
    r = metrics.impact_times_error(run, ref)
    assert r.max_abs == pytest.approx(2e-3, abs=1e-15)
    assert np.allclose(sorted(r.errors), sorted([1e-3, -2e-3, 5e-4]), atol=1e-15)
    assert (r.missing, r.extra) == (1, 1)
    assert metrics.impact_times_error(run, ref, count=1).max_abs == pytest.approx(1e-3, abs=1e-15)


def test_impact_times_filters():
    run = traj([0, 1], [0, 0], log=[(0.1, 0, -2.0), (0.2, 0, -1e-6), (0.9, 0, -1.0)])
    assert list(metrics.impact_times(run, min_speed=1e-3)[0]) == [0.1, 0.9]
    assert list(metrics.impact_times(run, t_max=0.5)[0]) == [0.1, 0.2]


def bounces(e, d0=0.9, g=9.81, dt=1e-3, n=4):
    """A ball's gap sampled every dt: exact parabolas, apex e^(2k) d0 after bounce k."""
    t0 = np.sqrt(2 * d0 / g)
    hits = [t0 * (1 + 2 * sum(e ** j for j in range(1, k + 1))) for k in range(n + 1)]
    t = np.arange(0, hits[-1], dt)
    gap = np.where(t < hits[0], d0 - 0.5 * g * t ** 2, 0.0)
    for k in range(n):
        v = e ** (k + 1) * g * t0  # rebound speed
        s = t - hits[k]
        gap = np.where((t >= hits[k]) & (t < hits[k + 1]), v * s - 0.5 * g * s ** 2, gap)
    apex_t = [hits[k] + e ** (k + 1) * t0 for k in range(n)]
    return t, gap, np.array([d0 * e ** (2 * k) for k in range(1, n + 1)]), np.array(apex_t)


def test_apexes_exact_for_sampled_parabolas():
    t, gap, heights, times = bounces(0.8, dt=7.3e-4)  # samples nowhere near the apexes
    h, ta = metrics.apexes(t, gap, count=3)
    assert np.abs(h - heights[:3]).max() < 1e-12 and np.abs(ta - times[:3]).max() < 1e-12


def test_apex_error_against_closed_form_and_trajectory():
    t, gap, heights, _ = bounces(0.5)
    run = traj(t, gap + 0.1, gap=gap)
    assert metrics.apex_error(run, heights, count=3).max_abs < 1e-12
    wrong = heights * [1.0, 1.01, 1.0, 1.0]
    r = metrics.apex_error(run, wrong, count=3)
    assert r.max_abs == pytest.approx(0.01 * heights[1], rel=1e-9) and r.missing == 0
    # a run that stops bouncing after the first apex: the missing ones count as their height
    flat = traj(t, gap, gap=np.where(t < 0.85, gap, 0.0))  # rests after impact 2 (0.857 s)
    r = metrics.apex_error(flat, run, count=3)
    assert r.missing == 2 and r.max_abs == pytest.approx(heights[1], rel=1e-9)


def test_state_error_euclidean_interpolates_both():
    tr_ = np.linspace(0, 1, 11)
    ts = np.linspace(0, 1, 7)
    ref = traj(tr_, np.c_[2 * tr_, -tr_], u=np.c_[np.full(11, 2.0), np.full(11, -1.0)])
    run = traj(ts, np.c_[2 * ts + 0.003, -ts - 0.001], u=np.c_[np.full(7, 2.0), np.full(7, -1.02)])
    r = metrics.state_error(run, ref, [0.25, 0.55, 0.9])  # linear q: interpolation is exact
    assert r.q_max == pytest.approx(0.003, abs=1e-14) and r.u_max == pytest.approx(0.02, abs=1e-14)
    assert np.allclose(r.q_err, 0.003, atol=1e-14)


def test_state_error_lie_group():
    model = ms.build_model(scene("box_drop")).pin
    q0 = ms.initial_state(ms.build_model(scene("box_drop"))).q
    v = np.array([0.1, -0.2, 0.3, 1.0, -2.0, 0.5])  # constant: a one-parameter subgroup
    tf, tc = np.linspace(0, 1, 101), np.linspace(0, 1, 6)
    def qs(ts):
        return np.array([pin.integrate(model, q0, s * v) for s in ts])
    ref, run = traj(tc, qs(tc)), traj(tf, qs(tf))
    r = metrics.state_error(run, ref, [0.13, 0.5, 0.77], model=model)
    assert r.q_max < 1e-12  # interpolation along the group is exact on a geodesic
    delta = np.array([1e-3, 0, 0, 0, 2e-3, 0])
    shifted = traj(tc, [pin.integrate(model, q, delta) for q in qs(tc)])
    r = metrics.state_error(shifted, ref, tc, model=model)
    assert r.q_max == pytest.approx(2e-3, rel=1e-9)
    euclid = metrics.state_error(shifted, ref, tc)  # without the model: raw quaternion components
    assert euclid.q_max != pytest.approx(2e-3, rel=1e-6)


def test_energy_error_and_penetration():
    t = np.linspace(0, 1, 11)
    ref = traj(t, t, E=np.full(11, 5.0))
    run = traj(t[:6], t[:6], E=5.0 + 0.1 * t[:6], gap=np.r_[0.1, 0.0, -2e-3, 0.0, 1e-3, 0.2])
    assert metrics.energy_error(run, ref) == pytest.approx(0.05, abs=1e-14)
    assert metrics.energy_error(run, ref, times=[0.1]) == pytest.approx(0.01, abs=1e-14)
    assert metrics.max_penetration(run) == pytest.approx(2e-3)
    assert metrics.max_penetration(ref) == 0.0
    assert metrics.max_penetration({"gap": np.array([[0.1, -0.5]])}) == 0.5
    assert metrics.max_penetration(np.array([0.3, 0.2])) == 0.0


def test_metrics_on_two_real_runs():
    """The stepper against the event-driven reference on the bouncing ball: first-order errors."""
    from moreau_sim.event_driven import simulate_event_driven

    model = ms.build_model(scene("bouncing_ball", restitution=0.8, duration=2.0))
    ref = simulate_event_driven(model)
    apex, times = [], []
    for h in (1e-2, 1e-3):
        run = ms.simulate(ms.build_model(scene("bouncing_ball", restitution=0.8, duration=2.0, dt=h)),
                          progress=False)
        apex.append(metrics.apex_error(run, ref, count=3).max_abs)
        r = metrics.impact_times_error(run, ref, count=3)
        assert (r.missing, r.extra) == (0, 0) and abs(r.errors[0]) <= h  # the first impact: within a step
        times.append(r.max_abs)
    assert apex[1] < apex[0] / 5 and times[1] < times[0] / 5  # converges (first order for e < 1)
