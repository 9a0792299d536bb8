"""The energy ledger (moreau_sim.ledger, docs/theory.md §5), its assertions (moreau_sim.testing), the
baselines of `moreau-sim regress` and the pytest fixture (docs/regression.md).

The per-scene check that every contact step dissipates what the law says, in every bundled scene,
is in test_scenes.py::test_every_bundled_scene_runs (the same runs)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from importlib.metadata import entry_points

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import trajectory
from moreau_sim.testing import (
    assert_budget_closes,
    assert_dissipation_follows_law,
    assert_matches_baseline,
    assert_no_energy_gain,
)
from moreau_sim.testing.references import cradle_simultaneous

from helpers import ROOT, SCENES, run


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_cradle_impact_dissipates_the_closed_form(e):
    """The touching cradle's one impact (f = 0, u- = (1, 0, 0, 0, 0), v = (0.2, ..., 0.2), unit masses):
    T- = 1/2, T+ = 1/2 |u+|^2 with u+ of docs/theory.md §4.2, dissipated = (1 - e^2)/2 |u- - v|^2."""
    L = ms.ledger(run("newton_cradle_5", restitution=e, duration=0.01))
    (imp,) = L.impacts
    u_plus = np.asarray(cradle_simultaneous(e))
    loss = 0.5 * (1 - e * e) * np.sum((np.eye(5)[0] - 0.2) ** 2)
    assert imp.contacts == 4 and imp.t == pytest.approx(5e-4)
    assert abs(imp.T_minus - 0.5) <= 1e-15 and abs(imp.T_plus - 0.5 * np.sum(u_plus ** 2)) <= 1e-15
    assert abs(imp.dissipated - loss) <= 1e-15 and abs(imp.predicted - loss) <= 1e-15
    assert abs(L.dissipation - loss) <= 1e-15  # the resting steps after it dissipate nothing (f = 0)


@pytest.mark.parametrize("h", [1e-3, 5e-4])
@pytest.mark.parametrize("e", [0.0, 0.5, 0.9])
@pytest.mark.parametrize("name", ["bouncing_ball", "newton_cradle_5_gapped", "rocking_block", "column_of_beads"])
def test_budget_closes_where_the_smooth_motion_is_exact(name, e, h):
    """Translations under constant gravity and the planar rocking block: E_end - E_0 = contact work +
    correction + smooth error to round-off, the smooth error itself is round-off, every impact follows
    the law (to the QP's accuracy: the column of beads' 10-contact steps are piqp's answers, 2e-11 of
    E_0 at worst) and no energy is gained."""
    traj = run(name, restitution=e, dt=h, duration=1.0)
    L = ms.ledger(traj)
    assert L.contact_steps > 0
    assert abs(L.smooth_error) <= 1e-12 * L.scale
    assert_budget_closes(traj, rtol=1e-12)
    assert_dissipation_follows_law(traj, rtol=1e-9)
    assert_no_energy_gain(traj, rtol=1e-12)


def _smooth_errors(name, hs, **options):
    return [ms.ledger(run(name, dt=h, **options)).smooth_error for h in hs]


def test_smooth_error_of_the_pendulum_is_second_order():
    """pendulum_wall (a double pendulum striking a wall; midpoint bias): the energy change of the
    contact-free part of the steps shrinks as h^2. Measured over 1 s: 1.5e-4, 3.6e-5, 9.1e-6 J."""
    hs = (2e-3, 1e-3, 5e-4)
    s = np.abs(_smooth_errors("pendulum_wall", hs, duration=1.0))
    assert s[0] > 1e-6
    for a, b in zip(s[:-1], s[1:]):
        assert 3.5 <= a / b <= 4.5  # order 2: h/2 -> /4


def test_smooth_error_of_the_spinning_box_is_zero_with_the_midpoint_bias_and_first_order_without():
    """spinning_box: the midpoint bias (docs/theory.md §2.4) keeps the free rotation's energy to
    round-off at every h; the explicit bias gains it at first order (7.8e-3, 3.9e-3, 1.9e-3 J over 2 s)."""
    hs = (2e-3, 1e-3, 5e-4)
    E0 = ms.ledger(run("spinning_box", duration=0.01)).scale
    for s in _smooth_errors("spinning_box", hs, duration=2.0):
        assert abs(s) <= 1e-13 * E0
    s = _smooth_errors("spinning_box", hs, duration=2.0, bias="explicit")
    assert s[0] > 1e-3
    for a, b in zip(s[:-1], s[1:]):
        assert 1.8 <= a / b <= 2.2  # order 1


def test_budget_residual_of_revolute_impacts_is_the_impact_steps_smooth_error():
    """What the budget leaves in pendulum_wall: the contact steps' own error of docs/theory.md §2.10, first
    order in h, is taken back by the energy cap, which ends the impact step at E_k + W_c + correction; what
    remains is minus that step's smooth error S_k (measured over 1 s: 2.5e-7, 3.8e-8, 3.5e-9 J at h = 2, 1,
    0.5 ms; before the cap 1.7e-2, 9.0e-3, 4.6e-3 J over 3 s), concentrated in the impact steps."""
    res = []
    for h in (2e-3, 1e-3, 5e-4):
        L = ms.ledger(run("pendulum_wall", dt=h, duration=1.0))
        res.append(abs(L.residual))
        assert res[-1] < 1e-2 * abs(L.smooth_error)
        assert np.count_nonzero(np.abs(L.residuals) > 1e-12 * L.scale) <= len(L.impacts)
    for a, b in zip(res[:-1], res[1:]):
        assert a / b >= 4.0


def test_event_driven_ledger():
    """The event-driven ball: every impact exactly the law, the budget closed to the ODE tolerance."""
    traj = run("bouncing_ball", integrator="event-driven", duration=2.0)
    L = ms.ledger(traj)
    assert len(L.impacts) >= 3
    assert_dissipation_follows_law(traj, rtol=1e-14)
    assert_budget_closes(traj, rtol=1e-12)


def test_totals_name_every_quantity():
    from moreau_sim.ledger import TOTALS

    assert tuple(ms.ledger(run("bouncing_ball", duration=0.5)).totals()) == TOTALS


def test_ledger_is_in_the_file_and_old_files_have_none(tmp_path):
    traj = run("box_drop", duration=0.5)
    back = ms.load_trajectory(traj.save(tmp_path / "b.npz"))
    assert back.meta["format"] == trajectory.FORMAT == "moreau-sim trajectory 5"
    assert ms.ledger(back).totals() == ms.ledger(traj).totals()
    flight = run("bouncing_ball", duration=0.1)  # no contact step: no time of a law difference, not NaN
    assert flight.meta["ledger"]["t_law_difference"] is None and np.isnan(ms.ledger(flight).t_law_difference)
    assert "NaN" not in json.dumps(flight.meta)
    arrays = {k: v for k, v in traj.arrays.items() if k not in trajectory.LEDGER_ARRAYS}
    meta = {k: v for k, v in traj.meta.items() if k != "ledger"}
    old = tmp_path / "old.npz"
    np.savez(old, meta=np.array(json.dumps({**meta, "format": "moreau-sim trajectory 2"})), **arrays)
    back = ms.load_trajectory(old)
    assert np.isnan(back.smooth_error).all() and len(back.impact_t) == 0
    with pytest.raises(ValueError, match="no energy ledger recorded"):
        ms.ledger(back)


def test_assertions_fail_with_a_table():
    """The explicit bias gains energy in a spinning box's free flight (docs/theory.md §2.4; a contact step
    cannot gain since the cap of §2.10): assert_no_energy_gain names the step and the samples."""
    traj = run("spinning_box", duration=1.0, bias="explicit")
    with pytest.raises(AssertionError) as exc:
        assert_no_energy_gain(traj)
    text = str(exc.value)
    assert "energy gained" in text and "one step" in text and "E(t) - E_0" in text
    assert len(text.splitlines()) <= 8


def test_changed_restitution_fails_the_baseline(tmp_path):
    base = run("solo_drop", duration=0.25)
    assert_matches_baseline(base, tmp_path / "new")  # no baseline yet: recorded in the new folder
    assert (tmp_path / "new" / "solo_drop.json").is_file()
    tmp_path = tmp_path / "new"
    assert_matches_baseline(run("solo_drop", duration=0.25), tmp_path)  # the same run: bitwise equal
    assert_matches_baseline(run("solo_drop", duration=0.25), tmp_path / "solo_drop.json")  # the file itself
    with pytest.raises(AssertionError) as exc:
        assert_matches_baseline(run("solo_drop", duration=0.25, restitution=0.6), tmp_path)
    text = str(exc.value)
    assert "solo_drop" in text and "dissipation" in text and "impact 1 dissipated" in text and "0.1815" in text
    # a looser tolerance on what moved lets it pass
    loose = {"default": (1.0, 10.0), "impacts": (1.0, 10.0)}
    assert_matches_baseline(run("solo_drop", duration=0.25, restitution=0.6), tmp_path, tolerances=loose)


def cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "moreau_sim", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=300)


def test_regress_command(tmp_path):
    ball, box = SCENES / "bouncing_ball.toml", SCENES / "box_drop.toml"
    base, xml = tmp_path / "base", tmp_path / "report.xml"
    r = cli("regress", ball, box, "--baseline", base, "--set", "duration=0.6", "--update")
    assert r.returncode == 0, r.stderr
    doc = json.loads((base / "box_drop.json").read_text())
    assert doc["overrides"] == {"duration": 0.6} and doc["options"]["duration"] == 0.6
    assert len(doc["scene_hash"]) == 64 and "pin" in doc["versions"] and doc["ledger"]["totals"]["impacts"] > 0
    r = cli("regress", ball, box, "--baseline", base, "--junit", xml)  # the recorded duration is reused
    assert r.returncode == 0 and "OK       box_drop" in r.stdout, r.stdout + r.stderr
    assert ET.parse(xml).getroot().get("failures") == "0"
    r = cli("regress", ball, box, "--baseline", base, "--set", "restitution=0.3", "-o", xml)
    assert r.returncode == 1 and "DRIFT    box_drop" in r.stdout and "restitution 0.5 -> 0.3" in r.stdout
    assert "energy_end" in r.stdout and "impact 1 dissipated" in r.stdout
    suite = ET.parse(xml).getroot().find("testsuite")
    assert suite.get("failures") == "2" and suite.find("testcase/failure").get("type") == "drift"
    r = cli("regress", box, "--baseline", base, "--set", "restitution=0.3", "--update")  # accept it, showing what
    assert r.returncode == 0 and "RECORDED box_drop" in r.stdout and "energy_end" in r.stdout
    assert cli("regress", box, "--baseline", base).returncode == 0  # the override is recorded too
    # bad input: exit 2 with one line naming the file or the flag; the other scenes still run
    (base / "bouncing_ball.json").write_text("{not json")
    r = cli("regress", ball, box, "--baseline", base)
    assert r.returncode == 2 and "bouncing_ball.json: not JSON" in r.stderr and "OK       box_drop" in r.stdout
    assert len(r.stderr.strip().splitlines()) == 1
    for args, words in ((("--tol", "x=1"), "--tol x=1"), (("--tol", "energy_edn=1e-3,0"), "unknown quantity"),
                        (("--set", "restitution=2"), "--set restitution=2")):
        r = cli("regress", box, "--baseline", base, *args)
        assert r.returncode == 2 and words in r.stderr, r.stderr
    r = cli("regress", SCENES / "zeno_ball.toml", "--baseline", base)
    assert r.returncode == 2 and "no baseline for scene zeno_ball" in r.stderr


USER_TEST = """
import moreau_sim as ms

