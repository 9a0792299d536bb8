"""A run checks its own invariants (moreau_sim/invariants.py, docs/theory.md §10): each check at its
edge, on hand-made states of the bouncing ball fed to the hook with a real Recorder and real steps;
strict runs, the CLI, regress and moreau_sim.testing counting a flagged run as a failure; and every
bundled scene holding its invariants under every integrator that takes it (the others refuse it by name)."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import invariants
from moreau_sim.data import make_data
from moreau_sim.energy import kinetic, potential
from moreau_sim.errors import SimulationError
from moreau_sim.invariants import Invariant, Invariants, InvariantViolation
from moreau_sim.protocol import FixedStep, Report, Status
from moreau_sim.recording import Recorder
from moreau_sim.state import State
from moreau_sim.stepper import step

from helpers import REFUSED, ROOT, SCENES, scene

_spec = importlib.util.spec_from_file_location("invariant_table", ROOT / "scripts" / "invariant_table.py")
table = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(table)

BELOW, ABOVE = 0.5, 1.5  # a violation at this fraction of its tolerance passes / is flagged


def ball(**options):
    """The bouncing ball (one translation z, radius r on the ground): model, data, r [m], m g [N]."""
    model = ms.build_model(scene("bouncing_ball", **options))
    data = make_data(model)
    q = np.zeros(model.nq)
    r = -float(ms.contacts.pair_distances(model, data, q)[0])  # the gap at z = 0 is -r
    mg = potential(model, data, np.ones(model.nq)) - potential(model, data, q)
    return model, data, r, mg


def started(model, data, q, u, **kw):
    """An Invariants hook and a Recorder after the start (its first sample, then the start check)."""
    inv, rec = Invariants(model, rtol=1e-8, **kw), Recorder(model, data, 8)
    s = State(0.0, np.array(q, float), np.array(u, float))
    rec.sample(s, 0.0, 0.0, 0)
    found = (inv("sample", s, None, rec) or []) + (inv("start", s, None, rec) or [])
    return inv, rec, found


def point(inv, rec, s, records=(), corr=0.0):
    return inv("point", s, Report(Status.RUNNING, s.t, s, tuple(records), 0.0, corr), rec)


@pytest.mark.parametrize("frac", [BELOW, ABOVE])
def test_a_start_inside_deeper_than_the_contact_tolerance_is_flagged(frac):
    model, data, r, _ = ball(contact_tolerance=1e-6)
    _, _, found = started(model, data, [r - frac * 1e-6], [0.0])
    assert [v["invariant"] for v in found] == ([Invariant.START_INSIDE.value] if frac > 1 else [])
    if found:
        assert found[0]["size"] == pytest.approx(1e-6 * frac, rel=1e-6) and found[0]["allowed"] == 1e-6


@pytest.mark.parametrize("frac", [BELOW, ABOVE])
@pytest.mark.parametrize("integrator, rel", [("time-stepping", invariants.FIXED_RTOL),
                                             ("event-driven", invariants.EXACT_FACTOR * 1e-8)])
def test_an_energy_gain_above_the_integrators_bound_is_flagged(frac, integrator, rel):
    """A point whose T + V lies frac x the bound above the start (nothing booked): an energy gain
    and a speed the energy does not allow, both at the integrator's bound rel x scale."""
    model, data, r, mg = ball(integrator=integrator)
    z = 1.0
    inv, rec, _ = started(model, data, [z], [0.0])
    E0 = potential(model, data, np.array([z]))
    T = frac * rel * E0
    u = np.sqrt(2 * T / kinetic(model, data, np.array([z]), np.ones(1)) / 2) * np.ones(1)
    found = point(inv, rec, State(1e-3, np.array([z]), u))
    kinds = {v["invariant"] for v in found or []}
    assert (Invariant.SPEED.value in kinds or Invariant.ENERGY_GAIN.value in kinds) == (frac > 1)
    assert inv.Ehat - inv.Emin == pytest.approx(T, rel=1e-6)


