"""Checkpoint and resume: a resumed run is bit-identical to an uninterrupted one (every array:
samples, energies, gaps, the percussion log, branches, the ledger; and the ledger's meta), also
after kill -9 of the process; a
killed sweep resumes to the same table; checkpoints of another run are refused by name."""

from __future__ import annotations

import csv
import signal
import subprocess
import sys
import time

import pytest

import moreau_sim as ms
from moreau_sim.checkpoint import Checkpoint
from moreau_sim.sweep import WALL_COLUMNS
from moreau_sim.trajectory import ARRAYS

from helpers import SCENES, damage_member, scene


def same_arrays(a: ms.Trajectory, b: ms.Trajectory) -> list[str]:
    """The names of the arrays that differ in dtype, shape or any bit."""
    def same(x, y):
        return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
    return [k for k in ARRAYS if not same(a.arrays[k], b.arrays[k])]


# box stacks: coal's GJK keeps cached guesses between steps (Data.warm_start); corner_point branches
@pytest.mark.parametrize("name,steps", [("zeno_ball", 400), ("box_stack_5", 150), ("corner_point", 60),
                                        ("newton_cradle_5", 200), ("rocking_block", 300)])
@pytest.mark.parametrize("e,h_factor", [(None, 1.0), (0.0, 0.5), (1.0, 2.0)])
@pytest.mark.parametrize("impl", ["python", "compiled"])
def test_resume_from_a_checkpoint_is_bitwise(tmp_path, name, steps, e, h_factor, impl):
    base = scene(name)
    h = base.options.dt * h_factor
    sc = base.with_options(dt=h, duration=steps * h, restitution=e, step_impl=impl, save_every=3)
    path = tmp_path / "c.npz"
    full = ms.simulate(ms.build_model(sc), progress=False,
                       checkpoint=Checkpoint(path=path, every=(steps // 3 + 1) * h, keep=True))
    ck = ms.load_trajectory(path).meta["checkpoint"]
    assert 0 < ck["steps"] < steps  # the last checkpoint, mid-run
    resumed = ms.simulate(ms.build_model(sc), progress=False, checkpoint=Checkpoint(path=path, resume=True))
    assert resumed.complete and same_arrays(full, resumed) == []
    assert resumed.meta["ledger"] == full.meta["ledger"]  # the ledger's running figures carried too
    assert not path.exists()  # removed once the run completed


def test_a_checkpoint_of_another_run_or_damaged_is_refused(tmp_path):
    sc = scene("bouncing_ball", duration=0.2)
    path = tmp_path / "c.npz"
    ms.simulate(ms.build_model(sc), progress=False, checkpoint=Checkpoint(path=path, every=0.05, keep=True))
    with pytest.raises(ms.SceneError, match="c.npz: a checkpoint of another run"):
        ms.simulate(ms.build_model(sc.with_options(restitution=0.3)), progress=False,
                    checkpoint=Checkpoint(path=path, resume=True))
    damage_member(path)
    with pytest.raises(ms.SceneError, match="c.npz.*delete it"):
        ms.simulate(ms.build_model(sc), progress=False, checkpoint=Checkpoint(path=path, resume=True))


# every integrator resumes through the same driver (driver.py): the integrator's state_dict() at an
# accepted point (an event, a phase's step, a fixed step), the driver's accumulators, the ledger's terms;
# slider_crank_clearance: the adaptive integrator's fixed steps and back (its fallbacks)
RESUMED = [(i, *c) for i in ("adaptive", "event-driven")
           for c in [("bouncing_ball", 2.0, None), ("rocking_block", 0.6, 0.3), ("zeno_ball", 1.5, 0.5),
                     ("box_drop", 0.6, None), ("pendulum_wall", 1.0, 0.9)]]
RESUMED += [("adaptive", "box_stack_5", 0.4, None), ("adaptive", "corner_point", 0.3, 0.5),
            ("adaptive", "newton_cradle_5", 0.3, 1.0), ("adaptive", "slider_crank_clearance", 0.05, None)]


@pytest.mark.parametrize("integrator,name,duration,e", RESUMED)
def test_every_integrator_resumes_bitwise(tmp_path, integrator, name, duration, e):
    sc = scene(name).with_options(duration=duration, restitution=e, integrator=integrator)
    path = tmp_path / "c.npz"
    full = ms.simulate(ms.build_model(sc), progress=False,
                       checkpoint=Checkpoint(path=path, every=duration / 7, keep=True))
    saved = ms.load_trajectory(path).meta
    ck, before = saved["checkpoint"], saved["run"]
    assert 0 < ck["t"] < duration  # the last checkpoint, mid-run
    resumed = ms.simulate(ms.build_model(sc), progress=False, checkpoint=Checkpoint(path=path, resume=True))
    assert resumed.complete and same_arrays(full, resumed) == []
    assert resumed.meta["ledger"] == full.meta["ledger"]
    for k in ("events", "impacts", "steps"):
        assert resumed.meta["run"][k] == full.meta["run"][k]
    # the loop's CPU time before the checkpoint is carried into the resumed run's (bookkeeping, not a speed)
    assert resumed.meta["run"]["cpu_seconds"] >= before["cpu_seconds"] > 0.0
    assert resumed.meta["zeno"] == full.meta["zeno"] and resumed.meta.get("fallbacks") == full.meta.get("fallbacks")


def cli(*args, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "moreau_sim", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def kill_when(p: subprocess.Popen, ready, timeout: float = 120.0) -> None:
    """SIGKILL p as soon as ready() (polled every 5 ms); fails if p ended first."""
    t_end = time.monotonic() + timeout
    while not ready():
        assert p.poll() is None, f"ended before it could be killed: {p.communicate()[1][-500:]}"
        assert time.monotonic() < t_end
        time.sleep(0.005)
    p.send_signal(signal.SIGKILL)
    p.communicate(timeout=60)
    assert p.returncode == -signal.SIGKILL


# (the runs last a few seconds: killed after the first checkpoint, before the end)
KILLED = [("time-stepping", "box_stack_5", "30", "3"), ("adaptive", "box_stack_5", "50", "2"),
          ("event-driven", "rocking_block", "2.5", "0.1")]


@pytest.mark.parametrize("integrator,name,duration,every",
                         [pytest.param(*k, id=k[0], marks=[pytest.mark.slow] if k[0] == "adaptive" else [])
                          for k in KILLED])
def test_a_killed_run_resumes_bit_identical(tmp_path, integrator, name, duration, every):
    """kill -9 of `moreau-sim run --set integrator=I --checkpoint-every` once its first checkpoint
    exists; `--resume` finishes it; every array equals the uninterrupted run's bit for bit; no
    temporary is left."""
    args = [SCENES / f"{name}.toml", "--duration", duration, "--set", f"integrator={integrator}", "--no-progress"]
    full = cli("run", *args, "-o", tmp_path / "full.npz")
    assert full.wait(timeout=300) == 0, full.communicate()[1]
    ck = tmp_path / "b.checkpoint.npz"
    kill_when(cli("run", *args, "-o", tmp_path / "b.npz", "--checkpoint-every", every), ck.exists)
    t = ms.load_trajectory(ck).meta["checkpoint"]["t"]
    assert 0 < t < float(duration) and not (tmp_path / "b.npz").exists()
    r = cli("run", *args, "-o", tmp_path / "b.npz", "--resume", "--checkpoint-every", every)
    _, err = r.communicate(timeout=300)
    assert r.returncode == 0, err
    a, b = ms.load_trajectory(tmp_path / "full.npz"), ms.load_trajectory(tmp_path / "b.npz")
    assert b.complete and same_arrays(a, b) == [] and b.meta["ledger"] == a.meta["ledger"]
    assert not ck.exists() and not list(tmp_path.glob("*.tmp"))


def table(path) -> list[dict]:
    with open(path, newline="") as fh:
        return [{k: v for k, v in r.items() if k not in WALL_COLUMNS} for r in csv.DictReader(fh)]


def test_a_killed_sweep_resumes_to_the_same_table(tmp_path):
    args = ["sweep", SCENES / "bouncing_ball.toml", "-p", "restitution=0:1:6", "-p", "duration=5", "-j", "1",
            "--no-progress"]
    full = cli(*args, "-o", tmp_path / "full")
    assert full.wait(timeout=300) == 0, full.communicate()[1]
    runs = tmp_path / "cut" / "runs"
    kill_when(cli(*args, "-o", tmp_path / "cut"), lambda: runs.is_dir() and len(list(runs.glob("*.npz"))) >= 2)
    done = len(list(runs.glob("*.npz")))
    assert 2 <= done < 6
    r = cli(*args, "-o", tmp_path / "cut", "--json")
    out, err = r.communicate(timeout=300)
    assert r.returncode == 0, err
    assert '"skipped": ' + str(done) in out
    assert table(tmp_path / "cut" / "sweep.csv") == table(tmp_path / "full" / "sweep.csv")
    assert not list((tmp_path / "cut").rglob("*.tmp"))
    for npz in sorted((tmp_path / "full" / "runs").glob("*.npz")):
        b = ms.load_trajectory(tmp_path / "cut" / "runs" / npz.name)
        assert same_arrays(ms.load_trajectory(npz), b) == []


@pytest.mark.parametrize("every", ["0", "-1", "nan"])
def test_checkpoint_every_must_be_positive(tmp_path, every):
    r = cli("run", SCENES / "bouncing_ball.toml", "-o", tmp_path / "b.npz", "--checkpoint-every", every)
    _, err = r.communicate(timeout=120)
    assert r.returncode == 2 and "--checkpoint-every" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("every", [0.0, -1.0, float("nan"), float("inf")])
def test_the_api_checks_the_interval(tmp_path, every):
    with pytest.raises(ms.SceneError, match="checkpoint_every: must be a finite time > 0 s"):
        ms.run(SCENES / "bouncing_ball.toml", duration=0.1, checkpoint=tmp_path / "c.npz", checkpoint_every=every)
