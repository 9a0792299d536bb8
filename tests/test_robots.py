"""Robot descriptions (docs/robots.md): package:// resolution and its search order, collision
meshes as convex hulls or BVHs, MJCF bodies, and the bundled robot scenes (quadruped_drop,
panda_table, solo_drop, mjcf_example) with their energy and penetration bounds.

Needs example-robot-data (the quadruped and solo scenes load its URDFs and meshes)."""

import collections
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import coal
import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import robots
from moreau_sim.robots import ENV_PACKAGE_PATH, MeshMode

from helpers import MODELS, SCENES

SHARE = robots.example_robot_data_share()
ERD = "package://example-robot-data/robots"


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def body_scene(tmp_path, body: str, statics: str = '[[statics]]\nname = "ground"\nshape = "halfspace"\n',
               name="s.toml", extra="") -> Path:
    return write(tmp_path / name, f"[simulation]\nduration = 0.1\n[[bodies]]\n{body}\n{statics}\n{extra}")


def energy(traj):
    return traj.kinetic_energy + traj.potential_energy


# ------------------------------------------------------------------ package:// resolution

def test_example_robot_data_share_is_found_through_its_distribution():
    import importlib.metadata
    assert SHARE is not None, "example-robot-data is not installed (pip install example-robot-data)"
    dist = importlib.metadata.distribution("example-robot-data")
    assert (SHARE / "example-robot-data" / "robots" / "a1_description" / "urdf" / "a1.urdf").is_file()
    assert str(SHARE).startswith(str(Path(dist.locate_file("")).resolve()))  # from the install, not a constant


def _package(root: Path, pkg: str, tag: str) -> Path:
    """root/pkg/urdf/ball.urdf (a ball whose mass tells which copy was loaded)."""
    text = (MODELS / "ball.urdf").read_text()
    return write(root / pkg / "urdf" / "ball.urdf", text.replace("<robot ", f"<!-- {tag} --><robot ", 1))


def test_search_order_package_dirs_then_environment_then_erd_then_parents(tmp_path, monkeypatch):
    a, b = _package(tmp_path / "a", "pkg", "a"), _package(tmp_path / "b", "pkg", "b")
    monkeypatch.setenv(ENV_PACKAGE_PATH, f"{tmp_path / 'b'}{__import__('os').pathsep}{tmp_path / 'nowhere'}")
    dirs = robots.search_dirs([tmp_path / "a"], tmp_path / "scenes")
    assert dirs[:3] == [tmp_path / "a", tmp_path / "b", tmp_path / "nowhere"]
    assert dirs[3] == SHARE and dirs[4:6] == [tmp_path / "scenes", tmp_path]
    body = 'name = "ball"\nurdf = "package://pkg/urdf/ball.urdf"\nroot_joint = "prismatic"\n'
    s = body_scene(tmp_path, body + 'package_dirs = ["a"]\n')  # the body's folders come first
    assert ms.load_scene(s).bodies[0].urdf == a.resolve()
    s = body_scene(tmp_path, body)  # then the environment variable
    assert ms.load_scene(s).bodies[0].urdf == b.resolve()
    monkeypatch.delenv(ENV_PACKAGE_PATH)
    # then example-robot-data, then the scene file's own folders (pkg sits next to the scene here)
    s = body_scene(tmp_path / "b", body)
    assert ms.load_scene(s).bodies[0].urdf == b.resolve()
    s = body_scene(tmp_path, f'name = "a1"\nurdf = "{ERD}/a1_description/urdf/a1.urdf"\nroot_joint = "fixed"\n')
    assert ms.load_scene(s).bodies[0].urdf == (SHARE / "example-robot-data/robots/a1_description/urdf/a1.urdf")


