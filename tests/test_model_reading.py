"""Reading a body's model file ends in a run or in one line naming the file (docs/robots.md):
symbolic links (loops, dangling), a model too large for Pinocchio's Data, physically impossible
inertias, and MJCF elements the reader does not use (refused by name, or ignored with a warning
where ignoring them cannot change the motion); ``<include>`` only inside the model's folder."""

import subprocess
import sys
import warnings

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import bodies, memory, model as model_module

from helpers import MODELS, ROOT

BALL = MODELS / "ball.urdf"


def scene(tmp_path, body: str, name="s.toml", duration=0.1) -> "ms.Scene":
    p = tmp_path / name
    p.write_text(f'[simulation]\nduration = {duration}\n[[bodies]]\nname = "b"\n{body}\n'
                 '[[statics]]\nname = "ground"\nshape = "halfspace"\n')
    return p


def refused(path, *fragments) -> str:
    with pytest.raises(ms.SceneError) as info:
        ms.build_model(ms.load_scene(path))
    msg = str(info.value)
    assert "\n" not in msg and len(msg) < 600, msg
    for f in fragments:
        assert str(f) in msg, (f, msg)
    return msg


def cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "moreau_sim", *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, timeout=120, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})


# ------------------------------------------------------------------ symbolic links

def test_urdf_symlink_loop_is_one_line_naming_the_file(tmp_path):
    (tmp_path / "loop.urdf").symlink_to("loop.urdf")
    s = scene(tmp_path, 'urdf = "loop.urdf"\nroot_joint = "free"')
    with pytest.raises(ms.SceneError, match="symbolic-link loop") as info:
        ms.load_scene(s)
    assert str(tmp_path / "loop.urdf") in str(info.value) and "\n" not in str(info.value)
    r = cli("run", s, "-o", tmp_path / "o.npz", cwd=tmp_path)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "loop.urdf" in r.stderr, r.stderr


def test_two_link_symlink_loop_and_dangling_link(tmp_path):
    (tmp_path / "a.urdf").symlink_to("b.urdf")
    (tmp_path / "b.urdf").symlink_to("a.urdf")
    (tmp_path / "dangling.urdf").symlink_to("nowhere.urdf")
    with pytest.raises(ms.SceneError, match="symbolic-link loop"):
        ms.load_scene(scene(tmp_path, 'urdf = "a.urdf"\nroot_joint = "free"'))
    with pytest.raises(ms.SceneError, match=r"file not found \(the symbolic link .*dangling.urdf points there\)"):
        ms.load_scene(scene(tmp_path, 'urdf = "dangling.urdf"\nroot_joint = "free"'))


def test_scene_file_and_package_dir_symlink_loops(tmp_path):
    (tmp_path / "s.toml").symlink_to("s.toml")
    with pytest.raises(ms.SceneError, match="symbolic-link loop"):
        ms.load_scene(tmp_path / "s.toml")
    (tmp_path / "pkg").symlink_to("pkg")
    s = scene(tmp_path, f'urdf = "{BALL}"\nroot_joint = "free"\npackage_dirs = ["pkg"]', name="p.toml")
    with pytest.raises(ms.SceneError, match=r"package_dirs.*symbolic-link loop"):
        ms.load_scene(s)


def test_symlink_to_a_model_outside_the_folder_is_read(tmp_path):
    """A link to a file elsewhere is followed (a user's own choice): the same model as the file."""
    (tmp_path / "ball.urdf").symlink_to(BALL)
    m = ms.build_model(ms.load_scene(scene(tmp_path, 'urdf = "ball.urdf"\nroot_joint = "free"')))
    assert m.pin.inertias[1].mass == 1.0 and m.bodies[0].urdf == BALL.resolve()


# ------------------------------------------------------------------ model size and the one Data

