"""Bad input stops with a message naming the file and the field, never a library traceback."""

import subprocess
import sys

import numpy as np
import pytest

import moreau_sim as ms

from helpers import MODELS, SCENES

BALL = """
[scene]
name = "ball"
[simulation]
restitution = 0.5
dt = 1e-3
duration = 0.1
[[bodies]]
name = "ball"
urdf = "{urdf}"
root_joint = "prismatic"
axis = [0, 0, 1]
q0 = [1.0]
[[statics]]
name = "ground"
shape = "halfspace"
"""


def write(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def ball(tmp_path, urdf=None, **replace):
    text = BALL.format(urdf=urdf or MODELS / "ball.urdf")
    for old, new in replace.items():
        text = text.replace(old.replace("__", " "), new)
    return write(tmp_path, text)


def expect_error(path, *fragments):
    with pytest.raises(ms.SceneError) as info:
        ms.build_model(ms.load_scene(path))
    msg = str(info.value)
    for f in (str(path),) + fragments:
        assert f in msg, (f, msg)
    return msg


def test_valid_inline_scene_builds(tmp_path):
    model = ms.build_model(ms.load_scene(ball(tmp_path)))
    assert (model.nq, model.nv) == (1, 1)


def test_missing_scene_file(tmp_path):
    with pytest.raises(ms.SceneError, match="scene file not found"):
        ms.load_scene(tmp_path / "nope.toml")


def test_missing_urdf(tmp_path):
    expect_error(ball(tmp_path, urdf=tmp_path / "missing.urdf"), "urdf", "file not found", "missing.urdf")


def test_malformed_toml(tmp_path):
    expect_error(write(tmp_path, "[scene\nname = 1"), "malformed TOML")


def test_unknown_key(tmp_path):
    expect_error(ball(tmp_path, **{"restitution": "restitusion"}), "[simulation]", "unknown key", "restitusion")
    expect_error(ball(tmp_path, **{"axis": "axes_typo"}), "[[bodies]][0]", "unknown key", "axes_typo")


@pytest.mark.parametrize("value", ["-0.1", "1.5", "nan", '"high"'])
def test_restitution_outside_range(tmp_path, value):
    expect_error(ball(tmp_path, **{"restitution = 0.5": f"restitution = {value}"}), "restitution")


@pytest.mark.parametrize("value", ["0", "-1e-3", "inf"])
def test_step_not_positive(tmp_path, value):
    expect_error(ball(tmp_path, **{"dt = 1e-3": f"dt = {value}"}), "dt")


def test_capsule_in_urdf_is_refused_with_the_link(tmp_path):
    """urdfdom drops every collision of a link with a <capsule> (with only a print): we refuse it."""
    urdf = (MODELS / "ball.urdf").read_text().replace('<sphere radius="0.1"/>', '<capsule radius="0.1" length="0.2"/>')
    u = write(tmp_path, urdf, "capsule.urdf")
    msg = expect_error(ball(tmp_path, urdf=u), "link 'ball'", "capsule")
    assert str(u) in msg


def test_malformed_urdf(tmp_path):
    u = write(tmp_path, "<robot name='x'><link name='a'>", "bad.urdf")
    expect_error(ball(tmp_path, urdf=u), "malformed URDF", str(u))


def test_wrong_initial_state_length(tmp_path):
    expect_error(ball(tmp_path, **{"q0 = [1.0]": "q0 = [1.0, 2.0]"}), "q0", "nq = 1")


def test_bad_enum_and_vector(tmp_path):
    expect_error(ball(tmp_path, **{'"prismatic"': '"slider"'}), "root_joint", "slider")
    expect_error(ball(tmp_path, **{"axis = [0, 0, 1]": "axis = [0, 0]"}), "axis", "3 numbers")
    expect_error(ball(tmp_path, **{"axis = [0, 0, 1]": "axis = [0, 0, 0]"}), "axis", "zero")


def test_collision_names_must_exist(tmp_path):
    p = ball(tmp_path)
    p.write_text(p.read_text() + '[collisions]\nexclude = [["ball", "wall"]]\n')
    expect_error(p, "[collisions] exclude", "'wall'")


def test_option_overrides_are_validated():
    sc = ms.load_scene(SCENES / "bouncing_ball.toml")
    with pytest.raises(ms.SceneError, match="restitution"):
        sc.with_options(restitution=2.0)
    with pytest.raises(ms.SceneError, match="dt"):
        sc.with_options(dt=0.0)
    with pytest.raises(ms.SceneError, match="separating"):
        sc.with_options(separating="sometimes")


def test_qp_failure_stops_with_step_and_time():
    """A QP that cannot be solved in its iteration budget stops the run naming step and time,
    with the samples so far attached and marked failed."""
    # the Python step, piqp alone (no active set): piqp is what is starved here
    sc = ms.load_scene(SCENES / "newton_cradle_5.toml").with_options(step_impl="python")
    model = ms.build_model(sc)
    import moreau_sim.qp as qp

    real = qp.solve

    def starved(*args, **kw):  # a real piqp solve with 1 iteration allowed
        kw["max_iter"] = 1
        kw["polish"] = qp.Polish.NONE
        return real(*args, **kw)

    qp.solve = starved
    try:
        with pytest.raises(ms.SimulationError) as info:
            ms.simulate(model, progress=False)
    finally:
        qp.solve = real
    msg = str(info.value)
    assert "step 1 " in msg and "t = 0 s" in msg and "PIQP_MAX_ITER_REACHED" in msg
    assert info.value.trajectory is not None and not info.value.trajectory.complete


def test_nan_state_stops_with_step_and_time():
    sc = ms.load_scene(SCENES / "bouncing_ball.toml")
    model = ms.build_model(sc)
    state = ms.State(0.0, np.array([np.nan]), np.array([0.0]))
    with pytest.raises(ms.SimulationError, match=r"step 1 .*non-finite"):
        ms.simulate(model, state=state, progress=False)


@pytest.mark.parametrize("tol", [1e-9, 1e-6])
def test_start_inside_an_obstacle_is_refused_beyond_the_contact_tolerance(tmp_path, tol):
    """A ball (r = 0.1 m) started 0.9 tol inside the ground builds; 1.1 tol inside is refused in one line
    naming the pair and its depth (the rest rule is for a step's own penetration, docs/theory.md §2.5)."""
    opt = f"dt = 1e-3\ncontact_tolerance = {tol!r}"
    ok = ball(tmp_path, **{"q0 = [1.0]": f"q0 = [{0.1 - 0.9 * tol!r}]", "dt = 1e-3": opt})
    model = ms.build_model(ms.load_scene(ok))
    g = ms.pair_distances(model, ms.make_data(model), model.q0)
    assert -tol < g[0] < -0.8 * tol
    ms.contacts.check_initial(model, ms.make_data(model), model.q0)  # the same rule for a state given to a run
    with pytest.raises(ms.SceneError, match=r"ball/ball_0\|ground starts .* m inside"):
        ms.contacts.check_initial(model, ms.make_data(model), model.q0 - 0.2 * tol)
    assert np.array_equal(ms.initial_state(model).q, model.q0)
    bad = ball(tmp_path, **{"q0 = [1.0]": f"q0 = [{0.1 - 1.1 * tol!r}]", "dt = 1e-3": opt})
    model = ms.build_model(ms.load_scene(bad))  # a model may be built there (to evaluate rows, gaps): not run
    with pytest.raises(ms.SceneError) as info:
        ms.initial_state(model)
    msg = str(info.value)
    for part in (str(bad), "ball/ball_0|ground", f"{1.1 * tol:.3g} m inside", f"contact_tolerance = {tol:g} m"):
        assert part in msg, (part, msg)
    assert "\n" not in msg
    with pytest.raises(ms.SceneError, match="m inside"):
        ms.simulate(model, progress=False)


def test_start_deep_inside_is_refused_by_the_cli(tmp_path):
    """rocking_block with the ground's offset 1.5 m: was lifted 1.5 m in one step (+14.6 J booked); now exit 2."""
    text = (SCENES / "rocking_block.toml").read_text()
    text = text.replace('shape = "halfspace"', 'shape = "halfspace"\noffset = 1.5')
    p = write(tmp_path, text.replace('"../models/', f'"{MODELS}/'))
    r = subprocess.run([sys.executable, "-m", "moreau_sim.cli", "run", str(p), "--out", str(tmp_path / "x.npz")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    line, = r.stderr.strip().splitlines()
    assert "block/" in line and "|ground starts 1.5 m inside" in line
    assert not (tmp_path / "x.npz").exists()