def test_unresolved_uri_names_scene_body_uri_and_folders(tmp_path, monkeypatch):
    monkeypatch.setenv(ENV_PACKAGE_PATH, str(tmp_path / "env"))
    (tmp_path / "mine").mkdir()
    s = body_scene(tmp_path, 'name = "robot"\nurdf = "package://nopkg/urdf/robot.urdf"\nroot_joint = "fixed"\n'
                             'package_dirs = ["mine"]\n')
    with pytest.raises(ms.SceneError) as info:
        ms.load_scene(s)
    msg = str(info.value)
    for part in (str(s), "(robot) urdf", "package://nopkg/urdf/robot.urdf", str(tmp_path / "mine"),
                 str(tmp_path / "env"), str(SHARE), ENV_PACKAGE_PATH):
        assert part in msg, (part, msg)
    assert msg.index(str(tmp_path / "mine")) < msg.index(str(tmp_path / "env")) < msg.index(str(SHARE))


def test_without_example_robot_data_the_error_says_to_install_it(tmp_path, monkeypatch):
    monkeypatch.setattr(robots, "example_robot_data_share", lambda: None)
    s = body_scene(tmp_path, f'name = "a1"\nurdf = "{ERD}/a1_description/urdf/a1.urdf"\nroot_joint = "free"\n')
    with pytest.raises(ms.SceneError, match="example-robot-data is not installed") as info:
        ms.load_scene(s)
    assert str(SHARE) not in str(info.value)


def test_bad_keys_are_scene_errors(tmp_path):
    base = 'name = "b"\nroot_joint = "free"\n'
    cases = {
        f'urdf = "{MODELS / "box.urdf"}"\nmjcf = "{MODELS / "pendulum.xml"}"\n': "either 'urdf' or 'mjcf'",
        f'urdf = "{MODELS / "box.urdf"}"\npackage_dirs = "x"\n': "package_dirs",
        f'urdf = "{MODELS / "box.urdf"}"\nmeshes = "voxels"\n': "meshes",
        'urdf = "http://example.com/x.urdf"\n': "not supported",
        'mjcf = "missing.xml"\n': "file not found",
    }
    for i, (keys, fragment) in enumerate(cases.items()):
        s = body_scene(tmp_path, base + keys, name=f"s{i}.toml")
        with pytest.raises(ms.SceneError, match=fragment) as info:
            ms.load_scene(s)
        assert str(s) in str(info.value)


def test_mesh_uri_resolves_through_the_urdf_folders(tmp_path):
    """A description package laid out as ROS does (mypkg/urdf, mypkg/meshes) needs no search path:
    package://mypkg/... is found from the folder above the URDF's package."""
    write(tmp_path / "mypkg" / "meshes" / "box.obj", (MODELS / "box_mesh.obj").read_text())
    urdf = (MODELS / "box_mesh.urdf").read_text().replace("box_mesh.obj", "package://mypkg/meshes/box.obj")
    write(tmp_path / "mypkg" / "urdf" / "box.urdf", urdf)
    s = body_scene(tmp_path / "scenes", 'name = "box"\nurdf = "../mypkg/urdf/box.urdf"\nroot_joint = "free"\n')
    m = ms.build_model(ms.load_scene(s))
    g = m.geom.geometryObjects[0]
    assert isinstance(g.geometry, coal.ConvexBase) and len(m.vertices[0]) == 8
    assert Path(g.meshPath) == (tmp_path / "mypkg" / "meshes" / "box.obj").resolve()


def test_unresolved_mesh_names_scene_body_link_uri_and_folders(tmp_path, monkeypatch):
    monkeypatch.setenv(ENV_PACKAGE_PATH, str(tmp_path / "env"))
    urdf = (MODELS / "box_mesh.urdf").read_text().replace("box_mesh.obj", "package://nomesh/meshes/box.obj")
    write(tmp_path / "pk" / "urdf" / "m.urdf", urdf)
    s = body_scene(tmp_path, 'name = "robot"\nurdf = "pk/urdf/m.urdf"\nroot_joint = "free"\n')
    with pytest.raises(ms.SceneError) as info:
        ms.build_model(ms.load_scene(s))
    msg = str(info.value)
    for part in (str(s), "(robot)", "link 'box'", "package://nomesh/meshes/box.obj", str(tmp_path / "env"),
                 str(SHARE), str(tmp_path / "pk" / "urdf")):
        assert part in msg, (part, msg)


# ------------------------------------------------------------------ mesh modes

