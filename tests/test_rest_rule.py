"""The lift in full of docs/theory.md §2.5 for bodies at rest along the normals: every closed contact of the bodies
of the penetrating contacts has |gamma^k| <= eps and |gamma^{k+1}| <= eps (eps = RESTING max|u_free - u_k|), sliding
and turning about the normal allowed; the lift keeps each of those contacts closed. Asserted on physics: the edge of
the criterion on a sliding, turning ball placed inside the ground (lifted by exactly its depth, booking m g depth, or
left to the budget rule), a rocking block never lifted beyond the budget while it turns, and quadruped_drop, whose
robot slides and turns on the frictionless ground after it has come down, with no penetration that persists."""

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
from moreau_sim import stepper
from moreau_sim.results import HOLD, RESTING

from helpers import FREE_BOX, GROUND, box_body, inline_scene, scene

G = 9.81
DEPTH = 1e-5  # [m] the ball's start inside the ground, far beyond contact_tolerance (1e-9 m)
LIFT = 1e-7  # [m] how much deeper than its other corners a turned box's corners start (the HOLD edge)


def sliding_ball(tmp_path, h: float, vz_of_eps: float, impl: str = "compiled"):
    """A free ball (1 kg, r = 0.1 m, placed turned by rpy (0.3, 0.2, 0.1): its row has no zero entry, so while
    it slides it is never at rest by the velocities of the rule before) DEPTH inside the ground, sliding at
    (3, -2) mm/s and turning at 0.01 rad/s about the normal, with a vertical speed of vz_of_eps times the
    criterion's eps (approaching for < 0): the model, its data and the state."""
    text = FREE_BOX.format(g=-G, e=0.5, T=0.01, bodies=box_body("ball", "ball.urdf", (0, 0, 0.1), (0.3, 0.2, 0.1)))
    model = ms.build_model(inline_scene(text + GROUND, tmp_path).with_options(step_impl=impl))
    data = ms.make_data(model)
    q = ms.initial_state(model).q.copy()
    q[2] -= DEPTH
    u = np.array([3e-3, -2e-3, 0.0, 0.0, 0.0, 1e-2])
    pb = stepper.assemble(model, data, ms.State(0.0, q, u), h=h, e=model.options.restitution)
    eps = RESTING * float(np.abs(pb.u_free - pb.u).max())
    u[2] = vz_of_eps * eps
    return model, data, ms.State(0.0, q, u)


@pytest.mark.parametrize("impl", ["compiled", "python"])
@pytest.mark.parametrize("h", [1e-3, 1e-2])
@pytest.mark.parametrize("vz", [0.0, -0.9, 0.9])
def test_a_sliding_turning_ball_just_inside_the_criterion_is_lifted_in_full(tmp_path, h, vz, impl):
    """Normal speed within eps (0, and 0.9 eps either way): one step puts the ball back on the ground (gap within
    contact_tolerance) and books the lift, m g DEPTH, to 1e-6 (the drift's own m g h vz is 1e-12 of it); its
    sliding and turning velocities are the law's (the lift changes q only)."""
    model, data, st = sliding_ball(tmp_path, h, vz, impl)
    r = ms.step(model, data, st, h=h)
    assert ms.pair_distances(model, data, r.state.q).min() >= -model.options.contact_tolerance
    assert r.correction_energy == pytest.approx(1.0 * G * DEPTH, rel=1e-6)
    assert r.u_law is None and r.state.u[3:] == pytest.approx(st.u[3:], rel=1e-9)


@pytest.mark.parametrize("impl", ["compiled", "python"])
@pytest.mark.parametrize("h", [1e-3, 1e-2])
@pytest.mark.parametrize("vz", [-1.1, -2.0, -10.0])
def test_a_ball_approaching_just_outside_the_criterion_keeps_the_budget_rule(tmp_path, h, vz, impl):
    """Approaching at 1.1 eps and more: not at rest along the normal; the budget rule gives back only what the step
    dissipated, (1/2) m vz^2 and the (h/2) m g |vz| it fell (5e-14 J at 1.1 eps, h = 1e-3; under 1e-6 of the lift
    m g DEPTH at 10 eps): the ball stays DEPTH inside to 1e-3."""
    model, data, st = sliding_ball(tmp_path, h, vz, impl)
    r = ms.step(model, data, st, h=h)
    assert ms.pair_distances(model, data, r.state.q).min() == pytest.approx(-DEPTH, rel=1e-3)
    assert r.correction_energy <= 1e-6 * G * DEPTH


