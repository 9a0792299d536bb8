"""Robots load as their authors meant (docs/robots.md, "Self-collision pairs", "MJCF"): the SRDF
beside a URDF disables its pairs (checked against the SRDF parsed here with xml.etree), self pairs
overlapping at a reference pose are left out with one warning naming them, go2 and solo12 run on
the ground, `moreau-sim info` lists the joints in the order of q, ur5's penetration explained,
unsupported MJCF elements refused with their file and line, MJCF ranges in the position limits.

Needs example-robot-data."""

import json
import math
import subprocess
import sys
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
from moreau_sim import robots

from helpers import ROOT

SHARE = robots.example_robot_data_share()
ERD = "package://example-robot-data/robots"
ROBOTS = {  # body name -> URDF URI, the SRDF example-robot-data's own loader pairs with it
    "go2": ("go2_description/urdf/go2.urdf", "go2_description/srdf/go2.srdf"),
    "solo12": ("solo_description/robots/solo12.urdf", "solo_description/srdf/solo.srdf"),
    "a1": ("a1_description/urdf/a1.urdf", "a1_description/srdf/a1.srdf"),
    "ur5": ("ur_description/urdf/ur5_robot.urdf", "ur_description/srdf/ur5.srdf"),
}


def scene(tmp_path: Path, name: str, body: str = "", *, root="free", duration=0.1, name_file="s.toml",
          collisions="") -> Path:
    path = tmp_path / name_file
    path.write_text(f'[scene]\nname = "{name}"\n[simulation]\nrestitution = 0.2\ndt = 1e-3\nduration = {duration}\n'
                    f'[[bodies]]\nname = "{name}"\nurdf = "{ERD}/{ROBOTS[name][0]}"\nroot_joint = "{root}"\n{body}\n'
                    f'[[statics]]\nname = "ground"\nshape = "halfspace"\n{collisions}')
    return path


def build(path: Path) -> ms.Model:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the overlap warning: its own test below
        return ms.build_model(ms.load_scene(path))


def srdf_links(srdf: Path) -> set[frozenset[str]]:
    """The link pairs of the SRDF's <disable_collisions>, read here with xml.etree."""
    return {frozenset((d.get("link1"), d.get("link2"))) for d in ET.parse(srdf).getroot().iter("disable_collisions")}


def link_pairs(model: ms.Model, names) -> list[frozenset[str]]:
    """Each pair's two link names (without the body prefix)."""
    link = {go.name: model.pin.frames[go.parentFrame].name.split("/", 1)[1] for go in model.geom.geometryObjects
            if "/" in go.name}
    return [frozenset(link.get(n, n) for n in name.split("|")) for name in names]


# ------------------------------------------------------------------ SRDF

@pytest.mark.parametrize("name", ["go2", "solo12", "a1", "ur5"])
def test_the_srdf_beside_the_urdf_disables_its_pairs(tmp_path, name):
    """Every automatic pair (the model without SRDF) whose links the SRDF disables is left out,
    and only those: counted against the SRDF file parsed here."""
    srdf = SHARE / "example-robot-data" / "robots" / ROBOTS[name][1]
    model = build(scene(tmp_path, name, root="fixed" if name == "ur5" else "free", name_file="a.toml"))
    bare = build(scene(tmp_path, name, "srdf = false", root="fixed" if name == "ur5" else "free", name_file="b.toml"))
    assert ms.load_scene(tmp_path / "a.toml").bodies[0].srdf == srdf.resolve()
    disabled = srdf_links(srdf)
    every = [*bare.pair_names, *(n for n, why in bare.excluded if why.startswith("overlaps"))]  # automatic
    expected = {n for n, links in zip(every, link_pairs(bare, every)) if links in disabled}
    by_srdf = {n for n, why in model.excluded if why == "disabled by the SRDF"}
    assert by_srdf == expected
    # solo.srdf disables only adjacent links (a link and its parent), which the automatic rule skips
    assert bool(expected) == (name != "solo12")
    overlap = {n for n, why in model.excluded if why.startswith("overlaps")}
    assert set(model.pair_names) == set(every) - expected - overlap
    # the scene may name the SRDF itself: the same pairs
    named = build(scene(tmp_path, name, f'srdf = "{ERD}/{ROBOTS[name][1]}"', root="fixed" if name == "ur5" else "free",
                        name_file="c.toml"))
    assert named.pair_names == model.pair_names