def _box_mesh_drop(mode: str | None, duration=2.0, urdf="box_mesh.urdf"):
    sc = ms.load_scene(SCENES / "box_drop.toml").with_options(duration=duration)
    body = sc.bodies[0]
    body = dataclasses.replace(body, urdf=MODELS / urdf, **({"meshes": MeshMode(mode)} if mode else {}))
    return dataclasses.replace(sc, bodies=(body,))


def test_mesh_modes_give_a_convex_hull_or_the_bvh():
    convex = ms.build_model(_box_mesh_drop(None, 0.1))  # the default
    g = convex.geom.geometryObjects[0].geometry
    assert isinstance(g, coal.ConvexBase) and g.num_points == 8
    assert len(convex.vertices[0]) == 8 and len(convex.face_normals[0]) == 12  # hull triangles
    bvh = ms.build_model(_box_mesh_drop("bvh", 0.1))
    assert isinstance(bvh.geom.geometryObjects[0].geometry, coal.BVHModelOBBRSS) and len(bvh.vertices[0]) == 0
    # lying on a face: the hull gives the 4 corners, the BVH coal's single contact of the pair
    q = np.array([0, 0, 0.2, 0, 0, 0, 1.0])
    assert ms.detect(convex, ms.make_data(convex), q).m == 4
    assert ms.detect(bvh, ms.make_data(bvh), q).m == 1


@pytest.mark.parametrize("urdf, check", [
    # a link and a fixed joint both named gripperStator: appendModel refused it before the rename
    ("z1_description/urdf/z1.urdf", lambda m: "r/gripperStator:FIXED_JOINT" in [f.name for f in m.pin.frames]),
    # <collision_checking><convex/>: Pinocchio's convex has no normals (coal's normals() segfaults)
    ("simple_humanoid_description/urdf/simple_humanoid.urdf",
     lambda m: m.face_normals[1].shape == (12, 3) and isinstance(m.geom.geometryObjects[0].geometry, coal.Capsule)),
])
def test_example_robot_data_quirks_load(tmp_path, urdf, check):
    s = body_scene(tmp_path, f'name = "r"\nurdf = "{ERD}/{urdf}"\nroot_joint = "free"\n')
    assert check(ms.build_model(ms.load_scene(s)))


def test_a_mesh_coal_cannot_hull_is_a_scene_error_suggesting_bvh(tmp_path):
    s = body_scene(tmp_path, f'name = "c"\nurdf = "{ERD}/centauro_description/urdf/centauro.urdf"\n'
                             'root_joint = "free"\n')
    with pytest.raises(ms.SceneError, match=r'pelvis.*Too many neighbors.*meshes = "bvh"') as info:
        ms.build_model(ms.load_scene(s))
    assert str(s) in str(info.value) and "(c)" in str(info.value)
    bvh = s.read_text().replace('root_joint = "free"', 'root_joint = "free"\nmeshes = "bvh"')
    assert ms.build_model(ms.load_scene(write(tmp_path / "bvh.toml", bvh))).nv == 45


def test_convex_mesh_box_drops_as_the_box_primitive():
    """box_drop with its box as a 12-triangle mesh: the hull rests on a face at z = 0.1 m like the
    Box primitive, with the same energy (docs/robots.md: with meshes = "bvh" it sinks through)."""
    mesh = ms.simulate(ms.build_model(_box_mesh_drop("convex")), progress=False)
    prim = ms.simulate(ms.build_model(ms.load_scene(SCENES / "box_drop.toml")), progress=False)
    assert abs(mesh.q[-1, 2] - 0.1) < 1e-6 and abs(prim.q[-1, 2] - 0.1) < 1e-6
    assert abs(energy(mesh)[-1] - energy(prim)[-1]) < 1e-5
    assert energy(mesh).max() <= energy(mesh)[0] + 1e-12
    assert ms.summary(mesh)["min_gap"] > -1e-3
    assert mesh.kinetic_energy[-200:].max() < 1e-4


# ------------------------------------------------------------------ MJCF