@pytest.mark.parametrize("e", [0.0, 0.5, 0.9])
@pytest.mark.parametrize("h", [1e-3, 1e-2])
def test_a_rocking_block_is_never_lifted_beyond_the_budget_while_it_turns(e, h):
    """rocking_block (3 s): a step that raises T + V (a lift beyond what the step dissipated: the rest rule) ends with
    the block not turning (|theta'| <= 1e-6 rad/s). A contact-only criterion (the pivot's gamma+ = 0) lifted the
    pivot in full at each slow impact while the block turned at 1-2 rad/s: at e = 0.9, h = 1e-2 it booked 0.56 J
    of lifts against 0.12 J, and was still rocking at 3 s."""
    tr = ms.simulate(ms.build_model(scene("rocking_block", restitution=e, dt=h)), progress=False)
    assert tr.complete, tr.meta.get("invariants")
    E = tr.kinetic_energy + tr.potential_energy
    rose = np.flatnonzero(np.diff(E) > 1e-14 * abs(E[0])) + 1
    assert np.abs(tr.u[rose, 2]).max(initial=0.0) <= 1e-6, (tr.t[rose], tr.u[rose, 2])


def test_quadruped_drop_rests_on_the_ground_without_penetration():
    """quadruped_drop (1 s), the compiled and the Python step bit for bit over the whole run (both of its lifts at
    rest along the normals, 0.581 s and 0.618 s, included): the run holds every invariant (docs/theory.md §10; it
    was flagged for penetration, 3.4e-5 inside at 0.53 s); once the robot has come down it slides and turns on
    the frictionless ground (base 7e-4 m/s, yaw 1.5e-3 rad/s) with no contact deeper than contact_tolerance from
    0.62 s (its nine contacts used to stay 9.5e-6 to 3.6e-5 inside for good); T + V less the booked correction never
    rises above its start by more than the fixed step's bound (1e-8 of the energy scale; the run's own check,
    against its running minimum, is in tr.complete)."""
    runs = {}
    for impl in ("compiled", "python"):
        model = ms.build_model(scene("quadruped_drop", step_impl=impl))
        runs[impl] = tr = ms.simulate(model, progress=False)
        assert tr.complete, tr.meta.get("invariants")
        assert tr.gap[tr.t >= 0.62].min() >= -model.options.contact_tolerance
        E = tr.kinetic_energy + tr.potential_energy - np.cumsum(tr.correction_energy)
        assert E.max() - E[0] <= 1e-8 * max(abs(E[0]), tr.kinetic_energy.max())
    for key in ("q", "u", "correction_energy", "gap"):
        assert np.array_equal(runs["compiled"].arrays[key], runs["python"].arrays[key]), key


def _corner_gaps(q: np.ndarray, half=(0.1, 0.1, 0.2)) -> np.ndarray:
    """The heights above the ground (z = 0) of the 4 bottom corners of a free box at q (x, y, z, quaternion x y z w):
    those at y = -half[1], then those at y = +half[1]."""
    R = pin.Quaternion(q[6], q[3], q[4], q[5]).toRotationMatrix()
    c = np.array([[sx * half[0], sy * half[1], -half[2]] for sy in (-1, 1) for sx in (-1, 1)])
    return q[2] + (c @ R.T)[:, 2]