def chain_urdf(path, n):
    link = ('<link name="l{i}"><inertial><mass value="1"/><inertia ixx="1" iyy="1" izz="1" ixy="0" ixz="0" '
            'iyz="0"/></inertial></link>')
    joint = ('<joint name="j{i}" type="revolute"><parent link="l{p}"/><child link="l{i}"/><origin xyz="0 0 0.1"/>'
             '<axis xyz="1 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>')
    path.write_text('<robot name="chain">' + "".join(link.format(i=i) for i in range(n))
                    + "".join(joint.format(i=i, p=i - 1) for i in range(1, n)) + "</robot>")
    return path


def test_a_2000_link_chain_is_refused_with_its_size_and_what_needs_it(tmp_path):
    """Pinocchio 4.1's Data holds four nv^3 tensors: 238 GiB at nv = 1999, refused before allocating."""
    urdf = chain_urdf(tmp_path / "chain.urdf", 2000)
    s = scene(tmp_path, 'urdf = "chain.urdf"\nroot_joint = "fixed"')
    gib = 32 * 1999 ** 3 / 2 ** 30
    refused(s, s, urdf, "nv = 1999", "Pinocchio 4.1's Data", f"{gib:.3g} GiB", "memory available")
    r = cli("run", s, "-o", tmp_path / "o.npz", cwd=tmp_path)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "GiB" in r.stderr, r.stderr


def test_a_data_that_cannot_be_allocated_names_its_size(tmp_path, monkeypatch):
    """The size check against the memory available (probed, here set to 1 kB: a 10-link chain's
    Data needs 32 kB)."""
    chain_urdf(tmp_path / "chain.urdf", 11)
    monkeypatch.setattr(memory, "available_memory", lambda: 1000)
    refused(scene(tmp_path, 'urdf = "chain.urdf"\nroot_joint = "fixed"'), "nv = 10", "more than the")


def test_model_building_makes_no_data_of_the_whole_model(monkeypatch):
    """The mass-matrix check and the velocity-bias probe run body by body on each body's own model
    (M is block diagonal by bodies): Datas of the bodies' sizes only, none of the whole model's nv."""
    made = []
    real = model_module.new_data
    monkeypatch.setattr(model_module, "new_data", lambda m, where, **kw: made.append(m.nv) or real(m, where, **kw))
    m = ms.build_model(ms.load_scene(ROOT / "scenes" / "newton_cradle_5.toml"))
    assert made == [b.v_slice.stop - b.v_slice.start for b in m.bodies] == [1] * 5


def test_the_data_limit_is_stated_and_overridable(tmp_path, monkeypatch):
    """$MOREAU_SIM_DATA_LIMIT_GB replaces the memory available as the limit (here 1e-6 GiB, about 1 kB:
    a 10-link chain's Data needs 32 kB); the refusal names it, the scene, the bodies and nv."""
    chain_urdf(tmp_path / "chain.urdf", 11)
    s = scene(tmp_path, 'urdf = "chain.urdf"\nroot_joint = "fixed"')
    monkeypatch.setenv(memory.DATA_LIMIT_VARIABLE, "1e-6")
    refused(s, s, "1 bodies", "nv = 10", "MOREAU_SIM_DATA_LIMIT_GB = 1e-6 GiB")
    monkeypatch.setenv(memory.DATA_LIMIT_VARIABLE, "lots")
    refused(s, "MOREAU_SIM_DATA_LIMIT_GB", "a number of GiB expected")
    monkeypatch.setenv(memory.DATA_LIMIT_VARIABLE, "1")
    assert ms.build_model(ms.load_scene(s)).nv == 10


# ------------------------------------------------------------------ inertias

def inertia_urdf(tmp_path, ixx, iyy, izz, name="i.urdf", ixy=0.0):
    text = BALL.read_text().replace('ixx="0.004" iyy="0.004" izz="0.004" ixy="0"',
                                    f'ixx="{ixx!r}" iyy="{iyy!r}" izz="{izz!r}" ixy="{ixy!r}"')
    assert text != BALL.read_text()
    (tmp_path / name).write_text(text)
    return tmp_path / name