def test_mjcf_pendulum_equals_the_same_pendulum_as_urdf(tmp_path):
    """models/pendulum.xml (MuJoCo geom masses) against a URDF with the inertia MuJoCo's rule gives:
    rod 0.5 kg box 0.04 x 0.04 x 0.5 m centred 0.25 m below the hinge, bob 1 kg solid sphere r = 0.1
    at 0.5 m. Same inertia, same collision shapes, same run bit for bit."""
    m_rod, m_bob, L = 0.5, 1.0, 0.5
    mass = m_rod + m_bob
    c = -(m_rod * 0.25 + m_bob * L) / mass
    ixx = (m_rod / 12 * (0.04 ** 2 + 0.5 ** 2) + m_rod * (0.25 + c) ** 2 + 0.4 * m_bob * 0.01 + m_bob * (L + c) ** 2)
    izz = m_rod / 12 * 2 * 0.04 ** 2 + 0.4 * m_bob * 0.01
    sc = ms.load_scene(SCENES / "mjcf_example.toml")
    model = ms.build_model(sc)
    inertia = model.pin.inertias[1]
    assert model.nq == model.nv == 1 and [g.name for g in model.geom.geometryObjects] == [
        "pendulum/rod", "pendulum/bob", "wall"]
    assert inertia.mass == pytest.approx(mass) and inertia.lever == pytest.approx([0, 0, c])
    assert np.diag(inertia.inertia) == pytest.approx([ixx, ixx, izz], rel=1e-12)
    lever, Ic = inertia.lever, inertia.inertia

    def f(x):
        return repr(float(x))

    urdf = write(tmp_path / "pendulum.urdf", f"""<robot name="pendulum"><link name="base"/>
  <link name="link">
    <inertial><origin xyz="0 0 {f(lever[2])}"/><mass value="{f(inertia.mass)}"/>
      <inertia ixx="{f(Ic[0, 0])}" iyy="{f(Ic[1, 1])}" izz="{f(Ic[2, 2])}" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><origin xyz="0 0 -0.25"/><geometry><box size="0.04 0.04 0.5"/></geometry></collision>
    <collision><origin xyz="0 0 -0.5"/><geometry><sphere radius="0.1"/></geometry></collision>
  </link>
  <joint name="hinge" type="revolute"><parent link="base"/><child link="link"/><axis xyz="0 1 0"/>
    <limit lower="-10" upper="10" effort="0" velocity="0"/></joint></robot>""")
    s = write(tmp_path / "u.toml", sc.source.replace('mjcf = "../models/pendulum.xml"', f'urdf = "{urdf}"'))
    a = ms.simulate(model, progress=False)
    b = ms.simulate(ms.build_model(ms.load_scene(s)), progress=False)
    assert a.impacts == b.impacts == 2
    assert np.array_equal(a.q, b.q) and np.array_equal(a.u, b.u)


def test_mjcf_root_joint_is_added_whether_or_not_the_top_body_has_a_joint(tmp_path):
    """Pinocchio 4.1's MJCF reader drops a root joint when the top body has its own joint; robots.py
    attaches the root itself. A jointless MJCF box on a free root drops as box_drop's URDF box."""
    s = body_scene(tmp_path, f'name = "p"\nmjcf = "{MODELS / "pendulum.xml"}"\nroot_joint = "prismatic"\n'
                             'axis = [0, 0, 1]\n')
    m = ms.build_model(ms.load_scene(s))
    assert (m.nq, m.nv) == (2, 2) and [m.pin.names[j] for j in (1, 2)] == ["p/root", "p/hinge"]
    write(tmp_path / "box.xml", '<mujoco model="box"><worldbody><body name="box">'
                                '<geom name="box" type="box" size="0.1 0.1 0.2" mass="1"/></body></worldbody></mujoco>')
    src = (SCENES / "box_drop.toml").read_text().replace('urdf = "../models/box.urdf"',
                                                         f'mjcf = "{tmp_path / "box.xml"}"')
    mj = ms.build_model(ms.load_scene(write(tmp_path / "b.toml", src)).with_options(duration=0.6))
    ur = ms.build_model(ms.load_scene(SCENES / "box_drop.toml").with_options(duration=0.6))
    assert (mj.nq, mj.nv) == (7, 6) and mj.pin.inertias[1].isApprox(ur.pin.inertias[1], 1e-14)
    a, b = ms.simulate(mj, progress=False), ms.simulate(ur, progress=False)
    assert a.impacts == b.impacts > 0 and np.abs(a.q - b.q).max() < 1e-12  # (chaotic later: 3e-17 in I)


