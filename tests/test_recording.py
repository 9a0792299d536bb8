"""The Recorder (moreau_sim.recording): columns grow past their first capacity, the arrays follow
trajectory.ARRAYS (names, order, dtypes, shapes), percussions are logged above LOG_RELATIVE with new
impacts flagged; a spilling recording gives the same arrays bit for bit; memory follows the data
(in memory) or stays flat (spilling)."""

import errno
import json
import os
import subprocess
import sys

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import columns, trajectory
from moreau_sim.checkpoint import Checkpoint
from moreau_sim.recording import LOG_RELATIVE

from helpers import SCENES, scene


def test_columns_grow_and_keep_every_sample():
    model = ms.build_model(scene("bouncing_ball"))
    rec = ms.Recorder(model, ms.make_data(model), n_samples=1)
    for k in range(100):
        rec.sample(ms.State(0.01 * k, np.array([1.0 + k]), np.array([-k / 10])), work=-k, corr=k / 2, n_contacts=k % 3)
    a = rec.arrays()
    assert rec.n == 100 and len(a["t"]) == 100
    np.testing.assert_array_equal(a["q"][:, 0], 1.0 + np.arange(100))
    np.testing.assert_array_equal(a["contact_work"], -np.arange(100.0))
    np.testing.assert_array_equal(a["n_contacts"], np.arange(100) % 3)
    np.testing.assert_allclose(a["potential_energy"], 9.81 * (1.0 + np.arange(100)), rtol=1e-15)
    np.testing.assert_array_equal(a["gap"][:, 0], 0.9 + np.arange(100))


def test_arrays_follow_the_schema():
    model = ms.build_model(scene("box_drop"))
    rec = ms.Recorder(model, ms.make_data(model))
    rec.sample(ms.initial_state(model), 0.0, 0.0, 0)
    a = rec.arrays()
    assert tuple(a) == trajectory.ARRAYS
    sizes = {"nq": model.nq, "nv": model.nv, "gaps": len(model.pairs)}  # a listed model: a gap per pair
    schema = {**trajectory.SAMPLES, **trajectory.LOG, **trajectory.BRANCHES, **trajectory.CANDIDATES,
              **trajectory.IMPACTS}
    for name, (dtype, shape) in schema.items():
        assert a[name].dtype == np.dtype(dtype), name
        assert a[name].shape[1:] == tuple(sizes.get(d, d) for d in shape), name
    assert len(a["t"]) == 1 and len(a["log_P"]) == 0 and len(a["branch_step"]) == 0


def test_percussions_are_logged_above_the_threshold_with_new_impacts_flagged():
    """The cradle's first step: 4 contacts; a percussion below LOG_RELATIVE of the step's largest is
    not logged; a contact already pushing in the previous step is not a new impact."""
    model = ms.build_model(scene("newton_cradle_5"))
    data = ms.make_data(model)
    r = ms.step(model, data, ms.initial_state(model))
    rec = ms.Recorder(model, data)
    P = r.P.copy()
    P[1] = 0.5 * LOG_RELATIVE * P.max()
    first = (int(r.contacts.pair[0]), int(r.contacts.kind[0]), int(r.contacts.feature[0]))
    keys = rec.log_percussions(1, 5e-4, r.contacts, P, r.gamma_minus, r.gamma_plus, previous={first}, h=1e-3)
    assert not len(rec.arrays()["log_P"])  # the step's rows wait for its ledger: a persistent step may fold them
    rec.account_step(1, 5e-4, ms.initial_state(model), r, 1e-3, model.options.restitution)
    a = rec.arrays()
    assert keys == r.contacts.keys() and len(keys) == 4
    np.testing.assert_array_equal(a["log_pair"], r.contacts.pair[[0, 2, 3]])
    np.testing.assert_array_equal(a["log_impact"], [False, True, True])
    np.testing.assert_array_equal(a["log_P"], P[[0, 2, 3]])
    assert np.all(a["log_step"] == 1) and np.all(a["log_t"] == 5e-4)
    assert np.all(a["log_steps"] == 1) and np.all(a["log_duration"] == 1e-3)


def same_arrays(a: ms.Trajectory, b: ms.Trajectory) -> list[str]:
    """The names of the arrays that differ in dtype, shape or any bit."""
    def same(x, y):
        return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
    return [k for k in trajectory.ARRAYS if not same(a.arrays[k], b.arrays[k])]


