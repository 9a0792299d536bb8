"""The table of bundled robot scenes in docs/robots.md, measured, not typed.

    python scripts/robots_table.py [--out docs/bench]   # run the scenes, write robots.json, print the table
    python scripts/robots_table.py --table docs/bench/robots.json docs/robots.md  # rewrite it from the JSON

Each robot scene runs with its own options; the row gives its size, the wall time per step of the
run (this machine, whatever its load: a figure for scale, not a benchmark), the impacts, the
energy at start and end, the largest rise of T + V above its start, and the deepest gap."""

from __future__ import annotations

import argparse
import datetime
import json
import os
from pathlib import Path

import moreau_sim as ms
from moreau_sim.recording import versions

from . import OUT, scene_path, write_tables

ROBOTS = {"quadruped_drop": "Unitree A1 (`a1.urdf`: boxes, cylinders, sphere feet)",
          "panda_table": "Franka Panda, sphere/cylinder model (`models/panda_arm_collision.urdf`)",
          "solo_drop": "ODRI Solo (`solo.urdf`: 13 OBJ meshes → hulls)",
          "mjcf_example": "MJCF pendulum (`models/pendulum.xml`)"}


def measure(name: str) -> dict:
    """One robot scene's run: size, µs per step, impacts, energies [J], deepest gap [m]."""
    traj = ms.run(scene_path(name))
    s = ms.summary(traj)
    m = traj.meta["model"]
    return {"nv": m["nv"], "pairs": len(m["collision_pairs"]),
            **{k: s[k] for k in ("us_per_step", "impacts", "energy_start", "energy_end", "energy_max_increase",
                                 "min_gap")}}


def row(name: str, robot: str, r: dict) -> str:
    rise = r["energy_max_increase"]
    return (f"| `{name}` | {robot} | {r['nv']} | {r['pairs']} | {r['us_per_step']:.0f} | "
            f"{r['impacts']} | {r['energy_start']:.4g} → {r['energy_end']:.4g} J | "
            f"{'0' if rise <= 0 else f'{rise:.2g} J'} | {1e3 * r['min_gap']:.2f} mm |")


def table(rows: dict) -> str:
    """The Markdown table from robots.json's "scenes" (in ROBOTS' order; scenes it lacks are left out)."""
    head = ("| scene | robot | nv | pairs | µs/step (run) | impacts | T + V start → end | max rise of T + V | "
            "deepest gap |\n|---|---|---:|---:|---:|---:|---|---:|---:|")
    return "\n".join([head] + [row(n, robot, rows[n]) for n, robot in ROBOTS.items() if n in rows])


def doc_tables(data: dict) -> dict[str, str]:
    """The tables of docs/robots.md this script's JSON gives (marker name: Markdown)."""
    return {"robots table": table(data["scenes"])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT,
                    help="output folder of robots.json (docs/bench: the committed file)")
    ap.add_argument("--table", nargs=2, type=Path, metavar=("JSON", "DOC"),
                    help="only rewrite the table in DOC (docs/robots.md) from a robots.json, and exit")
    a = ap.parse_args(argv)
    if a.table:
        write_tables(a.table[0], a.table[1], doc_tables)
        print(f"wrote the table into {a.table[1]}")
        return 0
    scenes = {name: measure(name) for name in ROBOTS}
    meta = {"created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "cpus": os.cpu_count(), "load": os.getloadavg()[0], "versions": versions()}
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "robots.json").write_text(json.dumps({"meta": meta, "scenes": scenes}, indent=1))
    print(table(scenes))
    print(f"wrote {a.out / 'robots.json'}")
    return 0
