"""Every snippet a user can copy from README.md and docs/ runs as written, from a fresh folder.

The fresh folder is a copy of the repository's tracked files (what `git clone` gives: no out/,
no outputs of earlier runs), with `.venv` pointing at this environment (README's step 1 makes
it) and the package importable as installed. Per Markdown file:

- its ```python blocks run in order as one script (a reader following the page in one session);
  a block that is a pytest module (it defines ``test_*`` functions) is saved as a test file and
  run by pytest, as the page tells;
- every command of its ```sh blocks and of its indented shell blocks runs in one bash session
  (``set -e``), and every ``$ command`` of a transcript block (an untyped block) runs and must
  print what the page shows;
- its ```toml blocks are scene fragments: they parse and load as a scene file.

```text blocks are output or usage synopses with placeholders and are not run. A command that
installs software or runs a long benchmark is excluded only through EXCLUDED below, each with
its reason; the list is checked against the pages (no stale entry)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tomllib
from importlib.metadata import entry_points
from pathlib import Path

import pytest

import moreau_sim as ms

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
INDENTED_SHELL = re.compile(r"(?:^|\n)\n((?: {4}(?:\.venv/|moreau-sim |python|pip |apt-get )[^\n]*\n)+)")

# (page, start of the command line) -> why the suite does not run it
EXCLUDED = {
    ("README.md", "python3 -m venv .venv && .venv/bin/pip install"):
        "installs the package (compiles the C++ step, ~4 min): the set-up step CI runs itself",
    ("README.md", "{ [ -x /usr/bin/chromedriver ]"): "installs Chromium and the test extras, then runs this suite",
    ("benchmarks.md", ".venv/bin/pip install -e '.[peers]'"): "installs the peers (pip and apt-get)",
    ("benchmarks.md", ".venv/bin/python -m benchmarks.work_precision --out docs/bench"):
        "long benchmark (2-3 min), rewrites the committed figures",
    ("benchmarks.md", ".venv/bin/python -m benchmarks.work_precision --quick"):
        "the same command is tests/test_work_precision_smoke.py (into its tmp_path)",
    ("benchmarks.md", ".venv/bin/python -m benchmarks.check_peers"): "runs every peer simulator (benchmark, minutes)",
    ("benchmarks.md", ".venv/bin/python -m benchmarks.step_costs --out"):
        "long benchmark, rewrites the committed figures",
    ("benchmarks.md", ".venv/bin/python -m benchmarks.compiled_costs"): "long benchmark",
    ("benchmarks.md", ".venv/bin/python -m benchmarks.adaptive_costs"): "long benchmark",
    ("benchmarks.md", "OPENBLAS_NUM_THREADS=1 .venv/bin/python -m benchmarks.scaling"):
        "long benchmark (up to 500 beads)",
    ("stability.md", ".venv/bin/pip install -e '.[peers]' && apt-get install"):
        "installs the peers, then the 2.5 min stability benchmark",
    ("viewer.md", "MOREAU_SIM_DOCS_IMG=1 .venv/bin/python -m pytest tests/test_viewer.py"):
        "runs tests/test_viewer.py, which this suite runs itself",
}


def blocks(path: Path, lang: str) -> list[str]:
    return [body for kind, body in FENCE.findall(path.read_text(encoding="utf-8")) if kind == lang]


def shell_lines(path: Path) -> list[str]:
    """Command lines of the page's sh blocks and indented shell blocks (comments dropped)."""
    text = path.read_text(encoding="utf-8")
    bodies = blocks(path, "sh") + [textwrap_dedent(b) for b in INDENTED_SHELL.findall(FENCE.sub("", text))]
    return [line for body in bodies for line in body.splitlines() if line.strip() and not line.lstrip().startswith("#")]


def textwrap_dedent(body: str) -> str:
    return "\n".join(line[4:] for line in body.splitlines())


def excluded(doc: Path, line: str) -> str | None:
    return next((why for (page, start), why in EXCLUDED.items() if page == doc.name and line.startswith(start)), None)


def transcripts(path: Path) -> list[tuple[str, list[str]]]:
    """(command, the lines the page shows it printing) of each `$ ` line of untyped blocks."""
    out = []
    for body in blocks(path, ""):
        lines = body.splitlines()
        for i, line in enumerate(lines):
            if line.startswith("$ "):
                shown = []
                for nxt in lines[i + 1:]:
                    if nxt.startswith("$ "):
                        break
                    shown.append(nxt)
                out.append((line[2:], shown))
    return out