def test_a_malformed_or_missing_srdf_is_one_line(tmp_path):
    bad = tmp_path / "bad.srdf"
    bad.write_text("<robot><disable_collisions link1='a'")
    for value, fragment in ((str(bad), "malformed SRDF"), ("nothere.srdf", "file not found"),
                            ("1", "srdf: must be a path string")):
        body = f'srdf = "{value}"' if value != "1" else "srdf = 1"
        with pytest.raises(ms.SceneError) as info:
            build(scene(tmp_path, "go2", body))
        assert fragment in str(info.value) and "\n" not in str(info.value)


def test_pairs_overlapping_at_a_reference_pose_are_left_out_with_one_warning(tmp_path):
    """solo12 with solo.srdf (written for the 8-dof solo, whose upper legs hang from the base):
    its base hull and the four upper-leg hulls overlap at the neutral pose and at the SRDF's poses.
    One warning line names the four pairs; without that rule the start is refused naming one."""
    path = scene(tmp_path, "solo12", "position = [0.0, 0.0, 0.5]")
    with pytest.warns(UserWarning) as record:
        model = ms.build_model(ms.load_scene(path))
    (w,) = [r for r in record if "overlap at its reference pose" in str(r.message)]
    msg = str(w.message)
    expected = {f"solo12/{leg}_UPPER_LEG_0|solo12/base_link_0" for leg in ("FL", "FR", "HL", "HR")}
    assert "\n" not in msg and all(p in msg for p in expected) and "[collisions] include" in msg
    assert {n for n, why in model.excluded if why.startswith("overlaps")} == expected
    # the depth each names is coal's at neutral, measured on the model that keeps the pairs
    keep = build(scene(tmp_path, "solo12", "position = [0.0, 0.0, 0.5]", name_file="k.toml",
                       collisions="[collisions]\ninclude = [" + ", ".join(
                   f'["solo12/base_link", "solo12/{leg}_UPPER_LEG"]' for leg in ("FL", "FR", "HL", "HR")) + "]"))
    assert expected <= set(keep.pair_names)
    gd = pin.GeometryData(keep.geom)
    q = pin.neutral(keep.pin)
    pin.computeDistances(keep.pin, keep.pin.createData(), keep.geom, gd, q)
    for k, name in enumerate(keep.pair_names):
        if name in expected:
            assert gd.distanceResults[k].min_distance < -1e-3
    refusal = r"UPPER_LEG_0\|solo12/base_link_0 starts .* inside.*\(3 more pair\(s\) too\); two parts of body solo12"
    with pytest.raises(ms.SceneError, match=refusal):
        ms.model.initial_state(keep)  # kept by include: the start is refused, naming a pair and the remedy


# Reference pose "standing" of each SRDF (solo.srdf's for solo12), root at the origin.
STANDING = {"go2": [0.068, 0.785, -1.44, -0.068, 0.785, -1.44, 0.068, 0.785, -1.44, -0.068, 0.785, -1.44],
            "solo12": [0.1, 0.8, -1.6, -0.1, 0.8, -1.6, 0.1, -0.8, 1.6, -0.1, -0.8, 1.6]}