def test_triangle_inequality_violation_is_refused_naming_file_link_and_moments(tmp_path):
    u = inertia_urdf(tmp_path, 0.001, 0.001, 1.0)
    msg = refused(scene(tmp_path, f'urdf = "{u}"\nroot_joint = "free"'), u, "link 'ball'", "0.001, 0.001, 1 kg m^2",
                  "triangle inequality")
    assert "physically impossible" in msg


@pytest.mark.parametrize("excess, ok", [(0.9e-4, True), (1.1e-4, False)])
def test_triangle_inequality_tolerance_edge(tmp_path, excess, ok):
    """I3 - I1 - I2 = excess * I3 with I3 = 1: accepted within INERTIA_RTOL = 1e-4 (round-off of
    values written with 4-5 digits), refused beyond it. The principal axes are rotated (ixy != 0)
    so that the check works on the eigenvalues, not the diagonal."""
    assert bodies.INERTIA_RTOL == 1e-4
    i12 = (1.0 - excess) / 2  # I1 = I2
    # I1 = i12 + c, I2 = i12 - c about axes rotated in the x-y plane: the same moments
    c = 0.1
    a = i12
    u = inertia_urdf(tmp_path, a, a, 1.0, ixy=c)
    w = np.linalg.eigvalsh([[a, c, 0], [c, a, 0], [0, 0, 1.0]])
    assert w[2] - w[0] - w[1] == pytest.approx(excess, rel=1e-9)
    s = scene(tmp_path, f'urdf = "{u}"\nroot_joint = "free"')
    if ok:
        assert ms.build_model(ms.load_scene(s)).nv == 6
    else:
        refused(s, "triangle inequality", u)


def test_negative_principal_moment_is_refused(tmp_path):
    """Positive diagonal, one negative principal moment (ixy > ixx): impossible, refused by name."""
    u = inertia_urdf(tmp_path, 0.004, 0.004, 0.004, ixy=0.006)
    refused(scene(tmp_path, f'urdf = "{u}"\nroot_joint = "free"'), u, "link 'ball'", "negative principal moment")


def test_a_thin_rod_is_at_the_triangle_edge_and_accepted(tmp_path):
    """A rod along x: I = (0, I, I), I3 = I1 + I2 exactly (prismatic root: the zero moment is never moved)."""
    u = inertia_urdf(tmp_path, 0.0, 0.004, 0.004)
    m = ms.build_model(ms.load_scene(scene(tmp_path, f'urdf = "{u}"\nroot_joint = "prismatic"')))
    assert m.nv == 1


def test_mjcf_impossible_inertia_is_refused(tmp_path):
    (tmp_path / "m.xml").write_text('<mujoco model="m"><worldbody><body name="slab" pos="0 0 1">'
                                    '<inertial pos="0 0 0" mass="1" diaginertia="0.001 0.001 1"/>'
                                    '<geom type="sphere" size="0.1" contype="1"/></body></worldbody></mujoco>')
    refused(scene(tmp_path, 'mjcf = "m.xml"\nroot_joint = "free"'), tmp_path / "m.xml", "body 'slab'",
            "triangle inequality")


def test_welded_placeholder_inertias_are_judged_with_their_link():
    """example-robot-data's go1 has a 1e-6 kg 'base' link with the placeholder inertia (1e-6 on
    every entry: impossible alone) welded to its trunk: only the sum moves, and it is physical."""
    from moreau_sim.robots import example_robot_data_share

    share = example_robot_data_share()
    assert share is not None, "example-robot-data (a test dependency) is not installed"
    go1 = share / "example-robot-data" / "robots" / "go1_description" / "urdf" / "go1.urdf"
    import pinocchio as pin
    m = pin.buildModelFromUrdf(str(go1))
    bodies.check_inertias(m, go1, "test", "urdf")  # no error


# ------------------------------------------------------------------ MJCF elements

HINGE = ('<body name="b" pos="0 0 1"><joint name="h" type="hinge" axis="0 1 0"/>'
         '<geom type="sphere" size="0.1" mass="1"/>')


