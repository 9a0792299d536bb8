"""Property-based fuzz of scene files (hypothesis): every mutation of a bundled scene either
loads, builds and runs to a complete, finite trajectory, or stops with a named SceneError or
SimulationError of one line — never another exception, a crash or a non-finite "complete".

The same property over the model files a scene names: symbolic links (loops, dangling, to
elsewhere) in place of the scene's URDF, MJCF, package folder or a mesh; MJCF files with elements
the reader reads, ignores or refuses and with ``<include>``s of every kind; and URDF inertias
(random symmetric tensors, around the triangle inequality's edge)."""

from __future__ import annotations

import math
import tempfile
import tomllib
import warnings
from pathlib import Path

import numpy as np
import tomli_w
from hypothesis import HealthCheck, given, settings, strategies as st

import moreau_sim as ms
from moreau_sim import bodies, robots

from helpers import MODELS, SCENES

BASES = {name: tomllib.loads((SCENES / f"{name}.toml").read_text()) for name in ("bouncing_ball", "box_drop",
                                                                                  "newton_cradle_5", "rocking_block")}
VALUES = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False, width=64), st.sampled_from([0, -1, 1, 1e-12, 1e300, -1e300]),
    st.integers(-10, 10), st.booleans(), st.text(max_size=12),
    st.lists(st.floats(allow_nan=False, allow_infinity=False, min_value=-1e3, max_value=1e3), max_size=4),
    st.sampled_from(["free", "fixed", "planar", "prismatic", "revolute", "translation", "halfspace", "box",
                     "sphere", "cylinder", "primal", "dual", "elastic", "newton", "none", "bvh", "convex",
                     "../models/ball.urdf", "../models/box.urdf", "nope.urdf", "package://x/y.urdf"]))


def tables(doc):
    """(path, table) of every table of a scene document, including each [[bodies]]/[[statics]] entry."""
    out = [((k,), v) for k, v in doc.items() if isinstance(v, dict)]
    for key in ("bodies", "statics"):
        out += [((key, i), t) for i, t in enumerate(doc.get(key, []))]
    return out


def scaled(value, factor):
    """A number or a list of numbers times factor; other values unchanged."""
    if isinstance(value, bool):
        return value
    if isinstance(value, (int, float)):
        return type(value)(value * factor) if isinstance(value, float) else int(value * factor)
    if isinstance(value, list):
        return [scaled(v, factor) for v in value]
    return value


@st.composite
def mutated(draw):
    name = draw(st.sampled_from(sorted(BASES)))
    doc = tomllib.loads(tomli_w.dumps(BASES[name]))  # a deep copy
    for _ in range(draw(st.integers(1, 3))):
        path, table = draw(st.sampled_from(tables(doc)))
        keys = sorted(table) + ["restitution", "dt", "duration", "gravity", "radius", "size", "axis", "q0", "u0",
                                "root_joint", "urdf", "shape", "normal", "position", "rpy", "unknown_key"]
        key = draw(st.sampled_from(keys))
        old = table.get(key)
        if old is not None and draw(st.booleans()):  # a plausible edit: scale what is there
            factor = draw(st.sampled_from([0.0, 0.5, 2.0, -1.0, 1e-6, 1e6]))
            table[key] = scaled(old, factor)
        elif key in table and draw(st.booleans()):
            del table[key]
        else:
            table[key] = draw(VALUES)
    return name, tomli_w.dumps(doc)