@pytest.mark.parametrize("name", ["go2", "solo12"])
def test_go2_and_solo12_take_100_steps_on_the_ground(tmp_path, name):
    """With the automatic pairs (no [collisions]) both failed before the first step (thigh and
    base hulls overlapping at the start: 'PIQP_PRIMAL_INFEASIBLE (746 closed contacts)'). Dropped
    standing, the lowest point 5 mm above the ground: they land, take 100 steps, never gain energy,
    and the ground stops them within 1 mm."""
    q0 = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, *STANDING[name]]
    probe = build(scene(tmp_path, name, f"q0 = {q0}", name_file="p.toml"))
    gd = pin.GeometryData(probe.geom)
    pin.computeDistances(probe.pin, probe.pin.createData(), probe.geom, gd, probe.q0)
    low = min(r.min_distance for r, n in zip(gd.distanceResults, probe.pair_names) if n.endswith("|ground"))
    q0[2] = 0.005 - low
    model = build(scene(tmp_path, name, f"q0 = {q0}"))
    traj = ms.simulate(model, progress=False)
    assert traj.meta["status"] == "complete" and len(traj.t) == 101 and np.isfinite(traj.q).all()
    assert len(traj.arrays["log_pair"]) > 0  # it landed
    e = traj.kinetic_energy + traj.potential_energy
    assert e.max() - e[0] < 1e-9
    assert np.nanmin(traj.arrays["gap"]) > -1e-3


# ------------------------------------------------------------------ info

def test_info_lists_the_joints_in_q_order_and_the_excluded_pairs(tmp_path):
    path = scene(tmp_path, "go2")
    model = build(path)
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-m", "moreau_sim", "info", str(path)], capture_output=True, text=True,
                         timeout=300, env=env, check=True).stdout
    lines = out.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("  joints in the order of q"))
    rows = [line.split() for line in lines[start + 1:start + model.pin.njoints]]
    order = sorted(range(1, model.pin.njoints), key=lambda j: model.pin.joints[j].idx_q)
    assert [r[0] for r in rows] == [model.pin.names[j] for j in order]
    for r, j in zip(rows, order):
        jm = model.pin.joints[j]
        q = f"q[{jm.idx_q}]" if jm.nq == 1 else f"q[{jm.idx_q}:{jm.idx_q + jm.nq}]"
        assert q in r
        if jm.nq == 1:  # the revolute joints: their URDF limits, in radians
            lo, up = model.pin.lowerPositionLimit[jm.idx_q], model.pin.upperPositionLimit[jm.idx_q]
            assert f"[{lo:.6g}, {up:.6g}]" in " ".join(r) and r[-1] == "rad"
    assert f"excluded pairs ({len(model.excluded)}" in out
    d = json.loads(subprocess.run([sys.executable, "-m", "moreau_sim", "info", "--json", str(path)],
                                  capture_output=True, text=True, timeout=300, env=env, check=True).stdout)
    assert [j["name"] for j in d["joints"]] == [model.pin.names[j] for j in order]
    assert [j["q"][0] for j in d["joints"]] == [model.pin.joints[j].idx_q for j in order]
    assert {e["pair"] for e in d["excluded_pairs"]} == {n for n, _ in model.excluded}


# ------------------------------------------------------------------ ur5

def test_ur5_on_the_ground_at_neutral_starts_with_its_wrist_in_the_ground(tmp_path):
    """ur5's zero configuration holds the arm level at the shoulder height d1 = 0.0892 m with the
    wrist hanging d5 = 0.0947 m below it: the wrist_3 hull reaches 4.85 cm below the base's plane.
    On a fixed root at the ground that is the -4.85e-2 m 'penetration': refused, naming the pair."""
    with pytest.raises(ms.SceneError) as info:
        ms.model.initial_state(build(scene(tmp_path, "ur5", root="fixed")))
    msg = str(info.value)
    model = build(scene(tmp_path, "ur5", root="fixed", name_file="u.toml"))
    d = model.pin.createData()
    pin.forwardKinematics(model.pin, d, pin.neutral(model.pin))
    k = next(i for i, go in enumerate(model.geom.geometryObjects) if go.name == "ur5/wrist_3_link_0")
    go = model.geom.geometryObjects[k]
    M = d.oMi[go.parentJoint]
    V = model.vertices[k] @ M.rotation.T + M.translation  # the hull's vertices (joint frame) in the world
    assert "ur5/wrist_3_link_0|ground" in msg and f"{-V[:, 2].min():.3g} m inside" in msg
    assert abs(V[:, 2].min() + 0.0485) < 5e-4