# zeno_ball: its rest is a log row that every step changes (kept in memory across spills and the checkpoint);
# box_stack_5: stretches of up to 14 rows, more than a block; corner_point: branches and candidates
@pytest.mark.parametrize("name,steps", [("zeno_ball", 4000), ("box_stack_5", 60), ("corner_point", 60),
                                        ("newton_cradle_5", 200)])
@pytest.mark.parametrize("e,h_factor", [(None, 1.0), (0.0, 0.5), (1.0, 2.0)])
def test_a_spilling_recording_is_bitwise_the_in_memory_one(monkeypatch, tmp_path, name, steps, e, h_factor):
    """Rows moved to the spill files in blocks of 300 bytes (1 to 12 rows; the ball: samples and
    percussion rows, its rest's row changed by every step after it was first spilled; the corner: branches and
    candidates too): the same arrays (dtypes, shapes, bits) and
    checksum, read-only; a checkpoint written mid-run and a run resumed from it into spill files
    give them too; the saved file reads back the same; the spill files never have a name."""
    monkeypatch.setattr(columns, "SPILL_BYTES", 300)
    base = scene(name)
    h = base.options.dt * h_factor
    sc = base.with_options(dt=h, duration=steps * h, restitution=e, save_every=2)
    folder = tmp_path / "spill"
    folder.mkdir()
    plain = ms.simulate(ms.build_model(sc), progress=False)
    path = tmp_path / "c.npz"
    spilled = ms.simulate(ms.build_model(sc), progress=False, spill=folder,
                          checkpoint=Checkpoint(path=path, every=(steps // 3 + 1) * h, keep=True))
    assert 0 < ms.load_trajectory(path).meta["checkpoint"]["steps"] < steps
    resumed = ms.simulate(ms.build_model(sc), progress=False, spill=folder,
                          checkpoint=Checkpoint(path=path, resume=True))
    assert len(plain.t) > 3
    if name == "zeno_ball" and e != 1.0:  # a stretch of persistent steps across the spills (e = 1: no rest)
        assert plain.log_steps.max() > 1000  # (e = 0: all but the first steps; the checkpoint is inside it)
    if name == "box_stack_5":  # stretches of more rows than a block holds
        block = columns.SPILL_BYTES // sum(np.dtype(d).itemsize * (3 if s else 1)
                                             for d, s in trajectory.LOG.values())
        assert max(np.count_nonzero(plain.log_step == k) for k in np.unique(plain.log_step[plain.log_steps > 1])) \
            > block
    for traj in (spilled, resumed):
        assert same_arrays(plain, traj) == []
        assert trajectory.checksum(traj.arrays) == trajectory.checksum(plain.arrays)
        assert not any(a.flags.writeable for a in traj.arrays.values())
    assert resumed.meta["ledger"] == plain.meta["ledger"]
    assert same_arrays(plain, ms.load_trajectory(spilled.save(tmp_path / "s.npz"))) == []
    assert os.listdir(folder) == []


MEMORY_PROBE = """
import json, resource, sys
import moreau_sim as ms
from moreau_sim import columns
spill = sys.argv[3] if len(sys.argv) > 3 else None
columns.SPILL_BYTES = 1 << 19  # blocks of 5461 samples and 4332 percussion rows
sc = ms.load_scene(sys.argv[1]).with_options(step_impl="compiled")
ms.simulate(ms.build_model(sc.with_options(duration=1.0)), progress=False, spill=spill).save(sys.argv[2])  # warm
model = ms.build_model(sc.with_options(duration=100.0))
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
traj = ms.simulate(model, progress=False, spill=spill)
traj.save(sys.argv[2])
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"growth": (peak - base) * 1024, "data": sum(a.nbytes for a in traj.arrays.values()),
                  "rows": len(traj.log_P), "samples": len(traj.t)}))
"""


@pytest.mark.parametrize("spill", [False, True])
def test_memory_is_proportional_to_the_data(tmp_path, spill):
    """A resting ball over 10^5 steps, recorded and saved: in memory, the peak RSS grows by the recorded
    arrays and little more (the recorder copies nothing while recording, the save streams); spilling, by a
    small part of them (one block of rows in memory; the save hands back the pages of the maps it has read).
    Its rest is one row of the percussion log (a stretch of persistent steps, docs/theory.md §5.2), not a row a
    step. A byte bound on ru_maxrss, not a timing; run in a fresh process so that nothing else moves the peak."""
    args = [str(SCENES / "zeno_ball.toml"), str(tmp_path / "ball.npz")] + ([str(tmp_path)] if spill else [])
    r = subprocess.run([sys.executable, "-c", MEMORY_PROBE, *args], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads(r.stdout)
    assert m["rows"] < 1000 and m["samples"] == 100_001
    if spill:
        assert m["growth"] <= 0.25 * m["data"], m  # data: 9.6 MB
    else:
        assert m["growth"] <= 1.5 * m["data"] + 8e6, m  # data: 9.6 MB; allocator slack and one joined column


def test_a_full_disk_under_the_spill_files_is_a_named_error(monkeypatch, tmp_path):
    """`moreau-sim run` keeps its rows in unnamed files beside the output: when that folder fills
    up during the run, one line naming the folder and the output, exit 2, no traceback."""
    from click.testing import CliRunner

    from moreau_sim.cli import main

    monkeypatch.setattr(columns, "SPILL_BYTES", 10_000)
    write = columns.write_at
    calls = []

    def full(f, a, offset):
        calls.append(offset)
        if len(calls) > 30:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        write(f, a, offset)

    monkeypatch.setattr(columns, "write_at", full)
    out = tmp_path / "ball.npz"
    r = CliRunner().invoke(main, ["run", str(SCENES / "zeno_ball.toml"), "-o", str(out), "--duration", "2"])
    assert r.exit_code == 2, r.output
    assert r.output.strip() == (f"moreau-sim: error: {tmp_path}: cannot write there (No space left on device); "
                                f"nothing written to {out}")
    assert os.listdir(tmp_path) == []


def test_a_format_3_checkpoint_resumes_with_a_row_a_step_before_it(tmp_path):
    """A checkpoint written before log_steps and log_duration (format 3: no such columns, no "rest" carried)
    resumes: its rows read as one step each, of an unrecorded length (NaN), and every row after it, the samples
    and the ledger are the uninterrupted run's. zeno_ball (e = 0.8) bounces until ~2.9 s: the last checkpoint,
    at ~2 s, is between bounces, no stretch open."""
    sc = scene("zeno_ball", duration=2.5)
    plain = ms.simulate(ms.build_model(sc), progress=False)
    path = tmp_path / "c.npz"
    ms.simulate(ms.build_model(sc), progress=False, checkpoint=Checkpoint(path=path, every=1.0, keep=True))
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files if k not in ("log_steps", "log_duration")}
    meta = json.loads(str(arrays.pop("meta")))
    meta["checkpoint"]["recorder"].pop("rest")
    meta.pop("checksum", None)
    np.savez(path, meta=np.array(json.dumps(meta)), **arrays)
    k = len(arrays["log_P"])
    resumed = ms.simulate(ms.build_model(sc), progress=False, checkpoint=Checkpoint(path=path, resume=True))
    assert 0 < k < len(plain.log_P)
    assert resumed.log_steps[:k].tolist() == [1] * k and np.isnan(resumed.log_duration[:k]).all()
    for name in trajectory.ARRAYS:
        a, b = resumed.arrays[name], plain.arrays[name]
        if name == "log_duration":
            a, b = a[k:], b[k:]
        assert a.tobytes() == b.tobytes(), name


def test_a_urdf_several_bodies_name_is_read_once_and_kept_once_in_the_meta():
    """The cradle's five balls share one URDF: each body's entry in meta["scene"]["urdf"] is that file's text, one
    string for all five (recording._model_meta reads a file once; the meta of each run keeps it once)."""
    from pathlib import Path

    model = ms.build_model(scene("newton_cradle_5", duration=0.01))
    texts = [ms.simulate(model, progress=False).meta["scene"]["urdf"] for _ in range(2)]
    for urdf in texts:
        assert len(urdf) == 5 and len({id(t) for t in urdf.values()}) == 1
        assert all(t == Path(b.urdf).read_text(encoding="utf-8") for t, b in zip(urdf.values(), model.scene.bodies))
    assert texts[0] is not texts[1]  # each trajectory's meta is its own