def test_mjcf_errors(tmp_path):
    not_mjcf = write(tmp_path / "x.xml", "<robot name='x'/>")
    bad = write(tmp_path / "bad.xml", "<mujoco><worldbody>")
    for xml, fragment in ((not_mjcf, "expected <mujoco>"), (bad, "malformed MJCF")):
        s = body_scene(tmp_path, f'name = "b"\nmjcf = "{xml}"\nroot_joint = "free"\n', name=f"{xml.stem}.toml")
        with pytest.raises(ms.SceneError, match=fragment) as info:
            ms.build_model(ms.load_scene(s))
        assert str(xml) in str(info.value) and str(s) in str(info.value)


# ------------------------------------------------------------------ bundled robot scenes

@pytest.fixture(scope="module")
def runs():
    cache = {}

    def get(name):
        if name not in cache:
            model = ms.build_model(ms.load_scene(SCENES / f"{name}.toml"))
            cache[name] = (model, ms.simulate(model, progress=False))
        return cache[name]
    return get


def _check_run(model, traj, *, rise: float, penetration: float, flagged: frozenset = frozenset()):
    """No NaN; T + V never above its start by more than `rise` [J]; gaps >= -penetration [m]; every
    invariant held, or exactly the `flagged` ones broke (docs/theory.md §10)."""
    assert traj.meta["status"] == ("flagged" if flagged else "complete")
    assert {v["invariant"] for v in traj.meta.get("invariants", [])} == flagged
    assert np.isfinite(traj.q).all() and np.isfinite(traj.u).all()
    E = energy(traj)
    assert E.max() - E[0] <= rise, E.max() - E[0]
    s = ms.summary(traj)
    assert s["min_gap"] >= -penetration, s["min_gap"]
    return s


def test_quadruped_drop(runs):
    model, traj = runs("quadruped_drop")
    assert (model.nq, model.nv, len(model.pairs)) == (19, 18, 25)
    assert all(isinstance(go.geometry, (coal.Box, coal.Cylinder, coal.Sphere, coal.Halfspace))
               for go in model.geom.geometryObjects)
    # every invariant holds (docs/theory.md §10; it was flagged for penetration until the correction's second
    # shortening and the lift at rest along the normals, §2.5); its contact steps no longer gain (the cap scales the
    # whole tree in contact, §2.10)
    s = _check_run(model, traj, rise=1e-12, penetration=5e-3)  # measured: rise 2.6e-13 J, gap -1.6e-3 m
    assert s["impacts"] > 50
    # it comes to rest lying on its trunk (0.114 m high), level
    assert traj.kinetic_energy[-1] < 1e-3 and abs(traj.q[-1, 2] - 0.057) < 2e-3 and abs(traj.q[-1, 6]) > 0.999
    names = model.pair_names + tuple(lim.name for lim in model.limits)  # log_pair: the pairs, then the joint limits
    used = {names[p] for p in traj.arrays["log_pair"]}
    # the knees fold until their joint limits stop them (calf lower, -2.70 rad), before a foot reaches its hip
    assert {"a1/trunk_0|ground", "a1/FL_foot_0|ground", "a1/FL_calf_joint lower", "a1/RR_calf_joint lower"} <= used


