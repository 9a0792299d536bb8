"""moreau_sim.testing.references against closed-form values written out here (docs/theory.md §4)."""

import math

import pytest

from moreau_sim.testing import references as R

G, D0 = 9.81, 0.9  # the bundled ball: gravity [m/s^2], initial gap [m]
T0 = math.sqrt(2 * 0.9 / 9.81)  # first impact [s]: d0 = g t0^2 / 2


@pytest.mark.parametrize("e,expected", [
    (1.0, [-0.6, 0.4, 0.4, 0.4, 0.4]),  # the line of five: ball 1 bounces back, the rest share
    (0.5, [-0.2, 0.3, 0.3, 0.3, 0.3]),
    (0.0, [0.2, 0.2, 0.2, 0.2, 0.2]),  # plastic: all move together
])
def test_touching_cradle_of_five(e, expected):
    u = R.cradle_simultaneous(e)
    assert u == pytest.approx(expected, abs=1e-15)
    assert sum(u) == pytest.approx(1.0, abs=1e-15)  # momentum of unit masses


def test_cradle_other_sizes_and_speed():
    assert R.cradle_simultaneous(1.0, n=2, v0=2.0) == pytest.approx([0.0, 2.0], abs=1e-15)  # two balls swap
    assert R.cradle_simultaneous(1.0, n=3) == pytest.approx([-1 / 3, 2 / 3, 2 / 3], abs=1e-15)


def test_gapped_cradle():
    assert R.cradle_sequential(1.0) == [0.0, 0.0, 0.0, 0.0, 1.0]  # elastic: the velocity is handed on
    assert R.cradle_sequential(0.0) == pytest.approx([0.2] * 5, abs=1e-12)  # plastic: one block
    v = R.cradle_sequential(0.5)
    assert sum(v) == pytest.approx(1.0, abs=1e-12)
    assert all(a <= b + 1e-15 for a, b in zip(v, v[1:]))  # nobody approaches
    # e = 0.5, first sweep: 1 -> (0.25, 0.75) -> (0.25, 0.1875, 0.5625) -> ...
    assert v[-1] < 0.75


@pytest.mark.parametrize("e", [0.0, 0.5, 0.8, 1.0])
def test_ball_impacts_and_apexes(e):
    assert R.ball_first_impact() == pytest.approx(T0, rel=1e-15)
    # a flight after an impact at speed e^k v0 lasts 2 e^k t0: t_k = t0 + 2 t0 (e + ... + e^k)
    t = R.ball_impact_times(e, 4)
    assert t == pytest.approx([T0, T0 + 2 * T0 * e, T0 + 2 * T0 * (e + e * e), T0 + 2 * T0 * (e + e * e + e ** 3)],
                              rel=1e-14)
    # bounce n leaves at e^n v0, rising e^(2n) d0 in e^n t0
    assert R.ball_apex_gaps(e, 3) == pytest.approx([D0 * e ** 2, D0 * e ** 4, D0 * e ** 6], rel=1e-14, abs=1e-300)
    assert R.ball_apex_times(e, 2) == pytest.approx([T0 + e * T0, T0 + 2 * T0 * e + e * e * T0], rel=1e-14)


@pytest.mark.parametrize("e", [0.5, 0.8])
def test_zeno_time(e):
    # t_inf = t0 + 2 t0 (e + e^2 + ...) = t0 (1 + e) / (1 - e)
    assert R.zeno_time(e) == pytest.approx(T0 * (1 + e) / (1 - e), rel=1e-14)
    assert R.zeno_time(e) == pytest.approx(R.ball_impact_times(e, 400)[-1], rel=1e-12)
    assert R.zeno_time(1.0) == math.inf
    assert R.ball_reference(e)["t_inf"] == R.zeno_time(e)


def test_zeno_rest_bound_of_zeno_ball():
    e, h, d0 = 0.8, 1e-3, 0.5  # zeno_ball.toml
    n = math.log(h * G / math.sqrt(2 * G * d0)) / math.log(e)  # bounces faster than h g
    assert R.zeno_bounces(e, h) == pytest.approx(n, rel=1e-14)
    expected = 2 * n * h / (1 - e) + 2 * math.log(1e-12 / (h * G)) / math.log(e) * h
    assert R.zeno_rest_bound(e, h) == pytest.approx(expected, rel=1e-14)
    assert 0.1 < R.zeno_rest_bound(e, h) < 0.5


def test_ball_energy_lost():
    mgd = 1.0 * G * D0
    assert R.ball_energy_lost(0.5, 0.9 * T0) == 0.0  # before the first impact
    assert R.ball_energy_lost(0.5, 1.1 * T0) == pytest.approx(mgd * (1 - 0.25), rel=1e-14)  # one impact
    assert R.ball_energy_lost(0.5, 4 * T0) == pytest.approx(mgd, rel=1e-15)  # at rest after t_inf = 3 t0
    assert R.ball_energy_lost(1.0, 10.0) == 0.0  # elastic


def test_corner_point_outcomes():
    assert R.corner_point_outcomes(1.0) == {(-1.0, 1.0), (1.0, -1.0), (-1.0, -1.0)}
    assert R.corner_point_outcomes(0.0) == {(0.0, 1.0), (1.0, 0.0), (0.0, 0.0)}