def test_a_contact_free_fixed_step_books_its_smooth_error_and_a_correction_is_booked():
    """The change of T + V in a contact-free fixed step is the midpoint rule's (booked); a rise the
    position correction booked is not a gain either."""
    model, data, r, mg = ball()
    inv, rec, _ = started(model, data, [1.0], [0.0])
    s0 = State(0.0, np.array([1.0]), np.array([0.0]))
    res = step(model, data, s0, h=1e-3, e=0.5)
    assert res.contacts.m == 0
    lifted = State(2e-3, res.state.q + 1e-3, res.state.u)
    assert point(inv, rec, res.state, [FixedStep(1, 5e-4, s0, res, 1e-3, 0.5)]) is None
    assert point(inv, rec, lifted, corr=1e-3 * mg) is None
    assert point(inv, rec, State(3e-3, lifted.q + 1e-3, lifted.u)) is not None  # the same lift, not booked


@pytest.mark.parametrize("frac", [BELOW, ABOVE])
def test_penetration_beyond_the_steps_transient_for_persist_steps_is_flagged(frac):
    """A ball at rest inside the ground by frac x (contact_tolerance + 2 h h |g|): the real step's
    midpoint gap, PERSIST steps in a row."""
    model, data, r, mg = ball(restitution=0.0)
    h, g = model.options.dt, 9.81
    allowed = model.options.contact_tolerance + invariants.ACCELERATION * h * h * g + invariants.GAP_ROUND_OFF
    s = State(0.0, np.array([r - frac * allowed]), np.array([0.0]))
    inv, rec, _ = started(model, data, s.q, s.u)
    res = step(model, data, s, h=h, e=0.0)
    assert -res.contacts.g.min() == pytest.approx(frac * allowed, rel=1e-3)
    found = [point(inv, rec, s, [FixedStep(k, 0.0, s, res, h, 0.0)]) for k in range(invariants.PERSIST)]
    assert found[:-1] == [None] * (invariants.PERSIST - 1)
    assert (found[-1] is not None) == (frac > 1)
    if frac > 1:
        assert found[-1][0]["invariant"] == Invariant.PENETRATION.value
        assert found[-1][0]["allowed"] == pytest.approx(allowed, rel=1e-9)


@pytest.mark.parametrize("frac", [BELOW, ABOVE])
def test_a_pair_inside_keeps_the_allowance_of_the_impact_that_put_it_there(frac):
    """A ball that struck the ground at 1 m/s (its step's allowance A = contact_tolerance + h (|gamma-| +
    2 h |g|)) and stays inside, at rest, by frac x A: held to A, not to the slow steps' own allowance
    (the depth an impact left persists where the correction is dropped, docs/theory.md §10)."""
    model, data, r, mg = ball(restitution=0.0)
    h = model.options.dt
    fast = State(0.0, np.array([r]), np.array([-1.0]))
    inv, rec, _ = started(model, data, fast.q, fast.u)
    res = step(model, data, fast, h=h, e=0.0)
    assert point(inv, rec, res.state, [FixedStep(0, 0.5 * h, fast, res, h, 0.0)]) is None
    A = (model.options.contact_tolerance + h * (-res.gamma_minus.min() + invariants.ACCELERATION * h * 9.81)
         + invariants.GAP_ROUND_OFF)
    s = State(h, np.array([r - frac * A]), np.array([0.0]))
    slow = step(model, data, s, h=h, e=0.0)
    assert -slow.contacts.g.min() == pytest.approx(frac * A, rel=1e-3)
    found = [point(inv, rec, s, [FixedStep(k, 0.0, s, slow, h, 0.0)]) for k in range(1, 1 + invariants.PERSIST)]
    assert (found[-1] is not None) == (frac > 1)
    if frac > 1:
        assert found[-1][0]["invariant"] == Invariant.PENETRATION.value
        assert found[-1][0]["allowed"] == pytest.approx(A, rel=1e-9)


@pytest.mark.parametrize("frac", [BELOW, ABOVE])
def test_a_ledger_gain_is_allowed_the_contact_steps_smooth_deficit(frac):
    """A capped contact step closes the budget up to -S_k (docs/theory.md §2.10): a fixed-step residual
    gain of X (the recorded sum of max(-S_k, 0)) + frac x the bound is flagged only beyond it."""
    model, data, r, mg = ball()
    inv, rec, _ = started(model, data, [1.0], [0.0])
    bound = invariants.FIXED_RTOL * mg
    rec.smooth_deficit = X = 1e-3 * mg
    s = State(1e-3, np.array([1.0]), np.array([0.0]))
    rec.sample(s, -(X + frac * bound), 0.0, 0)
    assert (inv("sample", s, None, rec) is not None) == (frac > 1)


