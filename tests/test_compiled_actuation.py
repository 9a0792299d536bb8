"""Joint torques in the compiled run loop (src/actuation.hpp in src/run.cpp's Runner, moreau_sim/compiled_run.py)
against the Python run: the scene's PD targets (constants, tables, sines, velocity targets, effort clamps), MJCF
<motor>/<position> actuators (ctrl schedules, forcerange, actuatorfrcrange) and a Python controller called back
once per step give the Python run's arrays, ledger figures and status bit for bit, through impacts, checks that
hand a step back, checkpoints and the controller's errors (one line naming the step, the samples so far kept).
The torques' work in the ledger is summed in index order on both sides (sums.ordered: docs/theory.md §2.8)."""

from __future__ import annotations

import array
from pathlib import Path

import numpy as np
import pytest

import moreau_sim as ms
import moreau_sim.compiled as compiled
from moreau_sim import compiled_run
from moreau_sim.checkpoint import Checkpoint

from helpers import ROOT, inline_scene

SCENES = sorted((Path(ROOT) / "scenes").glob("*.toml"))
MAX_STEPS = 400


def _differ(a, b) -> list[str]:
    def same(x, y):
        return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
    keys = set(a.arrays) | set(b.arrays)
    return sorted(k for k in keys if k not in a.arrays or k not in b.arrays or not same(a.arrays[k], b.arrays[k]))


def _both(model, **kw):
    """The Python run and the compiled run of `model` (a SimulationError: its message and trajectory)."""
    got = []
    for python_run in (True, False):
        try:
            got.append(ms.simulate(model, progress=False, python_run=python_run, **kw))
        except ms.SimulationError as exc:
            got.append(exc)
    return got


def _same(ref, new) -> None:
    assert type(ref) is type(new)
    if isinstance(ref, Exception):
        assert str(ref) == str(new)
        ref, new = ref.trajectory, new.trajectory
    assert ref.meta["run"]["loop"] == "python" and new.meta["run"]["loop"] == "compiled"
    assert _differ(ref, new) == []
    assert ref.meta["ledger"] == new.meta["ledger"]
    assert ref.meta["status"] == new.meta["status"] and ref.meta.get("invariants") == new.meta.get("invariants")


@pytest.fixture(scope="module", autouse=True)
def _compiled():
    assert compiled.available(), compiled.unavailable_reason()


ACTUATED = [p for p in SCENES if "[[actuators]]" in p.read_text()]


@pytest.mark.parametrize("path", ACTUATED, ids=[p.stem for p in ACTUATED])
def test_actuated_scenes_same_run_both_loops(path):
    """Every bundled scene with [[actuators]] the compiled step takes gives the Python run's arrays bit for bit
    (the others: not for their torques)."""
    sc = ms.load_scene(path)
    sc = sc.with_options(duration=min(sc.options.duration, MAX_STEPS * sc.options.dt))
    model = ms.build_model(sc)
    assert model.actuation is not None
    why = compiled_run.unsupported(model, None)
    if why is not None:
        assert "torque" not in why
        return
    ref, new = _both(model)
    _same(ref, new)
    t = new if not isinstance(new, Exception) else new.trajectory
    assert np.any(t.arrays["actuator_work"] != 0.0)


ARM = """<mujoco model="arm">
  <compiler angle="radian"/>
  <default><position kp="40" kv="2" ctrlrange="-1.5 1.5"/></default>
  <worldbody><body name="rod"><joint name="shoulder" type="hinge" axis="0 1 0" actuatorfrcrange="-30 30"/>
    <geom name="bob" type="sphere" size="0.05" pos="0 0 -0.4" mass="1"/>
    <body name="slider" pos="0 0 -0.4"><joint name="extend" type="slide" axis="1 0 0"/>
      <geom name="block" type="sphere" size="0.04" mass="0.5"/></body></body></worldbody>
  <actuator><position name="lift" joint="shoulder"/><motor name="twist" joint="shoulder" gear="3"/>
    <motor name="push" joint="extend" gear="2" forcerange="-5 5"/></actuator>
</mujoco>"""
CTRL = {  # the controls of lift, twist, push: constants, a table, a sine
    "constant": "ctrl = [0.8, 0.5, 1.0]",
    "table": "ctrl = { t = [0.0, 0.1, 0.25], ctrl = [[1.2, 0.0, -1.0], [-0.4, 2.0, 1.0], [0.3, -1.0, 0.5]] }",
    "sine": "ctrl = { sine = { amplitude = [1.0, 3.0, 2.0], frequency = 4.0, phase = 0.3 } }",
}


