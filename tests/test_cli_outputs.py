"""The command line's edges (issue 28): where it writes (never over an input, a suffix, a trailing
slash is a folder, folders made only below the current directory or the scene's folder, no empty
names), SIGINT/SIGTERM (one line, exit 130/143, a sweep's workers ended with it), `info`, `sweep`'s
exit status, `--set` everywhere, and readable summaries."""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

import moreau_sim as ms

ROOT = Path(__file__).resolve().parent.parent


def cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "moreau_sim.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


@pytest.fixture
def repo(tmp_path):
    """A copy of scenes/ and models/ (the commands are tried against their own inputs)."""
    for d in ("scenes", "models"):
        shutil.copytree(ROOT / d, tmp_path / d)
    return tmp_path


def one_error(r, *words):
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert all(w in lines[0] for w in words), lines[0]


@pytest.mark.parametrize("out", ["scenes/bouncing_ball.toml", "models/ball.urdf"])
def test_run_never_writes_over_an_input(repo, out):
    before = (repo / out).read_bytes()
    one_error(cli("run", "scenes/bouncing_ball.toml", "--duration", "0.1", "-o", out, cwd=repo), "--out", out)
    assert (repo / out).read_bytes() == before


def test_an_input_is_refused_by_its_resolved_path(repo):
    """Through a symlink and a relative detour: the same file, refused as an input (plot FILE -o FILE)."""
    assert cli("run", "scenes/bouncing_ball.toml", "--duration", "0.1", "-o", "b.npz", cwd=repo).returncode == 0
    (repo / "link.npz").symlink_to(repo / "b.npz")
    before = (repo / "b.npz").read_bytes()
    for out in ("link.npz", "scenes/../b.npz"):
        one_error(cli("plot", "b.npz", "-o", out, cwd=repo), "input")
    assert (repo / "b.npz").read_bytes() == before


def test_output_rules(repo):
    one_error(cli("run", "scenes/bouncing_ball.toml", "-o", "x.txt", cwd=repo), ".npz")
    one_error(cli("run", "scenes/bouncing_ball.toml", "-o", "", cwd=repo), "empty")
    one_error(cli("run", "scenes/bouncing_ball.toml", "-o", "/nonexistent_moreau_dir/x.npz", cwd=repo),
              "/nonexistent_moreau_dir", "does not exist")
    assert not Path("/nonexistent_moreau_dir").exists()
    r = cli("run", "scenes/bouncing_ball.toml", "--duration", "0.1", "-o", "out/", cwd=repo)  # a folder
    assert r.returncode == 0 and (repo / "out" / "bouncing_ball.npz").is_file() and not (repo / "out").is_file()
    r = cli("run", "scenes/bouncing_ball.toml", "--duration", "0.1", "-o", "new/sub/b.npz", cwd=repo)  # below cwd
    assert r.returncode == 0 and ms.load_trajectory(repo / "new/sub/b.npz").complete


def test_empty_output_field_is_named(repo):
    scene = repo / "scenes" / "bouncing_ball.toml"
    scene.write_text(scene.read_text().replace('file = "bouncing_ball.npz"', 'file = ""'))
    one_error(cli("run", scene, "--duration", "0.1", cwd=repo), "[output] file", "empty")


def test_every_writing_command_checks_its_output(repo):
    assert cli("run", "scenes/bouncing_ball.toml", "--duration", "0.1", "-o", "b.npz", cwd=repo).returncode == 0
    one_error(cli("plot", "b.npz", "-o", "b.npz", cwd=repo), "input")
    one_error(cli("plot", "b.npz", "-o", "/nonexistent_moreau_dir/b.png", cwd=repo), "does not exist")
    r = cli("plot", "b.npz", "-o", "pics/", cwd=repo)
    assert r.returncode == 0 and (repo / "pics" / "b.png").is_file(), r.stderr
    one_error(cli("view", "b.npz", "-o", "b.npz", cwd=repo), "input")
    one_error(cli("view", "b.npz", "-o", "b.txt", cwd=repo), ".html")
    one_error(cli("regress", "scenes/bouncing_ball.toml", "-b", "bl", "--update", "--junit",
                  "scenes/bouncing_ball.toml", cwd=repo), "--junit", "input")
    one_error(cli("regress", "scenes/bouncing_ball.toml", "-b", "/nonexistent_moreau_dir/bl", "--update", cwd=repo),
              "--baseline")
    one_error(cli("sweep", "scenes/bouncing_ball.toml", "-p", "restitution=0.5", "-o", "", cwd=repo), "empty")
    one_error(cli("sweep", "scenes/bouncing_ball.toml", "-p", "restitution=0.5", "-o", "/nonexistent_moreau_dir/s",
                  cwd=repo), "/nonexistent_moreau_dir")
    assert not Path("/nonexistent_moreau_dir").exists()


