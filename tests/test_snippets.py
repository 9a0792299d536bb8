"""Every code block a user can copy from README.md and docs/ runs as written.

Per Markdown file, its ```python blocks run in order as one script, and every line of its ```sh
blocks that starts with `moreau-sim` runs as a command, in a scratch folder that holds the
repository's scenes/ and models/ (the paths the docs use). Install commands (pip, apt-get) run
in CI itself; usage synopses with placeholders are ```text blocks and are not run."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)


def blocks(path: Path, lang: str) -> list[str]:
    return [body for kind, body in FENCE.findall(path.read_text(encoding="utf-8")) if kind == lang]


def commands(path: Path) -> list[str]:
    out = []
    for body in blocks(path, "sh"):
        for line in body.splitlines():
            line = line.split("  #")[0].strip()
            if line.startswith("moreau-sim "):
                out.append(line)
    return out


@pytest.fixture
def workdir(tmp_path):
    for name in ("scenes", "models"):
        (tmp_path / name).symlink_to(ROOT / name)
    (tmp_path / "out").mkdir()
    return tmp_path


def _env():
    return {**os.environ, "MPLBACKEND": "Agg", "PYTHONPATH": str(ROOT)}


@pytest.mark.parametrize("doc", [d for d in DOCS if blocks(d, "python")], ids=lambda d: d.name)
def test_python_blocks_run(doc, workdir):
    script = "\n\n".join(blocks(doc, "python"))
    r = subprocess.run([sys.executable, "-c", script], cwd=workdir, env=_env(), capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, f"{doc.name}:\n{script}\n--- stderr:\n{r.stderr[-3000:]}"


@pytest.mark.parametrize("doc", [d for d in DOCS if commands(d)], ids=lambda d: d.name)
def test_shell_commands_run(doc, workdir):
    for line in commands(doc):
        argv = [sys.executable, "-m", "moreau_sim", *shlex.split(line)[1:]]
        r = subprocess.run(argv, cwd=workdir, env=_env(), capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, f"{doc.name}: {line}\n--- stderr:\n{r.stderr[-3000:]}"
