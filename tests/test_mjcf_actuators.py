"""MJCF <motor> and <position> actuators (moreau_sim/mjcf_actuators.py, docs/robots.md#mjcf-actuators):
the torques are MuJoCo's, checked against hand-computed values (and MuJoCo's own qfrc_actuator where MuJoCo
is installed); the scene gives the control signal ([[actuators]] mjcf/ctrl, 0 by default); a servo holds a
slider at its closed-form equilibrium with the ledger closed; everything else under <actuator> is refused
with file:line; `moreau-sim info` lists the actuators."""

import json
import subprocess
import sys

import numpy as np
import pytest

import moreau_sim as ms

from helpers import ROOT

G = 9.81

ARM = """<mujoco model="arm">
  <compiler angle="radian"/>
  <default><position kp="50" kv="3" ctrlrange="-1 1"/><default class="b"><motor gear="2"/></default></default>
  <worldbody><body name="l1"><joint name="j" type="hinge" axis="0 1 0"/>
    <geom type="sphere" size=".1" mass="1" pos="0 0 -0.5"/>
    <body name="l2" pos="0 0 -1"><joint name="k" type="slide" axis="1 0 0"/><geom type="sphere" size=".1" mass="1"/>
    </body></body></worldbody>
  <actuator>{actuators}</actuator>
</mujoco>"""
ACTS = ('<position joint="j"/><motor class="b" joint="k" forcerange="-0.5 0.5"/>'
        '<position name="p2" joint="k" gear="3" kp="10"/>')

SCENE = """[scene]
name = "arm"
[simulation]
dt = {h}
duration = {T}
restitution = {e}
[[bodies]]
name = "arm"
mjcf = "arm.xml"
root_joint = "fixed"
position = [0, 0, 3]
{extra}"""


def arm(tmp_path, actuators=ACTS, extra="", h=1e-3, T=0.01, e=0.5, xml=ARM):
    (tmp_path / "arm.xml").write_text(xml.format(actuators=actuators))
    p = tmp_path / "s.toml"
    p.write_text(SCENE.format(h=h, T=T, e=e, extra=extra))
    return p


def model(path):
    return ms.build_model(ms.load_scene(path))


CTRL = '[[actuators]]\nbody = "arm"\nmjcf = ["actuator 0", "actuator 1", "p2"]\nctrl = [{}, {}, {}]\n'


@pytest.mark.parametrize("q, u, c", [((0.2, 0.1), (0.5, -0.3), (2.0, 3.0, 0.4)),
                                     ((-0.4, 0.02), (0.0, 1.0), (0.3, -0.2, -5.0))])
def test_torques_are_mujocos_by_hand(tmp_path, q, u, c):
    """tau = gear F, F = clamp(gain clamp(c, ctrlrange) - kp gear q - kv gear u, forcerange): the hinge's
    position servo (kp 50, kv 3 from the default class, ctrlrange [-1, 1]); on the slide a motor (gear 2 from
    class b, forcerange +-0.5) plus a position servo (gear 3, kp 10, kv 3 inherited)."""
    m = model(arm(tmp_path, extra=CTRL.format(*c)))
    tau = m.actuation.torque(0.0, np.array(q), np.array(u))
    clip = lambda x, lo, hi: min(max(x, lo), hi)  # noqa: E731
    hinge = 50.0 * (clip(c[0], -1, 1) - q[0]) - 3.0 * u[0]
    motor = 2.0 * clip(clip(c[1], -1, 1), -0.5, 0.5)
    servo = 3.0 * (10.0 * (clip(c[2], -1, 1) - 3.0 * q[1]) - 3.0 * (3.0 * u[1]))
    assert tau.tolist() == pytest.approx([hinge, motor + servo], rel=1e-15, abs=1e-15)


def test_torques_equal_mujocos_qfrc_actuator(tmp_path):
    """The same model in MuJoCo itself: qfrc_actuator equals our tau (to round-off). MuJoCo is in the `test`
    extra: a missing one fails here rather than skipping."""
    import mujoco
    mm = mujoco.MjModel.from_xml_string(ARM.format(actuators=ACTS))
    d = mujoco.MjData(mm)
    m = model(arm(tmp_path, extra=CTRL.format(2.0, 3.0, 0.4)))
    for q, u in [((0.2, 0.1), (0.5, -0.3)), ((1.1, -0.7), (-2.0, 0.4))]:
        d.qpos[:], d.qvel[:], d.ctrl[:] = q, u, (2.0, 3.0, 0.4)
        mujoco.mj_forward(mm, d)
        assert m.actuation.torque(0.0, np.array(q), np.array(u)) == pytest.approx(d.qfrc_actuator, rel=1e-12)


