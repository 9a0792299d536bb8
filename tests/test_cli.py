"""The command line: run (NPZ + summary), info, plot, and its error messages."""

import json
import subprocess
import sys

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim.trajectory import ARRAYS

from helpers import BUNDLED, SCENES


def cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "moreau_sim.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=300)


@pytest.mark.parametrize("name", BUNDLED)
def test_run_writes_a_self_describing_npz(name, tmp_path):
    out = tmp_path / f"{name}.npz"
    r = cli("run", SCENES / f"{name}.toml", "--duration", "0.3", "--out", out, "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    # a run that broke an invariant (docs/theory.md §10) is flagged, says so in one line, and is written too
    assert summary["status"] in ("complete", "flagged") and summary["steps"] == round(0.3 / ms.load_scene(
        SCENES / f"{name}.toml").options.dt)
    assert (summary["status"] == "flagged") == ("moreau-sim: flagged: " in r.stderr)
    with np.load(out, allow_pickle=False) as z:
        assert set(ARRAYS) | {"meta"} <= set(z.files)
        meta = json.loads(str(z["meta"]))
    assert meta["status"] == summary["status"] and bool(meta.get("invariants")) == (meta["status"] == "flagged")
    assert meta["scene"]["name"] == name and "[[bodies]]" in meta["scene"]["toml"]
    assert all("<robot" in text or "<mujoco" in text for text in meta["scene"]["urdf"].values())
    assert meta["options"]["duration"] == 0.3
    assert {"pin", "coal", "piqp", "numpy", "moreau-sim"} <= set(meta["versions"])
    traj = ms.load_trajectory(out)
    assert len(traj.t) == summary["samples"]


def test_run_prints_a_summary_and_overrides(tmp_path):
    out = tmp_path / "b.npz"
    r = cli("run", SCENES / "bouncing_ball.toml", "--dt", "1e-3", "--duration", "1", "-e", "1.0", "--out", out)
    assert r.returncode == 0, r.stderr
    assert "1000 steps" in r.stdout and "impacts" in r.stdout and "us/step" in r.stdout
    meta = ms.load_trajectory(out).meta
    assert meta["options"]["restitution"] == 1.0


def test_info(tmp_path):
    r = cli("info", SCENES / "newton_cradle_5.toml", "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["nq"] == 5 and d["nv"] == 5 and len(d["collision_pairs"]) == 4 and d["restitution"] == 1.0
    r = cli("info", SCENES / "pendulum_wall.toml")
    assert "collision pairs (2)" in r.stdout and "nv = 2" in r.stdout


def test_plot_writes_png(tmp_path):
    out = tmp_path / "b.npz"
    assert cli("run", SCENES / "bouncing_ball.toml", "--duration", "1.5", "--out", out).returncode == 0
    png = tmp_path / "b.png"
    r = cli("plot", out, "--save", png)
    assert r.returncode == 0, r.stderr
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000


def test_errors_are_one_clear_line(tmp_path):
    r = cli("run", SCENES / "bouncing_ball.toml", "--restitution", "1.5", "--out", tmp_path / "x.npz")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "restitution" in r.stderr and "[0, 1]" in r.stderr
    assert not (tmp_path / "x.npz").exists()
    r = cli("run", tmp_path / "missing.toml")
    assert r.returncode == 2 and "missing.toml" in r.stderr and "Traceback" not in r.stderr
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    r = cli("plot", bad)
    assert r.returncode == 2 and "bad.npz" in r.stderr and "Traceback" not in r.stderr


def test_progress_bar_on_long_runs(tmp_path):
    """The bar appears once a run has lasted the delay (2 s by default; 0 here so it always shows),
    on stderr, when forced with --progress (stderr is a pipe here), and not with --no-progress."""
    import os

    env = dict(os.environ, MOREAU_SIM_PROGRESS_DELAY="0")
    args = [sys.executable, "-m", "moreau_sim.cli", "run", str(SCENES / "bouncing_ball.toml"), "--duration", "3",
            "--out", str(tmp_path / "b.npz")]
    r = subprocess.run(args + ["--progress"], capture_output=True, text=True, env=env, timeout=300)  # forced
    assert r.returncode == 0 and "step" in r.stderr and "3000" in r.stderr
    r = subprocess.run(args + ["--no-progress"], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0 and "3000" not in r.stderr
