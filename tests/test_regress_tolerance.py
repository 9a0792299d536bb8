"""`moreau-sim regress` at its default tolerance (rtol 1e-6, atol 1e-9 J; docs/regression.md): a drift
just above it is reported, one just below passes. The drift is made exactly: gravity scaled by
(1 + delta) scales every energy of the elastic ball (e = 1: E = m g z, nothing dissipated) by
(1 + delta) and leaves its impact steps where they were."""

import subprocess
import sys
from pathlib import Path

import pytest

from moreau_sim.regress import check_scene

BALL = Path(__file__).resolve().parents[1] / "scenes" / "bouncing_ball.toml"
G = 9.81


def gravity(delta: float) -> tuple[float, float, float]:
    return (0.0, 0.0, -G * (1.0 + delta))


@pytest.fixture(scope="module")
def baseline(tmp_path_factory):
    folder = tmp_path_factory.mktemp("baselines")
    r = check_scene(BALL, folder, update=True, overrides={"restitution": 1.0, "duration": 1.0})
    assert r.status == "recorded"
    return folder


@pytest.mark.parametrize("delta,status", [(2e-6, "drift"), (0.5e-6, "ok"), (-2e-6, "drift"), (-0.5e-6, "ok")])
def test_a_drift_just_above_the_default_tolerance_is_reported(baseline, delta, status):
    r = check_scene(BALL, baseline, overrides={"gravity": gravity(delta)})
    assert r.status == status, r.report()
    if status == "drift":  # the energies drifted by delta relative, nothing else
        assert {d.quantity for d in r.drifts} >= {"energy_start", "energy_end"}
        assert not {d.quantity for d in r.drifts} & {"impacts", "impact_t"}


@pytest.mark.parametrize("delta,code", [(2e-6, 1), (0.5e-6, 0)])
def test_the_command_exits_1_on_a_drift_just_above_and_0_just_below(baseline, delta, code):
    g = gravity(delta)
    r = subprocess.run([sys.executable, "-m", "moreau_sim", "regress", str(BALL), "--baseline", str(baseline),
                        "--set", f"gravity=[{g[0]!r},{g[1]!r},{g[2]!r}]"], capture_output=True, text=True)
    assert r.returncode == code, r.stdout + r.stderr
    assert ("DRIFT" in r.stdout) == (code == 1)