# the joints' actuatorfrcrange: on the slide k its own, on the hinge j its class's (b); MuJoCo clamps the sum of a
# joint's actuators (qfrc_actuator), not each actuator's force
CLAMPED = (ARM.replace('<motor gear="2"/></default>', '<motor gear="2"/><joint actuatorfrcrange="-4 4"/></default>')
           .replace('<joint name="j" type="hinge"', '<joint name="j" class="b" type="hinge"')
           .replace('type="slide" axis="1 0 0"', 'type="slide" axis="1 0 0" actuatorfrcrange="-2 1.5"'))


@pytest.mark.parametrize("c", [(2.0, 3.0, 0.4), (0.01, 0.02, 0.01), (-1.0, -3.0, -0.2)])
def test_joint_actuator_force_range_is_mujocos(tmp_path, c):
    """A joint's actuatorfrcrange clamps the sum of its actuators' torques as MuJoCo's qfrc_actuator does (the
    slide's motor + servo sum to 25.6 N at the first state: 1.5 N), inside the range nothing changes: our tau
    equals MuJoCo's to round-off, clamped or not, for the joint's own range and its class's."""
    import mujoco
    mm = mujoco.MjModel.from_xml_string(CLAMPED.format(actuators=ACTS))
    assert mm.jnt_actfrclimited.tolist() == [1, 1]
    d = mujoco.MjData(mm)
    m = model(arm(tmp_path, extra=CTRL.format(*c), xml=CLAMPED))
    clamped = free = 0
    for q, u in [((0.2, 0.1), (0.5, -0.3)), ((1.1, -0.7), (-2.0, 0.4)), ((0.0, 0.001), (0.01, 0.0)),
                 ((-1.0, -0.06), (0.0, 0.0))]:
        d.qpos[:], d.qvel[:], d.ctrl[:] = q, u, c
        mujoco.mj_forward(mm, d)
        tau = m.actuation.torque(0.0, np.array(q), np.array(u))
        assert tau == pytest.approx(d.qfrc_actuator, rel=1e-12, abs=1e-15), (q, u, tau, d.qfrc_actuator)
        raw = np.zeros(2)  # the joints' sums before MuJoCo's clamp
        np.add.at(raw, mm.actuator_trnid[:, 0], mm.actuator_gear[:, 0] * d.actuator_force)
        hit = np.abs(raw - d.qfrc_actuator) > 1e-9
        clamped, free = clamped + int(hit.sum()), free + int((~hit).sum())
    assert clamped >= 2 and free >= 1  # the clamp acted, and left sums inside the range alone


def test_joint_actuator_force_range_clamps_the_motion(tmp_path):
    """Two motors asking 10 N and 5 N of a 2 kg vertical slider whose joint has actuatorfrcrange [-3, 3]: the joint
    gets 3 N in all, so it accelerates at 3/2 - g0 exactly; with actuatorfrclimited="false" the range is not read
    (15/2 - g0); a limited joint without its range is one line with file:line."""
    acts = '<motor name="a" joint="z"/><motor name="b" joint="z"/>'
    ctrl = '[[actuators]]\nbody = "arm"\nmjcf = "all"\nctrl = [10.0, 5.0]\n'
    for flag, force in [("", 3.0), (' actuatorfrclimited="false"', 15.0)]:
        xml = SLIDER.replace('axis="0 0 1"', f'axis="0 0 1" actuatorfrcrange="-3 3"{flag}')
        tr = ms.simulate(model(arm(tmp_path, acts, ctrl, T=0.1, xml=xml)), progress=False)
        assert tr.u[-1, 0] == pytest.approx(0.1 * (force / 2.0 - G), rel=1e-12)
    with pytest.raises(ms.SceneError) as info:
        model(arm(tmp_path, acts, ctrl, xml=SLIDER.replace('axis="0 0 1"', 'axis="0 0 1" actuatorfrclimited="true"')))
    assert "\n" not in str(info.value) and "arm.xml:2: joint 'z': actuatorfrcrange=None is not two numbers" in str(
        info.value), str(info.value)