def _arm(tmp_path, ctrl: str, h: float, e: float, T: float = 0.4, extra: str = ""):
    """The MJCF arm swinging from 1 rad down onto the ground (its bob and slider strike it), its three actuators
    under the given controls."""
    (tmp_path / "arm.xml").write_text(ARM)
    p = tmp_path / "arm.toml"
    p.write_text(f'[simulation]\ndt = {h}\nduration = {T}\nrestitution = {e}\n'
                 f'[[bodies]]\nname = "arm"\nmjcf = "arm.xml"\nroot_joint = "fixed"\nposition = [0, 0, 0.43]\n'
                 f'q0 = [1.0, 0.05]\n[[statics]]\nname = "ground"\nshape = "halfspace"\n'
                 f'[[actuators]]\nbody = "arm"\nmjcf = "all"\n{CTRL[ctrl]}\n{extra}')
    return ms.build_model(ms.load_scene(p))


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("h", [1e-3, 2e-3])
@pytest.mark.parametrize("ctrl", sorted(CTRL))
def test_mjcf_actuators_same_run_both_loops(tmp_path, ctrl, h, e):
    """<position> and <motor> on one hinge (their sum clamped to the joint's actuatorfrcrange), a motor with a
    forcerange on a slide, under constant, tabled and sine controls: the same run bit for bit, impacts included."""
    model = _arm(tmp_path, ctrl, h, e)
    ref, new = _both(model)
    _same(ref, new)
    assert new.meta["run"]["python_steps"] < new.meta["run"]["steps"]
    assert len(new.arrays["log_P"]) > 0  # it struck the ground


PD = {  # a [[actuators]] PD entry on the arm's two joints (no MJCF ctrl: the servos' ctrl is 0)
    "table": 'target = { t = [0.0, 0.2, 0.3], q = [[0.5, 0.1], [-0.3, -0.1], [0.2, 0.0]] }\neffort = 12.0',
    "sine": 'target = { sine = { amplitude = [0.7, 0.1], frequency = 2.0, offset = [0.2, 0.0] } }',
    "velocity": 'target = [0.4, 0.0]\nvelocity = { t = [0.0, 0.2], u = [[0.0, 0.0], [1.0, -0.5]] }\neffort = 6.0',
}


@pytest.mark.parametrize("e", [0.0, 0.5])
@pytest.mark.parametrize("pd", sorted(PD))
def test_pd_targets_same_run_both_loops(tmp_path, pd, e):
    """PD targets (a table, a sine, a velocity table; an effort clamp) beside the MJCF servos: bit for bit."""
    model = _arm(tmp_path, "constant", 1e-3, e,
                 extra=f'[[actuators]]\nbody = "arm"\njoints = ["shoulder", "extend"]\nkp = 25.0\nkd = 1.5\n{PD[pd]}\n')
    ref, new = _both(model)
    _same(ref, new)


def _pd_controller():
    calls = [0]

    def f(t, q, u):
        calls[0] += 1
        return np.array([-8.0 * (q[0] - 0.3 * np.sin(5.0 * t)) - 0.5 * u[0], 2.0 * np.cos(3.0 * t) - 0.1 * u[1]])
    return f, calls


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_a_controller_same_run_both_loops(tmp_path, e):
    """A Python controller, called back from the Runner once per step (the meta says so), and the scene's
    actuators: bit for bit, and the controller called exactly once per step in either loop."""
    model = _arm(tmp_path, "table", 1e-3, e)
    f, calls = _pd_controller()
    g, calls_g = _pd_controller()
    ref = ms.simulate(model, progress=False, python_run=True, controller=f)
    new = ms.simulate(model, progress=False, controller=g)
    _same(ref, new)
    steps = new.meta["run"]["steps"]
    assert calls[0] == calls_g[0] == steps
    assert new.meta["run"]["python_calls"] == "the controller, once a step"


