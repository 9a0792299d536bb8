"""Prescribed joint motion, the rheonomic joint (moreau_sim/drive.py, docs/theory.md §2.13): the driven rows
hold u_d = xdot(t_m) in a step, the law is solved in the free rows with the driven rows' share as the
constraint's rate. Closed forms: a ball struck by a paddle on a driven prismatic joint at constant V reverses
its relative velocity with factor e; a pendulum driven at constant angular velocity strikes a free ball as an
infinite-mass striker; the ledger books the drive's work and closes; no penetration persists."""

import math

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim.errors import SceneError

from helpers import MODELS, SCENES, inline_scene

PADDLE = """
[scene]
name = "driven_paddle_test"
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
[[bodies]]
name = "paddle"
urdf = "{models}/flat_box.urdf"
root_joint = "prismatic"
axis = [0, 0, 1]
q0 = [0.0]
u0 = [{V}]
[[drives]]
body = "paddle"
joint = "{joint}"
motion = {{ velocity = {V} }}
"""


def joint_name(tmp_path, body):
    sc = inline_scene(PADDLE.format(e=0.5, h=1e-3, T=0.1, g=0.0, z0=0.5, u0=0.0, V=0.0, joint="x",
                                    models=MODELS).split("[[drives]]")[0], tmp_path)
    m = ms.build_model(sc)
    return next(n.split("/", 1)[1] for n in m.pin.names[1:] if n.startswith(body + "/"))


def paddle(tmp_path, *, e, h, T=0.3, V=0.5, u0=-2.0, g=0.0, z0=0.2):
    joint = joint_name(tmp_path, "paddle")
    return inline_scene(PADDLE.format(e=e, h=h, T=T, g=g, z0=z0, u0=u0, V=V, joint=joint, models=MODELS), tmp_path)


@pytest.mark.parametrize("e", [0.0, 0.3, 0.8, 1.0])
@pytest.mark.parametrize("h", [1e-3, 3e-4])
def test_driven_paddle_reverses_relative_velocity(tmp_path, e, h):
    """No gravity, ball at -2 m/s, paddle driven up at V = 0.5 m/s: u+ - V = -e (u- - V) exactly; the paddle
    keeps V; the ledger books the drive's work (P V, P = (1 + e) |u- - V| m) and closes."""
    V, u0 = 0.5, -2.0
    tr = ms.simulate(ms.build_model(paddle(tmp_path, e=e, h=h, V=V, u0=u0)))
    assert tr.impacts == 1
    assert tr.u[-1, 0] == pytest.approx(V - e * (u0 - V), abs=1e-12)
    assert np.all(tr.u[:, 1] == V)
    assert tr.log_gamma_plus[0] == pytest.approx(-e * tr.log_gamma_minus[0], abs=1e-12)
    L = ms.ledger(tr)
    assert abs(L.residual) <= 1e-12 * L.scale
    assert L.obstacle_work == pytest.approx((1 + e) * abs(u0 - V) * V, rel=1e-12)
    assert tr.q[-1, 0] - tr.q[-1, 1] >= 0.1 + 0.05 - 1e-9  # ball above the paddle's top: no penetration


@pytest.mark.parametrize("e", [0.5, 1.0])
@pytest.mark.parametrize("h", [1e-3, 5e-4])
def test_driven_paddle_under_gravity_ledger_closes(tmp_path, e, h):
    """Under gravity the ball bounces on the rising paddle repeatedly; every impact step obeys the law in the
    paddle's frame and the budget (drive work included) closes to round-off; the ball never ends inside."""
    tr = ms.simulate(ms.build_model(paddle(tmp_path, e=e, h=h, T=1.0, V=0.2, u0=0.0, g=-9.81, z0=0.5)))
    assert tr.impacts >= 2
    fast = (tr.log_P > 0) & (tr.log_gamma_minus < -0.1)  # slower ones take e = 0 (slow_impacts, §2.3)
    assert fast.sum() >= 2
    assert np.allclose(tr.log_gamma_plus[fast], -e * tr.log_gamma_minus[fast], atol=1e-12)
    L = ms.ledger(tr)
    assert abs(L.residual) <= 1e-12 * L.scale
    gap = tr.q[:, 0] - tr.q[:, 1] - 0.15  # ball centre less the paddle's top and the radius [m]
    assert gap.min() >= -h * abs(tr.log_gamma_minus).max()  # within a step of its approach speed
    assert gap[-1] >= -1e-9  # and none persists


