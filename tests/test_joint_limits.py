"""Joint limits as unilateral constraints of the same law (moreau_sim/limits.py, docs/theory.md §1, §2.1):
the limit impact against Newton's law exactly, rest on the limit, a limit and a contact in one impact, no
energy gain, the compiled and the Python step alike, `joint_limits = false`, robots within their limits."""

import math

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
from moreau_sim.contacts import FeatureKind
from moreau_sim.stepper import step
from moreau_sim.testing import assert_budget_closes, assert_dissipation_follows_law

from helpers import MODELS, inline_scene, scene

LOWER = 0.5  # [rad] models/pendulum_limit.urdf's lower limit
Q0 = math.pi / 2
INTEGRATORS = ("time-stepping", "adaptive", "event-driven")


def _run(sc, **opts):
    return ms.simulate(ms.build_model(sc.with_options(**opts)), progress=False)


def _omega_minus(model) -> float:
    """The closed-form angular velocity at the limit after falling from rest at Q0: energy conservation,
    I omega^2 / 2 = V(Q0) - V(LOWER), with I and V from Pinocchio (the hinge's inertia is constant)."""
    d = model.pin.createData()
    inertia = float(pin.crba(model.pin, d, np.array([LOWER]))[0, 0])
    dV = pin.computePotentialEnergy(model.pin, d, np.array([Q0])) - pin.computePotentialEnergy(
        model.pin, d, np.array([LOWER]))
    return -math.sqrt(2.0 * dV / inertia)


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("h", [1e-3, 1e-4])
def test_impact_step_on_the_limit_reverses_omega_by_e(e, h):
    """A step starting at the impact (q on the limit, omega- < 0): omega+ = -e omega- to round-off,
    the percussion on the limit's own row (kind JOINT_LIMIT, feature = the hinge's joint id)."""
    model = ms.build_model(scene("pendulum_limit", restitution=e, dt=h))
    data = ms.Data(model)
    om = _omega_minus(model)
    r = step(model, data, ms.State(0.0, np.array([LOWER]), np.array([om])))
    assert r.contacts.m == 1 and r.contacts.kind[0] == FeatureKind.JOINT_LIMIT
    assert r.contacts.feature[0] == model.limits[0].joint and r.contacts.pair[0] == len(model.pairs)
    assert abs(r.state.u[0] + e * om) <= 1e-13 * abs(om)
    assert r.P[0] > 0.0
    assert r.contact_work <= 1e-14 * abs(r.P[0] * om)


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_first_strike_obeys_newton_and_the_falls_energy(e, integrator):
    """The first logged impact of a run: gamma+ = -e gamma- to round-off; where the integrator locates it
    (adaptive, event-driven) gamma- is the closed-form omega- and the instant's q is on the limit."""
    model = ms.build_model(scene("pendulum_limit", restitution=e, duration=1.0, integrator=integrator))
    tr = ms.simulate(model, progress=False)
    assert set(tr.log_kind.tolist()) == {int(FeatureKind.JOINT_LIMIT)}
    i = int(np.flatnonzero(tr.log_impact)[0])
    gm, gp = tr.log_gamma_minus[i], tr.log_gamma_plus[i]
    assert abs(gp + e * gm) <= 1e-12 * abs(gm)
    if integrator != "time-stepping":
        assert abs(tr.log_gap[i]) <= 1e-12
        assert gm == pytest.approx(_omega_minus(model), rel=1e-7)