def test_quadruped_drop_pairs_are_all_that_touch():
    """With every automatic pair (212: no [collisions], a1.srdf not read) the run is the same, except
    that the hips may touch when they strike their joint limits (the cylinder pairs the scene leaves
    out so that the compiled step takes it: the rear hips 5 percussions from 0.3125 s, the front hips 2
    at 0.32 s, with the energy cap of docs/theory.md §2.10 over the whole robot); the run is identical
    until then and no other excluded pair closes (the closest comes within 2.3 mm). Compared
    without the swept test, whose trigger is the model's thinnest pair (7.2 cm with the scene's pairs,
    1.7 cm with all)."""
    hips = {"a1/FR_hip_0|a1/FL_hip_0", "a1/RR_hip_0|a1/RL_hip_0"}
    sc = ms.load_scene(SCENES / "quadruped_drop.toml").with_options(duration=0.6, tunnelling="none")
    full = dataclasses.replace(sc, collisions=ms.scene.Collisions(),
                               bodies=tuple(dataclasses.replace(b, srdf=None) for b in sc.bodies))
    ma, mf = ms.build_model(sc), ms.build_model(full)
    a = ms.simulate(ma, progress=False)
    assert len(mf.pairs) == 212
    b = ms.simulate(mf, progress=False)
    used = collections.Counter(mf.pair_names[p] for p in b.arrays["log_pair"] if p < len(mf.pairs))
    assert set(used) - set(ma.pair_names) <= hips
    t_hips = min([t for t, p in zip(b.log_t, b.log_pair) if p < len(mf.pairs) and mf.pair_names[p] in hips],
                 default=np.inf)
    before = a.t < t_hips
    assert np.array_equal(a.q[before], b.q[before])
    kept = np.isin(np.array(mf.pair_names), ma.pair_names + tuple(hips))
    assert np.nanmin(b.arrays["gap"][:, ~kept]) > mf.options.contact_tolerance


def test_panda_table(runs):
    model, traj = runs("panda_table")
    assert (model.nq, model.nv, len(model.pairs)) == (7, 7, 36)
    # holds every invariant since the cap scales the whole arm (docs/theory.md §2.10: before, its contact steps on
    # link 4 and below gained ~4e-6 J each while the wrist swung)
    s = _check_run(model, traj, rise=1e-12, penetration=1e-3)  # measured: rise 0 J, gap -3.1e-4 m
    assert s["impacts"] > 10
    log_pair = traj.arrays["log_pair"]  # the pairs, then the joint limits
    hit = {model.pair_names[p].split("|")[0].rsplit("_", 1)[0] for p in log_pair if p < len(model.pairs)}  # links
    assert {"panda/panda_link4", "panda/panda_hand"} <= hit
    assert "panda/panda_joint4 upper" in {model.limits[p - len(model.pairs)].name for p in log_pair
                                          if p >= len(model.pairs)}
    assert traj.arrays["gap"][-100:].min(axis=1).max() < 1e-3  # still lying on the table at the end


def test_solo_drop_mesh_robot(runs):
    model, traj = runs("solo_drop")
    assert (model.nq, model.nv, len(model.pairs)) == (15, 14, 13)
    hulls = [go.geometry for go in model.geom.geometryObjects[:-1]]
    assert len(hulls) == 13 and all(isinstance(g, coal.ConvexBase) for g in hulls)
    assert all(len(v) >= 297 for v in model.vertices[:-1])
    _check_run(model, traj, rise=1e-13, penetration=1e-3)  # measured: rise 4.3e-14 J, gap -2.2e-4 m
    # rests on its belly: level, still, not sinking
    assert traj.kinetic_energy[-200:].max() < 1e-6 and abs(traj.q[-1, 6]) > 0.9999
    assert np.ptp(traj.q[-200:, 2]) < 1e-6 and traj.q[-1, 2] > 0.02


def test_mjcf_example(runs):
    model, traj = runs("mjcf_example")
    # a revolute pendulum's free swing is not integrated exactly: |E - E0| = O(h^2), 2.1e-5 J measured
    s = _check_run(model, traj, rise=5e-5, penetration=1e-3)
    assert s["impacts"] == 2


@pytest.mark.parametrize("name", ["quadruped_drop", "panda_table", "solo_drop", "mjcf_example"])
def test_cli_runs_the_robot_scenes(name, tmp_path):
    out = tmp_path / f"{name}.npz"
    r = subprocess.run([sys.executable, "-m", "moreau_sim.cli", "run", str(SCENES / f"{name}.toml"), "--duration",
                        "0.2", "--out", str(out), "--json"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["status"] == "complete" and summary["us_per_step"] > 0 and out.is_file()