def test_ur5_mounted_above_the_ground_has_no_persistent_penetration(tmp_path):
    model = build(scene(tmp_path, "ur5", "position = [0.0, 0.0, 0.1]", root="fixed", duration=1.0))
    traj = ms.simulate(model, progress=False)
    gap = traj.arrays["gap"]
    assert traj.meta["status"] == "complete" and len(traj.arrays["log_pair"]) > 0
    assert np.nanmin(gap) > -1e-3 and np.nanmin(gap[-100:]) > -1e-4  # measured: -2.6e-4 m, -9.6e-6 m


# ------------------------------------------------------------------ MJCF

BODY = ('<body name="b" pos="0 0 1">\n<joint name="h" type="hinge" axis="0 1 0"/>\n'
        '<geom type="sphere" size="0.1" mass="1"/>\n')


def mjcf_scene(tmp_path: Path, before="", inside="", name="m.xml") -> Path:
    (tmp_path / name).write_text(f'<mujoco model="m">\n<compiler angle="radian"/>\n{before}\n<worldbody>\n{BODY}'
                                 f'{inside}\n</body>\n</worldbody>\n</mujoco>\n')
    path = tmp_path / f"{name}.toml"
    path.write_text(f'[[bodies]]\nname = "m"\nmjcf = "{name}"\nroot_joint = "fixed"\n')
    return path


def refused_line(path: Path, *fragments) -> str:
    """The error of loading `path`, by the API and by the command line: one line, no traceback."""
    with pytest.raises(ms.SceneError) as info:
        ms.build_model(ms.load_scene(path))
    msg = str(info.value)
    assert "\n" not in msg and all(f in msg for f in fragments), (fragments, msg)
    r = subprocess.run([sys.executable, "-m", "moreau_sim", "info", str(path)], capture_output=True, text=True,
                       timeout=120, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert r.returncode != 0 and "Traceback" not in r.stderr and all(f in r.stderr for f in fragments)
    return msg


@pytest.mark.parametrize("tag", sorted(robots.MJCF_WHY))
def test_each_unsupported_mjcf_element_is_refused_with_its_file_and_line(tmp_path, tag):
    """Every element of the one list of unsupported elements (robots.MJCF_WHY) stops the load
    with its file and line (line 3: after <mujoco> and <compiler>) and why."""
    path = mjcf_scene(tmp_path, before=f"<{tag}/>")
    refused_line(path, f"{tmp_path / 'm.xml'}:3: <{tag}> is not supported", robots.MJCF_WHY[tag])


def test_unsupported_elements_in_bodies_and_included_files_name_their_line(tmp_path):
    refused_line(mjcf_scene(tmp_path, inside='<composite type="grid" count="2 2 1" spacing="0.1"/>'),
                 f"{tmp_path / 'm.xml'}:8: <composite> is not supported")
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "t.xml").write_text('<mujoco>\n\n<tendon><fixed name="t"/></tendon>\n</mujoco>\n')
    refused_line(mjcf_scene(tmp_path, before='<include file="parts/t.xml"/>', name="i.xml"),
                 f"{tmp_path / 'parts' / 't.xml'}:3: <tendon> is not supported")
    (tmp_path.parent / "outside.xml").write_text("<mujoco/>")
    refused_line(mjcf_scene(tmp_path, before='<include file="../outside.xml"/>', name="o.xml"),
                 f"{tmp_path / 'o.xml'}:3: <include", "only files inside the model's folder")