def test_ball_energy(energy_ledger):
    traj = ms.run("{scene}", duration=1.0, restitution={e})
    energy_ledger.check(traj)
"""


def test_pytest_fixture_in_three_lines(tmp_path):
    """A user's test: the first run records its baseline and fails once, the next passes, a changed
    restitution fails with the drift table, --ledger-update accepts it."""
    test = tmp_path / "test_user.py"

    # an installed package registers the plugin by its entry point; a source tree needs -p
    installed = any(ep.name == "moreau_sim" for ep in entry_points(group="pytest11"))
    plugin = [] if installed else ["-p", "moreau_sim.pytest_plugin"]

    def pytest_run(e, *extra):
        test.write_text(USER_TEST.format(scene=SCENES / "bouncing_ball.toml", e=e))
        return subprocess.run([sys.executable, "-m", "pytest", *plugin, "-q", str(test), "-p", "no:cacheprovider",
                               *extra], capture_output=True, text=True, cwd=tmp_path,
                              env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=300)

    r = pytest_run(0.8)
    assert r.returncode == 1 and "recorded" in r.stdout, r.stdout
    assert (tmp_path / "ledger_baselines" / "test_user" / "test_ball_energy.json").exists()
    assert pytest_run(0.8).returncode == 0
    r = pytest_run(0.7)
    assert r.returncode == 1 and "moved from its baseline" in r.stdout and "impact 1 dissipated" in r.stdout
    assert pytest_run(0.7, "--ledger-update").returncode == 0
    assert pytest_run(0.7).returncode == 0
