"""Smoke test of `python -m benchmarks.work_precision`: a tiny sweep (--quick:
2 step sizes, short runs, one repeat) with whichever peers benchmarks.peers.available()
reports; checks the JSON schema and the PNGs, never timings."""

import json
import subprocess
import sys

from benchmarks.peers import available
from helpers import ROOT

POINT_KEYS = {"case", "scene", "e", "method", "h", "T", "cpu_repeats", "cpu_per_sim_s", "error", "rel_error"}


def test_quick_sweep_writes_json_table_and_pngs(tmp_path):
    cmd = [sys.executable, "-m", "benchmarks.work_precision", "--quick", "--out", str(tmp_path)]
    cp = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert cp.returncode == 0, cp.stdout[-2000:] + cp.stderr[-3000:]
    doc = json.loads((tmp_path / "work_precision.json").read_text())
    assert set(doc) == {"meta", "cases", "points", "summary", "solvers"}
    assert doc["meta"]["quick"] and doc["meta"]["steps"] == [1e-2, 1e-3]

    usable = [p for p, why in available().items() if why is None]
    for peer, why in available().items():  # a missing peer is announced, never skipped silently
        if why is not None:
            assert f"peer {peer} skipped" in cp.stdout
            assert any(s["peer"] == peer for s in doc["meta"]["peers_skipped"])
    cases = {c["key"]: c for c in doc["cases"]}
    assert {"newton_cradle_5", "rocking_block", "pendulum_wall", "box_drop"} <= set(cases)
    for p in doc["points"]:
        assert POINT_KEYS <= set(p) or p.get("failed")
        if not p.get("failed"):
            assert p["cpu_per_sim_s"] > 0 and p["rel_error"] >= 0 and len(p["cpu_repeats"]) == 1
    methods = {p["method"] for p in doc["points"]}
    assert "moreau-sim" in methods
    assert {m.split("-")[0] for m in methods} - {"moreau"} == set(usable)
    for key, c in cases.items():
        ours = [p for p in doc["points"] if p["case"] == key and p["method"] == "moreau-sim"]
        assert sorted(p["h"] for p in ours) == [1e-3, 1e-2]
        adaptive = [p for p in doc["points"] if p["case"] == key and p["method"] == "moreau-sim adaptive"]
        assert sorted(p["rtol"] for p in adaptive) == [1e-10, 1e-6]  # the adaptive curve: an rtol sweep
        if c["peer_scene"] is None:  # a scene the peers cannot express is reported as such
            assert all(p["method"] in ("moreau-sim", "moreau-sim adaptive") for p in doc["points"] if p["case"] == key)
            assert all("no peer can express" in r["note"] for r in doc["summary"] if r["case"] == key)
        png = tmp_path / f"wp_{key}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert {r["level"] for r in doc["summary"]} == {1e-3, 1e-6, 1e-10}
    assert all(r["ratio"] is None or r["ratio"] >= 0 for r in doc["summary"])
    assert {"piqp primal", "pinocchio ADMM", "pinocchio PGS"} <= {r["solver"] for r in doc["solvers"]}
    assert all(r["max_abs_v_diff"] < 1e-6 for r in doc["solvers"])
    assert (tmp_path / "work_precision_table.md").read_text().startswith("| case |")


def test_cases_and_steps_select_the_sweep(tmp_path):
    """--cases and --steps run only those (the fixed steps asked for; the adaptive runs and the reference keep
    dt = STEPS[0]), and the table says so."""
    cmd = [sys.executable, "-m", "benchmarks.work_precision", "--quick", "--out", str(tmp_path), "--peers", "",
           "--no-solvers", "--cases", "pendulum_wall", "--steps", "5e-3,2.5e-3"]
    cp = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert cp.returncode == 0, cp.stdout[-2000:] + cp.stderr[-3000:]
    doc = json.loads((tmp_path / "work_precision.json").read_text())
    assert [c["key"] for c in doc["cases"]] == ["pendulum_wall"]
    assert sorted(p["h"] for p in doc["points"] if p["method"] == "moreau-sim") == [2.5e-3, 5e-3]
    assert {p["case"] for p in doc["points"]} == {"pendulum_wall"}


def test_steps_that_miss_the_output_instants_or_unknown_cases_are_refused(tmp_path):
    """A step must divide OUTPUT_DT (to round-off, 1e-9 of the ratio): 2.5e-3 does (4 steps), 3e-3 does not; an
    unknown case is named. One line each, exit 2, nothing written."""
    for args, says in ((["--steps", "3e-3"], "--steps: 0.003 does not divide OUTPUT_DT = 0.01 s"),
                       (["--steps", "0"], "--steps: 0 does not divide"),
                       (["--cases", "no_such_case"], "--cases: unknown case 'no_such_case'")):
        cmd = [sys.executable, "-m", "benchmarks.work_precision", "--quick", "--out", str(tmp_path / "x"), *args]
        cp = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=ROOT)
        assert cp.returncode == 2 and says in cp.stderr and "Traceback" not in cp.stderr, cp.stderr
        assert not (tmp_path / "x").exists()
