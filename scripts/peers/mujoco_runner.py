#!/usr/bin/env python3
"""MuJoCo runner for the moreau-sim impact scenes.

MuJoCo has no restitution coefficient: every contact is a soft spring-damper. With the
direct solref format solref="-k -b" and a constant impedance d (solimp dmin = dmax) the
normal motion inside a contact is  r'' = -k r - b r' - (1 - d) g  (shared/notes/peers.md), so
the restitution depends only on zeta = b / (2 sqrt k). We invert the Schwager & Poschel (2007)
map for a force-clamped linear dashpot,
    e = exp(-x (pi - atan2(2x, 1 - x^2))),   x = zeta / sqrt(1 - zeta^2),
which is the fair one (the textbook zeta = -ln e / sqrt(pi^2 + ln^2 e) ignores that the
contact ends when the force reaches zero, not when r does: asked 0.8, it gives ~0.807).

Stiffness: MuJoCo integrates the spring explicitly inside its step, so the contact
frequency omega = sqrt(k) must satisfy h*omega << 1 (peers.md: bodies are launched once
h*omega > 2); the penetration is ~ v_in / omega. We tie the stiffness to the step:
omega = omega_h / h (default omega_h = 0.2, i.e. ~16 steps per contact half-period).
Pass k=... to fix the stiffness instead.

Usage:  python scripts/peers/mujoco_runner.py bouncing_ball --e 0.8 --h 1e-3 --T 3
"""
from __future__ import annotations

import math
import sys
import time

import numpy as np

try:
    from . import _common as C
except ImportError:  # run as a script
    import _common as C

PEER = "mujoco"

PEER_DEFAULTS = {
    "omega_h": 0.2,          # sqrt(k) * h
    "k": None,               # explicit stiffness [1/s^2]; overrides omega_h
    "damping_map": "schwager_poschel",  # or "textbook"
    "impedance": 0.95,       # solimp dmin = dmax (constant impedance d); MuJoCo default dmax
    "solimp": None,          # full solimp list, overrides `impedance` (e.g. MuJoCo default
                             # [0.9, 0.95, 0.001, 0.5, 2])
    "integrator": "Euler",   # MuJoCo default
    "solver": "Newton",
    "iterations": 100,
    "tolerance": 1e-10,
    "use_rollout": True,     # mujoco.rollout (C loop) instead of a Python mj_step loop
}


# ------------------------------------------------------------- damping maps
def e_of_zeta(zeta: float) -> float:
    """Restitution of a force-clamped linear spring-dashpot contact (Schwager & Poschel)."""
    if zeta <= 0:
        return 1.0
    if zeta < 1:
        x = zeta / math.sqrt(1 - zeta * zeta)
        return math.exp(-x * (math.pi - math.atan2(2 * x, 1 - x * x)))
    # critically/over-damped: delta(0)=0, delta'(0)=1, k=1, b=2 zeta; the contact ends when
    # the force delta + b delta' reaches 0; e = -delta'(t_end).
    b = 2 * zeta
    if zeta == 1:
        def dd(t):
            return t * math.exp(-t), (1 - t) * math.exp(-t)
    else:
        s = math.sqrt(zeta * zeta - 1)
        lp, lm = -zeta + s, -zeta - s

        def dd(t):
            return ((math.exp(lp * t) - math.exp(lm * t)) / (lp - lm),
                    (lp * math.exp(lp * t) - lm * math.exp(lm * t)) / (lp - lm))
    lo, hi = 0.0, 1.0
    while True:  # bracket the zero of the force
        d, v = dd(hi)
        if d + b * v <= 0:
            break
        lo, hi = hi, 2 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        d, v = dd(mid)
        if d + b * v > 0:
            lo = mid
        else:
            hi = mid
    return -dd(hi)[1]


def zeta_for_e(e: float, damping_map: str = "schwager_poschel") -> float:
    if not 0.0 <= e <= 1.0:
        raise ValueError(f"restitution e={e} outside [0, 1]")
    if e == 1.0:
        return 0.0
    if damping_map == "textbook":
        if e == 0.0:
            return 1.0
        le = math.log(e)
        return -le / math.sqrt(math.pi ** 2 + le * le)
    if damping_map != "schwager_poschel":
        raise ValueError(f"damping_map must be 'schwager_poschel' or 'textbook', got {damping_map!r}")
    if e == 0.0:
        raise ValueError("a linear spring-dashpot cannot give e = 0 exactly (zeta -> infinity)")
    lo, hi = 0.0, 1.0
    while e_of_zeta(hi) > e:
        hi *= 2
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if e_of_zeta(mid) > e:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


# ------------------------------------------------------------- models
def _contact_settings(e, h, P):
    omega = math.sqrt(P["k"]) if P["k"] is not None else P["omega_h"] / h
    k = omega * omega
    zeta = zeta_for_e(e, P["damping_map"])
    b = 2 * zeta * omega
    if P["solimp"] is not None:
        solimp = [float(x) for x in P["solimp"]]
    else:
        d = float(P["impedance"])
        solimp = [d, d, 0.001, 0.5, 2.0]
    return {
        "k": k, "b": b, "zeta": zeta, "omega": omega, "h_omega": h * omega,
        "solref": [-k, -b], "solimp": solimp,
        "expected_e_continuous": e_of_zeta(zeta),
    }


