"""One command-line convention (-o/--out on every command that writes, --set NAME=VALUE with the
scene-file names, python -m moreau_sim, no progress bar in logs) and self-describing output."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

import moreau_sim as ms

ROOT = Path(__file__).resolve().parent.parent
BALL = str(ROOT / "scenes" / "bouncing_ball.toml")


def cli(*args, env=None):
    return subprocess.run([sys.executable, "-m", "moreau_sim", *map(str, args)], capture_output=True, text=True,
                          env={**os.environ, **(env or {})}, timeout=300)


def test_python_m_and_set_reach_every_option(tmp_path):
    out = tmp_path / "b.npz"
    r = cli("run", BALL, "--duration", "0.2", "--set", "bias=explicit", "--set", "gravity=[0,0,-1.62]",
            "--set", "save_every=2", "-o", out, "--json")
    assert r.returncode == 0, r.stderr
    meta = ms.load_trajectory(out).meta
    assert meta["options"]["bias"] == "explicit" and meta["options"]["gravity"] == [0.0, 0.0, -1.62]
    assert meta["options"]["save_every"] == 2 and json.loads(r.stdout)["samples"] == 101


def test_set_errors_name_the_flag(tmp_path):
    for arg, words in (("nope=1", "unknown option"), ("restitution=3", "[0, 1]"), ("restitution", "NAME=")):
        r = cli("run", BALL, "--set", arg, "-o", tmp_path / "x.npz")
        assert r.returncode == 2 and f"--set {arg}" in r.stderr and words in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1


def test_every_writing_command_takes_out(tmp_path):
    npz, png, html = tmp_path / "b.npz", tmp_path / "b.png", tmp_path / "b.html"
    assert cli("run", BALL, "--duration", "0.5", "-o", npz).returncode == 0
    r = cli("plot", npz, "-o", png, "--panels", "energy,q,u")
    assert r.returncode == 0 and png.stat().st_size > 10_000, r.stderr
    assert cli("plot", npz, "--save", tmp_path / "old.png").returncode == 0  # the old name still works
    assert cli("view", npz, "-o", html).returncode == 0 and "<html" in html.read_text()[:2000].lower()
    r = cli("plot", npz, "--panels", "energy,bogus")
    assert r.returncode == 2 and "panels" in r.stderr


def test_no_progress_bar_in_logs(tmp_path):
    """stderr is a pipe here, as in CI logs: the bar must not be drawn even on a long run."""
    r = cli("run", BALL, "--duration", "3", "-o", tmp_path / "b.npz", env={"MOREAU_SIM_PROGRESS_DELAY": "0"})
    assert r.returncode == 0 and "step/s" not in r.stderr and "it/s" not in r.stderr and r.stderr == ""


def test_output_names_and_units_of_q_and_u():
    for name, nq in (("box_drop", 7), ("pendulum_wall", 2), ("newton_cradle_5", 5)):
        traj = ms.run(ROOT / "scenes" / f"{name}.toml", duration=0.01)
        m = traj.meta
        assert len(m["q_names"]) == len(m["q_units"]) == nq == traj.q.shape[1]
        assert len(m["u_names"]) == len(m["u_units"]) == traj.u.shape[1]
        assert len(set(m["q_names"])) == nq  # distinct
    m = ms.run(ROOT / "scenes" / "box_drop.toml", duration=0.01).meta
    assert [n.split("/")[-1] for n in m["q_names"]] == ["x", "y", "z", "qx", "qy", "qz", "qw"]
    assert m["u_units"] == ["m/s"] * 3 + ["rad/s"] * 3


def test_trajectory_repr_is_short():
    traj = ms.run(BALL, duration=1.0)
    text = repr(traj)
    assert len(text) < 200 and "bouncing_ball" in text and "1001 samples" in text and "array" not in text
    assert np.isfinite(traj.q).all()


def test_run_prints_its_summary_for_every_integrator(tmp_path):
    """An event-driven run has no fixed steps (us_per_step is None): `run` still ends with its summary."""
    out = tmp_path / "ball.npz"
    r = cli("run", ROOT / "scenes" / "bouncing_ball.toml", "--set", "integrator=event-driven", "--duration", "1",
            "-o", out)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr and out.exists()
    assert "us/step" not in r.stdout and "wall" in r.stdout