@pytest.mark.parametrize("impl", ["compiled", "python"])
@pytest.mark.parametrize("g_of_tol", [0.0, 0.25, HOLD * (1 - 1e-3), HOLD, HOLD * (1 + 1e-3), 0.75, 1.0])
def test_a_lift_at_rest_along_the_normals_keeps_each_closed_contact_within_hold_tolerances(tmp_path, g_of_tol, impl):
    """The edge of results.HOLD: box.urdf (1 kg, 0.2 x 0.2 x 0.4 m) on the ground, sliding along y at 3 mm/s and
    turning about the vertical at 0.01 rad/s (so not at rest by its velocities, _resting), turned by theta about x so
    that its two bottom corners at y = +0.1 m have the gap g_s = g_of_tol contact_tolerance (closed) and the two at
    y = -0.1 m lie LIFT = 1e-7 m deeper. The projection least in the kinetic metric would lift the shallow corners
    too, by 2.5e-8 m ((I_x - m b^2)/(I_x + m b^2) LIFT, b = 0.1 m); the lift at rest along the normals bounds each
    closed contact by g_i' + w_i'dq <= max(g_i', HOLD tol). So one step ends with the deep corners on the ground and
    the shallow ones at max(g_s, HOLD tol), to the lift's second order (0.2 theta^2 / 2, 3e-14 m): raised to HOLD tol
    from below it, kept where they were from above it (sliding along y and turning about the vertical move no corner
    up or down). It books m g times the rise of the centre."""
    tol = 1e-9  # the scene's contact_tolerance (asserted below)
    text = FREE_BOX.format(g=-G, e=0.5, T=0.01, bodies=box_body("box", "box.urdf", (0, 0, 0.3)))
    model = ms.build_model(inline_scene(text + GROUND, tmp_path).with_options(step_impl=impl))
    assert model.options.contact_tolerance == tol
    data = ms.make_data(model)
    g_s = g_of_tol * tol
    s = LIFT / 0.2  # sin(theta): the corners at y = -0.1 lie 0.2 sin(theta) below those at y = +0.1
    theta = np.arcsin(s)
    q = ms.initial_state(model).q.copy()
    q[3:7] = (np.sin(theta / 2), 0.0, 0.0, np.cos(theta / 2))
    q[2] = g_s - 0.1 * s + 0.2 * np.cos(theta)
    np.testing.assert_allclose(_corner_gaps(q), [g_s - LIFT] * 2 + [g_s] * 2, rtol=0, atol=1e-16)
    u = np.array([0.0, 3e-3, 0.0, 0.0, 1e-2 * s, 1e-2 * np.cos(theta)])  # turning about the vertical: no corner rises
    r = ms.step(model, data, ms.State(0.0, q, u), h=1e-3)
    gaps = _corner_gaps(r.state.q)
    np.testing.assert_allclose(gaps[:2], 0.0, rtol=0, atol=1e-13)
    np.testing.assert_allclose(gaps[2:], max(g_s, HOLD * tol), rtol=0, atol=1e-13)
    assert r.correction_energy == pytest.approx(G * (r.state.q[2] - q[2]), rel=1e-6)


@pytest.mark.parametrize("e, h", [(0.0, 1e-3), (0.5, 1e-3), (0.0, 2e-3)])
def test_the_correction_never_pushes_a_joint_past_a_limit_it_does_not_hold(e, h):
    """quadruped_drop at e = 0 (h = 1, 2 ms; e = 0.5): at 0.353 s the feet's impact swings the front-right hip, just
    off its lower limit (12.6 urad, the limit not closed), back towards it, and the position correction that lifted the
    feet's penetrating contacts turned the hip 74 urad further: past its limit, a row the correction did not know. The
    run was flagged (151 urad inside against 122 allowed). The correction's guard reads the limits' gaps as it reads
    the pairs' distances (stepper._guarded; src/step.cpp limits_hold): over 0.4 s, at every step and every limit, the
    gap at the step's end is at least min(g_k, 0) less the joint's own approach over the two half steps,
    (h/2) (max(0, -s u_k) + max(0, -s u_{k+1})) (s the limit's sign), and contact_tolerance (docs/theory.md §2.5):
    at 0.353 s the hip ended 99.8 urad inside where its approach allows 51; the compiled and the Python step bit for
    bit."""
    ends = {}
    for impl in ("compiled", "python"):
        model = ms.build_model(scene("quadruped_drop", restitution=e, dt=h, step_impl=impl))
        data, st = ms.make_data(model), ms.initial_state(model)
        tol = model.options.contact_tolerance
        lims = [(lim.sign, lim.bound, lim.idx_q, lim.idx_v) for lim in model.limits]
        assert len(lims) == 24
        while st.t < 0.4:
            nxt = ms.step(model, data, st, h=h).state
            for s, bound, iq, iv in lims:
                g0, g1 = s * (st.q[iq] - bound), s * (nxt.q[iq] - bound)
                own = 0.5 * h * (max(0.0, -s * st.u[iv]) + max(0.0, -s * nxt.u[iv]))
                assert g1 >= min(g0, 0.0) - own - tol, (impl, st.t, iq, g0, g1, own)
            st = nxt
        ends[impl] = st
    assert np.array_equal(ends["compiled"].q, ends["python"].q) and np.array_equal(ends["compiled"].u, ends["python"].u)
