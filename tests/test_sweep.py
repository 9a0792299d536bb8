"""Parameter sweeps: --param parsing and validation, a real sweep in a process pool, resume,
failed points, the same sweep on a Dask cluster (identical table), the command."""

import csv
import dataclasses
import json
import os
import re
import sys

import numpy as np
import pytest
from click.testing import CliRunner

import moreau_sim as ms
from moreau_sim import invariants
from moreau_sim.cli.sweep import sweep
from moreau_sim.sweep import (
    FIELDS,
    RUNS,
    TABLE,
    WALL_COLUMNS,
    Kind,
    Param,
    SweepError,
    grid,
    parse_param,
    point_id,
    run_sweep,
)

from helpers import SCENES

BALL = SCENES / "bouncing_ball.toml"
# 2 x 2 grid; 0.5 s so that the ball (gap 0.9 m) hits the ground once
PARAMS = ("restitution=0.5,0.9", "dt=1e-2,1e-3", "duration=0.5")


def params(*texts):
    return [parse_param(t) for t in texts]


def read_csv(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def mtimes(out):
    return {p.name: p.stat().st_mtime_ns for p in (out / RUNS).glob("*.npz")}


@pytest.fixture(scope="module")
def local(tmp_path_factory):
    """The 2 x 2 sweep in the default local process pool (one worker per core)."""
    out = tmp_path_factory.mktemp("local")
    return run_sweep(BALL, params(*PARAMS), out, progress=False)


# --- parsing -----------------------------------------------------------------------------------

def test_range_is_inclusive_and_exact():
    p = parse_param("restitution=0:1:11")
    assert p == Param("restitution", tuple(i / 10 for i in range(11)), "restitution=0:1:11")
    assert p.values[3] == 0.3 and p.values[-1] == 1.0
    assert parse_param("dt=1e-3:1e-3:1").values == (1e-3,)


def test_lists_of_every_kind():
    assert parse_param("dt=1e-2,1e-3").values == (1e-2, 1e-3)
    assert parse_param("restitution=1").values == (1.0,) and isinstance(parse_param("restitution=1").values[0], float)
    assert parse_param("save_every=1,10").values == (1, 10)
    assert parse_param("qp_form=primal,dual").values == ("primal", "dual")
    assert parse_param("gravity=[0,0,-9.81], [0, 0, -1.62]").values == ((0.0, 0.0, -9.81), (0.0, 0.0, -1.62))


def test_every_option_is_sweepable():
    assert set(FIELDS) == {f.name for f in dataclasses.fields(ms.Options)}
    assert FIELDS["restitution"][0] is Kind.FLOAT and FIELDS["save_every"][0] is Kind.INT
    assert FIELDS["gravity"][0] is Kind.VECTOR and FIELDS["qp_form"] == (Kind.CHOICE, ms.QPForm)


@pytest.mark.parametrize("text, msg", [
    ("restitution", "expected NAME=A:B:N"),
    ("=1", "expected NAME=A:B:N"),
    ("bounciness=0:1:3", "unknown option 'bounciness'; options: restitution, dt"),
    ("restitution=0:1.5:4", "restitution: must lie in [0, 1], got 1.5"),
    ("restitution=-0.1,0.5", "restitution: must lie in [0, 1], got -0.1"),
    ("dt=1e-3,0", "dt: must be a finite step > 0 s, got 0.0"),
    ("duration=-1", "duration: must be > 0 s"),
    ("contact_tolerance=1", "contact_tolerance: must lie in [0, 1e-3) m"),
    ("restitution=0:1", "a range is A:B:N"),
    ("restitution=0:1:0", "N = 0 must be >= 1"),
    ("restitution=0:1:x", "N = 'x' must be an integer"),
    ("restitution=0:1:1", "N = 1 points cannot span 0 to 1"),
    ("restitution=a,b", "'a' is not a number"),
    ("restitution=nan", "'nan' is not finite"),
    ("restitution=0.5,0.5", "repeated values"),
    ("save_every=1.5", "'1.5' is not an integer"),
    ("save_every=0", "save_every: must be an integer >= 1"),
    ("save_every=1:10:10", "a range A:B:N is only for real-valued options, not save_every"),
    ("qp_form=banana", "'banana' is not one of ['primal', 'dual']"),
    ("gravity=[0,0]", "'[0,0]' is not a vector [x,y,z]"),
])
def test_bad_params_name_the_param(text, msg):
    with pytest.raises(ms.SceneError) as exc:
        parse_param(text)
    assert str(exc.value).startswith(f"--param {text}: ") and msg in str(exc.value)


def test_grid_is_the_cartesian_product_first_slowest():
    g = grid(params("restitution=0,1", "dt=1e-2,1e-3,1e-4"))
    assert g == tuple({"restitution": e, "dt": h} for e in (0.0, 1.0) for h in (1e-2, 1e-3, 1e-4))
    assert grid([]) == ({},)
    with pytest.raises(ms.SceneError, match="--param dt given more than once"):
        grid(params("dt=1e-2", "dt=1e-3"))


def test_a_point_invalid_with_the_scene_is_named(tmp_path):
    with pytest.raises(ms.SceneError, match=r"--param point dt=1e-09 duration=10.0: dt: duration/dt"):
        run_sweep(BALL, params("dt=1e-9", "duration=10"), tmp_path, progress=False)
    assert not (tmp_path / "sweep.csv").exists()


def test_point_id_depends_on_options_and_scene_only():
    sc = ms.load_scene(BALL)
    assert point_id(sc.with_options(dt=1e-3)) == point_id(sc) == point_id(ms.load_scene(BALL))
    assert point_id(sc.with_options(dt=1e-2)) != point_id(sc)
    assert re.fullmatch(r"[0-9a-f]{16}", point_id(sc))


# --- running -----------------------------------------------------------------------------------

def test_local_sweep_writes_the_table_and_the_runs(local):
    out = local.out_dir
    assert (local.computed, local.skipped, local.failed) == (4, 0, 0)
    assert [(r["restitution"], r["dt"]) for r in local.rows] == [(0.5, 1e-2), (0.5, 1e-3), (0.9, 1e-2), (0.9, 1e-3)]
    rows = read_csv(local.table)
    assert list(rows[0])[:6] == ["id", "restitution", "dt", "duration", "status", "message"]
    assert [r["id"] for r in rows] == [r["id"] for r in local.rows]
    for r, csv_row in zip(local.rows, rows):
        assert r["status"] == "complete" and r["message"] is None and r["impacts"] == 1
        assert r["steps"] == round(0.5 / r["dt"]) and r["energy_start"] == pytest.approx(9.81)
        # floats are written with repr: the CSV holds exactly the numbers
        assert float(csv_row["energy_lost"]) == r["energy_lost"] == r["energy_start"] - r["energy_end"]
        traj = ms.load_trajectory(out / r["npz"])
        assert traj.complete and traj.meta["options"]["restitution"] == r["restitution"]
        assert ms.summary(traj)["energy_end"] == r["energy_end"]
    # more restitution, less energy lost in the one impact
    lost = {(r["restitution"], r["dt"]): r["energy_lost"] for r in local.rows}
    assert lost[0.9, 1e-3] < lost[0.5, 1e-3]
    assert local.parquet is None or local.parquet.is_file()


def test_resume_computes_only_what_is_missing(tmp_path):
    # an "interrupted" sweep: only e = 0.5 was done
    first = run_sweep(BALL, params("restitution=0.5", *PARAMS[1:]), tmp_path, workers=1, progress=False)
    assert (first.computed, first.skipped) == (2, 0)
    before = mtimes(tmp_path)
    full = run_sweep(BALL, params(*PARAMS), tmp_path, workers=1, progress=False)
    assert (full.computed, full.skipped, full.failed) == (2, 2, 0)
    after = mtimes(tmp_path)
    assert len(after) == 4 and all(after[k] == v for k, v in before.items())
    assert [r["id"] for r in full.rows] == [r["id"] for r in read_csv(full.table)]

    # a run whose NPZ and row are lost is recomputed, and only it
    lost = full.rows[1]
    (tmp_path / lost["npz"]).unlink()
    rows = read_csv(full.table)
    with open(full.table, "w", newline="") as fh:
        w = csv.DictWriter(fh, list(rows[0]))
        w.writeheader()
        w.writerows(r for r in rows if r["id"] != lost["id"])
    before = mtimes(tmp_path)
    again = run_sweep(BALL, params(*PARAMS), tmp_path, workers=1, progress=False)
    assert (again.computed, again.skipped, again.failed) == (1, 3, 0)
    after = mtimes(tmp_path)
    assert all(after[k] == v for k, v in before.items()) and f"{lost['id']}.npz" in after
    assert [r["id"] for r in read_csv(again.table)] == [r["id"] for r in full.rows]
    no_wall = [{k: v for k, v in r.items() if k not in WALL_COLUMNS} for r in again.rows]
    assert no_wall == [{k: v for k, v in r.items() if k not in WALL_COLUMNS} for r in full.rows]

    # a run whose NPZ was written but whose row was not (killed in between): the row is rebuilt
    # from the NPZ, nothing is recomputed, nothing changes
    table = tmp_path / "sweep.csv"
    rows = read_csv(table)
    with open(table, "w", newline="") as fh:
        w = csv.DictWriter(fh, list(rows[0]))
        w.writeheader()
        w.writerows(rows[1:])
    before = mtimes(tmp_path)
    rebuilt = run_sweep(BALL, params(*PARAMS), tmp_path, workers=1, progress=False)
    assert (rebuilt.computed, rebuilt.skipped) == (0, 4) and mtimes(tmp_path) == before
    assert rebuilt.rows == again.rows and read_csv(table) == rows


def test_rows_of_other_sweeps_are_kept(tmp_path):
    a = run_sweep(BALL, params("restitution=0.8", "duration=0.1"), tmp_path, workers=1, progress=False)
    b = run_sweep(BALL, params("dt=1e-2", "duration=0.1"), tmp_path, workers=1, progress=False)
    # the same simulation (e = 0.8 and dt = 1e-3, the scene's) is one id in both: not rerun
    c = run_sweep(BALL, params("dt=1e-3", "duration=0.1"), tmp_path, workers=1, progress=False)
    assert (c.computed, c.skipped) == (0, 1) and c.rows[0]["id"] == a.rows[0]["id"]
    rows = read_csv(c.table)
    assert [r["id"] for r in rows] == [a.rows[0]["id"], b.rows[0]["id"]]
    assert list(rows[0])[:4] == ["id", "dt", "duration", "restitution"]
    assert rows[0]["dt"] == "0.001" and rows[1]["restitution"] == ""


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_a_failed_point_is_recorded_not_fatal(tmp_path):
    # gravity 1.7e308 m/s^2 with h = 1 s: the potential energy overflows at step 1 (SimulationError)
    ps = params("gravity=[0,0,-9.81],[0,0,1.7e308]", "dt=1", "duration=3")
    res = run_sweep(BALL, ps, tmp_path, workers=1, progress=False)
    assert (res.computed, res.skipped, res.failed) == (1, 0, 1)
    ok, bad = res.rows
    assert ok["status"] == "complete" and ok["gravity"] == "[0.0, 0.0, -9.81]"
    assert bad["status"] == "failed" and "step 1" in bad["message"] and "non-finite" in bad["message"]
    assert bad["npz"] == f"{RUNS}/{bad['id']}.failed.npz" and bad["steps"] == 0  # none completed cleanly
    partial = ms.load_trajectory(tmp_path / bad["npz"])
    assert partial.meta["status"].startswith("failed: step 1")
    assert read_csv(res.table)[1]["message"] == bad["message"]
    again = run_sweep(BALL, ps, tmp_path, workers=1, progress=False)  # failed points are retried
    assert (again.computed, again.skipped, again.failed) == (0, 1, 1)


def test_a_flagged_point_is_recorded_and_not_recomputed(tmp_path, monkeypatch):
    """A point that ran to its end but broke an invariant (the fixed step's bound set below zero,
    so that every run breaks it at once) is flagged, with its violations; a resume keeps it."""
    monkeypatch.setattr(invariants, "FIXED_RTOL", -1.0)
    ps = params("dt=1e-3", "duration=0.05")
    res = run_sweep(BALL, ps, tmp_path, workers=1, progress=False)
    assert (res.computed, res.skipped, res.failed, res.flagged) == (1, 0, 0, 1)
    row = res.rows[0]
    assert row["status"] == "flagged" and "speed beyond the energy" in row["message"]
    assert row["npz"] == f"{RUNS}/{row['id']}.npz"
    assert ms.load_trajectory(tmp_path / row["npz"]).meta["status"] == "flagged"
    assert read_csv(res.table)[0]["status"] == "flagged"
    again = run_sweep(BALL, ps, tmp_path, workers=1, progress=False)
    assert (again.computed, again.skipped, again.failed) == (0, 1, 0) and again.rows[0]["status"] == "flagged"
    (tmp_path / TABLE).unlink()  # the row lost: rebuilt from the NPZ, still flagged
    rebuilt = run_sweep(BALL, ps, tmp_path, workers=1, progress=False)
    row = rebuilt.rows[0]
    assert rebuilt.skipped == 1 and row["status"] == "flagged" and "speed beyond the energy" in row["message"]


def test_dask_cluster_gives_the_same_table(local, tmp_path):
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        res = run_sweep(BALL, params(*PARAMS), tmp_path, dask_address=cluster.scheduler_address, progress=False)
    assert (res.computed, res.skipped, res.failed) == (4, 0, 0)
    strip = lambda rows: [{k: v for k, v in r.items() if k not in WALL_COLUMNS} for r in rows]  # noqa: E731
    # bitwise: the CSV text of every numeric summary column, and the rows' floats
    assert strip(read_csv(res.table)) == strip(read_csv(local.table))
    assert strip(res.rows) == strip(local.rows)
    for r in res.rows:
        a, b = ms.load_trajectory(tmp_path / r["npz"]), ms.load_trajectory(local.out_dir / r["npz"])
        assert all(np.array_equal(a.arrays[k], b.arrays[k]) for k in a.arrays)


def test_dask_not_installed_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    with pytest.raises(SweepError, match=re.escape("--dask needs the optional dependency dask[distributed]")):
        run_sweep(BALL, params("duration=0.1"), tmp_path, dask_address="tcp://127.0.0.1:1", progress=False)


# --- command -----------------------------------------------------------------------------------

def test_command(tmp_path):
    runner = CliRunner()
    args = ["-p", "restitution=0.5,1", "-p", "duration=0.1", "-j", "1", "--out", str(tmp_path)]
    r = runner.invoke(sweep, [str(BALL), *args, "--no-progress"])
    assert r.exit_code == 0, r.output
    assert f"2 points: 2 computed, 0 already done, 0 failed -> {tmp_path / 'sweep.csv'}" in r.output
    r = runner.invoke(sweep, [str(BALL), *args, "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output)
    assert (out["points"], out["computed"], out["skipped"]) == (2, 0, 2) and len(out["rows"]) == 2
    r = runner.invoke(sweep, [str(BALL), "-p", "restitution=0:2:3", "--out", str(tmp_path)])
    assert r.exit_code == 2
    assert "moreau-sim: error: --param restitution=0:2:3: restitution: must lie in [0, 1], got 2.0" in r.output
    r = runner.invoke(sweep, [str(tmp_path / "missing.toml"), "--out", str(tmp_path)])
    assert r.exit_code == 2 and "scene file not found" in r.output
    assert os.listdir(tmp_path / RUNS)


def test_one_sweep_at_a_time_per_directory(tmp_path):
    from moreau_sim.sweep import locked

    with locked(tmp_path):
        with pytest.raises(SweepError, match="another sweep is writing this directory"):
            run_sweep(BALL, params("duration=0.1"), tmp_path, workers=1, progress=False)
    assert run_sweep(BALL, params("duration=0.1"), tmp_path, workers=1, progress=False).computed == 1