def mjcf(tmp_path, before="", inside="", name="m.xml"):
    (tmp_path / name).write_text(f'<mujoco model="m">{before}<worldbody>{HINGE}{inside}</body></worldbody></mujoco>')
    return scene(tmp_path, f'mjcf = "{name}"\nroot_joint = "fixed"', name=f"{name}.toml")


@pytest.mark.parametrize("element, why", [
    ('<equality><joint joint1="h" joint2="h2"/></equality>', "equality constraints"),
    ('<tendon><fixed name="t"><joint joint="h" coef="1"/></fixed></tendon>', "tendons"),
    ('<contact><exclude body1="b" body2="b"/></contact>', "[collisions]"),
    ('<asset><hfield name="hf" nrow="2" ncol="2" size="1 1 1 1"/></asset>', "height fields"),
    ('<extension><plugin plugin="x"/></extension>', "plugins"),
    ('<deformable/>', "deformable"),
    ('<frobnicate/>', "does not read"),
])
def test_unsupported_mjcf_elements_are_refused_by_name(tmp_path, element, why):
    tag = element[1:].split(">")[0].split()[0].rstrip("/")
    tag = "hfield" if "hfield" in element else tag
    refused(mjcf(tmp_path, before=element), tmp_path / "m.xml", f"<{tag}> is not supported", why)


@pytest.mark.parametrize("element, tag", [
    ('<composite type="grid" count="2 2 1" spacing="0.1"><geom size="0.01"/></composite>', "composite"),
    ('<flexcomp name="f" type="grid" count="2 2 1" spacing="0.1"/>', "flexcomp"),
    ('<geom type="hfield" hfield="x"/>', 'geom type="hfield"'),
    ('<frame><geom type="sphere" size="0.1"/></frame>', "frame"),
])
def test_unsupported_elements_inside_a_body_are_refused(tmp_path, element, tag):
    refused(mjcf(tmp_path, inside=element), tmp_path / "m.xml", f"<{tag}", "not supported")


def test_tendon_coupled_hinges_are_refused_not_run_independently(tmp_path):
    """The issue's case: two hinges coupled by a tendon ran as independent hinges (exit 0)."""
    (tmp_path / "t.xml").write_text(
        f'<mujoco model="t"><worldbody>{HINGE}<body name="c" pos="0 0 -0.3"><joint name="h2" type="hinge" '
        'axis="0 1 0"/><geom type="sphere" size="0.1" mass="1"/></body></body></worldbody><tendon><fixed '
        'name="couple"><joint joint="h" coef="1"/><joint joint="h2" coef="-1"/></fixed></tendon></mujoco>')
    s = scene(tmp_path, 'mjcf = "t.xml"\nroot_joint = "fixed"')
    refused(s, "<tendon>")
    r = cli("run", s, "-o", tmp_path / "o.npz", cwd=tmp_path)
    assert r.returncode == 2 and "<tendon>" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_ignored_elements_warn_once_and_do_not_change_the_run(tmp_path):
    """Visual-only and MuJoCo-solver elements: one warning naming them; the run is bit-identical."""
    plain = ms.simulate(ms.build_model(ms.load_scene(mjcf(tmp_path, name="a.xml"))), progress=False)
    extra = ('<visual><quality shadowsize="0"/></visual><option timestep="0.01" gravity="0 0 -1"/>'
             '<asset><texture name="t" type="2d" builtin="checker" width="8" height="8"/></asset>'
             '<sensor><jointpos joint="h"/></sensor><keyframe><key qpos="0.3"/></keyframe>')
    s = mjcf(tmp_path, before=extra, inside='<camera name="c"/><light name="l"/>', name="b.xml")
    with pytest.warns(UserWarning) as record:
        model = ms.build_model(ms.load_scene(s))
    ours = [w for w in record if "ignored" in str(w.message)]
    msgs = [str(w.message) for w in ours]
    assert len(msgs) == 1 and "\n" not in msgs[0] and ours[0].filename == str(tmp_path / "b.xml")
    assert ours[0].lineno == 0  # shown as one line: "b.xml:0: UserWarning: MJCF element(s) ..."
    for tag in ("visual", "option", "texture", "sensor", "keyframe", "camera", "light"):
        assert f"<{tag}>" in msgs[0], (tag, msgs[0])
    other = ms.simulate(model, progress=False)
    assert np.array_equal(plain.q, other.q) and np.array_equal(plain.u, other.u)