def _xml(scene, e, h, P, cs):
    solref = f"{-cs['k']:.17g} {-cs['b']:.17g}"
    solimp = " ".join(f"{x:.17g}" for x in cs["solimp"])
    g = P.get("g", 0.0)
    opt = (f'<option timestep="{h:.17g}" gravity="0 0 {-g:.17g}" integrator="{P["integrator"]}" '
           f'solver="{P["solver"]}" iterations="{int(P["iterations"])}" '
           f'tolerance="{P["tolerance"]:.17g}"/>')
    # condim=1: frictionless normal contact; margin/gap 0: contact exactly at touching.
    dflt = (f'<default><geom condim="1" solref="{solref}" solimp="{solimp}" margin="0" '
            f'gap="0"/></default>')
    if scene == "bouncing_ball":
        body = (f'<geom name="ground" type="plane" size="0 0 1"/>'
                f'<body name="ball" pos="0 0 {P["z0"]:.17g}"><freejoint/>'
                f'<geom type="sphere" size="{P["r"]:.17g}" mass="{P["m"]:.17g}"/></body>')
    elif scene == "newton_cradle_5":
        parts = []
        for i in range(int(P["n"])):
            x = i * (2 * P["r"] + P["gap"])
            parts.append(f'<body name="b{i}" pos="{x:.17g} 0 0"><joint type="slide" axis="1 0 0"/>'
                         f'<geom type="sphere" size="{P["r"]:.17g}" mass="{P["m"]:.17g}"/></body>')
        body = "".join(parts)
    elif scene == "box_drop":
        q = C.rpy_to_quat(P["rpy"])
        hx, hy, hz = P["half_extents"]
        body = (f'<geom name="ground" type="plane" size="0 0 1"/>'
                f'<body name="box" pos="0 0 {P["z0"]:.17g}" quat="{q[0]:.17g} {q[1]:.17g} {q[2]:.17g} {q[3]:.17g}">'
                f'<freejoint/><geom type="box" size="{hx:.17g} {hy:.17g} {hz:.17g}" '
                f'mass="{P["m"]:.17g}"/></body>')
    else:
        raise ValueError(scene)
    return f"<mujoco>{opt}{dflt}<worldbody>{body}</worldbody></mujoco>"


def run(scene: str, *, e: float, h: float, T: float, **params) -> dict:
    import mujoco

    P = C.merge_params(scene, PEER_DEFAULTS, params)
    if scene == "newton_cradle_5":
        P["g"] = 0.0
    cs = _contact_settings(e, h, P)
    xml = _xml(scene, e, h, P, cs)
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    if scene == "newton_cradle_5":
        data.qvel[0] = P["v0"]  # ball 0 moves toward the others
    mujoco.mj_forward(model, data)
    N = C.n_steps(h, T)
    nq, nv = model.nq, model.nv
    stride = max(1, int(P["stride"]))
    q0, v0 = data.qpos.copy(), data.qvel.copy()

    if P["use_rollout"]:
        from mujoco import rollout

        spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        nstate = mujoco.mj_stateSize(model, spec)
        init = np.empty(nstate)
        mujoco.mj_getState(model, data, init, spec)
        out = np.empty((1, N, nstate))
        # warm-up on a tiny horizon so that one-time initialisation is not timed
        rollout.rollout(model, data, init[None], nstep=1)
        c0 = time.process_time()
        rollout.rollout(model, data, init[None], nstep=N, state=out)
        cpu = time.process_time() - c0
        # FULLPHYSICS state layout starts with time, qpos, qvel
        traj = out[0]
        qpos = np.vstack([q0[None], traj[:, 1:1 + nq]])
        qvel = np.vstack([v0[None], traj[:, 1 + nq:1 + nq + nv]])
        tt = np.concatenate([[0.0], traj[:, 0]])
    else:
        qpos = np.empty((N + 1, nq))
        qvel = np.empty((N + 1, nv))
        qpos[0] = data.qpos
        qvel[0] = data.qvel
        step = mujoco.mj_step
        c0 = time.process_time()
        for k in range(1, N + 1):
            step(model, data)
            qpos[k] = data.qpos
            qvel[k] = data.qvel
        cpu = time.process_time() - c0
        tt = np.arange(N + 1) * h

    sl = slice(None, None, stride)
    settings = {
        "timestep": h, "integrator": P["integrator"], "solver": P["solver"],
        "iterations": int(P["iterations"]), "tolerance": P["tolerance"],
        "contact_model": "soft spring-damper, solref direct format -k -b",
        "damping_map": P["damping_map"], "omega_h": cs["h_omega"],
        "stiffness_k": cs["k"], "damping_b": cs["b"], "zeta": cs["zeta"],
        "solref": cs["solref"], "solimp": cs["solimp"], "condim": 1, "margin": 0.0,
        "penetration_estimate_per_mps": 1.0 / cs["omega"],
        "loop": "mujoco.rollout" if P["use_rollout"] else "python mj_step loop",
        "xml": xml,
    }
    settings.update({k: P[k] for k in C.SCENE_DEFAULTS[scene]})
    res = {"peer": PEER, "scene": scene, "e": e, "h": h, "T": T, "settings": settings,
           "t": tt[sl], "cpu_seconds": cpu, "version": mujoco.__version__}
    if scene == "bouncing_ball":
        res["z"] = qpos[sl, 2]
        res["vz"] = qvel[sl, 2]
    elif scene == "newton_cradle_5":
        x0 = np.array([i * (2 * P["r"] + P["gap"]) for i in range(int(P["n"]))])
        res["x"] = qpos[sl] + x0
        res["vx"] = qvel[sl]
        res["vx_final"] = qvel[-1].copy()
    else:
        pos = qpos[:, 0:3]
        quat = qpos[:, 3:7]
        res["pos"] = pos[sl]
        res["quat"] = quat[sl]  # (w, x, y, z)
        res["vel"] = qvel[sl, 0:3]
        res["min_corner_z"] = C.min_corner_height(pos, quat, P["half_extents"])[sl]
    return res


def version():
    import mujoco
    return mujoco.__version__


if __name__ == "__main__":
    sys.exit(C.cli(PEER, run))
