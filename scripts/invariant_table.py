"""Every bundled scene under every integrator, short runs: did each hold its invariants (status
complete), was it flagged (with the reason), did it fail, or does the integrator not accept it?
Writes a markdown table (scene x integrator) and the counts; tests/test_invariants.py runs the same
runs (duration()) and asserts that none is silent.

    python scripts/invariant_table.py [OUT.md] [--only SUBSTR ...]
"""

from __future__ import annotations

import sys
from pathlib import Path

import moreau_sim as ms
from moreau_sim.errors import SceneError, SimulationError
from moreau_sim.gaps import UnsupportedModel
from moreau_sim.invariants import one_line

ROOT = Path(__file__).resolve().parents[1]
SCENES = sorted((ROOT / "scenes").glob("*.toml"))
INTEGRATORS = ("time-stepping", "adaptive", "event-driven")
CAP = {"time-stepping": 1.0, "adaptive": 0.5, "event-driven": 0.3}  # [s] the longest run of each integrator
HEAVY = ("quadruped", "solo", "panda", "column_of_beads_100", "box_stack_10", "heavy_on_light_box_10000",
         "alternating_stack_10")
HEAVY_CAP = 0.1  # [s] the event integrators on the scenes of many contacts (each costs seconds beyond)


def duration(scene: Path, integrator: str) -> float:
    """The simulated time [s] of a table run: the scene's duration, capped."""
    cap = HEAVY_CAP if integrator != "time-stepping" and any(h in scene.stem for h in HEAVY) else CAP[integrator]
    return min(ms.load_scene(scene).options.duration, cap)


def outcome(scene: Path, integrator: str) -> tuple[str, str]:
    """("held" | "flagged" | "failed" | "not accepted", the reason) of one run."""
    try:
        traj = ms.run(scene, duration=duration(scene, integrator), integrator=integrator)
    except (UnsupportedModel, SceneError) as exc:  # a model or a scene (torques, moving statics) it does not take
        return "not accepted", str(exc).splitlines()[0][:120]
    except SimulationError as exc:
        return "failed", str(exc).splitlines()[0][:160]
    status = traj.meta["status"]
    if status == "complete":
        return "held", ""
    return status, one_line(traj.meta.get("invariants", []))


def main(argv: list[str]) -> None:
    only = [a for a in argv if a.startswith("--only=")]
    keys = [a.split("=", 1)[1] for a in only]
    out = next((Path(a) for a in argv if not a.startswith("--")), None)
    rows, counts = [], {}
    for scene in SCENES:
        if keys and not any(k in scene.stem for k in keys):
            continue
        for integ in INTEGRATORS:
            what, why = outcome(scene, integ)
            counts[(integ, what)] = counts.get((integ, what), 0) + 1
            rows.append(f"| {scene.stem} | {integ} | {duration(scene, integ):g} | {what} | {why} |")
            print(rows[-1], flush=True)
    lines = ["| scene | integrator | duration [s] | outcome | reason |", "|---|---|---|---|---|", *rows, "",
             "| integrator | held | flagged | failed | not accepted | silent |", "|---|---|---|---|---|---|"]
    for integ in INTEGRATORS:
        n = [counts.get((integ, k), 0) for k in ("held", "flagged", "failed", "not accepted")]
        lines.append(f"| {integ} | " + " | ".join(map(str, n)) + " | 0 |")
    text = "\n".join(lines) + "\n"
    if out is not None:
        out.write_text(text, encoding="utf-8")
    print(text)


if __name__ == "__main__":
    main(sys.argv[1:])