@pytest.mark.parametrize("frac", [BELOW, ABOVE])
def test_a_ledger_residual_above_its_bound_is_flagged(frac):
    """A sample whose contact work explains frac x the bound less than T + V changed (a gain: the
    fixed step's residual counts only as a gain)."""
    model, data, r, mg = ball()
    inv, rec, _ = started(model, data, [1.0], [0.0])
    bound = invariants.FIXED_RTOL * mg
    s = State(1e-3, np.array([1.0]), np.array([0.0]))
    rec.sample(s, -frac * bound, 0.0, 0)
    found = inv("sample", s, None, rec)
    assert (found is not None) == (frac > 1)
    if found:
        assert found[0]["invariant"] == Invariant.LEDGER.value and found[0]["size"] == pytest.approx(frac * bound)


def test_a_non_finite_state_stops_the_run():
    model, data, r, _ = ball()
    inv, rec, _ = started(model, data, [1.0], [0.0])
    with pytest.raises(SimulationError, match="non-finite"):
        point(inv, rec, State(1e-3, np.array([1.0]), np.array([np.nan])))


def test_a_violation_is_reported_again_only_when_it_grew():
    model, data, r, mg = ball()
    inv, rec, _ = started(model, data, [1.0], [0.0])
    sizes = [inv._violate(Invariant.LEDGER, 0.0, x, 1.0, "J", "") for x in (2.0, 5.0, 19.0, 21.0)]
    assert [bool(v) for v in sizes] == [True, False, False, True]


# ---- a flagged run: its status, strict, the CLI, regress, moreau_sim.testing ----------------------------------


@pytest.fixture
def strict_bound(monkeypatch):
    """A fixed step's stated bound set below zero: every run of the fixed step breaks it at once."""
    monkeypatch.setattr(invariants, "FIXED_RTOL", -1.0)


def test_a_run_that_broke_an_invariant_is_flagged_and_strict_makes_it_an_error(strict_bound):
    model = ms.build_model(scene("bouncing_ball", duration=0.05))
    traj = ms.simulate(model, progress=False)
    assert traj.meta["status"] == "flagged" and not traj.complete
    assert Invariant.SPEED.value in {v["invariant"] for v in traj.meta["invariants"]}
    with pytest.raises(InvariantViolation) as err:
        ms.simulate(model, progress=False, strict=True)
    assert err.value.trajectory.meta["status"].startswith("failed: step 1 ")
    with pytest.raises(InvariantViolation):
        ms.run(SCENES / "bouncing_ball.toml", duration=0.05, strict=True)


def test_the_start_of_a_run_given_a_state_inside_is_flagged():
    """A ball given to a run 3 m under the ground (the rest rule would lift it and book 30 J)."""
    model = ms.build_model(scene("bouncing_ball", duration=0.01))
    traj = ms.simulate(model, progress=False, state=State(0.0, np.array([-3.0]), np.array([0.0])))
    assert traj.meta["status"] == "flagged"
    assert traj.meta["invariants"][0]["invariant"] == Invariant.START_INSIDE.value


def test_the_cli_prints_one_line_and_strict_exits_3(tmp_path):
    """`moreau-sim run`: a run that holds prints nothing about invariants; one that broke one (the
    fixed step's bound set below zero in the child) prints one line and exits 0; with --strict it
    exits 3 and keeps the samples so far in FILE.partial.npz."""
    out = tmp_path / "b.npz"
    cmd = [sys.executable, "-m", "moreau_sim", "run", str(SCENES / "bouncing_ball.toml"), "--duration", "0.05",
           "-o", str(out), "--no-progress"]
    ok = subprocess.run(cmd, capture_output=True, text=True)
    assert ok.returncode == 0 and "flagged" not in ok.stderr
    code = ("import sys, moreau_sim.invariants as i; i.FIXED_RTOL = -1.0; "
            "from moreau_sim.cli import main; sys.argv = ['moreau-sim'] + sys.argv[1:]; main()")
    flagged = subprocess.run([sys.executable, "-c", code, *cmd[3:]], capture_output=True, text=True)
    assert flagged.returncode == 0 and flagged.stderr.count("\n") == 1 and "flagged: " in flagged.stderr
    strict = subprocess.run([sys.executable, "-c", code, *cmd[3:], "--strict"], capture_output=True, text=True)
    assert strict.returncode == 3 and "invariant violated: " in strict.stderr
    assert ms.load_trajectory(tmp_path / "b.partial.npz").meta["status"].startswith("failed")