def test_ctrl_defaults_to_zero_and_follows_a_schedule(tmp_path):
    """Without a ctrl the control is 0 (MuJoCo's default): the hinge servo pulls to q = 0. A sine ctrl for
    one actuator: c(t) = 0.5 sin(2 pi t) reaches the torque at t = 0.25 s."""
    m = model(arm(tmp_path))
    assert m.actuation.torque(0.0, np.array([0.2, 0.0]), np.zeros(2))[0] == pytest.approx(-50.0 * 0.2)
    sine = ('[[actuators]]\nbody = "arm"\nmjcf = ["actuator 0"]\n'
            'ctrl = { sine = { amplitude = 0.5, frequency = 1.0 } }\n')
    m = model(arm(tmp_path, extra=sine))
    assert m.actuation.torque(0.25, np.zeros(2), np.zeros(2))[0] == pytest.approx(50.0 * 0.5, rel=1e-15)
    table = '[[actuators]]\nbody = "arm"\nmjcf = "all"\nctrl = { t = [0.0, 1.0], ctrl = [[0, 0, 0], [1, 1, 0.2]] }\n'
    m = model(arm(tmp_path, extra=table))
    tau = m.actuation.torque(0.5, np.zeros(2), np.zeros(2))
    assert tau.tolist() == pytest.approx([50.0 * 0.5, 2.0 * 0.5 + 3.0 * 10.0 * 0.1], rel=1e-15)


SLIDER = """<mujoco model="slider"><compiler angle="radian"/>
  <worldbody><body name="b"><joint name="z" type="slide" axis="0 0 1"/><geom type="sphere" size=".1" mass="2"/>
  </body></worldbody><actuator>{actuators}</actuator></mujoco>"""


@pytest.mark.parametrize("h", [1e-3, 4e-4])
@pytest.mark.parametrize("gear", [1.0, 2.0])
def test_position_servo_holds_the_closed_form_equilibrium(tmp_path, h, gear):
    """A 2 kg vertical slider under <position kp=400 kv=40 gear=g> with ctrl 0.3: at rest
    g kp (c - g z) = m g0, z = (c - m g0/(g kp))/g exactly; the ledger closes to round-off (M constant)."""
    acts = f'<position name="lift" joint="z" kp="400" kv="40" gear="{gear}"/>'
    extra = '[[actuators]]\nbody = "arm"\nmjcf = ["lift"]\nctrl = 0.3\n'
    tr = ms.simulate(model(arm(tmp_path, acts, extra, h=h, T=6.0, xml=SLIDER)), progress=False)
    z = (0.3 - 2.0 * G / (gear * 400.0)) / gear
    assert tr.q[-1, 0] == pytest.approx(z, abs=1e-9)
    assert abs(tr.u[-1, 0]) <= 1e-9
    L = ms.ledger(tr)
    assert abs(L.residual) <= 1e-12 * L.scale and abs(L.smooth_error) <= 1e-12 * L.scale
    assert L.actuator_work == pytest.approx(float(np.asarray(tr.arrays["actuator_work"]).sum()), abs=0)


def test_motor_force_range_clamps(tmp_path):
    """A motor asking for 10 N (ctrl 10, gear 1) with forcerange [-3, 3]: the 2 kg slider accelerates at
    3/2 - g0 exactly."""
    acts = '<motor name="m" joint="z" forcerange="-3 3"/>'
    tr = ms.simulate(model(arm(tmp_path, acts, '[[actuators]]\nbody = "arm"\nmjcf = "all"\nctrl = 10.0\n',
                               T=0.1, xml=SLIDER)), progress=False)
    assert tr.u[-1, 0] == pytest.approx(0.1 * (3.0 / 2.0 - G), rel=1e-12)


@pytest.mark.parametrize("acts, fragments", [
    ('<general joint="j"/>', ["<general> is not supported", "other than <motor> and <position>"]),
    ('<velocity joint="j" kv="1"/>', ["<velocity> is not supported"]),
    ('<motor tendon="t"/>', ["<motor tendon=...> is not supported", "transmission must be a joint"]),
    ('<position joint="j" dampratio="1"/>', ["<position dampratio=...> is not supported"]),
    ('<position joint="j" timeconst="0.1"/>', ["<position timeconst=...> is not supported"]),
    ('<motor joint="j" gear="1 0 0 1 0 0"/>', ["only the first entry acts"]),
    ('<motor joint="nope"/>', ["joint 'nope' names no joint"]),
    ('<motor joint="j" ctrlrange="1 -1"/>', ["ctrlrange 1 -1 must be finite with lower < upper"]),
    ('<motor/>', ["has no joint="]),
])
def test_other_actuators_are_refused_with_file_and_line(tmp_path, acts, fragments):
    with pytest.raises(ms.SceneError) as info:
        model(arm(tmp_path, acts))
    msg = str(info.value)
    assert "\n" not in msg and f"{tmp_path / 'arm.xml'}:8" in msg, msg
    for f in fragments:
        assert f in msg, (f, msg)


