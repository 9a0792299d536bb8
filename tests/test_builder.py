"""ms.SceneBuilder: a scene built from Python is the scene file it stands for."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import moreau_sim as ms

ROOT = Path(__file__).resolve().parent.parent


def ball_builder(**options):
    b = ms.SceneBuilder("bouncing_ball", folder=ROOT / "scenes", **({"restitution": 0.8, "dt": 1e-3, "duration": 3.0}
                                                                     | options))
    b.add_body("ball", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1), q0=[1.0])
    return b.add_halfspace("ground")


def test_built_ball_runs_as_the_bundled_file():
    """Same bodies, statics and options as scenes/bouncing_ball.toml: the same trajectory, bit for bit."""
    a = ms.run(ball_builder().build())
    b = ms.run(ROOT / "scenes" / "bouncing_ball.toml")
    assert np.array_equal(a.q, b.q) and np.array_equal(a.u, b.u) and np.array_equal(a.log_P, b.log_P)
    assert a.meta["scene"]["toml"] == ball_builder().toml()  # the output describes itself


def test_errors_name_the_field_as_for_a_file():
    with pytest.raises(ms.SceneError, match="restitution"):
        ball_builder(restitution=1.5).build()
    with pytest.raises(ms.SceneError, match="root_joint"):
        ms.SceneBuilder("x").add_body("b", ROOT / "models/ball.urdf", root_joint="hinge").build()
    with pytest.raises(ValueError, match="exactly one"):
        ms.SceneBuilder("x").add_body("b")


def test_saved_file_loads_back(tmp_path):
    b = ball_builder(bias=ms.Bias.EXPLICIT, gravity=np.array([0.0, 0.0, -1.62]), save_every=5)
    b.add_box("step", (0.2, 0.2, 0.1), position=(1.0, 0.0, 0.05)).exclude("ball", "step")
    sc = ms.load_scene(b.save(tmp_path / "ball.toml"))
    assert sc.options == b.build().options
    assert sc.options.bias is ms.Bias.EXPLICIT and sc.options.gravity == (0.0, 0.0, -1.62)
    assert sc.options.save_every == 5 and [s.name for s in sc.statics] == ["ground", "step"]
    assert sc.collisions.exclude == (("ball", "step"),)


def test_save_makes_the_missing_folder(tmp_path):
    """docs/scenes.md's `b.save("out/ball_and_box.toml")` in a fresh clone (no out/ yet)."""
    path = ball_builder().save(tmp_path / "out" / "deeper" / "ball.toml")
    assert path.is_file() and ms.load_scene(path).options == ball_builder().build().options


def test_bodies_sharing_a_model_file_each_have_it_and_errors_still_name_the_body(tmp_path):
    """A model file is looked up once per scene however many bodies name it (scene._parse_body's `files`);
    every body still gets it, its SRDF lookup and its errors: the first body naming a missing file is named,
    and duplicate names are all listed."""
    b = ms.SceneBuilder("beads", folder=ROOT / "scenes")
    for k in range(5):
        b.add_body(f"bead{k}", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1), q0=[0.1 + 0.2 * k])
    sc = b.add_halfspace("ground").build()
    assert {bd.urdf for bd in sc.bodies} == {(ROOT / "models" / "ball.urdf").resolve()}
    assert {bd.srdf for bd in sc.bodies} == {None}
    b.add_body("bead5", tmp_path / "gone.urdf", root_joint="prismatic", axis=(0, 0, 1))
    b.add_body("bead6", tmp_path / "gone.urdf", root_joint="prismatic", axis=(0, 0, 1))
    with pytest.raises(ms.SceneError, match=r"\[\[bodies\]\]\[5\] \(bead5\) urdf: file not found"):
        b.build()
    dup = ms.SceneBuilder("dup", folder=ROOT / "scenes")
    for name in ("a", "b", "a", "c", "b"):
        dup.add_body(name, "../models/ball.urdf", root_joint="free")
    with pytest.raises(ms.SceneError, match=r"duplicate body/static names \['a', 'b'\]"):
        dup.build()