def is_test_module(block: str) -> bool:
    return re.search(r"^def test_\w+\(", block, re.M) is not None


@pytest.fixture(scope="module")
def clone(tmp_path_factory) -> Path:
    """The repository's tracked files (a fresh clone's content), copied once per module."""
    dest = tmp_path_factory.mktemp("clone") / "moreau-sim"
    try:
        files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True,
                               timeout=60).stdout.decode().split("\0")
    except (OSError, subprocess.CalledProcessError):
        files = [str(p.relative_to(ROOT)) for d in ("scenes", "models", "scripts", "docs")
                 for p in (ROOT / d).rglob("*") if p.is_file()]
    for name in filter(None, files):
        src = ROOT / name
        if src.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name)
    return dest


@pytest.fixture
def fresh(clone, tmp_path) -> Path:
    """A fresh folder per page: the clone's files, `.venv` = this environment (README step 1)."""
    folder = tmp_path / "moreau-sim"
    shutil.copytree(clone, folder, symlinks=True)
    (folder / ".venv").symlink_to(sys.prefix)
    assert not (folder / "out").exists()
    return folder


def _env():
    return {**os.environ, "MPLBACKEND": "Agg", "PYTHONPATH": str(ROOT),
            "PATH": os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])}


def _plugin() -> list[str]:
    installed = any(ep.name == "moreau_sim" for ep in entry_points(group="pytest11"))
    return [] if installed else ["-p", "moreau_sim.pytest_plugin"]


