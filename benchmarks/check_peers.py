"""Measure how each available peer reproduces the exact impact references.

- bouncing_ball, e in {0.5, 0.8, 1.0}, h in {1e-2, 1e-3, 1e-4}, T = 3 s: apex gaps of the
  first 3 bounces vs e^{2n} d0, effective restitution e_n = sqrt(apex_n / apex_{n-1})
  (apex_0 = d0 = 0.9 m), deepest penetration, final gap z(T) - r, CPU per simulated second.
- newton_cradle_5 (touching) and newton_cradle_5_gapped (1 mm gaps), e in {1, 0.5}, h = 1e-3,
  T = 0.5 s: final velocities vs Glocker's simultaneous result (touching) or the binary-impact
  sequence (gapped), momentum and kinetic energy (Siconos with exact_gaps, as in work_precision).
- box_drop, e = 0.5, h = 1e-3, T = 1.5 s: deepest penetration, where the box comes to rest
  (no exact reference: frictionless tumbling is sensitive; this shows resting-contact health).

Every peer runs the neutral spec of the bundled scene (benchmarks.spec) with its runner's
defaults; apexes are found by metrics.apexes. This is a measurement, not a test: it never fails
on a bad number.

    python -m benchmarks.check_peers --out out/peers.json [--md out/peers.md]
"""
from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

import moreau_sim as ms
from moreau_sim.testing.metrics import apexes
from moreau_sim.testing.references import BALL_GAP as D0, ball_reference, cradle_sequential, cradle_simultaneous

from . import peers, scene_path
from .spec import min_corner_height, quat_to_mats, to_jsonable

R = 0.1  # ball radius [m]
ES = (0.5, 0.8, 1.0)
HS = (1e-2, 1e-3, 1e-4)
T_BALL = 3.0
T_CRADLE = 0.5
H_CRADLE = 1e-3
CRADLE_PARAMS = {"siconos": {"exact_gaps": True}}  # Siconos given exact touching / exact 1 mm gaps
HALF = np.array([0.1, 0.1, 0.2])  # box_drop's half extents [m]


def run(peer, scene, *, e, h, T, **kw):
    """(t, q, u, result) of `peer` on the bundled scene with restitution e, step h, duration T."""
    model = ms.build_model(ms.load_scene(scene_path(scene)).with_options(restitution=e, dt=h, duration=T))
    return peers.run_model(peer, model, **kw)


def configs(avail):
    out = []
    if avail.get("mujoco") is None:
        out.append(("mujoco", "mujoco", {}))
    if avail.get("pybullet") is None:
        out.append(("pybullet-default", "pybullet", {"config": "default"}))
        out.append(("pybullet-tuned", "pybullet", {"config": "tuned"}))
    if avail.get("siconos") is None:
        out.append(("siconos", "siconos", {}))
    return out


def ball_row(label, peer, kw, e, h):
    ref = ball_reference(e)
    try:
        t, q, u, res = run(peer, "bouncing_ball", e=e, h=h, T=T_BALL, **kw)
    except peers.PeerError as exc:
        return {"label": label, "e": e, "h": h, "error": str(exc)}
    z = q[:, 0]
    gaps, times = (x.tolist() for x in apexes(t, z - R, count=3, skip_t=0.5 * ref["t0"]))
    prev = [D0] + gaps[:-1]
    e_eff = [math.sqrt(a / b) for a, b in zip(gaps, prev)]
    rel = [(a - b) / b for a, b in zip(gaps, ref["apex_gap"])]
    return {
        "label": label, "peer": peer, "params": kw, "e": e, "h": h, "T": T_BALL,
        "apex_gap": gaps, "apex_time": times, "apex_gap_ref": ref["apex_gap"],
        "apex_time_ref": ref["apex_time"], "apex_rel_err": rel, "e_eff": e_eff,
        "max_penetration": float(max(0.0, R - z.min())), "final_gap": float(z[-1] - R),
        "t_inf_ref": ref["t_inf"], "cpu_seconds": res["cpu_seconds"],
        "cpu_per_sim_second": res["cpu_seconds"] / T_BALL, "version": res["version"],
        "settings": {k: v for k, v in res["settings"].items() if k != "xml"},
    }