def test_bundled_mjcf_loads_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ms.build_model(ms.load_scene(ROOT / "scenes" / "mjcf_example.toml"))


def test_several_top_level_bodies_are_refused(tmp_path):
    """Pinocchio 4.1's MJCF reader reads the first top-level body and drops the others silently."""
    second = HINGE.replace('name="b"', 'name="c"').replace('"h"', '"h2"')
    (tmp_path / "two.xml").write_text(f'<mujoco model="two"><worldbody>{HINGE}</body>{second}'
                                      '</body></worldbody></mujoco>')
    refused(scene(tmp_path, 'mjcf = "two.xml"\nroot_joint = "fixed"'), "2 top-level bodies (b, c)")


@pytest.mark.parametrize("folder_key", ["meshdir", "assetdir"])
def test_include_inside_the_folder_is_read_as_if_inlined(tmp_path, folder_key):
    """<include> (which Pinocchio's reader skips) is expanded: the same model and run as the file
    with the included body written inline, meshes found through <compiler meshdir> or assetdir."""
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "box.obj").write_text((MODELS / "box_mesh.obj").read_text())
    lower = ('<body name="c" pos="0 0 -0.3"><joint name="h2" type="hinge" axis="0 1 0"/>'
             '<geom type="mesh" mesh="bm" mass="1"/></body>')
    head = f'<compiler {folder_key}="meshes"/><asset><mesh name="bm" file="box.obj" scale="0.5 0.5 0.5"/></asset>'
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "lower.xml").write_text(f"<mujoco>{lower}</mujoco>")
    a = mjcf(tmp_path, before=head, inside=lower, name="inline.xml")
    b = mjcf(tmp_path, before=head, inside='<include file="parts/lower.xml"/>', name="inc.xml")
    ma, mb = (ms.build_model(ms.load_scene(s)) for s in (a, b))
    assert ma.nv == mb.nv == 2  # and three geometries: the two bodies', the ground
    assert len(ma.geom.geometryObjects) == len(mb.geom.geometryObjects) == 3
    ta, tb = (ms.simulate(m, progress=False) for m in (ma, mb))
    assert np.array_equal(ta.q, tb.q)


@pytest.mark.parametrize("target", ["/etc/passwd", "../outside.xml", "link.xml"])
def test_include_outside_the_folder_is_refused(tmp_path, target):
    (tmp_path / "outside.xml").write_text("<mujoco/>")
    model = tmp_path / "model"
    model.mkdir()
    (model / "link.xml").symlink_to(tmp_path / "outside.xml")  # a link inside, pointing out
    s = mjcf(model, inside=f'<include file="{target}"/>')
    refused(s, f'<include file="{target}">', "only files inside the model's folder")


def test_include_of_itself_is_refused(tmp_path):
    refused(mjcf(tmp_path, inside='<include file="m.xml"/>'), "includes itself")


def test_pinocchios_own_prints_do_not_reach_the_output(tmp_path, capfd):
    """Pinocchio's MJCF reader prints "Warning - Only texture with files are supported" to stdout
    and refuses a nameless texture: an ignored element is not handed to it (one warning, the run);
    what Pinocchio itself refuses is one line, without its prints."""
    with pytest.warns(UserWarning, match="<texture>"):
        assert ms.build_model(ms.load_scene(mjcf(tmp_path, before="<asset><texture/></asset>"))).nv == 1
    s = mjcf(tmp_path, before='<asset><mesh name="m" file="missing.obj"/></asset>', name="mesh.xml",
             inside='<geom type="mesh" mesh="m"/>')
    refused(s, "Pinocchio cannot load this MJCF")
    out, err = capfd.readouterr()
    assert "Warning - " not in out + err
