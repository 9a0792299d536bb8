"""Every table of figures in docs/*.md, generated from the committed JSON in docs/bench/.

    python -m benchmarks.doc_tables          # rewrite every table from the committed JSON
    python -m benchmarks.doc_tables --check  # exit 1 naming each table that differs (tests do this)

Each benchmark driver saves its JSON (`--out docs/bench`) and rewrites its own tables with
`--table JSON DOC`; this module lists them all (TABLES) so that none can drift from its JSON."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from . import (
    REPO,
    adaptive_costs,
    compiled_costs,
    events,
    robots_table,
    scaling,
    splice_table,
    stability,
    step_costs,
    work_precision,
)

# (document, JSON, the driver's doc_tables(data) -> {marker name: Markdown}), paths relative to the repository
TABLES = (("docs/benchmarks.md", "docs/bench/work_precision.json", work_precision.doc_tables),
          ("docs/benchmarks.md", "docs/bench/step_costs.json", step_costs.doc_tables),
          ("docs/benchmarks.md", "docs/bench/compiled_costs.json", compiled_costs.doc_tables),
          ("docs/benchmarks.md", "docs/bench/adaptive_costs.json", adaptive_costs.doc_tables),
          ("docs/benchmarks.md", "docs/bench/events.json", events.doc_tables),
          ("docs/benchmarks.md", "docs/bench/scaling.json", scaling.doc_tables),
          ("docs/benchmarks.md", "docs/bench/scaling_build.json", scaling.doc_tables),
          ("docs/benchmarks.md", "docs/bench/scaling_runs.json", scaling.doc_tables),
          ("docs/robots.md", "docs/bench/robots.json", robots_table.doc_tables),
          ("docs/stability.md", "docs/bench/stability.json", stability.doc_tables))


def generated(doc: str, root: Path = REPO) -> str:
    """The text `doc` should have: its current text with every table of TABLES regenerated."""
    text = (root / doc).read_text(encoding="utf-8")
    for d, source, render in TABLES:
        if d == doc:
            for name, table in render(json.loads((root / source).read_text(encoding="utf-8"))).items():
                text = splice_table(text, name, table, where=doc)
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="only report the documents whose tables differ")
    a = ap.parse_args(argv)
    stale = []
    for doc in dict.fromkeys(d for d, _, _ in TABLES):
        text = generated(doc)
        if text != (REPO / doc).read_text(encoding="utf-8"):
            stale.append(doc)
            if not a.check:
                (REPO / doc).write_text(text, encoding="utf-8")
    verb = "differ from their JSON" if a.check else "rewritten"
    print(f"tables {verb}: {', '.join(stale)}" if stale else "every generated table matches its JSON")
    return 1 if stale and a.check else 0


if __name__ == "__main__":
    raise SystemExit(main())