def test_plot_of_a_non_npz_is_one_plain_line(repo):
    r = cli("plot", "scenes/bouncing_ball.toml", cwd=repo)
    one_error(r, "bouncing_ball.toml", "not a")
    assert "pickle" not in r.stderr


def test_a_complete_run_removes_the_stale_partial_file(repo):
    assert cli("run", "scenes/bouncing_ball.toml", "--duration", "0.1", "-o", "b.npz", cwd=repo).returncode == 0
    stale = repo / "b.partial.npz"
    shutil.copy(repo / "b.npz", stale)  # what an interrupted attempt leaves (status "failed: interrupted")
    r = cli("run", "scenes/bouncing_ball.toml", "--duration", "0.1", "-o", "b.npz", "--resume", cwd=repo)
    assert r.returncode == 0 and not stale.exists(), r.stderr


def test_an_interrupted_run_keeps_its_samples_then_resume_clears_them(repo):
    args = [sys.executable, "-m", "moreau_sim.cli", "run", "scenes/box_stack_10.toml", "--duration", "1000",
            "--checkpoint-every", "0.01", "-o", "s.npz", "--no-progress"]
    p = subprocess.Popen(args, cwd=repo, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ck = repo / "s.checkpoint.npz"
    for _ in range(600):
        if ck.exists() or p.poll() is not None:
            break
        time.sleep(0.1)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 143 and "SIGTERM" in err and "Traceback" not in err, err
    assert (repo / "s.partial.npz").exists()
    assert ms.load_trajectory(repo / "s.partial.npz").meta["status"].startswith("failed")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_start_up_is_one_line(sig, tmp_path):
    """The imports take a moment: a signal at any point of them is one line, exit 128 + its number.
    (It is sent once the package's imports have begun, i.e. once coal or Pinocchio is being loaded:
    before that, in the interpreter's own start-up, Python's default applies.)"""
    for delay in (0.0, 0.05, 0.1, 0.2, 0.4):
        script = Path(sys.executable).with_name("moreau-sim")  # the console script, not on CI's PATH
        command = [str(script), "info", str(ROOT / "scenes" / "bouncing_ball.toml")]
        p = subprocess.Popen(command,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
        maps = Path(f"/proc/{p.pid}/maps")
        for _ in range(3000):
            try:
                if p.poll() is not None or any(lib in maps.read_text() for lib in ("coal", "pinocchio")):
                    break
            except OSError:
                break
            time.sleep(0.001)
        time.sleep(delay)
        p.send_signal(sig)
        _, err = p.communicate(timeout=60)
        assert "Traceback" not in err and len(err.strip().splitlines()) <= 1, err
        # 0: it had finished; -sig: it was in the interpreter's own shutdown, after the command
        assert p.returncode in (0, 128 + sig, -sig), (delay, p.returncode, err)
        if p.returncode == 128 + sig:
            assert sig.name in err


def test_sigterm_ends_a_sweeps_workers(repo):
    args = [sys.executable, "-m", "moreau_sim.cli", "sweep", "scenes/box_stack_10.toml", "-p",
            "duration=1000,1001,1002", "-j", "2", "-o", "sw", "--no-progress"]
    p = subprocess.Popen(args, cwd=repo, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc = psutil.Process(p.pid)
    for _ in range(600):  # the forkserver and both workers
        kids = proc.children(recursive=True)
        if sum("forkserver" in " ".join(k.cmdline()) for k in kids) >= 3:
            break
        time.sleep(0.1)
    time.sleep(0.5)
    kids = proc.children(recursive=True)
    assert len(kids) >= 3
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 143 and "SIGTERM" in err and "Traceback" not in err, err
    gone, alive = psutil.wait_procs(kids, timeout=30)
    assert not alive, [" ".join(k.cmdline()) for k in alive]


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_sweep_exit_status(repo):
    ok = cli("sweep", "scenes/bouncing_ball.toml", "-p", "restitution=0.5,0.6", "--set", "duration=0.1", "-o", "a",
             "-j", "1", cwd=repo)
    assert ok.returncode == 0, ok.stderr
    # gravity 1.7e308 m/s^2 with h = 1 s: the energy overflows at step 1 (a failed point)
    some = cli("sweep", "scenes/bouncing_ball.toml", "-p", "gravity=[0,0,-9.81],[0,0,1.7e308]", "-s", "dt=1", "-s",
               "duration=3", "-o", "b", "-j", "1", cwd=repo)
    assert some.returncode == 1 and "1 failed" in some.stdout, some.stderr
    every = cli("sweep", "scenes/bouncing_ball.toml", "-p", "gravity=[0,0,1.7e308]", "-s", "dt=1", "-s",
                "duration=3", "-o", "c", "-j", "1", cwd=repo)
    assert every.returncode == 1
    one_error(cli("sweep", "scenes/bouncing_ball.toml", "-p", "bogus=1", cwd=repo), "bogus")
    one_error(cli("sweep", "scenes/bouncing_ball.toml", "-s", "duration=1,2", cwd=repo), "--set")


def test_set_is_one_spelling_on_run_regress_and_sweep(repo):
    r = cli("run", "scenes/bouncing_ball.toml", "-s", "duration=0.1", "-o", "b.npz", cwd=repo)
    assert r.returncode == 0 and ms.load_trajectory(repo / "b.npz").meta["options"]["duration"] == 0.1
    r = cli("regress", "scenes/bouncing_ball.toml", "-b", "bl", "--update", "-s", "duration=0.1", cwd=repo)
    assert r.returncode == 0, r.stderr
    assert "wall time" in r.stdout  # not to be read as the simulated 0.1 s


def test_info_lists_coordinates_in_order_and_summarises_pairs(repo):
    r = cli("info", "scenes/newton_cradle_5.toml", cwd=repo)
    assert r.returncode == 0, r.stderr
    model = ms.build_model(ms.load_scene(repo / "scenes" / "newton_cradle_5.toml"))
    names = model.coordinates()["q_names"]
    assert f"coordinates q ({len(names)}): {', '.join(names)}" in r.stdout
    scene = repo / "scenes" / "box_stack_10.toml"
    pairs = ms.build_model(ms.load_scene(scene)).pair_names
    assert len(pairs) > 10
    short = cli("info", scene, cwd=repo).stdout
    assert f"collision pairs ({len(pairs)})" in short and f"and {len(pairs) - 10} more" in short
    assert sum(p in short for p in pairs) == 10
    full = cli("info", scene, "--all-pairs", cwd=repo).stdout
    assert all(p in full for p in pairs)


def test_summary_prints_readably_and_stays_a_dict():
    traj = ms.run(ROOT / "scenes" / "bouncing_ball.toml", duration=0.5)
    s = ms.summary(traj)
    assert isinstance(s, dict) and s["impacts"] == traj.impacts and s["steps"] == 500
    text = str(s)
    assert text.startswith("bouncing_ball: complete") and "{" not in text and "impacts 1" in text
    assert {"t", "q", "u", "gap", "log_P"} <= set(dir(traj))
    assert traj.t is traj.arrays["t"] and traj.q.shape == (501, 1) and traj.u.shape == (501, 1)


def test_sigterm_stops_a_serial_sweep_without_failing_its_point(repo):
    """With -j 1 the point runs in the sweep's own process: a stop is a stop, not a failed point."""
    args = [sys.executable, "-m", "moreau_sim.cli", "sweep", "scenes/box_stack_10.toml", "-p", "duration=1000,1001",
            "-j", "1", "-o", "sw", "--no-progress"]
    p = subprocess.Popen(args, cwd=repo, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for _ in range(600):
        if (repo / "sw" / ".sweep.lock").exists() or p.poll() is not None:
            break
        time.sleep(0.1)
    time.sleep(1.0)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 143 and "SIGTERM" in err and "Traceback" not in err, err
    assert not list((repo / "sw").rglob("*.failed.npz"))
    table = (repo / "sw" / "sweep.csv")
    assert not table.exists() or ",failed," not in table.read_text()