@settings(max_examples=120, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(mutated())
def test_mutated_scenes_fail_by_name_or_run_complete(case):
    name, text = case
    try:
        sc = ms.parse_scene(text, path=SCENES / f"{name}.toml")
        n = sc.options.n_steps
        if n > 200:  # keep each run short: the first 200 steps
            sc = sc.with_options(duration=200 * sc.options.dt)
        traj = ms.simulate(ms.build_model(sc), progress=False)
    except ms.SceneError as exc:
        msg = str(exc)
        assert "\n" not in msg and 0 < len(msg) < 600, msg
        return
    except ms.SimulationError as exc:
        assert str(exc).startswith("step ") and "\n" not in str(exc)
        assert exc.trajectory is not None and not exc.trajectory.complete
        return
    assert traj.complete
    for key in ("q", "u", "kinetic_energy", "potential_energy", "gap"):
        assert np.isfinite(traj.arrays[key]).all(), key
    assert math.isfinite(float(traj.total_energy[-1]))


def outcome(scene_path: Path, steps: int = 20) -> str:
    """Load, build and run `steps` steps: "ran", or "refused: <message>" for a one-line SceneError;
    any other exception fails the test."""
    try:
        sc = ms.load_scene(scene_path)
        sc = sc.with_options(duration=steps * sc.options.dt)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # ignored MJCF elements: one warning, checked elsewhere
            traj = ms.simulate(ms.build_model(sc), progress=False)
    except ms.SceneError as exc:
        msg = str(exc)
        assert "\n" not in msg and 0 < len(msg) < 600, msg
        return f"refused: {msg}"
    except ms.SimulationError as exc:
        assert str(exc).startswith("step ") and "\n" not in str(exc)
        return "failed"
    assert traj.complete and np.isfinite(traj.q).all()
    return "ran"


def body_scene(folder: Path, body: str) -> Path:
    p = folder / "s.toml"
    # the ground 1 m below the body at its origin: a run may not start inside an obstacle
    p.write_text(f'[simulation]\ndt = 1e-3\n[[bodies]]\nname = "b"\n{body}\n'
                 '[[statics]]\nname = "ground"\nshape = "halfspace"\noffset = -1.0\n')
    return p


# ------------------------------------------------------------------ symbolic links

LINK_TARGETS = ["self", "other", "dangling", "ball", "outside_text", "folder", "chain"]


@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(["urdf", "mjcf", "package_dir", "mesh", "scene"]), st.sampled_from(LINK_TARGETS))
def test_symlinked_model_files_fail_by_name_or_run(where, target):
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        link = d / "link"
        outside = d / "outside.txt"
        outside.write_text("not a model")
        (d / "sub").mkdir()
        targets = {"self": link, "other": d / "link2", "dangling": d / "nowhere", "ball": MODELS / "ball.urdf",
                   "outside_text": outside, "folder": d / "sub", "chain": d / "link2"}
        if target == "other":
            (d / "link2").symlink_to(link)  # link -> link2 -> link
        if target == "chain":
            (d / "link2").symlink_to(MODELS / ("pendulum.xml" if where == "mjcf" else "ball.urdf"))
        link.symlink_to(targets[target])
        if where == "urdf":
            s = body_scene(d, 'urdf = "link"\nroot_joint = "prismatic"\nq0 = [1.0]')
        elif where == "mjcf":
            s = body_scene(d, 'mjcf = "link"\nroot_joint = "fixed"')
        elif where == "package_dir":
            s = body_scene(d, f'urdf = "{MODELS / "ball.urdf"}"\nroot_joint = "prismatic"\nq0 = [1.0]\n'
                              'package_dirs = ["link"]')
        elif where == "mesh":
            (d / "m.urdf").write_text((MODELS / "box_mesh.urdf").read_text().replace(
                'filename="box_mesh.obj"', 'filename="link"'))
            s = body_scene(d, 'urdf = "m.urdf"\nroot_joint = "free"')
        else:
            s = link
        result = outcome(s)
        if target in ("self", "other") and where != "mesh" and where != "package_dir":
            assert result.startswith("refused") and "symbolic-link loop" in result, result


# ------------------------------------------------------------------ MJCF elements

MJCF_TAGS = sorted(robots.MJCF_READ | robots.MJCF_IGNORED | set(robots.MJCF_WHY)
                   | {"frame", "replicate", "attach", "flex", "skin", "unknown_tag"})
PLACES = ["top", "worldbody", "body", "default", "asset"]


@st.composite
def mjcf_case(draw):
    extras = draw(st.lists(st.tuples(st.sampled_from(MJCF_TAGS), st.sampled_from(PLACES)), min_size=1, max_size=3))
    include = draw(st.sampled_from([None, "part.xml", "../outside.xml", "/etc/passwd", "m.xml", "missing.xml",
                                    "sub/part.xml"]))
    return extras, include


@settings(max_examples=80, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(mjcf_case())
def test_mjcf_elements_are_read_ignored_with_a_warning_or_refused_by_name(case):
    extras, include = case
    where = {p: "" for p in PLACES}
    for tag, place in extras:
        where[place] += f"<{tag}/>"
    if include:
        where["body"] += f'<include file="{include}"/>'
    xml = (f'<mujoco model="m">{where["top"]}<default>{where["default"]}</default><asset>{where["asset"]}</asset>'
           f'<worldbody>{where["worldbody"]}<body name="b" pos="0 0 1"><joint name="h" type="hinge" axis="0 1 0"/>'
           f'<geom type="sphere" size="0.1" mass="1"/>{where["body"]}</body></worldbody></mujoco>')
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp) / "model"
        (d / "sub").mkdir(parents=True)
        (Path(tmp) / "outside.xml").write_text("<mujoco/>")
        part = '<mujoco><body name="c" pos="0 0 -0.3"><joint name="h2" type="hinge"/><geom type="sphere" ' \
               'size="0.05" mass="0.5"/></body></mujoco>'
        (d / "part.xml").write_text(part)
        (d / "sub" / "part.xml").write_text(part.replace('"c"', '"c2"').replace('"h2"', '"h3"'))
        (d / "m.xml").write_text(xml)
        result = outcome(body_scene(d, 'mjcf = "m.xml"\nroot_joint = "fixed"'))
    refused_tags = [t for t, p in extras if p != "default" and t not in robots.MJCF_READ | robots.MJCF_IGNORED]
    if any(t == "include" for t, _ in extras):  # an <include/> without a file (expanded anywhere, as MuJoCo)
        assert result.startswith("refused") and "<include" in result, result
    elif include in ("../outside.xml", "/etc/passwd"):
        assert "only files inside the model's folder" in result, result
    elif include == "m.xml":
        assert "includes itself" in result, result
    elif refused_tags and not include:
        assert result.startswith("refused") and any(f"<{t}>" in result for t in refused_tags), result


