"""The pytest integration is as quiet and explicit as `moreau-sim regress` (docs/regression.md): a
drift failure shows the test's line, why the ledger moved and the table, not moreau_sim's source;
no assertion-rewrite warning with an editable install; baselines name their scene relative to
themselves."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from importlib.metadata import entry_points

import moreau_sim as ms
from moreau_sim.regress import baseline_scene, differences, read_baseline, write_baseline

from helpers import ROOT, SCENES

USER_TEST = """
import moreau_sim as ms


def test_ball_energy(energy_ledger):
    traj = ms.run("{scene}", duration=0.6, restitution={e})
    energy_ledger.check(traj)
"""


def pytest_run(folder, *args, pre_import: str = "", pythonpath=(ROOT,)):
    """pytest in a subprocess from `folder`; the plugin by -p unless an installed package registers it."""
    installed = any(ep.name == "moreau_sim" for ep in entry_points(group="pytest11"))
    plugin = "" if installed or pre_import else "'-p', 'moreau_sim.pytest_plugin', "
    code = (f"import sys{', ' + pre_import if pre_import else ''}; import pytest; "
            f"sys.exit(pytest.main([{plugin}'-p', 'no:cacheprovider', '-rA', *sys.argv[1:]]))")
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, cwd=folder,
                          env={**os.environ, "PYTHONPATH": os.pathsep.join(map(str, pythonpath))}, timeout=300)


def test_a_drift_failure_is_the_tests_line_the_reason_and_the_table(tmp_path):
    test = tmp_path / "test_user.py"
    test.write_text(USER_TEST.format(scene=SCENES / "bouncing_ball.toml", e=0.8))
    assert pytest_run(tmp_path, test).returncode == 1  # records the baseline, fails once
    assert pytest_run(tmp_path, test).returncode == 0
    test.write_text(USER_TEST.format(scene=SCENES / "bouncing_ball.toml", e=0.7))
    r = pytest_run(tmp_path, test)
    out = r.stdout
    assert r.returncode == 1 and "moved from its baseline" in out, out
    assert "note: options: restitution 0.8 -> 0.7" in out, out
    failure = out[out.index("FAILURES"):out.index("short test summary")]
    for source in ("__tracebackhide__", "def check(", "def assert_matches_baseline", "raise AssertionError",
                   "moreau_sim/testing", "moreau_sim/pytest_plugin"):
        assert source not in failure, (source, failure)
    assert "energy_ledger.check(traj)" in failure  # the test's own line
    assert len(failure.splitlines()) < 30, failure


def test_an_unchanged_setup_says_so_when_the_ledger_moves(tmp_path):
    """A baseline edited by hand (a figure changed): same scene, options and versions, said as such."""
    traj = ms.run(SCENES / "bouncing_ball.toml", duration=0.6)
    path = write_baseline(tmp_path / "b.json", traj)
    doc = json.loads(path.read_text())
    doc["ledger"]["totals"]["dissipation"] *= 1.01
    path.write_text(json.dumps(doc))
    from moreau_sim.testing import assert_matches_baseline
    try:
        assert_matches_baseline(traj, path)
    except AssertionError as exc:
        text = str(exc)
    else:
        raise AssertionError("the edited baseline passed")
    assert "same scene file, options and library versions" in text and "dissipation" in text


def test_no_assertion_rewrite_warning_with_an_editable_install(tmp_path):
    """scikit-build-core's editable install: a top-level import hook `_editable_skbc_moreau_sim`,
    imported by a .pth at interpreter start and listed among the files of the distribution that
    declares the plugin. Reproduced with that layout: pytest warns without the plugin, not with it."""
    site = tmp_path / "site"
    info = site / "moreau_sim-0.0.dist-info"
    info.mkdir(parents=True)
    (site / "_editable_skbc_moreau_sim.py").write_text("")
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: moreau-sim\nVersion: 0.0\n")
    (info / "RECORD").write_text("_editable_skbc_moreau_sim.py,,\nmoreau_sim-0.0.dist-info/METADATA,,\n")
    (info / "entry_points.txt").write_text("[pytest11]\nmoreau_sim = moreau_sim.pytest_plugin\n")
    (tmp_path / "test_x.py").write_text("def test_x():\n    assert 1\n")
    args = dict(pre_import="_editable_skbc_moreau_sim", pythonpath=(site, ROOT))
    if any(ep.name == "moreau_sim" and ep.dist and ep.dist.name != "moreau-sim"
           for ep in entry_points(group="pytest11")):
        return
    without = pytest_run(tmp_path, "test_x.py", "-p", "no:moreau_sim", **args)
    assert without.returncode == 0 and "_editable_skbc_moreau_sim" in without.stdout, without.stdout  # the layout
    r = pytest_run(tmp_path, "test_x.py", **args)
    assert r.returncode == 0 and "plugins:" in r.stdout and "moreau-sim" in r.stdout, r.stdout
    assert "PytestAssertRewriteWarning" not in r.stdout and "warning" not in r.stdout.lower(), r.stdout


def test_baselines_name_their_scene_relative_to_themselves(tmp_path):
    """Written relative to the baseline's folder; an absolute path (files written before) is read too;
    a moved checkout (scene and baselines together) still names its scene."""
    checkout = tmp_path / "a"
    (checkout / "scenes").mkdir(parents=True)
    for name in ("scenes/bouncing_ball.toml",):
        shutil.copy(ROOT / name, checkout / name)
    (checkout / "models").symlink_to(ROOT / "models")
    traj = ms.run(checkout / "scenes" / "bouncing_ball.toml", duration=0.3)
    path = write_baseline(checkout / "baselines" / "bouncing_ball.json", traj)
    doc = read_baseline(path)
    assert doc["scene_path"] == "../scenes/bouncing_ball.toml"
    assert baseline_scene(doc, path) == (checkout / "scenes" / "bouncing_ball.toml").resolve()
    moved = tmp_path / "b"
    shutil.move(checkout, moved)
    assert baseline_scene(doc, moved / "baselines" / "bouncing_ball.json") == moved / "scenes" / "bouncing_ball.toml"
    old = dict(doc, scene_path=str(SCENES / "bouncing_ball.toml"))  # an absolute path, as written before
    assert baseline_scene(old, path) == SCENES / "bouncing_ball.toml"
    # regress names a baseline recorded from another scene file
    again = ms.run(moved / "scenes" / "bouncing_ball.toml", duration=0.3)
    assert any(n.startswith("scene file: ") for n in differences(old, again, path))
    assert not any(n.startswith("scene file: ") for n in differences(doc, again, moved / "baselines" / "x.json"))