def test_a_zero_controller_through_handed_back_steps():
    """slider_crank_clearance breaks its penetration check: the Runner hands those steps back to the Python run, which
    replays the controller's answer (not asking it twice); a counting controller is called once per step and the
    arrays are the Python run's."""
    sc = ms.load_scene(Path(ROOT) / "scenes" / "slider_crank_clearance.toml")
    model = ms.build_model(sc)
    runs, counts = [], []
    for python_run in (True, False):
        calls = [0]

        def zero(t, q, u, calls=calls):
            calls[0] += 1
            return np.zeros(model.nv)
        runs.append(ms.simulate(model, progress=False, python_run=python_run, controller=zero))
        counts.append(calls[0])
    ref, new = runs
    _same(ref, new)
    assert new.meta["run"]["python_steps"] > 0  # steps handed back after the controller was asked
    assert counts[0] == counts[1] == new.meta["run"]["steps"]


FAULTS = {  # a controller's faulty answer: its fault, the error's line
    "raise": (lambda q: 1 / 0, "the controller raised ZeroDivisionError: division by zero"),
    "shape": (lambda q: np.zeros(3), "the controller returned shape (3,), expected (2,)"),
    "column": (lambda q: np.zeros((2, 1)), "the controller returned shape (2, 1), expected (2,)"),
    "scalar": (lambda q: 0.0, "the controller returned shape (), expected (2,)"),
    "nan": (lambda q: np.array([np.nan, 0.0]), "the controller returned a non-finite torque"),
    "inf": (lambda q: np.array([0.0, -np.inf]), "the controller returned a non-finite torque"),
    "nan list": (lambda q: [0.0, float("nan")], "the controller returned a non-finite torque"),
    "strings": (lambda q: ["a", "b"], "the controller raised ValueError: could not convert string to float: 'a'"),
    "writes q": (lambda q: q.__setitem__(0, 0.0), "the controller raised ValueError: assignment destination is "
                 "read-only"),
}


@pytest.mark.parametrize("fault", sorted(FAULTS))
def test_controller_errors_as_in_the_python_run(tmp_path, fault):
    """A controller that raises, returns the wrong shape, a NaN or an inf (an array or a list), what numpy cannot
    read as floats, or writes into its q at step 151 (t_m = 0.1505 s): the same one-line error naming the step (and
    its time) in both loops, with the same samples so far."""
    model = _arm(tmp_path, "constant", 1e-3, 0.5)
    answer, message = FAULTS[fault]

    def bad(t, q, u):
        if t > 0.15:
            return answer(q)
        return np.array([-q[0], 0.0])
    ref, new = _both(model, controller=bad)
    assert isinstance(ref, ms.SimulationError) and message in str(ref)
    assert str(ref).startswith("step 151 (t = 0.15 s): ")
    assert "\n" not in str(ref)
    _same(ref, new)
    assert len(new.trajectory.arrays["t"]) == 151  # the start and the 150 steps before


ANSWERS = {  # what a controller may return besides a float64 array: numpy reads each as (nv,) floats
    "list": lambda f: f.tolist(), "tuple": lambda f: tuple(f), "float32": lambda f: f.astype(np.float32),
    "int": lambda f: np.rint(f).astype(int), "strided": lambda f: np.repeat(f, 2)[::2],
    "big-endian": lambda f: f.astype(">f8"), "array.array": lambda f: array.array("d", f),
    "negative zero": lambda f: np.copysign(0.0, -f),
}


@pytest.mark.parametrize("kind", sorted(ANSWERS))
def test_controller_answers_numpy_reads(tmp_path, kind):
    """A controller returning a list, a tuple, float32 or integers, a strided view, big-endian floats, an
    array.array or negative zeros: the compiled run takes the numbers numpy.asarray(f, float) reads, the Python
    run's arrays bit for bit."""
    model = _arm(tmp_path, "constant", 1e-3, 0.5, T=0.2)
    f, _ = _pd_controller()
    ref, new = _both(model, controller=lambda t, q, u: ANSWERS[kind](f(t, q, u)))
    _same(ref, new)
    assert np.any(new.arrays["actuator_work"] != 0.0) or kind == "negative zero"