PENDULUM = """
[scene]
name = "driven_pendulum_test"
[simulation]
restitution = {e}
dt = {h}
duration = 0.3
gravity = [0, 0, 0]
[[bodies]]
name = "pendulum"
urdf = "{models}/pendulum_limit.urdf"
root_joint = "fixed"
position = [0.0, 0.0, 1.0]
q0 = [0.3]
u0 = [{w}]
joint_limits = false
[[bodies]]
name = "ball"
urdf = "{models}/ball.urdf"
root_joint = "free"
position = [0.16, 0.0, {zb}]
[[drives]]
body = "pendulum"
joint = "hinge"
motion = {{ velocity = {w} }}
"""


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("h", [1e-3, 2e-4])
def test_driven_pendulum_strikes_ball_as_infinite_mass(tmp_path, e, h):
    """A pendulum (hinge at z = 1 m, bob 0.5 m below, r = 0.05 m) driven at omega = -2 rad/s strikes a free ball
    (r = 0.1 m, at rest, no gravity): the ball leaves with (1 + e) (n . v_c) n, v_c = omega y x (c_bob - pivot),
    n from the bob's centre to the ball's at the step's midpoint (the striker's mass does not enter)."""
    w = -2.0
    tr = ms.simulate(ms.build_model(inline_scene(PENDULUM.format(e=e, h=h, w=w, zb=0.52, models=MODELS), tmp_path)))
    assert tr.impacts == 1
    v = tr.u[:, 1:4]  # the ball's linear velocity (world)
    k = int(np.flatnonzero(np.abs(v).max(axis=1) > 0)[0]) - 1  # the impact step: sample k -> k + 1
    theta = tr.q[k, 0] + 0.5 * h * w
    pivot = np.array([0.0, 0.0, 1.0])
    c_bob = pivot + 0.5 * np.array([-math.sin(theta), 0.0, -math.cos(theta)])
    c_ball = tr.q[k, 1:4] + 0.5 * h * tr.u[k, 1:4]
    n = (c_ball - c_bob) / np.linalg.norm(c_ball - c_bob)
    v_c = np.cross([0.0, w, 0.0], c_bob - pivot)
    expected = (1.0 + e) * float(n @ v_c) * n
    assert np.allclose(v[k + 1], expected, rtol=0, atol=1e-12 * np.linalg.norm(v_c))
    assert np.allclose(tr.u[:, 0], w)  # the drive holds the pendulum's velocity
    assert tr.q[-1, 0] == pytest.approx(0.3 + w * tr.t[-1], abs=1e-12)
    L = ms.ledger(tr)
    assert abs(L.residual) <= 1e-12 * L.scale


def _pendulum(tmp_path, extra="", **kw):
    args = dict(e=0.5, h=1e-3, w=-2.0, zb=0.52, models=MODELS) | kw
    return inline_scene(PENDULUM.format(**args) + extra, tmp_path)


@pytest.mark.parametrize("change, field", [
    (lambda s: s + '[[actuators]]\nbody = "pendulum"\nkp = 10.0\n', "also has an actuator"),
    (lambda s: s.replace("joint_limits = false\n", "").replace("q0 = [0.3]", "q0 = [1.0]"),
     "leaves the joint's limits"),
    (lambda s: s.replace('joint = "hinge"', 'joint = "nope"'), "names no joint"),
    (lambda s: s.replace("u0 = [-2.0]\n", ""), "u0"),
    (lambda s: s.replace('body = "pendulum"\njoint = "hinge"', 'body = "ball"\njoint = "root"'),
     "floating base"),
    (lambda s: s.replace("motion = { velocity = -2.0 }", "motion = 3"), "motion"),
])
def test_driven_joint_refusals_name_the_field(tmp_path, change, field):
    text = change(PENDULUM.format(e=0.5, h=1e-3, w=-2.0, zb=0.52, models=MODELS))
    with pytest.raises(SceneError, match=field) as exc:
        ms.build_model(inline_scene(text, tmp_path))  # the model refuses it: its Drive is built with it
    assert "\n" not in str(exc.value) and "[[drives]][0]" in str(exc.value)


def test_the_drive_is_a_declared_field_of_the_model(tmp_path):
    """build_model makes the model's Drive (Model.drive, a field of the frozen Model, None without [[drives]]):
    a run sets nothing on the model for it, and a copy made with dataclasses.replace keeps it."""
    import dataclasses
    model = ms.build_model(_pendulum(tmp_path))
    assert "drive" in {f.name for f in dataclasses.fields(model)}
    assert [j.name for j in model.drive.joints] == ["pendulum/hinge"] and model.drive.d.tolist() == [0]
    ms.simulate(model, progress=False)
    assert {k for k in vars(model) if "drive" in k} == {"drive"}  # no cache set on the frozen model (it was)
    assert dataclasses.replace(model).drive is model.drive
    assert ms.build_model(ms.load_scene(SCENES / "pendulum_wall.toml")).drive is None


@pytest.mark.parametrize("integrator", ["adaptive", "event-driven"])
def test_other_integrators_refuse_a_driven_joint(tmp_path, integrator):
    model = ms.build_model(_pendulum(tmp_path).with_options(integrator=integrator))
    with pytest.raises(SceneError, match="driven joint"):
        ms.simulate(model)