# ------------------------------------------------------------------ inertias

@settings(max_examples=80, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.floats(-0.05, 1.0), min_size=3, max_size=3), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0),
       st.sampled_from([None, 0.5e-4, 2e-4, 1e-3]))
def test_inertias_are_refused_by_name_exactly_when_impossible(moments, angle, tilt, edge):
    """A tensor R diag(I) R^T with random principal moments (or ones at a given distance from the
    triangle inequality's edge) and a random rotation: refused, naming the link and "physically
    impossible", exactly when I1 < 0 or I3 - I1 - I2 exceeds the tolerance."""
    principal = np.sort(np.asarray(moments)) + 1e-3
    if edge is not None:  # I3 = I1 + I2 + edge * I3
        principal[2] = (principal[0] + principal[1]) / (1 - edge)
    c, s, ct, st_ = math.cos(angle), math.sin(angle), math.cos(tilt), math.sin(tilt)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, ct, -st_], [0, st_, ct]])
    J = R @ np.diag(principal) @ R.T
    text = (MODELS / "ball.urdf").read_text().replace(
        'ixx="0.004" iyy="0.004" izz="0.004" ixy="0" ixz="0" iyz="0"',
        " ".join(f'{k}="{float(J[i, j])!r}"' for k, (i, j) in zip(("ixx", "iyy", "izz", "ixy", "ixz", "iyz"),
                                                          ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)))))
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "i.urdf").write_text(text)
        result = outcome(body_scene(d, 'urdf = "i.urdf"\nroot_joint = "free"'), steps=5)
    w = np.linalg.eigvalsh(J)
    tol = bodies.INERTIA_RTOL * np.abs(w).max()
    impossible = w[0] < -tol * (1 + 1e-6) or w[2] - w[0] - w[1] > tol * (1 + 1e-6)
    possible = w[0] > -tol * (1 - 1e-6) and w[2] - w[0] - w[1] < tol * (1 - 1e-6)
    if impossible:
        assert "physically impossible" in result and "link 'ball'" in result, result
    elif possible:
        assert result == "ran", result


# Output paths (issue 28): every kind of -o/--out a user may give `run`, in a fresh folder holding
# the scene and its model: an input of the run (directly, through a symlink or a detour), no or
# another suffix, a trailing slash, an empty or blank name, a folder that does not exist outside
# the current one, a "folder" that is a file, an unwritable place.
OUTPUT_KINDS = ["scenes/ball.toml", "models/ball.urdf", "link.toml", "scenes/../scenes/ball.toml", "x", "x.txt",
                "x.NPZ", "x.npz", "out/", "out/sub/", "", "  ", "/nonexistent_moreau_fuzz/x.npz", "new/x.npz",
                "file.npz/x.npz", "/proc/x.npz", "scenes", "scenes/"]


@settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(OUTPUT_KINDS), st.sampled_from(["--out", "-o", "field"]))
def test_output_paths_are_written_or_refused_by_name(out, how):
    import os

    from click.testing import CliRunner

    from moreau_sim.cli import main

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        (folder / "scenes").mkdir()
        (folder / "models").mkdir()
        (folder / "models" / "ball.urdf").write_bytes((MODELS / "ball.urdf").read_bytes())
        text = (SCENES / "bouncing_ball.toml").read_text()
        if how == "field":
            text = text.replace('file = "bouncing_ball.npz"', f"file = {out!r}".replace("'", '"'))
        (folder / "scenes" / "ball.toml").write_text(text)
        (folder / "link.toml").symlink_to(folder / "scenes" / "ball.toml")
        (folder / "file.npz").write_bytes(b"a file, not a folder")
        inputs = {p: p.read_bytes() for p in (folder / "scenes" / "ball.toml", folder / "models" / "ball.urdf")}
        cwd = os.getcwd()
        os.chdir(folder)
        try:
            args = ["run", "scenes/ball.toml", "--duration", "0.01"] + ([] if how == "field" else [how, out])
            r = CliRunner().invoke(main, args)
        finally:
            os.chdir(cwd)
        assert r.exit_code in (0, 2) and r.exception is None or isinstance(r.exception, SystemExit), r.output
        assert all(p.read_bytes() == b for p, b in inputs.items()), "an input was overwritten"
        assert not Path("/nonexistent_moreau_fuzz").exists() and not Path("/proc/x.npz").exists()
        if r.exit_code == 2:
            lines = r.output.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith("moreau-sim: error:"), r.output
        else:
            written = r.output.strip().splitlines()[-1].split("-> ")[-1]
            path = Path(written) if Path(written).is_absolute() else folder / written
            assert path.suffix == ".npz" and ms.load_trajectory(path).complete