def test_motor_outside_actuator_and_on_a_ball_joint_are_refused(tmp_path):
    xml = ARM.replace('<geom type="sphere" size=".1" mass="1" pos="0 0 -0.5"/>',
                      '<geom type="sphere" size=".1" mass="1" pos="0 0 -0.5"/><motor joint="j"/>')
    with pytest.raises(ms.SceneError, match=r"arm.xml:5: <motor> is not supported"):
        model(arm(tmp_path, xml=xml))
    ball = ARM.replace('type="slide" axis="1 0 0"', 'type="ball"')
    with pytest.raises(ms.SceneError, match="only hinge and slide joints are actuated"):
        model(arm(tmp_path, '<motor joint="k"/>', xml=ball))


@pytest.mark.parametrize("extra, fragment", [
    ('[[actuators]]\nbody = "arm"\nmjcf = ["nope"]\nctrl = 1.0\n', "'nope' names no MJCF actuator of arm"),
    ('[[actuators]]\nbody = "arm"\nmjcf = ["p2"]\nctrl = [1.0, 2.0]\n', "ctrl: must be a list of 1 numbers"),
    ('[[actuators]]\nbody = "arm"\nmjcf = ["p2"]\n', "missing required key 'ctrl'"),
    ('[[actuators]]\nbody = "arm"\nmjcf = ["p2"]\nctrl = 1.0\nkp = 3.0\n', "unknown key(s) ['kp']"),
    ('[[actuators]]\nbody = "arm"\nmjcf = ["p2"]\nctrl = 1.0\n[[actuators]]\nbody = "arm"\nmjcf = ["p2"]\n'
     'ctrl = 2.0\n', "'p2' is given a ctrl by two entries"),
])
def test_bad_ctrl_entries_are_one_line(tmp_path, extra, fragment):
    with pytest.raises(ms.SceneError) as info:
        model(arm(tmp_path, extra=extra))
    assert "\n" not in str(info.value) and fragment in str(info.value), str(info.value)


def test_ctrl_on_a_urdf_body_is_refused(tmp_path):
    p = tmp_path / "u.toml"
    p.write_text(f'[[bodies]]\nname = "p"\nurdf = "{ROOT}/models/pendulum_limit.urdf"\nroot_joint = "fixed"\n'
                 '[[actuators]]\nbody = "p"\nmjcf = "all"\nctrl = 1.0\n')
    with pytest.raises(ms.SceneError, match="not read from an MJCF file"):
        model(p)


def test_info_lists_the_actuators(tmp_path):
    p = arm(tmp_path, extra=CTRL.format(1, 1, 1))
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    r = subprocess.run([sys.executable, "-m", "moreau_sim", "info", str(p)], capture_output=True, text=True,
                       env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "actuators (3)" in r.stdout
    assert "arm/p2  arm/k  mjcf position  gear = 3, kp = 10, kv = 3, ctrl from scene  (ctrlrange [-1, 1])" in r.stdout
    r = subprocess.run([sys.executable, "-m", "moreau_sim", "info", "--json", str(p)], capture_output=True,
                       text=True, env=env, timeout=120)
    acts = json.loads(r.stdout)["actuators"]
    assert [a["kind"] for a in acts] == ["mjcf position", "mjcf motor", "mjcf position"]
    assert acts[1]["forcerange"] == [-0.5, 0.5] and acts[1]["gear"] == 2.0


def test_the_bundled_servo_arm_follows_its_controls(tmp_path):
    """models/servo_arm.xml (docs/robots.md's example): the position servo "lift" (kp 40, kv 2 from its
    default class) gives 40 (0.8 - q) - 2 u on the hinge for ctrl 0.8 rad, the motor "push" (gear 2, ctrl 1)
    2 N on the slide; the arm runs."""
    p = tmp_path / "s.toml"
    p.write_text(f'[simulation]\ndt = 1e-3\nduration = 0.2\n[[bodies]]\nname = "arm"\n'
                 f'mjcf = "{ROOT}/models/servo_arm.xml"\nroot_joint = "fixed"\nposition = [0, 0, 1]\n'
                 '[[actuators]]\nbody = "arm"\nmjcf = ["lift", "push"]\nctrl = [0.8, 1.0]\n')
    m = model(p)
    q, u = np.array([0.3, 0.1]), np.array([0.2, -0.4])
    tau = m.actuation.torque(0.0, q, u)
    assert tau.tolist() == pytest.approx([40.0 * (0.8 - 0.3) - 2.0 * 0.2, 2.0 * 1.0], rel=1e-15)
    tr = ms.simulate(m, progress=False)
    assert np.isfinite(tr.q).all() and tr.meta["status"] == "complete"
