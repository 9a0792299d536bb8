"""Energy-ledger baselines (docs/regression.md): run scenes, record their ledgers as readable JSON
files, compare later runs with them, and report (text, JUnit XML for CI systems).

A baseline file DIR/SCENE.json holds the scene's name, path (relative to DIR; absolute in files
written before, both read) and hash (of its TOML and URDF texts),
the option overrides it was run with, its options, the library versions, the tolerances (if
given) and the ledger record (ledger.Ledger.record: totals, every impact, E(t) at <= 100 samples).
"""

from __future__ import annotations

import datetime
import hashlib
import json
import os
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

from .errors import MoreauSimError, SceneError, SimulationError
from .invariants import flagged, one_line
from .ledger import Drift, compare, drift_table, ledger
from .model import build_model
from .scene import load_scene
from .simulate import simulate
from .trajectory import Trajectory, atomic_write

FORMAT = "moreau-sim baseline 1"


def baseline_path(directory: str | Path, scene_name: str) -> Path:
    return Path(directory) / f"{scene_name}.json"


def scene_hash(traj: Trajectory) -> str:
    """SHA-256 of the scene's TOML text and its bodies' URDF texts (as the trajectory recorded them)."""
    sc = traj.meta.get("scene", {})
    h = hashlib.sha256((sc.get("toml") or "").encode())
    for name, text in sorted((sc.get("urdf") or {}).items()):
        h.update(f"\0{name}\0{text}".encode())
    return h.hexdigest()


def write_baseline(path: str | Path, traj: Trajectory, *, overrides: dict | None = None,
                   tolerances: dict | None = None) -> Path:
    """Write the baseline of a trajectory (readable JSON, keys sorted; atomic)."""
    path = Path(path)
    m = traj.meta
    scene = m.get("scene", {}).get("path")
    if scene:  # relative to the baseline's folder: a checkout moved elsewhere still names it
        try:
            scene = Path(os.path.relpath(Path(scene).resolve(), path.resolve().parent)).as_posix()
        except ValueError:  # another drive (Windows): keep it absolute
            pass
    doc = {"format": FORMAT, "scene": m.get("scene", {}).get("name"), "scene_path": scene,
           "scene_hash": scene_hash(traj), "overrides": overrides or {}, "options": m.get("options", {}),
           "versions": m.get("versions", {}),
           "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
           "ledger": ledger(traj).record()}
    if tolerances:
        doc["tolerances"] = {k: list(v) for k, v in tolerances.items()}
    return atomic_write(path, lambda tmp: tmp.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n",
                                                         encoding="utf-8"))


def baseline_scene(doc: dict, path: str | Path) -> Path | None:
    """The scene file a baseline `doc` (read from `path`) was recorded from: its ``scene_path``
    relative to the baseline's folder, or absolute (files written before); None if not recorded."""
    value = doc.get("scene_path")
    if not isinstance(value, str) or not value:
        return None
    return Path(os.path.normpath(Path(path).resolve().parent / value))


def read_baseline(path: str | Path) -> dict:
    """A baseline file as a dict. Raises ValueError naming the file and what is wrong with it."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the baseline ({exc.strerror or exc})") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not JSON (line {exc.lineno}: {exc.msg})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        fmt = doc.get("format") if isinstance(doc, dict) else None
        raise ValueError(f"{path}: not a moreau-sim baseline (format: {fmt!r}, expected {FORMAT!r})")
    led = doc.get("ledger")
    for key, sub in (("totals", None), ("impacts", ("t", "dissipated")), ("energy", ("t", "E"))):
        if not isinstance(led, dict) or not isinstance(led.get(key), dict) or \
                any(not isinstance(led[key].get(s), list) for s in sub or ()):
            raise ValueError(f"{path}: field ledger.{key} is missing or malformed")
    return doc


@dataclass
class Result:
    """One scene of a regress run: status "ok", "drift", "failed" (the run stopped), "flagged" (the
    run broke an invariant, docs/theory.md §10: a failure like drift, and no baseline is recorded from
    it), "recorded" (--update), "error" (bad input: scene, options, baseline file); drifts; notes (what differs
    from the baseline: scene file, options, versions); message (failed, error); seconds of wall time."""

    scene: str
    path: str
    status: str
    drifts: list[Drift] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    message: str = ""
    seconds: float = 0.0

    def report(self) -> str:
        head = f"{self.status.upper():8} {self.scene}  ({self.path}, wall time {self.seconds:.1f} s)"
        lines = [head] + [f"  note: {n}" for n in self.notes]
        if self.message:
            lines.append(f"  {self.message}")
        if self.drifts:
            lines.append(drift_table(self.drifts))
        return "\n".join(lines)


def differences(doc: dict, traj: Trajectory, path: str | Path | None = None) -> list[str]:
    """What differs between the baseline `doc` (read from `path`) and the run `traj`, besides the
    ledger: the scene file's path and text, the options, the library versions."""
    notes = []
    old = baseline_scene(doc, path) if path is not None else None
    new = traj.meta.get("scene", {}).get("path")
    if old is not None and new and old != Path(new).resolve():
        notes.append(f"scene file: {old} -> {new}")
    if doc.get("scene_hash") != scene_hash(traj):
        notes.append("the scene file (TOML or URDF) changed since the baseline")
    for key, show in (("options", repr), ("versions", str)):
        old, new = doc.get(key, {}), traj.meta.get(key, {})
        changed = [f"{k} {show(old.get(k))} -> {show(new.get(k))}" for k in sorted(set(old) | set(new))
                   if old.get(k) != new.get(k)]
        if changed:
            notes.append(f"{key}: " + ", ".join(changed))
    return notes


