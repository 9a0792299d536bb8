"""Assertions on the energy ledger of a run (docs/theory.md §5, docs/regression.md), for a user's
tests and the project's own. Each takes a Trajectory (or its Ledger) and raises AssertionError
with a short table of what moved, by how much and where in time.

    import moreau_sim as ms
    from moreau_sim.testing import assert_no_energy_gain, assert_dissipation_follows_law
    traj = ms.run("scenes/bouncing_ball.toml", duration=1.0)
    assert_no_energy_gain(traj)
    assert_dissipation_follows_law(traj)

Tolerances are relative to the run's energy scale, max(|E_0|, max T) [J] (Ledger.scale), plus an
absolute atol [J] where given.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..invariants import flagged, one_line
from ..ledger import Ledger, compare, drift_table, ledger
from ..regress import baseline_path, differences, read_baseline, write_baseline
from ..trajectory import Trajectory

__all__ = ["assert_budget_closes", "assert_dissipation_follows_law", "assert_invariants_held",
           "assert_matches_baseline", "assert_no_energy_gain"]


def _ledger(x: Trajectory | Ledger) -> Ledger:
    return x if isinstance(x, Ledger) else ledger(x)


def _fail(title: str, header: str, rows: list[str]) -> None:
    __tracebackhide__ = True  # pytest shows the caller's line and this message, not this module's source
    raise AssertionError("\n".join([title, header, *rows]))


def assert_no_energy_gain(traj: Trajectory | Ledger, *, rtol: float = 1e-9, atol: float = 0.0) -> None:
    """No step raises T + V by more than atol + rtol * scale [J], and no sample lies above E_0 by
    more than that. For passive scenes (no motors, no external work)."""
    __tracebackhide__ = True
    L = _ledger(traj)
    tol = atol + rtol * L.scale
    rows = []
    if L.max_step_rise > tol:
        rows.append(f"  {'one step':<14} {L.t_step_rise:12.6g} {L.max_step_rise:+12.3e} {tol:10.1e}")
    above = np.flatnonzero(L.E - L.energy_start > tol)
    for i in above[np.argsort(-(L.E[above] - L.energy_start))][:5]:
        rows.append(f"  {'E(t) - E_0':<14} {L.t[i]:12.6g} {L.E[i] - L.energy_start:+12.3e} {tol:10.1e}")
    if rows:
        _fail(f"{L.scene}: energy gained (scale {L.scale:.3g} J)",
              f"  {'what':<14} {'t [s]':>12} {'rise [J]':>12} {'tolerance':>10}", rows)


def assert_invariants_held(traj: Trajectory) -> None:
    """The run held every invariant it checks of itself (docs/theory.md §10): its status is not
    "flagged"; else the violations, one per invariant with its size, where and when."""
    __tracebackhide__ = True
    if flagged(traj.meta):
        nan = float("nan")
        rows = [f"  {v.get('invariant', '?'):<24} {v.get('t', nan):12.6g} {v.get('size', nan):12.3e} "
                f"{v.get('allowed', nan):10.1e} {v.get('unit', '')}" for v in traj.meta.get("invariants", [])[:10]]
        _fail(f"{traj.meta.get('scene', {}).get('name', 'run')}: flagged: {one_line(traj.meta.get('invariants', []))}",
              f"  {'invariant':<24} {'t [s]':>12} {'size':>12} {'allowed':>10}", rows)


def assert_dissipation_follows_law(traj: Trajectory | Ledger, *, rtol: float = 1e-9, atol: float = 0.0) -> None:
    """Every contact step dissipates what the law says, (1 - e^2)/2 |u- - v|_M^2 (with the
    per-contact bounds of docs/theory.md §2.7), to atol + rtol * scale [J]; and no impact gains energy."""
    __tracebackhide__ = True
    L = _ledger(traj)
    tol = atol + rtol * L.scale
    bad = [r for r in L.impacts if abs(r.difference) > tol or r.dissipated < -tol]
    rows = [f"  {r.t:12.6g} {r.dissipated:14.6e} {r.predicted:14.6e} {r.difference:+11.2e}" for r in bad[:8]]
    if L.max_law_difference > tol and not bad:
        rows.append(f"  {L.t_law_difference:12.6g} {'(contact step)':>14} {'':>14} {L.max_law_difference:+11.2e}")
    if rows:
        _fail(f"{L.scene}: impact dissipation departs from the law by more than {tol:.1e} J "
              f"(scale {L.scale:.3g} J; largest {L.max_law_difference:.2e} J)",
              f"  {'t [s]':>12} {'dissipated':>14} {'law':>14} {'difference':>11}", rows)


def assert_budget_closes(traj: Trajectory | Ledger, *, rtol: float = 1e-9, atol: float = 0.0) -> None:
    """E_end - E_0 = contact work + correction + smooth error, to atol + rtol * scale [J] (the
    residual, docs/theory.md §5: the contact steps' own error, round-off where the smooth motion
    is exact, first order in h in rotating and revolute scenes)."""
    __tracebackhide__ = True
    L = _ledger(traj)
    tol = atol + rtol * L.scale
    if abs(L.residual) <= tol:
        return
    worst = np.argsort(-np.abs(L.residuals))[:5]
    rows = [f"  {L.t[i]:12.6g} {L.residuals[i]:+12.3e}" for i in worst if L.residuals[i] != 0.0]
    _fail(f"{L.scene}: the energy budget leaves {L.residual:+.3e} J (tolerance {tol:.1e} J): "
          f"E_end - E_0 = {L.energy_end - L.energy_start:+.6e} J, contact work {L.contact_work:+.6e} J, "
          f"correction {L.correction:+.6e} J, smooth error {L.smooth_error:+.6e} J",
          f"  {'t [s]':>12} {'left [J]':>12}   (largest per sample)", rows)


def assert_matches_baseline(traj: Trajectory | Ledger, baseline: str | Path | dict, *,
                            tolerances: dict | None = None, update: bool = False) -> None:
    """The ledger matches a recorded baseline: a JSON file of `moreau-sim regress` (a path ending in
    .json; any other path is a folder holding SCENE_NAME.json) or its dict, within tolerances
    {quantity: (rtol, atol [J])} ("default" for the rest; docs/regression.md).
    update: write the baseline from this run instead (also when the file does not exist yet).
    A flagged run (it broke an invariant) fails, and records no baseline."""
    __tracebackhide__ = True
    if isinstance(traj, Trajectory):
        assert_invariants_held(traj)
    L = _ledger(traj)
    path = None
    if not isinstance(baseline, dict):
        path = Path(baseline)
        if path.suffix != ".json":
            path = baseline_path(path, L.scene)
        if update or not path.exists():
            if not isinstance(traj, Trajectory):
                raise ValueError("writing a baseline needs the Trajectory (its scene and options), not a Ledger")
            write_baseline(path, traj)
            return
        baseline = read_baseline(path)
    drifts = compare(L.record(), baseline["ledger"], tolerances or baseline.get("tolerances"))
    if drifts:
        notes = differences(baseline, traj, path) if isinstance(traj, Trajectory) else []
        why = [f"  note: {n}" for n in notes] or ["  note: same scene file, options and library versions as the "
                                                  "baseline (a change in the code or the machine moved it)"]
        raise AssertionError("\n".join([f"{L.scene}: the energy ledger moved from its baseline"
                                         + (f" ({path})" if path else ""), *why,
                                         drift_table(drifts)]))
