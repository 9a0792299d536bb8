"""Prescribed motion of a static (moreau_sim/prescribed.py, docs/theory.md §2.9): its velocity V enters
the law as the constraint's own rate, gamma = W'u + dg/dt, dg/dt = -n.V. Closed forms: the relative
velocity of a ball on a paddle at constant velocity reverses with factor e; the bouncing ball on a
vibrating table obeys v+ = -e v- + (1 + e) V_table at each impact step; the ledger books the obstacle's
work -P.dg/dt and closes to round-off (translations)."""

import math

import numpy as np
import pytest

import moreau_sim as ms

from helpers import MODELS, inline_scene

SCENE = """
[scene]
name = "paddle"
[simulation]
restitution = {e}
dt = {h}
duration = {T}
gravity = [0, 0, {g}]
[[bodies]]
name = "ball"
urdf = "{models}/ball.urdf"
root_joint = "prismatic"
axis = [0, 0, 1]
q0 = [{z0}]
u0 = [{u0}]
[[statics]]
name = "paddle"
shape = "halfspace"
motion = {motion}
"""


def paddle(tmp_path, *, e, h, T, motion, g=-9.81, z0=0.5, u0=0.0):
    return inline_scene(SCENE.format(e=e, h=h, T=T, g=g, z0=z0, u0=u0, motion=motion, models=MODELS), tmp_path)


@pytest.mark.parametrize("e", [0.0, 0.3, 0.8, 1.0])
@pytest.mark.parametrize("h", [1e-3, 3e-4])
def test_paddle_at_constant_velocity_reverses_relative_velocity(tmp_path, e, h):
    """No gravity, ball at -2 m/s, paddle rising at 0.5 m/s: u+ - V = -e (u- - V), u+ = 0.5 + 2.5 e."""
    V, u0 = 0.5, -2.0
    sc = paddle(tmp_path, e=e, h=h, T=0.3, motion=f"{{ velocity = [0, 0, {V}] }}", g=0.0, z0=0.2, u0=u0)
    tr = ms.simulate(ms.build_model(sc))
    assert tr.impacts == 1
    assert tr.u[-1, 0] == pytest.approx(V - e * (u0 - V), abs=1e-12)
    assert tr.log_gamma_plus[0] == pytest.approx(-e * tr.log_gamma_minus[0], abs=1e-12)
    assert tr.log_gamma_minus[0] == pytest.approx(u0 - V, abs=1e-12)
    L = ms.ledger(tr)
    assert abs(L.residual) <= 1e-12 * L.scale
    # the paddle's work: P V, with P = (1 + e) |u- - V| m
    assert L.obstacle_work == pytest.approx((1 + e) * abs(u0 - V) * V, rel=1e-12)


@pytest.mark.parametrize("e", [0.5, 0.8])
@pytest.mark.parametrize("h", [1e-3, 5e-4])
def test_vibrating_table_impact_map(tmp_path, e, h):
    """Bouncing ball on a table z = A sin(2 pi f t): every step with a new impact obeys the impact map
    v+ = -e v- + (1 + e) V_table(t_m), t_m the step's midpoint (an impact slower than one step of gravity
    takes e_i = 0 instead, a closed contact already separating e_i = 1, docs/theory.md §2.2-2.3); T + V of the
    ball follows the ledger."""
    A, f = 0.01, 8.0
    sc = paddle(tmp_path, e=e, h=h, T=2.0, motion=f"{{ sine = {{ amplitude = [0, 0, {A}], frequency = {f} }} }}")
    tr = ms.simulate(ms.build_model(sc))
    assert len(tr.t) == round(2.0 / h) + 1 and tr.impacts >= 3
    checked = 0
    for s, t_m, new, gm in zip(tr.log_step, tr.log_t, tr.log_impact, tr.log_gamma_minus):
        V = A * 2 * math.pi * f * math.cos(2 * math.pi * f * t_m)
        assert gm == pytest.approx(tr.u[s - 1, 0] - V, abs=1e-12)  # gamma = W'u + dg/dt
        e_i = 1.0 if gm > 0 else e if -gm > 9.81 * h else 0.0  # the rules of §2.2 and §2.3
        assert tr.u[s, 0] == pytest.approx(-e_i * tr.u[s - 1, 0] + (1 + e_i) * V, abs=1e-12)
        checked += bool(new) and e_i == e
    assert checked >= 3
    L = ms.ledger(tr)
    assert abs(L.residual) <= 1e-12 * L.scale and abs(L.smooth_error) <= 1e-12 * L.scale
    assert L.max_law_difference <= 1e-12 * L.scale