def _free_ball(tmp_path):
    """A ball on a free root (rows 0-5 never actuated) dropped onto the ground."""
    return ms.build_model(inline_scene("""
[simulation]
dt = 1e-3
duration = 0.2
[[bodies]]
name = "ball"
urdf = "{models}/ball.urdf"
root_joint = "free"
q0 = [0, 0, 0.3, 0, 0, 0, 1]
[[statics]]
name = "ground"
shape = "halfspace"
""", tmp_path))


@pytest.mark.parametrize("row", [None, 2, 5])
def test_root_rows_as_in_the_python_run(tmp_path, row):
    """A controller on a free ball: zeros (negative zeros on the root rows) are taken; a torque on a root row at step
    101 stops both loops with the same line, the steps before it recorded."""
    model = _free_ball(tmp_path)

    def f(t, q, u):
        tau = -np.zeros(6)
        if row is not None and t > 0.1:
            tau[row] = 1e-3
        return tau
    ref, new = _both(model, controller=f)
    _same(ref, new)
    if row is None:
        assert not isinstance(new, Exception)
        return
    assert str(ref) == ("step 101 (t = 0.1 s): the controller returned a torque on the rows of a root joint that is "
                        "not fixed (ball/root) at t = 0.1005 s: floating bases are not actuated")
    assert len(new.trajectory.arrays["t"]) == 101


@pytest.mark.parametrize("keep", ["arrays", "slices", "nothing"])
def test_controller_keeps_what_it_is_given(tmp_path, keep):
    """The controller may keep the q and u it is given, or views of them: in the compiled run as in the Python run
    what it keeps holds q_m and u_k of that step, read-only, never rewritten by a later step (the Runner refills its
    arrays in place only where nothing else refers to them); the runs are the same bit for bit."""
    model = _arm(tmp_path, "constant", 1e-3, 0.5, T=0.1)
    kept, runs = [], []
    for python_run in (True, False):
        seen = []
        f, _ = _pd_controller()

        def controller(t, q, u, seen=seen, f=f):
            if keep != "nothing":
                seen.append((t, q, u) if keep == "arrays" else (t, q[1:], u[:1]))
            return f(t, q, u)
        runs.append(ms.simulate(model, progress=False, python_run=python_run, controller=controller))
        kept.append(seen)
    _same(*runs)
    ref, new = kept
    if keep == "nothing":
        return
    assert len(ref) == len(new) == 100
    for (t0, q0, u0), (t1, q1, u1) in zip(ref, new):
        assert t0 == t1 and q0.tobytes() == q1.tobytes() and u0.tobytes() == u1.tobytes()
        assert not q1.flags.writeable and not u1.flags.writeable
    assert len({q.tobytes() for _, q, _ in new}) > 90  # distinct configurations, each kept as it was


def test_resume_in_an_actuated_compiled_run(tmp_path):
    """A checkpoint in the middle of a compiled actuated run (a controller and tabled controls) and a resume from
    it give the uninterrupted Python run's arrays and ledger."""
    model = _arm(tmp_path, "table", 1e-3, 0.5, T=0.3)
    f, _ = _pd_controller()
    ref = ms.simulate(model, progress=False, python_run=True, controller=f)
    path = tmp_path / "c.npz"
    f, _ = _pd_controller()
    full = ms.simulate(model, progress=False, controller=f, checkpoint=Checkpoint(path=path, every=0.11, keep=True))
    assert 0 < ms.load_trajectory(path).meta["checkpoint"]["steps"] < 300
    f, _ = _pd_controller()
    resumed = ms.simulate(model, progress=False, controller=f, checkpoint=Checkpoint(path=path, resume=True))
    for run in (full, resumed):
        assert run.meta["run"]["loop"] == "compiled"
        assert _differ(ref, run) == [] and run.meta["ledger"] == ref.meta["ledger"]