def cradle_row(label, peer, kw, e, gap):
    scene = "newton_cradle_5" if gap == 0 else "newton_cradle_5_gapped"
    try:
        t, x, u, res = run(peer, scene, e=e, h=H_CRADLE, T=T_CRADLE, **kw, **CRADLE_PARAMS.get(peer, {}))
    except peers.PeerError as exc:
        return {"label": label, "e": e, "gap": gap, "error": str(exc)}
    v = u[-1]
    ref = cradle_simultaneous(e) if gap == 0 else cradle_sequential(e)
    return {
        "label": label, "peer": peer, "params": kw, "e": e, "gap": gap, "h": H_CRADLE,
        "T": T_CRADLE, "vx_final": v.tolist(), "ref": ref,
        "ref_kind": "simultaneous (Moreau)" if gap == 0 else "binary-impact sequence",
        "max_abs_err": float(np.max(np.abs(v - ref))),
        "momentum": float(v.sum()), "energy": float(0.5 * (v ** 2).sum()),
        "energy_ref": float(0.5 * np.sum(np.square(ref))),
        "max_overlap": float(max(0.0, -(np.diff(x, axis=1) - 2 * R).min())),
        "cpu_seconds": res["cpu_seconds"], "cpu_per_sim_second": res["cpu_seconds"] / T_CRADLE,
        "version": res["version"],
    }


def box_row(label, peer, kw, e=0.5, h=1e-3, T=1.5):
    try:
        t, q, u, res = run(peer, "box_drop", e=e, h=h, T=T, **kw)
    except peers.PeerError as exc:
        return {"label": label, "e": e, "h": h, "error": str(exc)}
    quat = np.c_[q[:, 6:7], q[:, 3:6]]  # Pinocchio's x y z w -> w x y z
    Rm = quat_to_mats(quat[-1:])[0]
    axis = int(np.argmax(np.abs(Rm[2, :])))  # body axis closest to vertical
    mz = min_corner_height(q[:, :3], quat, HALF)
    return {
        "label": label, "peer": peer, "params": kw, "e": e, "h": h, "T": T,
        "max_penetration": float(max(0.0, -mz.min())), "final_min_corner_z": float(mz[-1]),
        "final_z": float(q[-1, 2]), "rest_axis": "xyz"[axis],
        "rest_height": float(HALF[axis]),
        "final_speed": float(np.linalg.norm(u[-1, :3])),
        "cpu_seconds": res["cpu_seconds"], "cpu_per_sim_second": res["cpu_seconds"] / T,
        "version": res["version"],
    }


def _error_line(r):
    """A table row for a run that raised: label, e, h and the message, the other cells empty."""
    return [r["label"], f"{r['e']:g}", f"{r['h']:g}", "ERROR: " + r["error"][:60], "", "", "", "", ""]


def box_table(rows, md=False):
    head = ["peer/config", "e", "h", "max pen [mm]", "final centre z (rest height)",
            "axis up", "final min corner [mm]", "final speed", "CPU s/sim-s"]
    return _table(head, [_error_line(r) if "error" in r else [
        r["label"], f"{r['e']:g}", f"{r['h']:g}", f"{1000 * r['max_penetration']:.2f}",
        f"{r['final_z']:.4f} ({r['rest_height']:.1f})", r["rest_axis"], f"{1000 * r['final_min_corner_z']:+.2f}",
        f"{r['final_speed']:.3f}", f"{r['cpu_per_sim_second']:.4f}"] for r in rows], md)


def mujoco_scan():
    rows = []
    for wh in (0.05, 0.1, 0.2, 0.4):
        for e in ES:
            for h in HS:
                r = ball_row(f"mujoco omega_h={wh}", "mujoco", {"omega_h": wh}, e, h)
                r["omega_h"] = wh
                rows.append(r)
    return rows


# ----------------------------------------------------------------- formatting
def _f(x, fmt):
    return "—" if x is None else format(x, fmt)


def _list(xs, fmt, n=3):
    xs = list(xs) + [None] * (n - len(xs))
    return " ".join(_f(x, fmt) for x in xs[:n])


def ball_table(rows, md=False):
    head = ["peer/config", "e", "h", "apex gaps [m] (exact e^2n d0)", "rel err %",
            "e_eff 1..3", "max pen [mm]", "z(T)-r [mm]", "CPU s/sim-s"]
    return _table(head, [_error_line(r) if "error" in r else [
        r["label"], f"{r['e']:g}", f"{r['h']:g}",
        _list(r["apex_gap"], ".4f") + " (" + _list(r["apex_gap_ref"], ".4f") + ")",
        _list([100 * x for x in r["apex_rel_err"]], "+.2f"), _list(r["e_eff"], ".4f"),
        f"{1000 * r['max_penetration']:.2f}", f"{1000 * r['final_gap']:+.2f}", f"{r['cpu_per_sim_second']:.4f}"]
        for r in rows], md)