def check_scene(scene: str | Path, directory: str | Path, *, update: bool = False, overrides: dict | None = None,
                tolerances: dict | None = None) -> Result:
    """Run one scene and compare its ledger with DIR/NAME.json (or write it: update). The run uses
    the baseline's recorded overrides, updated by `overrides`. Raises SceneError or ValueError on
    bad input (scene, options, baseline file)."""
    t0 = time.perf_counter()
    sc = load_scene(scene)
    path = baseline_path(directory, sc.name)
    doc = None
    if not update:
        if not path.exists():
            raise ValueError(f"{path}: no baseline for scene {sc.name} (record it with --update)")
        doc = read_baseline(path)
    used = {**(doc or {}).get("overrides", {}), **(overrides or {})}
    try:
        sc = sc.with_options(**used)
        model = build_model(sc)
    except MoreauSimError as exc:
        raise SceneError(f"{scene}: {exc}") from None
    try:
        traj = simulate(model, progress=False)
    except SimulationError as exc:
        return Result(sc.name, str(scene), "failed", message=f"the run failed: {exc}",
                      seconds=time.perf_counter() - t0)
    if flagged(traj.meta):
        return Result(sc.name, str(scene), "flagged", message=f"the run broke an invariant: "
                      f"{one_line(traj.meta.get('invariants', []))}", seconds=time.perf_counter() - t0)
    if update:  # what the new baseline changes, when there was one, is shown (it is accepted)
        try:
            old = read_baseline(path) if path.exists() else None
        except ValueError:
            old = None
        accepted = compare(ledger(traj).record(), old["ledger"], tolerances) if old else []
        write_baseline(path, traj, overrides=used, tolerances=tolerances)
        return Result(sc.name, str(scene), "recorded", accepted,
                      [f"baseline written to {path}"] + (["it replaces these figures:"] if accepted else []),
                      seconds=time.perf_counter() - t0)
    tol = tolerances or {k: tuple(v) for k, v in doc.get("tolerances", {}).items()} or None
    drifts = compare(ledger(traj).record(), doc["ledger"], tol)
    notes = differences(doc, traj, path) if drifts else []
    return Result(sc.name, str(scene), "drift" if drifts else "ok", drifts, notes, seconds=time.perf_counter() - t0)


FAILURES = ("drift", "failed", "flagged")  # the statuses of Result that fail a regress run (exit 1)


def junit(results: list[Result], path: str | Path) -> Path:
    """A JUnit XML report (one testcase per scene; drift, failed and flagged runs are failures), atomically."""
    suite = ET.Element("testsuite", name="moreau-sim regress", tests=str(len(results)),
                       failures=str(sum(r.status in FAILURES for r in results)),
                       errors=str(sum(r.status == "error" for r in results)),
                       time=f"{sum(r.seconds for r in results):.3f}")
    for r in results:
        case = ET.SubElement(suite, "testcase", classname="moreau-sim.regress", name=r.scene, file=r.path,
                             time=f"{r.seconds:.3f}")
        if r.status in FAILURES + ("error",):
            what = r.message or ", ".join(d.quantity for d in r.drifts)
            tag = "error" if r.status == "error" else "failure"
            fail = ET.SubElement(case, tag, message=f"{r.scene}: {r.status}: {what}", type=r.status)
            fail.text = r.report()
        else:
            ET.SubElement(case, "system-out").text = r.report()
    root = ET.Element("testsuites", name="moreau-sim", tests=suite.get("tests"), failures=suite.get("failures"),
                      errors=suite.get("errors"))
    root.append(suite)
    tree = ET.ElementTree(root)
    ET.indent(tree)
    return atomic_write(path, lambda tmp: tree.write(tmp, encoding="utf-8", xml_declaration=True))
