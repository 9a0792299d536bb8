"""The trajectory file (moreau_sim.trajectory, docs/output.md): a bit-exact round trip, atomic writes,
format-1 files read into format 2, format-3 files (a log row a step) into 4, unreadable files named in the error."""

import json
import os

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import trajectory
from moreau_sim.contacts import FeatureKind

from helpers import run


@pytest.fixture(scope="module")
def traj():
    """box_drop for 0.6 s: samples, a percussion log with new impacts, several feature kinds."""
    return run("box_drop", duration=0.6)


def test_save_load_round_trip_is_bit_exact(traj, tmp_path):
    back = ms.load_trajectory(traj.save(tmp_path / "sub" / "box.npz"))
    assert list(back.arrays) == list(trajectory.ARRAYS)
    for k in trajectory.ARRAYS:
        assert back.arrays[k].dtype == traj.arrays[k].dtype, k
        np.testing.assert_array_equal(back.arrays[k], traj.arrays[k], strict=True)
    assert {k: v for k, v in back.meta.items() if k != "checksum"} == json.loads(json.dumps(traj.meta))
    assert back.meta["checksum"] == trajectory.checksum(traj.arrays)  # written with the file
    assert back.meta["format"] == trajectory.FORMAT and back.complete


def test_save_is_atomic(traj, tmp_path):
    """A write that fails half-way leaves the previous file whole and no temporary file behind; a
    written file gets the usual mode (umask), not mkstemp's 0600."""
    path = traj.save(tmp_path / "t.npz")
    before = path.read_bytes()
    broken = ms.Trajectory(traj.arrays, {**traj.meta, "bad": object()})  # not JSON: fails while writing
    with pytest.raises(TypeError):
        broken.save(path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.npz"]
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


FORMAT1_IDS = {FeatureKind.WITNESS: lambda f: -1, FeatureKind.VERTEX: lambda f: f,
               FeatureKind.PATCH: lambda f: 10_000 + f, FeatureKind.CORNER: lambda f: 20_000 + f,
               FeatureKind.SWEPT: lambda f: 30_000}


def test_format_1_files_load_with_kind_and_feature(traj, tmp_path):
    """A format-1 file (one log_feature id: WITNESS = -1, VERTEX k, PATCH 10000 + k, CORNER 20000 + f,
    SWEPT 30000; no log_kind) reads as log_kind + log_feature."""
    kinds = [FeatureKind.VERTEX, FeatureKind.WITNESS, FeatureKind.PATCH, FeatureKind.CORNER, FeatureKind.SWEPT]
    feats = [7, 0, 3, 1, 0]
    arrays = {k: v for k, v in traj.arrays.items() if k not in trajectory.LOG}
    n = len(kinds)
    for k, (dtype, shape) in trajectory.LOG.items():
        arrays[k] = np.zeros((n,) + shape, dtype)
    del arrays["log_kind"]
    arrays["log_feature"] = np.array([FORMAT1_IDS[k](f) for k, f in zip(kinds, feats)], np.int64)
    arrays["log_P"] = np.arange(1.0, n + 1)
    meta = {**traj.meta, "format": "moreau-sim trajectory 1"}
    path = tmp_path / "old.npz"
    np.savez_compressed(path, meta=np.array(json.dumps(meta)), **arrays)
    back = ms.load_trajectory(path)
    np.testing.assert_array_equal(back.log_kind, [int(k) for k in kinds])
    np.testing.assert_array_equal(back.log_feature, feats)
    np.testing.assert_array_equal(back.log_P, arrays["log_P"])
    assert set(back.arrays) == set(trajectory.ARRAYS)


def test_format_3_files_load_a_row_a_step(traj, tmp_path):
    """A format-3 file (no log_steps, log_duration: every row was one step's, of a length not recorded) reads
    with log_steps 1 and log_duration NaN; the rest as written."""
    arrays = {k: v for k, v in traj.arrays.items() if k not in ("log_steps", "log_duration")}
    path = tmp_path / "format3.npz"
    np.savez_compressed(path, meta=np.array(json.dumps({**traj.meta, "format": "moreau-sim trajectory 3"})),
                        **arrays)
    back = ms.load_trajectory(path)
    k = len(traj.log_P)
    assert k > 0 and back.log_steps.tolist() == [1] * k and np.isnan(back.log_duration).all()
    assert back.log_steps.dtype == np.int64 and set(back.arrays) == set(trajectory.ARRAYS)
    for name in arrays:
        np.testing.assert_array_equal(back.arrays[name], traj.arrays[name], strict=True)


def test_unreadable_files_are_named(traj, tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="junk.npz: not a moreau-sim trajectory"):
        ms.load_trajectory(junk)
    partial = tmp_path / "partial.npz"
    np.savez(partial, t=traj.t, meta=np.array("{}"))
    with pytest.raises(ValueError, match=r"partial.npz: not a moreau-sim trajectory \(missing \['q'"):
        ms.load_trajectory(partial)
    with pytest.raises(ValueError, match="nowhere.npz"):
        ms.load_trajectory(tmp_path / "nowhere.npz")


def test_a_signal_while_a_file_is_written_waits_until_it_is_in_place(tmp_path):
    """SIGTERM arriving inside a write (here: sent by the writer itself, between two members of a ZIP archive) is
    held until the file is complete and renamed into place, then raises KeyboardInterrupt as the command line's
    handler does (interrupts.raising): the archive whole, no zipfile error in its place, no temporary file left."""
    import signal
    import zipfile

    from moreau_sim import interrupts
    from moreau_sim.trajectory import atomic_write

    def write(tmp):
        with zipfile.ZipFile(tmp, "w") as z:
            z.writestr("a", b"1" * 1000)
            os.kill(os.getpid(), signal.SIGTERM)
            z.writestr("b", b"2" * 1000)

    previous = interrupts.raising()
    try:
        with pytest.raises(KeyboardInterrupt):
            atomic_write(tmp_path / "f.zip", write)
        assert interrupts.exit_status() == 143
    finally:
        interrupts.restore(previous)
    with zipfile.ZipFile(tmp_path / "f.zip") as z:
        assert z.read("b") == b"2" * 1000
    assert [p.name for p in tmp_path.iterdir()] == ["f.zip"]