def cradle_table(rows, md=False):
    head = ["peer/config", "gap", "e", "final vx (balls 0..4)", "reference", "max abs err",
            "momentum", "energy (ref)", "max overlap [mm]", "CPU s/sim-s"]
    lines = []
    for r in rows:
        if "error" in r:
            lines.append([r["label"], f"{r['gap']:g}", f"{r['e']:g}", "ERROR: " + r["error"][:60],
                          "", "", "", "", "", ""])
            continue
        lines.append([
            r["label"], f"{r['gap']:g}", f"{r['e']:g}",
            " ".join(f"{v:+.3f}" for v in r["vx_final"]),
            " ".join(f"{v:+.3f}" for v in r["ref"]),
            f"{r['max_abs_err']:.3f}", f"{r['momentum']:.4f}",
            f"{r['energy']:.4f} ({r['energy_ref']:.4f})", f"{1000 * r['max_overlap']:.2f}",
            f"{r['cpu_per_sim_second']:.4f}",
        ])
    return _table(head, lines, md)


def _table(head, lines, md):
    if md:
        out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        out += ["| " + " | ".join(l) + " |" for l in lines]
        return "\n".join(out)
    w = [max(len(str(x)) for x in col) for col in zip(head, *lines)]
    fmt = "  ".join("{:<%d}" % k for k in w)
    return "\n".join([fmt.format(*head), fmt.format(*["-" * k for k in w])]
                     + [fmt.format(*l) for l in lines])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=None, help="save all measurements as JSON here")
    ap.add_argument("--md", default=None, help="also save the tables as Markdown here")
    ap.add_argument("--peers", default=None, help="comma list of labels to keep "
                    "(mujoco,pybullet-default,pybullet-tuned,siconos)")
    ap.add_argument("--mujoco-omega-scan", action="store_true",
                    help="also scan MuJoCo's stiffness choice omega_h = h sqrt(k)")
    a = ap.parse_args(argv)

    t_start = time.time()
    avail = peers.available()
    print("peers:", {k: ("ok" if v is None else v) for k, v in avail.items()})
    cfgs = configs(avail)
    if a.peers:
        keep = set(a.peers.split(","))
        cfgs = [c for c in cfgs if c[0] in keep]

    ball = [ball_row(lbl, peer, kw, e, h) for (lbl, peer, kw) in cfgs for e in ES for h in HS]
    cradle = [cradle_row(lbl, peer, kw, e, gap) for (lbl, peer, kw) in cfgs
              for gap in (0.0, 1e-3) for e in (1.0, 0.5)]
    box = [box_row(lbl, peer, kw) for (lbl, peer, kw) in cfgs]
    scan = mujoco_scan() if a.mujoco_omega_scan and avail.get("mujoco") is None else []
    versions = {}
    for r in ball + cradle:
        if "version" in r:
            versions[r["peer"]] = r["version"]

    print(f"\nversions: {versions}")
    print("\n== bouncing_ball: r = 0.1, d0 = 0.9 m, T = 3 s ==")
    print(ball_table(ball))
    print(f"\n== newton_cradle_5: v0 = 1, h = {H_CRADLE:g}, T = {T_CRADLE:g} s ==")
    print(cradle_table(cradle))
    print("\n== box_drop: 0.2 x 0.2 x 0.4 box, rpy (0.3, 0.2, 0), z0 = 0.6, T = 1.5 s ==")
    print(box_table(box))
    if scan:
        print("\n== MuJoCo stiffness scan (omega_h = h sqrt(k)) ==")
        print(ball_table(scan))
    wall = time.time() - t_start
    print(f"\nwall time {wall:.1f} s")

    if a.out:
        with open(a.out, "w") as f:
            json.dump(to_jsonable({"available": avail, "versions": versions, "ball": ball,
                                   "cradle": cradle, "box": box, "mujoco_scan": scan,
                                   "wall_seconds": wall}), f, indent=1)
        print(f"saved {a.out}")
    if a.md:
        with open(a.md, "w") as f:
            f.write(f"versions: {versions}\n\n### bouncing_ball\n\n{ball_table(ball, True)}\n\n"
                    f"### newton_cradle_5\n\n{cradle_table(cradle, True)}\n\n"
                    f"### box_drop\n\n{box_table(box, True)}\n")
            if scan:
                f.write(f"\n### MuJoCo omega_h scan\n\n{ball_table(scan, True)}\n")
        print(f"saved {a.md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
