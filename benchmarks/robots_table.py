"""The tables of docs/robots.md (bundled robot scenes, the `meshes` modes), measured, not typed.

    python -m benchmarks.robots_table [--out docs/bench]   # run the scenes, write robots.json, print the table
    python -m benchmarks.robots_table --table docs/bench/robots.json docs/robots.md  # rewrite it from the JSON

Each robot scene runs with its own options; the row gives its size, the wall time per step of the
run (this machine, whatever its load: a figure for scale, not a benchmark), the impacts, the
energy at start and end, the largest rise of T + V above its start, and the deepest gap."""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
from pathlib import Path

import numpy as np

import moreau_sim as ms
from moreau_sim.options import MeshMode
from moreau_sim.recording import versions

from . import OUT, REPO, add_table_option, rewrite_tables, scene_path

ROBOTS = {"quadruped_drop": "Unitree A1 (`a1.urdf`: boxes, cylinders, sphere feet)",
          "panda_table": "Franka Panda, sphere/cylinder model (`models/panda_arm_collision.urdf`)",
          "solo_drop": "ODRI Solo (`solo.urdf`: 13 OBJ meshes → hulls)",
          "mjcf_example": "MJCF pendulum (`models/pendulum.xml`)"}


# docs/robots.md's comparison of the `meshes` modes: (key, scene, body file or None, mode, label)
MESH_CASES = (("box", "box_drop", None, None, "`box_drop`'s box (0.2 × 0.2 × 0.4 m), Box primitive"),
              ("box_mesh_convex", "box_drop", "models/box_mesh.urdf", MeshMode.CONVEX,
               "the same box as a 12-triangle OBJ (`models/box_mesh.urdf`)"),
              ("box_mesh_bvh", "box_drop", "models/box_mesh.urdf", MeshMode.BVH, "the same mesh"),
              ("solo_convex", "solo_drop", None, MeshMode.CONVEX, "`solo_drop` (13 OBJ meshes)"),
              ("solo_bvh", "solo_drop", None, MeshMode.BVH, "the same robot"))


def measure_meshes(scene: str, urdf: str | None, mode: MeshMode | None) -> dict:
    """One run of a scene with its first body's collision meshes in `mode` (and its model file
    replaced by `urdf`): µs per step, deepest gap [m], the root's height at the end [m], the largest
    kinetic energy over the last fifth of the run [J], T + V at the start and end [J]."""
    sc = ms.load_scene(scene_path(scene))
    body = sc.bodies[0]
    if urdf is not None:
        body = dataclasses.replace(body, urdf=REPO / urdf)
    if mode is not None:
        body = dataclasses.replace(body, meshes=mode)
    traj = ms.simulate(ms.build_model(dataclasses.replace(sc, bodies=(body,) + tuple(sc.bodies[1:]))),
                       progress=False)
    s = ms.summary(traj)
    T = traj.arrays["kinetic_energy"]
    last = traj.t >= 0.8 * traj.t[-1]
    z = traj.meta["q_names"].index(f"{body.name}/root/z")
    return {"us_per_step": s["us_per_step"], "min_gap": s["min_gap"], "z_end": float(traj.q[-1, z]),
            "T_max_last_fifth": float(np.max(T[last])), "energy_start": s["energy_start"],
            "energy_end": s["energy_end"], "energy_max_increase": s["energy_max_increase"],
            "duration": float(traj.t[-1])}


def mesh_table(rows: dict) -> str:
    """The `meshes` modes table of docs/robots.md from robots.json's "meshes"."""
    out = ["| body | mode | µs/step | deepest gap | root z at the end | max T, last fifth of the run | "
           "T + V start → end | max rise of T + V |", "|---|---|---:|---:|---:|---:|---|---:|"]
    for key, _, _, mode, label in MESH_CASES:
        r = rows.get(key)
        if r is None:
            continue
        rise = r["energy_max_increase"]
        out.append(f"| {label} | {'–' if mode is None else mode.value} | {r['us_per_step']:.0f} | "
                   f"{1e3 * r['min_gap']:.2f} mm | {r['z_end']:.4g} m | {r['T_max_last_fifth']:.2g} J | "
                   f"{r['energy_start']:.4g} → {r['energy_end']:.4g} J | {'0' if rise <= 0 else f'{rise:.2g} J'} |")
    return "\n".join(out)


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
    return {"robots table": table(data["scenes"]), "mesh-mode table": mesh_table(data["meshes"])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT,
                    help="output folder of robots.json (docs/bench: the committed file)")
    add_table_option(ap, "robots.json", "docs/robots.md")
    a = ap.parse_args(argv)
    if rewrite_tables(a, doc_tables):
        return 0
    scenes = {name: measure(name) for name in ROBOTS}
    meshes = {key: measure_meshes(scene, urdf, mode) for key, scene, urdf, mode, _ in MESH_CASES}
    meta = {"created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "cpus": os.cpu_count(), "load": os.getloadavg()[0], "versions": versions()}
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "robots.json").write_text(json.dumps({"meta": meta, "scenes": scenes, "meshes": meshes}, indent=1))
    print(table(scenes))
    print(mesh_table(meshes))
    print(f"wrote {a.out / 'robots.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
