"""Figure of one branched simulation: a corner impact with several admissible outcomes, and
where the motion goes from each of them.

Runs a corner scene, finds its first branching step (a corner impact whose set-valued law has
several stationary points, docs/theory.md §3), re-takes that step once per candidate
(`step(..., corner_choice=i)`), continues every branch with the scene's policy to the end, and
draws the paths of the body's centre in the x-z plane, the obstacles, and the chosen branch.

    python scripts/corner_branches.py [--scene scenes/block_on_step.toml] [--out out/corner_branches.png]
    python scripts/corner_branches.py --out docs/img/corner_branches.png   # the committed figure
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import moreau_sim as ms

SCENES = Path(__file__).resolve().parents[1] / "scenes"  # the bundled scenes of the source tree
OUT = Path("out")  # default output folder, relative to the current directory


def branches(scene_path: Path) -> dict:
    model = ms.build_model(ms.load_scene(scene_path))
    o = model.options
    base = ms.simulate(model, progress=False)
    if not len(base.branch_step):
        raise SystemExit(f"{scene_path}: no corner impact with several outcomes in this run")
    k = int(base.branch_step[0])  # the step that branched (1-based): it starts from sample k-1
    start = ms.State(float(base.t[k - 1]), base.q[k - 1], base.u[k - 1])
    n_cand = int(base.branch_count[0])
    out = {"scene": model.scene.name, "t_branch": float(base.branch_t[0]), "chosen": int(base.branch_chosen[0]),
           "branches": []}
    for i in range(n_cand):
        data = ms.make_data(model)
        r = ms.step(model, data, start, h=o.dt, e=o.restitution, corner_choice=i)
        rest = model.scene.with_options(duration=max(o.dt, o.duration - r.state.t))
        traj = ms.simulate(ms.build_model(rest), state=r.state, progress=False)
        j = int(base.branch_start[0]) + i
        out["branches"].append({"candidate": i, "u_plus": base.candidate_u_plus[j].tolist(),
                                "distance": float(base.candidate_distance[j]),
                                "global_min": bool(base.candidate_global_min[j]),
                                "x": np.r_[start.q[0], traj.q[:, 0]].tolist(),
                                "z": np.r_[start.q[1], traj.q[:, 1]].tolist()})
    return out


def draw(res: dict, scene_path: Path, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    sc = ms.load_scene(scene_path)
    fig, ax = plt.subplots(figsize=(7, 5), constrained_layout=True)
    for s in sc.statics:
        if s.shape.value == "box":
            ax.add_patch(Rectangle((s.position[0] - s.size[0] / 2, s.position[2] - s.size[2] / 2), s.size[0],
                                   s.size[2], color="0.8"))
        elif s.shape.value == "halfspace":
            ax.axhline(s.offset, color="0.4", lw=2)
    for b in res["branches"]:
        style = dict(lw=2.5 if b["candidate"] == res["chosen"] else 1.2,
                     ls="-" if b["global_min"] else "--")
        lab = (f"outcome {b['candidate']}: u+ = {np.round(b['u_plus'], 2).tolist()}, "
               f"distance {b['distance']:.3g} J" + (" (global min)" if b["global_min"] else "")
               + (" - chosen" if b["candidate"] == res["chosen"] else ""))
        ax.plot(b["x"], b["z"], label=lab, **style)
    ax.plot(res["branches"][0]["x"][0], res["branches"][0]["z"][0], "ko")
    ax.set_aspect("equal")
    xs = np.concatenate([b["x"] for b in res["branches"]])
    zs = np.concatenate([b["z"] for b in res["branches"]])
    pad = 0.1 * max(np.ptp(xs), np.ptp(zs), 0.2)
    ax.set_xlim(xs.min() - pad, xs.max() + pad)
    ax.set_ylim(min(zs.min(), min((s.offset for s in sc.statics if s.shape.value == "halfspace"), default=0)) - pad,
                zs.max() + 3 * pad)
    ax.set_xlabel("x [m] (body centre)")
    ax.set_ylabel("z [m]")
    ax.set_title(f"{res['scene']}: corner impact at t = {res['t_branch']:.4f} s, every admissible outcome")
    ax.legend(fontsize=7, loc="upper right")
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=120)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(SCENES / "block_on_step.toml"))
    ap.add_argument("--out", default=str(OUT / "corner_branches.png"),
                    help="the figure, and its data as .json (docs/img/corner_branches.png: the committed one)")
    a = ap.parse_args()
    res = branches(Path(a.scene))
    draw(res, Path(a.scene), Path(a.out))
    Path(a.out).with_suffix(".json").write_text(json.dumps({k: v for k, v in res.items()}, indent=1))
    for b in res["branches"]:
        print(f"outcome {b['candidate']}: u+ = {np.round(b['u_plus'], 4).tolist()}  distance {b['distance']:.4g} J"
              f"  global min {b['global_min']}  ends at x = {b['x'][-1]:.3f} m, z = {b['z'][-1]:.3f} m")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
