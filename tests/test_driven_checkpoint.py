"""Checkpoint and resume of driven runs (docs/output.md, docs/robots.md#actuation): joint torques (PD targets
on a time schedule, MJCF servos, a Python controller) and a moving static are functions of the step's time
and state alone, so a run killed with SIGKILL after a checkpoint and resumed gives every array (the work
terms actuator_work and obstacle_work included) and the ledger bit for bit as the uninterrupted run."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim.checkpoint import Checkpoint

from helpers import MODELS, ROOT

PADDLE = f"""[scene]
name = "driven_paddle"
[simulation]
restitution = 0.8
dt = 5e-4
duration = {{T}}
[[bodies]]
name = "ball"
urdf = "{MODELS}/ball.urdf"
root_joint = "prismatic"
axis = [0, 0, 1]
q0 = [0.5]
[[statics]]
name = "paddle"
shape = "halfspace"
motion = {{{{ sine = {{{{ amplitude = [0, 0, 0.01], frequency = 8.0 }}}} }}}}
[[actuators]]
body = "ball"
joints = ["root"]
kp = 20.0
kd = 0.5
target = {{{{ sine = {{{{ amplitude = 0.2, frequency = 1.5, offset = 0.1 }}}} }}}}
"""


def differing(a: ms.Trajectory, b: ms.Trajectory) -> list[str]:
    """Arrays (every one the files hold, the work terms included) that differ in dtype, shape or a bit."""
    assert sorted(a.arrays) == sorted(b.arrays)
    assert "actuator_work" in a.arrays
    x, y = a.arrays, b.arrays
    return [k for k in x
            if not (x[k].dtype == y[k].dtype and x[k].shape == y[k].shape and x[k].tobytes() == y[k].tobytes())]


def test_a_killed_driven_run_resumes_bit_identical(tmp_path):
    """A ball under a PD whose target is a sine, bouncing on a vibrating paddle: `moreau-sim run
    --checkpoint-every 1`, SIGKILL once the first checkpoint exists, `--resume`: identical to the full run."""
    s = tmp_path / "s.toml"
    s.write_text(PADDLE.format(T=3.0))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    run = [sys.executable, "-m", "moreau_sim", "run", str(s), "--no-progress"]
    full = subprocess.run(run + ["-o", str(tmp_path / "full.npz")], capture_output=True, text=True, env=env)
    assert full.returncode == 0, full.stderr
    cut = run + ["-o", str(tmp_path / "b.npz"), "--checkpoint-every", "1.0"]
    p = subprocess.Popen(cut, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    ck = tmp_path / "b.checkpoint.npz"
    t_end = time.monotonic() + 120
    while not ck.exists():
        assert p.poll() is None, p.communicate()[1][-500:]
        assert time.monotonic() < t_end
        time.sleep(0.005)
    p.send_signal(signal.SIGKILL)
    p.communicate(timeout=60)
    assert p.returncode == -signal.SIGKILL
    assert 0 < ms.load_trajectory(ck).meta["checkpoint"]["t"] < 3.0
    r = subprocess.run(cut + ["--resume"], capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    a, b = ms.load_trajectory(tmp_path / "full.npz"), ms.load_trajectory(tmp_path / "b.npz")
    assert len(a.arrays["log_t"]) > 5  # it strikes the paddle, before and after the cut
    assert b.complete and differing(a, b) == [] and b.meta["ledger"] == a.meta["ledger"]
    assert not ck.exists()


SERVO = """<mujoco model="slider"><compiler angle="radian"/>
  <worldbody><body name="b"><joint name="z" type="slide" axis="0 0 1"/><geom type="sphere" size=".1" mass="2"/>
  </body></worldbody><actuator><position name="lift" joint="z" kp="60" kv="2"/></actuator></mujoco>"""


@pytest.mark.parametrize("impl", ["python", "compiled"])
def test_resume_of_servo_and_controller_is_bitwise(tmp_path, impl):
    """An MJCF servo with a table ctrl plus a stateless Python controller, bouncing on the ground, on the
    Python and the compiled step: resumed from a mid-run checkpoint, every array and the ledger equal."""
    (tmp_path / "s.xml").write_text(SERVO)
    (tmp_path / "s.toml").write_text(
        '[simulation]\ndt = 1e-3\nduration = 1.5\nrestitution = 0.6\n'
        '[[bodies]]\nname = "s"\nmjcf = "s.xml"\nroot_joint = "fixed"\nposition = [0, 0, 0.3]\n'
        '[[statics]]\nname = "ground"\nshape = "halfspace"\n'
        '[[actuators]]\nbody = "s"\nmjcf = ["lift"]\nctrl = { t = [0.0, 0.5, 1.0], ctrl = [0.0, -0.4, 0.1] }\n')
    sc = ms.load_scene(tmp_path / "s.toml").with_options(step_impl=impl, save_every=2)

    def f(t, q, u):
        return np.array([3.0 * np.sin(7.0 * t)])

    path = tmp_path / "c.npz"
    full = ms.simulate(ms.build_model(sc), controller=f, progress=False,
                       checkpoint=Checkpoint(path=path, every=0.6, keep=True))
    assert 0 < ms.load_trajectory(path).meta["checkpoint"]["steps"] < 1500
    resumed = ms.simulate(ms.build_model(sc), controller=f, progress=False,
                          checkpoint=Checkpoint(path=path, resume=True))
    assert len(full.arrays["log_t"]) > 2  # it strikes the ground
    assert resumed.complete and differing(full, resumed) == [] and resumed.meta["ledger"] == full.meta["ledger"]
