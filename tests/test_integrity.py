"""Damaged files are found, never passed as complete: trajectory checksums, sweep resume, and
sweep workers that do not outlive a killed sweep."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim.sweep import parse_param, run_sweep

from helpers import SCENES, run

BALL = SCENES / "bouncing_ball.toml"


def rewrite(path: Path, **changes):
    """Rewrite an NPZ with some arrays changed and its meta (and recorded checksum) untouched."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays.update(changes)
    np.savez_compressed(path, **arrays)


def test_a_damaged_array_is_detected(tmp_path):
    p = run("bouncing_ball", duration=0.2).save(tmp_path / "b.npz")
    q = ms.load_trajectory(p).q.copy()
    q[50, 0] += 1e-9
    rewrite(p, q=q)
    with pytest.raises(ValueError, match="damaged"):
        ms.load_trajectory(p)
    assert ms.load_trajectory(p, verify=False).q[50, 0] == q[50, 0]  # still readable on request


def test_a_corrupted_file_is_a_named_error_not_a_zlib_traceback(tmp_path):
    p = run("bouncing_ball", duration=0.5).save(tmp_path / "b.npz")
    data = bytearray(p.read_bytes())
    for i in range(len(data) // 3, len(data) // 3 + 64):
        data[i] ^= 0xFF
    p.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=str(p.name)):
        ms.load_trajectory(p)
    r = subprocess.run([sys.executable, "-m", "moreau_sim", "plot", str(p), "-o", str(tmp_path / "b.png")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "b.npz" in r.stderr and "Traceback" not in r.stderr


def test_a_sweep_recomputes_a_damaged_point(tmp_path):
    ps = [parse_param("restitution=0.5,0.9"), parse_param("duration=0.3")]
    first = run_sweep(BALL, ps, tmp_path, workers=1, progress=False)
    assert (first.computed, first.skipped) == (2, 0)
    victim = tmp_path / first.rows[1]["npz"]
    u = ms.load_trajectory(victim).u.copy()
    u[10] = 0.0
    rewrite(victim, u=u)
    again = run_sweep(BALL, ps, tmp_path, workers=1, progress=False)
    assert (again.computed, again.skipped, again.failed) == (1, 1, 0)
    assert ms.load_trajectory(victim).complete  # verified and rewritten


def _tagged(tag: str) -> list[int]:
    """PIDs of live processes whose environment carries tag."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if tag.encode() in (d / "environ").read_bytes() and "(Z)" not in (d / "stat").read_text():
                    out.append(int(d.name))
            except OSError:
                pass
    return out


def test_workers_exit_when_the_sweep_is_killed(tmp_path):
    tag = f"MOREAU_SIM_TEST_{uuid.uuid4().hex}"
    code = textwrap.dedent(f"""
        from moreau_sim.sweep import parse_param, run_sweep
        if __name__ == "__main__":
            run_sweep({str(BALL)!r}, [parse_param("restitution=0.1,0.2,0.3,0.4"), parse_param("duration=200")],
                      {str(tmp_path / "s")!r}, workers=2, progress=False)
    """)
    (tmp_path / "sweep.py").write_text(code)
    p = subprocess.Popen([sys.executable, str(tmp_path / "sweep.py")], env={**os.environ, tag: "1"})
    deadline = time.time() + 60
    while time.time() < deadline and len(_tagged(tag)) < 3:  # the sweep and its workers
        time.sleep(0.2)
    assert len(_tagged(tag)) >= 3
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    deadline = time.time() + 10
    while time.time() < deadline and _tagged(tag):
        time.sleep(0.2)
    assert _tagged(tag) == [], json.dumps(_tagged(tag))


def test_package_uris_stay_under_their_roots(tmp_path):
    """package:// searches the declared roots and at most two folders above the naming file; '..'
    cannot climb out of a package."""
    from moreau_sim import robots

    deep = tmp_path / "a" / "b" / "c" / "d"
    deep.mkdir(parents=True)
    dirs = robots.search_dirs([], deep)
    assert dirs[-3:] == [deep, deep.parent, deep.parent.parent] and tmp_path not in dirs and Path("/") not in dirs
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "secret.urdf").write_text("<robot/>")
    assert robots.resolve("package://pkg/secret.urdf", dirs, deep) is None  # four levels up: not searched
    assert robots.resolve("package://pkg/secret.urdf", [tmp_path], deep) == tmp_path / "pkg" / "secret.urdf"
    with pytest.raises(ms.SceneError, match="climb"):
        robots.resolve("package://pkg/../../etc/passwd", [tmp_path], deep)
