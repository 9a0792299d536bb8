"""Nothing lost, nothing silently wrong: models that would crash a library are refused by name,
every solver fault stops the run with a SimulationError naming the step and time (the samples
so far attached), and nothing non-finite is ever reported complete."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import corners, qp, stepper

from helpers import MODELS, run

PLATE = """[scene]
name = "plate"
[simulation]
duration = 0.01
[[bodies]]
name = "plate"
urdf = "plate.urdf"
root_joint = "free"
position = [0, 0, 1]
{meshes}
[[statics]]
name = "ground"
shape = "halfspace"
"""

URDF = """<robot name="plate"><link name="plate">
<inertial><mass value="{mass}"/><inertia ixx="{ixx}" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial>
<collision><geometry>{geometry}</geometry></collision></link></robot>"""

SQUARE = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n"  # two triangles: flat
TETRA_NAN = "v 0 0 0\nv 1 0 0\nv 1 1 nan\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\nf 1 2 5\nf 2 3 5\n"


def load_in_subprocess(folder) -> subprocess.CompletedProcess:
    """Build the model in a child process: a regression to a library crash fails this test, not the suite."""
    code = textwrap.dedent(f"""
        import moreau_sim as ms
        try:
            ms.build_model(ms.load_scene({str(folder / "plate.toml")!r}))
            print("BUILT")
        except ms.SceneError as exc:
            print("SCENE_ERROR", exc)
    """)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def plate(tmp_path, *, mesh=None, geometry=None, mass="1", ixx="0.1", meshes=""):
    if mesh is not None:
        (tmp_path / "plate.obj").write_text(mesh)
        geometry = '<mesh filename="plate.obj"/>'
    (tmp_path / "plate.urdf").write_text(URDF.format(mass=mass, ixx=ixx, geometry=geometry))
    (tmp_path / "plate.toml").write_text(PLATE.format(meshes=meshes))
    return tmp_path


@pytest.mark.parametrize("mesh,words", [(SQUARE, ["is flat", 'meshes = "bvh"']), (TETRA_NAN, ["not finite"])])
def test_meshes_coal_cannot_hull_are_named_not_crashed(tmp_path, mesh, words):
    r = load_in_subprocess(plate(tmp_path, mesh=mesh))
    assert r.returncode == 0, f"crashed with {r.returncode}: {r.stderr[-500:]}"
    assert r.stdout.startswith("SCENE_ERROR") and "plate.obj" in r.stdout and all(w in r.stdout for w in words)
    assert len(r.stdout.strip().splitlines()) == 1 and "Jacobi" not in r.stderr  # one line, no library chatter


def test_a_flat_mesh_runs_as_a_bvh(tmp_path):
    r = load_in_subprocess(plate(tmp_path, mesh=SQUARE, meshes='meshes = "bvh"'))
    assert r.returncode == 0 and r.stdout.strip() == "BUILT", r.stdout + r.stderr[-500:]


@pytest.mark.parametrize("geometry,field", [('<sphere radius="-0.1"/>', "radius"), ('<box size="0.1 0 0.1"/>', "size"),
                                            ('<cylinder radius="0.1" length="nan"/>', "length")])
def test_shape_sizes_must_be_positive(tmp_path, geometry, field):
    with pytest.raises(ms.SceneError, match=f"{field}=.*must be"):
        ms.load_scene(plate(tmp_path, geometry=geometry) / "plate.toml") and ms.build_model(
            ms.load_scene(tmp_path / "plate.toml"))


@pytest.mark.parametrize("mass,ixx,words", [("0", "0.1", "singular"), ("-1", "0.1", "mass"), ("1", "nan", "ixx"),
                                            ("1", "0", "singular")])
def test_mass_and_inertia_are_checked_at_load(tmp_path, mass, ixx, words):
    sc = ms.load_scene(plate(tmp_path, geometry='<sphere radius="0.1"/>', mass=mass, ixx=ixx) / "plate.toml")
    with pytest.raises(ms.SceneError, match=words) as info:
        ms.build_model(sc)
    assert "plate" in str(info.value) and "\n" not in str(info.value)


def test_a_step_longer_than_the_duration_is_refused():
    with pytest.raises(ms.SceneError, match="dt.*longer than the duration"):
        ms.load_scene(MODELS.parent / "scenes" / "bouncing_ball.toml").with_options(dt=0.5, duration=0.1)


@pytest.mark.parametrize("options,words", [(dict(gravity=(0.0, 0.0, -1e300), dt=1e-2), "non-finite"),
                                           (dict(gravity=(0.0, 0.0, 1e300), dt=1e-2), "non-finite")])
def test_overflow_is_never_complete(options, words):
    with pytest.raises(ms.SimulationError, match=words) as info:
        run("bouncing_ball", duration=0.5, **options)
    traj = info.value.trajectory
    assert not traj.complete and traj.meta["status"].startswith("failed: step")
    assert info.value.step >= 1 and info.value.t is not None


def test_a_failed_correction_qp_stops_the_run(monkeypatch):
    """Fault injection at the package's own QP call of the position correction (the plastic ball
    at h = 1e-2 needs it at its first impact): the run stops, naming the step; nothing ignored."""
    real = qp.solve

    def failing(M, W, v0, *, b=None, **kw):
        if b is not None and not np.any(v0):  # the correction's problem: v0 = 0, b = -g
            return qp.QPResult("PIQP_MAX_ITER_REACHED", False, 250, False, v0, np.zeros(W.shape[1]))
        return real(M, W, v0, b=b, **kw)

    monkeypatch.setattr(stepper.qp, "solve", failing)
    with pytest.raises(ms.SimulationError, match=r"step \d+ .*position-correction QP failed") as info:
        run("bouncing_ball", restitution=0.0, dt=1e-2, duration=1.0, step_impl="python")  # the Python step's call
    assert info.value.trajectory is not None and not info.value.trajectory.complete


def test_a_corner_law_that_raises_is_a_named_stop(monkeypatch):
    def broken(*args, **kwargs):
        raise IndexError("list index out of range")

    monkeypatch.setattr(corners, "stationary_points", broken)  # corners.corner_law, every integrator's
    with pytest.raises(ms.SimulationError, match=r"step 1 \(t = 0 s\): IndexError") as info:
        run("corner_point")
    assert info.value.trajectory.meta["status"].startswith("failed: step 1")


def test_a_non_finite_qp_answer_is_not_a_solution():
    """qp.solve on a problem whose data overflow: never ok with a NaN or inf in v or lam."""
    M = np.eye(2)
    W = np.array([[1.0], [0.0]])
    res = qp.solve(M, W, np.array([-1e308 * 10, 0.0]))
    assert not res.ok or (np.isfinite(res.v).all() and np.isfinite(res.lam).all())


# --- the command line: output checked first, interrupts keep the work, temporaries do not outlive their writer

BALL = MODELS.parent / "scenes" / "bouncing_ball.toml"


def cli(*args, **kw):
    return subprocess.run([sys.executable, "-m", "moreau_sim", *map(str, args)], capture_output=True, text=True,
                          timeout=300, **kw)


def test_an_unwritable_output_fails_before_simulating(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    r = cli("run", BALL, "--duration", "100", "-o", blocker / "b.npz")  # 1e5 steps it must not start
    assert r.returncode == 2 and "--out" in r.stderr and "nothing was simulated" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_a_scene_output_stays_in_its_folder(tmp_path):
    text = BALL.read_text().replace('file = "bouncing_ball.npz"', 'file = "../escaped.npz"')
    text = text.replace('urdf = "../models/ball.urdf"', f'urdf = "{MODELS / "ball.urdf"}"')
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "ball.toml").write_text(text)
    r = cli("run", tmp_path / "s" / "ball.toml", "--duration", "0.1")
    assert r.returncode == 2 and "[output] file" in r.stderr and not (tmp_path / "escaped.npz").exists()
    (tmp_path / "s" / "ball.toml").write_text(text.replace("../escaped.npz", "runs/ball.npz"))
    r = cli("run", tmp_path / "s" / "ball.toml", "--duration", "0.1", cwd=tmp_path)
    assert r.returncode == 0 and (tmp_path / "s" / "runs" / "ball.npz").is_file()  # in the scene's folder


@pytest.mark.parametrize("sig,integrator", [(signal.SIGINT, "time-stepping"), (signal.SIGTERM, "time-stepping"),
                                            (signal.SIGINT, "adaptive"), (signal.SIGTERM, "event-driven")])
def test_an_interrupted_run_keeps_its_samples(tmp_path, sig, integrator):
    """Ctrl-C or SIGTERM in any integrator's loop (errors.named_stops): the samples so far, exit 130 or 143."""
    out = tmp_path / "b.npz"
    # long enough to be running when the signal comes: the compiled run takes 10^6 ball steps in ~1.5 s, the
    # adaptive one records 10^6 samples (in blocks, driver._Loop._block) in ~1.4 s
    duration = {"time-stepping": "20000", "adaptive": "10000"}.get(integrator, "1000")
    p = subprocess.Popen([sys.executable, "-m", "moreau_sim", "run", str(BALL), "--duration", duration, "-o", str(out),
                          "--set", f"integrator={integrator}"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         # the default disposition in the child: under nohup or a CI runner's background
                         # job SIGINT is ignored, and an ignored disposition is inherited across exec
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    time.sleep(4.0)  # past the model's build, well before the 2e7 steps (or 1e7, 1e6 samples) end
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 128 + sig, err  # 130 SIGINT, 143 SIGTERM (docs/cli.md)
    partial = ms.load_trajectory(tmp_path / "b.partial.npz")
    unit = "phase" if integrator == "event-driven" else "step"
    assert partial.meta["status"].startswith(f"failed: interrupted at {unit}") and len(partial.t) > 10
    assert partial.meta.get("integrator", "time-stepping") == integrator
    assert np.isfinite(partial.q).all() and not out.exists()
    assert not list(tmp_path.glob("*.tmp"))


def test_temporaries_of_a_killed_save_are_removed(tmp_path):
    dead = tmp_path / "b.npz.2147480000.x1y2.tmp"  # a writer PID that does not exist
    dead.write_bytes(b"half a file")
    run("bouncing_ball", duration=0.01).save(tmp_path / "b.npz")
    assert not dead.exists() and ms.load_trajectory(tmp_path / "b.npz").complete