@pytest.mark.parametrize("e", [0.0, 0.5])
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_at_rest_on_its_limit_the_joint_is_inside(e, integrator):
    tr = _run(scene("pendulum_limit", restitution=e, duration=4.0), integrator=integrator)
    assert tr.q[-1, 0] - LOWER >= -1e-9
    assert abs(tr.q[-1, 0] - LOWER) <= 1e-9 and abs(tr.u[-1, 0]) <= 1e-9  # at rest, on the limit


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_limit_impacts_never_create_energy(e, integrator):
    """Every logged percussion's work P (gamma+ + gamma-)/2 <= 0 (round-off); the located integrators'
    total energy never exceeds its start (their flight is exact to their tolerance)."""
    tr = _run(scene("pendulum_limit", restitution=e, duration=2.0), integrator=integrator)
    work = tr.log_P * (tr.log_gamma_plus + tr.log_gamma_minus) / 2
    assert (work <= 1e-12 * np.abs(tr.log_P * tr.log_gamma_minus).max()).all()
    E = tr.total_energy
    if integrator != "time-stepping":
        assert E.max() - E[0] <= 1e-7 * abs(E[0]) + 1e-9


def test_compiled_and_python_steps_give_the_same_trajectory():
    assert ms.compiled.available(), ms.compiled.unavailable_reason()  # the install builds it: missing is a failure
    a = _run(scene("pendulum_limit"), step_impl="compiled")
    b = _run(scene("pendulum_limit"), step_impl="python")
    for k in ("q", "u", "log_P", "log_gamma_plus", "log_gap"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k


WALL = """
[scene]
name = "limit_and_wall"
[simulation]
restitution = {e}
dt = {h}
duration = 0.8
gravity = {g}
integrator = "{integrator}"
[[bodies]]
name = "pendulum"
urdf = "{{models}}/pendulum_limit.urdf"
root_joint = "fixed"
position = [0.0, 0.0, 1.0]
q0 = [1.5707963267948966]
[[statics]]
name = "wall"
shape = "halfspace"
normal = [-1.0, 0.0, 0.0]
offset = {offset}
"""


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("h", [1e-3, 1e-4])
def test_limit_and_contact_closing_together_are_one_impact(tmp_path, e, h):
    """A wall placed where the bob touches it exactly at the limit (the bob's surface at x = 0.5 sin(0.5)
    - 0.05 m), no gravity: the step from the limit with omega- closes the limit and the contact at once,
    and the one QP solves both (two dependent rows on one dof). The combined impact keeps the law's
    identities (docs/theory.md §1.2-1.4): momentum M (u+ - u-) = W P, omega+ = -e omega-, and the energy
    loss T- - T+ = (1 - e^2)/2 |u- - v|_M^2, v = (u+ + e u-)/(1 + e)."""
    offset = 0.5 * math.sin(LOWER) - 0.05
    model = ms.build_model(inline_scene(WALL.format(e=e, h=h, g="[0, 0, 0]", integrator="time-stepping",
                                                    offset=offset), tmp_path))
    om = _omega_minus(ms.build_model(scene("pendulum_limit")))
    r = step(model, ms.Data(model), ms.State(0.0, np.array([LOWER]), np.array([om])))
    assert sorted(r.contacts.kind.tolist()) == sorted([int(FeatureKind.JOINT_LIMIT), int(FeatureKind.WITNESS)])
    assert (r.P > 0).any() and r.contacts.m == 2
    M, W, u1 = r.qp.M, r.qp.W, r.state.u
    assert abs(u1[0] + e * om) <= 1e-12 * abs(om)
    np.testing.assert_allclose(M @ (u1 - om), W @ r.P, rtol=1e-12, atol=1e-15)
    v = (u1 + e * om) / (1 + e)
    loss = 0.5 * float(M[0, 0]) * (om ** 2 - u1[0] ** 2)
    assert loss == pytest.approx(0.5 * (1 - e * e) * float(M[0, 0]) * (om - v[0]) ** 2, rel=1e-12, abs=1e-15)
    assert r.contact_work == pytest.approx(-loss, rel=1e-12, abs=1e-15)


@pytest.mark.parametrize("integrator", ["adaptive", "event-driven"])
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_located_limit_and_contact_are_one_impact(tmp_path, integrator, e):
    """The same wall, with gravity, under the integrators that locate events: the limit and the wall close at
    one located instant and make one impact, omega+ = -e omega-, omega- the closed form."""
    offset = 0.5 * math.sin(LOWER) - 0.05
    tr = ms.simulate(ms.build_model(inline_scene(WALL.format(e=e, h=1e-3, g="[0, 0, -9.81]", integrator=integrator,
                                                             offset=offset), tmp_path)), progress=False)
    t1 = tr.log_t[np.flatnonzero(tr.log_impact)[0]]
    # one impact at t1 (the dependent rows' percussion lands on one of them), not two in a row
    assert not ((tr.log_t > t1) & (tr.log_t < t1 + 1e-3) & tr.log_impact.astype(bool)).any()
    lim = np.flatnonzero(tr.log_t == t1)[0]
    gm, gp = tr.log_gamma_minus[lim], tr.log_gamma_plus[lim]
    assert abs(gp + e * gm) <= 1e-12 * abs(gm)
    assert gm == pytest.approx(_omega_minus(ms.build_model(scene("pendulum_limit"))), rel=1e-7)


def test_joint_limits_false_turns_them_off(tmp_path):
    text = (MODELS.parent / "scenes" / "pendulum_limit.toml").read_text()
    text = text.replace('urdf = "../models/', 'urdf = "{models}/')
    text = text.replace('root_joint = "fixed"', 'root_joint = "fixed"\njoint_limits = false')
    model = ms.build_model(inline_scene(text, tmp_path).with_options(duration=1.0))
    assert model.limits == ()
    tr = ms.simulate(model, progress=False)
    assert tr.q[:, 0].min() < 0.0 and len(tr.log_P) == 0  # it swings through the bottom, nothing stops it
    on = ms.build_model(scene("pendulum_limit"))
    assert [lim.name for lim in on.limits] == ["pendulum/hinge lower", "pendulum/hinge upper"]


def test_a_start_beyond_a_limit_is_refused_naming_the_joint(tmp_path):
    text = (MODELS.parent / "scenes" / "pendulum_limit.toml").read_text()
    text = text.replace('urdf = "../models/', 'urdf = "{models}/').replace("q0 = [1.5707963267948966]", "q0 = [0.2]")
    model = ms.build_model(inline_scene(text, tmp_path))
    with pytest.raises(ms.SceneError, match=r"joint pendulum/hinge starts at q = 0\.2, 0\.3 beyond its lower limit"):
        ms.initial_state(model)


ROBOTS = {
    # panda leaning forward near its shoulder's (joint2) upper limit: gravity drives it into it
    "panda": ('package://example-robot-data/robots/panda_description/urdf/panda.urdf', "fixed",
              "[0, 1.6, 0, -0.2, 0, 0.2, 0.785, 0.02, 0.02]"),
    "ur5": ('package://example-robot-data/robots/ur_description/urdf/ur5_robot.urdf', "fixed", None),
    "solo12": ('package://example-robot-data/robots/solo_description/robots/solo12.urdf', "free",
               "[0, 0, 0.4, 0, 0, 0, 1, 0, 0.8, -1.6, 0, 0.8, -1.6, 0, -0.8, 1.6, 0, -0.8, 1.6]"),
}


@pytest.mark.parametrize("robot", sorted(ROBOTS))
def test_robots_keep_their_joints_within_limits(tmp_path, robot):
    """A short drop of example-robot-data robots (self pairs excluded, a ground below): the limits are the
    URDF's; no sample is beyond a limit by more than the step's own penetration, h/2 max|u| (docs/theory.md
    §2.5), and the last one (at rest on its limits, for panda) within 1e-9 rad. The panda strikes them."""
    urdf, root, q0 = ROBOTS[robot]
    text = f"""
[scene]
name = "{robot}_drop"
[simulation]
restitution = 0.2
dt = 1e-3
duration = 0.5
[[bodies]]
name = "r"
urdf = "{urdf}"
root_joint = "{root}"
{"" if q0 is None else "q0 = " + q0}
[[statics]]
name = "ground"
shape = "halfspace"
offset = {-0.5 if root == "fixed" else 0.0}
[collisions]
exclude = [["r", "r"]]
"""
    model = ms.build_model(inline_scene(text, tmp_path))
    assert model.limits
    for lim in model.limits:
        bound = (model.pin.lowerPositionLimit if lim.sign > 0 else model.pin.upperPositionLimit)[lim.idx_q]
        assert lim.bound == bound
    tr = ms.simulate(model, progress=False)
    h = model.options.dt
    for lim in model.limits:
        g = lim.sign * (tr.q[:, lim.idx_q] - lim.bound)
        assert g.min() >= -0.5 * h * np.abs(tr.u[:, lim.idx_v]).max() - 1e-9, lim.name
        assert g[-1] >= -1e-9, lim.name
    if robot == "panda":
        assert (tr.log_kind == FeatureKind.JOINT_LIMIT).any()


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_the_ledger_books_the_limit_impacts(e):
    """The limit's percussions are the ledger's contact work. Every limit impact dissipates what the law
    says; the event-driven run's budget E_end - E_0 = contact work + smooth error closes to its ODE
    tolerance; what the fixed step's budget leaves is its impact steps' own error (a revolute impact's, as
    pendulum_wall's: docs/theory.md §5): in the impact step and the next only, and of second order in h
    at least (measured: 1.9e-5, 4.6e-6 J at h = 1e-3, 5e-4 for e = 0 and 0.5; 2.4e-7, 3.0e-8 J for e = 1)."""
    left = []
    for h in (1e-3, 5e-4):
        tr = _run(scene("pendulum_limit", restitution=e, dt=h, duration=2.0))
        L = ms.ledger(tr)
        assert L.contact_steps > 0 and L.impacts
        assert_dissipation_follows_law(tr, rtol=1e-9)
        assert np.count_nonzero(np.abs(np.diff(L.residuals)) > 1e-9 * L.scale) <= 2 * len(L.impacts)
        left.append(abs(L.residual))
        ed = _run(scene("pendulum_limit", restitution=e, dt=h, duration=2.0), integrator="event-driven")
        assert_dissipation_follows_law(ed, rtol=1e-12)
        assert_budget_closes(ed, rtol=1e-9)
    assert left[0] / left[1] >= 3.5


def test_continuous_joints_and_root_joints_have_no_limits(tmp_path):
    """A continuous joint (Pinocchio's unbounded revolute, nq = 2) and a body's root joint get none;
    a prismatic joint's <limit> is one (in metres)."""
    urdf = (MODELS / "pendulum_limit.urdf").read_text()
    (tmp_path / "cont.urdf").write_text(urdf.replace('type="revolute"', 'type="continuous"'))
    (tmp_path / "slide.urdf").write_text(urdf.replace('type="revolute"', 'type="prismatic"'))
    body = """
[[bodies]]
name = "{n}"
urdf = "{p}"
root_joint = "{root}"
position = [{x}, 0.0, 1.0]
q0 = {q0}
"""
    bodies = (("c", tmp_path / "cont.urdf", "fixed", 0.0, [1.0, 0.0]),  # continuous: q = (cos, sin)
              ("s", tmp_path / "slide.urdf", "fixed", 2.0, [1.0]),
              ("r", MODELS / "pendulum_limit.urdf", "prismatic", 4.0, [0.0, 1.0]))  # root, then the hinge
    text = '[scene]\nname = "c"\n' + "".join(body.format(n=n, p=p, root=r, x=x, q0=q0) for n, p, r, x, q0 in bodies)
    model = ms.build_model(inline_scene(text, tmp_path))
    assert [lim.name for lim in model.limits] == ["s/hinge lower", "s/hinge upper", "r/hinge lower", "r/hinge upper"]