def test_compiled_step_takes_driven_steps(tmp_path):
    """The compiled step takes a driven model's steps (bit for bit: tests/test_compiled_rheonomic.py)."""
    from moreau_sim import compiled
    model = ms.build_model(_pendulum(tmp_path))
    assert compiled.unsupported(model) is None


def test_bundled_driven_paddle_juggles_by_the_law():
    """scenes/driven_paddle.toml: the paddle's joint follows 0.03 sin(2 pi 3 t) m; every impact step (above the
    slow-impact threshold) reverses the ball's velocity relative to the paddle with factor e, the ledger with the
    drive's work closes to round-off, the driven joint tracks its trajectory to second order (the trapezoid of
    the step's end velocities, §2.13: within h^2 A omega^2), and no penetration persists."""
    tr = ms.run(SCENES / "driven_paddle.toml", progress=False)
    sc = ms.load_scene(SCENES / "driven_paddle.toml")
    e, h = sc.options.restitution, sc.options.dt
    assert tr.complete and tr.impacts >= 10
    fast = (tr.log_P > 0) & (tr.log_gamma_minus < -0.1)
    assert fast.sum() >= 10
    assert np.allclose(tr.log_gamma_plus[fast], -e * tr.log_gamma_minus[fast], rtol=0, atol=1e-12)
    L = ms.ledger(tr)
    assert abs(L.residual) <= 1e-12 * L.scale and L.obstacle_work != 0.0
    A, w = 0.03, 2 * math.pi * 3.0
    assert np.abs(tr.q[:, 1] - A * np.sin(w * tr.t)).max() <= h * h * A * w * w
    gap = tr.q[:, 0] - tr.q[:, 1] - 0.15
    assert gap.min() >= -h * abs(tr.log_gamma_minus).max() and gap[-1] >= -1e-9


def test_a_drive_into_an_obstacle_stops_the_run_by_name(tmp_path):
    """The driven pendulum swung into a static sphere (nothing free to give way): one line naming the pair."""
    text = PENDULUM.format(e=0.5, h=1e-3, w=-2.0, zb=0.52, models=MODELS).replace(
        '[[bodies]]\nname = "ball"\nurdf = "{}/ball.urdf"\nroot_joint = "free"\nposition = [0.16, 0.0, 0.52]\n'
        .format(MODELS), '[[statics]]\nname = "post"\nshape = "sphere"\nradius = 0.1\nposition = [0.16, 0.0, 0.52]\n')
    assert "post" in text
    with pytest.raises(ms.SimulationError, match="cannot be stopped") as exc:
        ms.simulate(ms.build_model(inline_scene(text, tmp_path)))
    assert "\n" not in str(exc.value)


def test_driven_double_pendulum_smooth_error_is_second_order(tmp_path):
    """pendulum_wall's double pendulum with its shoulder driven as pi/2 + 1.2 sin(pi t), elbow free, 1 s (no
    impact): the ledger's smooth error (the energy change the drive's booked work does not explain) falls by 4
    when h halves, and the driven coordinate follows its trajectory to second order."""
    text = (SCENES / "pendulum_wall.toml").read_text().replace(
        "q0 = [1.5707963267948966, 0.0]", "q0 = [1.5707963267948966, 0.0]\nu0 = [3.7699111843077517, 0.0]")
    text = text.replace('urdf = "../models/', f'urdf = "{MODELS}/')
    text += ('\n[[drives]]\nbody = "pendulum"\njoint = "shoulder"\n'
             'motion = { sine = { amplitude = 1.2, frequency = 0.5 } }\n')
    S, lag = [], []
    for h in (1e-3, 5e-4):
        tr = ms.run(inline_scene(text, tmp_path), dt=h, duration=1.0, progress=False)
        assert tr.impacts == 0
        S.append(ms.ledger(tr).smooth_error)
        lag.append(np.abs(tr.q[:, 0] - (math.pi / 2 + 1.2 * np.sin(math.pi * tr.t))).max())
    assert 3.5 < S[0] / S[1] < 4.5 and abs(S[0]) < 1e-4
    assert 3.5 < lag[0] / lag[1] < 4.5


def test_info_lists_the_driven_joints():
    """`moreau-sim info` names each [[drives]] entry: body, joint and motion (text and --json)."""
    import json
    import subprocess
    import sys

    root = SCENES.parent
    env = {"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"}
    args = [sys.executable, "-m", "moreau_sim", "info"]
    r = subprocess.run(args + [str(SCENES / "driven_paddle.toml")], capture_output=True, text=True, env=env,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert "driven joints (1)" in r.stdout and "paddle  root  sine: amplitude 0.03, 3 Hz, phase 0 rad" in r.stdout
    r = subprocess.run(args + ["--json", str(SCENES / "driven_paddle.toml")], capture_output=True, text=True,
                       env=env, timeout=120)
    assert json.loads(r.stdout)["drives"] == [
        {"body": "paddle", "joint": "root", "motion": "sine: amplitude 0.03, 3 Hz, phase 0 rad"}]