LIMITS = """<mujoco model="limits">
  {compiler}
  <default><default class="lim"><joint range="-10 20"/></default><default class="plain"/></default>
  <worldbody>
    <body name="a" pos="0 0 1"><joint name="h1" type="hinge" axis="0 1 0" range="-30 45" limited="true"/>
      <geom type="sphere" size="0.1" mass="1"/>
      <body name="b" pos="0 0 -0.5"><joint name="s1" type="slide" axis="1 0 0" range="-0.2 0.3"/>
        <geom type="sphere" size="0.1" mass="1"/>
        <body name="c" pos="0 0 -0.5" childclass="lim"><joint name="h2" type="hinge" axis="0 1 0"/>
          <geom type="sphere" size="0.1" mass="1"/>
          <body name="d" pos="0 0 -0.5" childclass="plain">
            <joint name="h3" type="hinge" axis="0 1 0" range="-60 60" limited="false"/>
            <geom type="sphere" size="0.1" mass="1"/>
            <body name="e" pos="0 0 -0.5"><joint name="h4" type="hinge" axis="0 1 0"/>
              <geom type="sphere" size="0.1" mass="1"/>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("compiler, to_radians", [("", math.radians), ('<compiler angle="degree"/>', math.radians),
                                                  ('<compiler angle="radian"/>', float)])
def test_mjcf_ranges_land_in_the_position_limits_in_radians(tmp_path, compiler, to_radians):
    """MuJoCo's reading of range and limited: a hinge's range in the compiler's angle unit
    (degrees by default), a slide's in metres, a class's range through childclass, limited="false"
    unlimited, no range unlimited; in the scene model's lowerPositionLimit / upperPositionLimit."""
    (tmp_path / "l.xml").write_text(LIMITS.format(compiler=compiler))
    (tmp_path / "l.toml").write_text('[[bodies]]\nname = "l"\nmjcf = "l.xml"\nroot_joint = "prismatic"\n')
    model = ms.build_model(ms.load_scene(tmp_path / "l.toml"))
    expected = {"l/h1": (to_radians(-30), to_radians(45)), "l/s1": (-0.2, 0.3),
                "l/h2": (to_radians(-10), to_radians(20)), "l/h3": (-np.inf, np.inf), "l/h4": (-np.inf, np.inf)}
    for name, (lo, up) in expected.items():
        i = model.pin.joints[model.pin.getJointId(name)].idx_q
        assert (model.pin.lowerPositionLimit[i], model.pin.upperPositionLimit[i]) == (lo, up), name


@pytest.mark.parametrize("joint, fragment", [
    ('<joint name="x" type="ball" range="0 50"/>', "a limited ball joint"),
    ('<joint name="x" type="hinge" limited="true"/>', "is not two numbers"),
    ('<joint name="x" type="hinge" range="20 -10"/>', "lower < upper"),
])
def test_mjcf_limits_that_cannot_be_read_are_refused(tmp_path, joint, fragment):
    path = mjcf_scene(tmp_path, inside=f'<body name="c" pos="0 0 -0.3">{joint}<geom type="sphere" size="0.1" '
                                       'mass="1"/></body>')
    refused_line(path, f"{tmp_path / 'm.xml'}:8: joint 'x'", fragment)


def test_the_replay_rebuilds_the_pairs_the_run_used(tmp_path):
    """The output keeps the SRDF's text: the model rebuilt from a trajectory alone has the run's
    pairs (the percussion log's pair indices point at the same pairs)."""
    from moreau_sim.viewer.stored import model_from_trajectory

    # go2 at its neutral q has its calves beyond their limits: the pairs, not the limits, are tested here
    model = build(scene(tmp_path, "go2", "position = [0.0, 0.0, 0.6]\njoint_limits = false", duration=0.005))
    traj = ms.simulate(model, progress=False)
    assert "go2" in traj.meta["scene"]["srdf"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        again = model_from_trajectory(traj)
    assert again.pair_names == model.pair_names and len(again.excluded) == len(model.excluded)