def test_table_motion_and_gap_at_samples(tmp_path):
    """A table of positions (linear interpolation): the recorded gap is taken with the paddle where it is
    at the sample's time."""
    sc = paddle(tmp_path, e=0.5, h=1e-3, T=0.5, g=0.0, z0=1.0,
                motion="{ t = [0.0, 1.0], position = [[0, 0, 0], [0, 0, 0.4]] }")
    tr = ms.simulate(ms.build_model(sc))
    assert np.allclose(tr.gap[:, 0], 1.0 - 0.1 - 0.4 * tr.t, atol=1e-12)


@pytest.mark.parametrize("motion, field", [
    ("{ t = [0.0, 0.0], position = [[0, 0, 0], [0, 0, 1]] }", "motion t: must be strictly increasing"),
    ("{ sine = { amplitude = [0, 0, 1] } }", "motion sine: missing required key 'frequency'"),
    ("{ velocity = [0, 1] }", "motion velocity: must be a list of 3 numbers"),
    ("{ t = [0.0, 1.0], position = [[0, 0, 0]] }", "motion position: must hold 2 rows"),
])
def test_motion_errors_name_the_field(tmp_path, motion, field):
    with pytest.raises(ms.SceneError) as ei:
        paddle(tmp_path, e=0.5, h=1e-3, T=0.1, motion=motion)
    assert field in str(ei.value) and "\n" not in str(ei.value)


def test_moving_static_against_a_polytope_is_refused(tmp_path):
    sc = inline_scene(f"""
[scene]
name = "box_on_paddle"
[[bodies]]
name = "box"
urdf = "{MODELS}/box.urdf"
root_joint = "free"
q0 = [0, 0, 1, 0, 0, 0, 1]
[[statics]]
name = "paddle"
shape = "halfspace"
motion = {{ velocity = [0, 0, 0.1] }}
""", tmp_path)
    with pytest.raises(ms.SceneError, match="a moving static and what it meets must be shapes without vertices"):
        ms.build_model(sc)


def test_event_driven_refuses_a_moving_static(tmp_path):
    sc = paddle(tmp_path, e=0.5, h=1e-3, T=0.1, motion="{ velocity = [0, 0, 0.1] }")
    with pytest.raises(ms.SceneError, match="does not take a moving static"):
        ms.simulate(ms.build_model(sc.with_options(integrator="event-driven")))


def test_bundled_vibrating_paddle():
    """scenes/vibrating_paddle.toml: every impact step follows the table map (docs/theory.md §2.9), the ball
    keeps bouncing (the paddle feeds it), the ledger closes to round-off."""
    sc = ms.load_scene(MODELS.parent / "scenes" / "vibrating_paddle.toml")
    e, h = sc.options.restitution, sc.options.dt
    tr = ms.simulate(ms.build_model(sc))
    A, f = 0.01, 8.0
    n = 0
    for s, t_m, new, gm in zip(tr.log_step, tr.log_t, tr.log_impact, tr.log_gamma_minus):
        V = A * 2 * math.pi * f * math.cos(2 * math.pi * f * t_m)
        e_i = 1.0 if gm > 0 else e if -gm > 9.81 * h else 0.0
        assert tr.u[s, 0] == pytest.approx(-e_i * tr.u[s - 1, 0] + (1 + e_i) * V, abs=1e-12)
        n += bool(new)
    assert n >= 10 and tr.log_t[tr.log_impact][-1] > 4.0  # still bouncing at the end
    L = ms.ledger(tr)
    assert abs(L.residual) <= 1e-12 * L.scale and L.obstacle_work > 0
