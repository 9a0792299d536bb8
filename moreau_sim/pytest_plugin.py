"""pytest plugin (entry point pytest11 "moreau_sim"): the `energy_ledger` fixture, so that an
energy-dissipation regression test is three lines (docs/regression.md):

    import moreau_sim as ms

    def test_solo_energy(energy_ledger):
        traj = ms.run("scenes/solo_drop.toml", duration=0.3)
        energy_ledger.check(traj)

check() asserts that the run held its invariants (docs/theory.md §10: a flagged run fails), that
every contact step dissipates what the law says and that the ledger matches
its baseline, the same JSON file as `moreau-sim regress` writes: by default
<test folder>/ledger_baselines/<test module>/<test name>.json (ini option
`moreau_sim_baselines` changes the folder). A missing baseline is recorded and the test fails
once (rerun it); `pytest --ledger-update` rewrites the baselines of the tests that run.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

# The simulator is imported when a test uses the fixture, not when pytest loads the plugin: every
# pytest run in an environment with moreau-sim installed loads it.


def pytest_addoption(parser, pluginmanager):
    _drop_editable_rewrite_warning(pluginmanager)
    group = parser.getgroup("moreau-sim")
    group.addoption("--ledger-update", action="store_true", default=False,
                    help="moreau-sim: rewrite the energy-ledger baselines of the tests that run")
    parser.addini("moreau_sim_baselines", "moreau-sim: folder of the energy-ledger baselines, relative to the "
                  "test file's folder (default ledger_baselines)", default="ledger_baselines")


EDITABLE_HOOK = "_editable_skbc_moreau_sim"


def _drop_editable_rewrite_warning(pluginmanager) -> None:
    """Withdraw pytest's "Module already imported so cannot be rewritten; _editable_skbc_moreau_sim".

    An editable install (scikit-build-core) lists its import hook, a top-level module imported by
    a .pth file at interpreter start, among the files of the distribution that declares this
    plugin; pytest marks every top-level module of such a distribution for assertion rewriting and
    warns, at every run in that environment, before any plugin loads (pytest skips setuptools'
    ``__editable__`` hooks, not scikit-build-core's). The warning is a recorded call of the
    historic hook ``pytest_warning_recorded``, replayed to the terminal reporter when it registers,
    after this plugin: removed here from that record (pluggy's ``_call_history``; if pluggy stores
    it otherwise, the warning stays)."""
    history = getattr(pluginmanager.hook.pytest_warning_recorded, "_call_history", None)
    if not isinstance(history, list):
        return

    def editable(entry) -> bool:
        kwargs = entry[0] if isinstance(entry, tuple) and entry and isinstance(entry[0], dict) else {}
        message = getattr(kwargs.get("warning_message"), "message", None)
        return (type(message).__name__ == "PytestAssertRewriteWarning" and str(message).endswith(EDITABLE_HOOK))

    history[:] = [entry for entry in history if not editable(entry)]


class EnergyLedger:
    """The fixture: check(traj) against this test's baseline file (`path`)."""

    def __init__(self, path: Path, update: bool):
        self.path = path
        self.update = update

    def check(self, traj, *, tolerances: dict | None = None, law_rtol: float | None = 1e-9,
              no_gain_rtol: float | None = None) -> None:
        """The run's invariants held (testing.assert_invariants_held: a flagged run fails); the law's
        dissipation in every contact step to law_rtol of the run's energy scale (None: not checked);
        no energy gain beyond no_gain_rtol (None, the default: not checked; the smooth motion of a
        jointed robot oscillates at O(h^2)); then the baseline within `tolerances`
        {quantity: (rtol, atol)} (regress.py's defaults otherwise)."""
        __tracebackhide__ = True  # a failure shows the test's line and the table, not this source
        from .regress import write_baseline
        from .testing import (assert_dissipation_follows_law, assert_invariants_held, assert_matches_baseline,
                              assert_no_energy_gain)

        if hasattr(traj, "meta"):  # a Trajectory (a Ledger carries no status)
            assert_invariants_held(traj)
        if no_gain_rtol is not None:
            assert_no_energy_gain(traj, rtol=no_gain_rtol)
        if law_rtol is not None:
            assert_dissipation_follows_law(traj, rtol=law_rtol)
        if self.update or not self.path.exists():
            write_baseline(self.path, traj, tolerances=tolerances)
            if not self.update:
                pytest.fail(f"no energy-ledger baseline yet: recorded {self.path}; run the test again", pytrace=False)
            return
        assert_matches_baseline(traj, self.path, tolerances=tolerances)


@pytest.fixture
def energy_ledger(request) -> EnergyLedger:
    """Energy-ledger regression check of one test (module doc)."""
    folder = Path(request.path).parent / request.config.getini("moreau_sim_baselines") / Path(request.path).stem
    name = re.sub(r"[^\w.=-]+", "_", request.node.name)
    return EnergyLedger(folder / f"{name}.json", request.config.getoption("--ledger-update"))