@pytest.mark.parametrize("doc", [d for d in DOCS if blocks(d, "python")], ids=lambda d: d.name)
def test_python_blocks_run(doc, fresh):
    script = "\n\n".join(b for b in blocks(doc, "python") if not is_test_module(b))
    r = subprocess.run([sys.executable, "-c", script], cwd=fresh, env=_env(), capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, f"{doc.name}:\n{script}\n--- stderr:\n{r.stderr[-3000:]}"
    for k, block in enumerate(b for b in blocks(doc, "python") if is_test_module(b)):
        test = fresh / f"test_snippet_{k}.py"
        test.write_text(block, encoding="utf-8")
        cmd = [sys.executable, "-m", "pytest", *_plugin(), "-q", "-p", "no:cacheprovider", test.name]
        r = subprocess.run(cmd, cwd=fresh, env=_env(), capture_output=True, text=True, timeout=600)
        if r.returncode == 1 and "no energy-ledger baseline yet" in r.stdout:  # the page: it fails once, recording
            r = subprocess.run(cmd, cwd=fresh, env=_env(), capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, f"{doc.name}: the pytest block\n{block}\n--- output:\n{r.stdout[-3000:]}"


# a page whose every command is excluded (EXCLUDED gives the reasons) has nothing to run here
@pytest.mark.parametrize("doc", [d for d in DOCS if any(not excluded(d, line) for line in shell_lines(d))],
                         ids=lambda d: d.name)
def test_shell_commands_run(doc, fresh):
    lines = [line for line in shell_lines(doc) if not excluded(doc, line)]
    for line in lines:  # one at a time, so that a failure names its line; the folder carries the state
        r = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", line], cwd=fresh, env=_env(), capture_output=True,
                           text=True, timeout=600)
        assert r.returncode == 0, f"{doc.name}: {line}\n--- stderr:\n{r.stderr[-3000:]}"


@pytest.mark.parametrize("doc", [d for d in DOCS if transcripts(d)], ids=lambda d: d.name)
def test_transcripts_print_what_the_page_shows(doc, fresh):
    for command, shown in transcripts(doc):
        r = subprocess.run(["bash", "-c", command], cwd=fresh, env=_env(), capture_output=True, text=True,
                           timeout=600)
        printed = (r.stdout + r.stderr).rstrip("\n").splitlines()
        assert printed == shown, f"{doc.name}: $ {command}\n--- printed:\n" + "\n".join(printed)


@pytest.mark.parametrize("doc", [d for d in DOCS if blocks(d, "toml")], ids=lambda d: d.name)
def test_toml_fragments_load_as_scenes(doc, fresh):
    for k, body in enumerate(blocks(doc, "toml")):
        tomllib.loads(body)
        if "[[bodies]]" in body and "example-robot-data" in body:
            from moreau_sim.robots import example_robot_data_share
            assert example_robot_data_share() is not None, "example-robot-data (a test dependency) is not installed"
        path = fresh / f"snippet_{k}.toml"
        path.write_text(body, encoding="utf-8")
        model = ms.build_model(ms.load_scene(path))
        assert model.nv > 0


def test_every_exclusion_names_a_command_of_its_page():
    for page, start in EXCLUDED:
        doc = next(d for d in DOCS if d.name == page)
        assert any(line.startswith(start) for line in shell_lines(doc)), (page, start)


def test_no_snippet_is_left_out():
    """Each page's code is python, sh, toml, text (output, synopses), an untyped block (a transcript
    or a listing), or an indented shell block: nothing in another language escapes the tests."""
    for doc in DOCS:
        kinds = {kind for kind, _ in FENCE.findall(doc.read_text(encoding="utf-8"))}
        assert kinds <= {"python", "sh", "toml", "text", ""}, (doc.name, kinds)


def test_the_solo_drop_ledger_on_the_page_is_the_runs():
    """docs/regression.md prints the ledger of solo_drop: every impact row (time, contacts, T-, T+,
    dissipated, law) as the run gives it (the difference column is round-off, not compared)."""
    text = (ROOT / "docs" / "regression.md").read_text(encoding="utf-8")
    table = text[text.index("ledger of solo_drop"):]
    table = table[:table.index("```")]
    rows = [line.split()[:6] for line in table.splitlines() if re.match(r"^\s+\d+\.\d+\s+\d+\s", line)]
    traj = ms.run(ROOT / "scenes" / "solo_drop.toml", duration=0.3, progress=False)
    run_rows = [line.split()[:6] for line in ms.ledger(traj).table().splitlines()
                if re.match(r"^\s+\d+\.\d+\s+\d+\s", line)]
    assert rows == run_rows and len(rows) == 4
    assert f"{len(rows)} impacts in" in table


def test_readme_first_screen_says_what_the_simulator_does_not_do():
    """README.md, within its first 30 lines: frictionless by design, actuation under the fixed step only (joint
    limits are enforced);
    and its two set-up commands (CI parses the line after "# 2.") unchanged: the tests but the slow ones, which
    .ci/run runs after them."""
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    first = "\n".join(lines[:30]).lower()
    for words in ("no friction", "frictionless", "actuation under the fixed step only",
                  "joint limits (urdf `<limit>`) are enforced"):
        assert words in first, words
    two = lines.index(next(line for line in lines if line.startswith("# 2.")))
    assert lines[two + 1].startswith("{ [ -x /usr/bin/chromedriver ] &&") and lines[two + 1].endswith(
        "&& .venv/bin/python -m pytest -n 2 -m 'not slow'")
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()
    assert ".venv/bin/python -m pytest -n 2 -m slow" in ci
    one = lines.index(next(line for line in lines if line.startswith("# 1.")))
    assert lines[one + 1].startswith("python3 -m venv .venv && .venv/bin/pip install -q -e . &&")


def test_stability_page_says_why_the_peers_run_frictionless():
    text = (ROOT / "docs" / "stability.md").read_text(encoding="utf-8")
    methods = text[:text.index("<!-- stability table")]
    assert "Friction 0 for every peer" in methods and "frictionless Newton law by design" in methods


def test_output_page_states_the_memory_bound_the_suite_checks():
    """docs/output.md's memory figure for 10^6 steps is a measurement; the page names the test and
    the bound it checks, and those are the test's own (a quarter spilled; 1.5 x + 8 MB in memory)."""
    page = " ".join((ROOT / "docs" / "output.md").read_text(encoding="utf-8").split())
    test = (ROOT / "tests" / "test_recording.py").read_text(encoding="utf-8")
    assert "test_recording.py::test_memory_is_proportional_to_the_data" in page
    assert 'm["growth"] <= 0.25 * m["data"]' in test and "at most a quarter of the recorded arrays" in page
    assert 'm["growth"] <= 1.5 * m["data"] + 8e6' in test and "at most 1.5 times them plus 8 MB" in page
    assert "179 MiB**" not in page  # no single figure stated as if it were bounded