def test_regress_and_testing_count_a_flagged_run_as_a_failure(tmp_path, monkeypatch):
    from moreau_sim.regress import check_scene
    from moreau_sim.testing import assert_invariants_held, assert_matches_baseline

    path = SCENES / "bouncing_ball.toml"
    assert check_scene(path, tmp_path, update=True, overrides={"duration": 0.05}).status == "recorded"
    assert check_scene(path, tmp_path).status == "ok"
    monkeypatch.setattr(invariants, "FIXED_RTOL", -1.0)
    r = check_scene(path, tmp_path)
    assert r.status == "flagged" and "speed beyond the energy" in r.message
    traj = ms.run(path, duration=0.05)
    with pytest.raises(AssertionError, match="flagged: speed beyond the energy"):
        assert_invariants_held(traj)
    with pytest.raises(AssertionError, match="flagged"):
        assert_matches_baseline(traj, tmp_path)


def test_a_checkpointed_run_resumes_its_checks(tmp_path):
    """The hook's figures go through a checkpoint: a resumed run ends with the same status and violations."""
    from moreau_sim.checkpoint import Checkpoint

    model = ms.build_model(scene("pendulum_wall", duration=0.8))
    whole = ms.simulate(model, progress=False)
    ck = Checkpoint(path=tmp_path / "c.npz", every=0.3, keep=True)
    ms.simulate(model, progress=False, checkpoint=ck)
    resumed = ms.simulate(model, progress=False, checkpoint=Checkpoint(path=tmp_path / "c.npz", resume=True))
    assert resumed.meta["status"] == whole.meta["status"]
    assert resumed.meta.get("invariants") == whole.meta.get("invariants")


# ---- every bundled scene under every integrator: held or flagged, never silent ----------------------------------

SLOW = ("column_of_beads", "alternating_stack_10", "quadruped", "solo", "panda", "box_stack_10",
        "heavy_on_light_box_10000")


def _case(path, integ):
    marks = [pytest.mark.slow] if integ != "time-stepping" and any(s in path.stem for s in SLOW) else []
    return pytest.param(path, integ, marks=marks, id=f"{path.stem}-{integ}")


@pytest.mark.parametrize("path, integ", [_case(p, i) for p in table.SCENES for i in table.INTEGRATORS])
def test_every_bundled_scene_holds_its_invariants_or_is_refused_by_name(path, integ):
    """A bundled scene under an integrator that takes it holds (status complete), shown here from its arrays:
    finite samples, no pair deeper inside another than contact_tolerance + h max |gamma-| (a step's transient at
    the largest approach the run logged), T + V never above its start by more than the positive correction and
    smooth error booked and the work done on it plus 1e-6 of the scale. An event integrator refuses exactly the
    scenes of helpers.REFUSED (torques, moving statics, driven joints), in one line naming the reason; any other
    error, a refusal of another scene, or a flagged run fails."""
    if integ != "time-stepping" and path.stem in REFUSED:
        exc, message = REFUSED[path.stem]
        with pytest.raises(exc, match=re.escape(message)):
            ms.run(path, duration=table.duration(path, integ), integrator=integ)
        return
    traj = ms.run(path, duration=table.duration(path, integ), integrator=integ)
    assert traj.meta["status"] == "complete", traj.meta.get("invariants")
    a = traj.arrays
    E = a["kinetic_energy"] + a["potential_energy"]
    assert np.isfinite(E).all() and np.isfinite(a["q"]).all()
    if a["gap"].size:
        o = traj.meta["options"]
        v = -a["log_gamma_minus"].min(initial=0.0)
        assert a["gap"].min() >= -(o["contact_tolerance"] + o["dt"] * v + 1e-12)  # the samples' rule
    scale = max(abs(E[0]), a["kinetic_energy"].max())
    booked = np.cumsum(np.maximum(a["correction_energy"], 0) + np.maximum(a["smooth_error"], 0)
                       + a.get("actuator_work", 0.0) + a.get("obstacle_work", 0.0))  # the work done on it (§5.5)
    assert (E - E[0] - booked).max() <= 1e-6 * scale
