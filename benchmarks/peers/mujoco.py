"""MuJoCo runner of the neutral spec (benchmarks.spec).

MuJoCo has no restitution coefficient: every contact is a soft spring-damper. With the direct
solref format solref="-k -b" and a constant impedance d (solimp dmin = dmax) the normal motion
inside a contact is r'' = -k r - b r' - (1 - d) g, so the restitution depends only on
zeta = b / (2 sqrt k). We invert the Schwager & Poschel (2007) map for a force-clamped linear
dashpot, e = exp(-x (pi - atan2(2x, 1 - x^2))), x = zeta / sqrt(1 - zeta^2) (the textbook
zeta = -ln e / sqrt(pi^2 + ln^2 e) ignores that the contact ends when the force reaches zero, not
when r does: asked 0.8, it gives ~0.807).

Stiffness: MuJoCo integrates the spring explicitly inside its step, so the contact frequency
omega = sqrt(k) must satisfy h omega << 1 (bodies are launched once h omega > 2); the penetration
is ~ v_in / omega. The stiffness is tied to the step: omega = omega_h / h (default omega_h = 0.2,
~16 steps per contact half-period); pass k=... to fix it instead. condim = 1 (frictionless),
margin = gap = 0; each body's mass and principal inertia from the spec (<inertial>).
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..spec import merge_params, n_steps, quat_to_mats, z_to

DEFAULTS = {
    "omega_h": 0.2,  # sqrt(k) * h
    "k": None,  # explicit stiffness [1/s^2]; overrides omega_h
    "damping_map": "schwager_poschel",  # or "textbook"
    "impedance": 0.95,  # solimp dmin = dmax (constant impedance d); MuJoCo's default dmax
    "solimp": None,  # full solimp list, overrides `impedance` (MuJoCo default [0.9, 0.95, 0.001, 0.5, 2])
    "integrator": "Euler",  # MuJoCo's default
    "solver": "Newton",
    "iterations": 100,
    "tolerance": 1e-10,
    "use_rollout": True,  # mujoco.rollout (a C loop) instead of a Python mj_step loop
    # > 0: also time the steps (`timing` in the result): the whole run by mujoco.rollout, and a Python
    # mj_step loop with a timer around each step, each that many times; the best of them per step
    "timing_repeats": 0,
}


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


def contact_settings(e: float, h: float, P: dict) -> dict:
    omega = math.sqrt(P["k"]) if P["k"] is not None else P["omega_h"] / h
    k = omega * omega
    zeta = zeta_for_e(e, P["damping_map"])
    if P["solimp"] is not None:
        solimp = [float(x) for x in P["solimp"]]
    else:
        d = float(P["impedance"])
        solimp = [d, d, 0.001, 0.5, 2.0]
    return {"k": k, "b": 2 * zeta * omega, "zeta": zeta, "omega": omega, "h_omega": h * omega,
            "solimp": solimp, "expected_e_continuous": e_of_zeta(zeta)}


def xml(spec: dict, P: dict, cs: dict) -> str:
    """The MJCF of `spec` with the contact settings `cs`."""
    h = float(spec["h"])
    f = lambda v: " ".join(f"{float(x):.17g}" for x in v)  # noqa: E731
    parts = [f'<mujoco><option timestep="{h:.17g}" gravity="{f(spec["gravity"])}" integrator="{P["integrator"]}" '
             f'solver="{P["solver"]}" iterations="{int(P["iterations"])}" tolerance="{P["tolerance"]:.17g}"/>',
             f'<default><geom condim="1" solref="{-cs["k"]:.17g} {-cs["b"]:.17g}" solimp="{f(cs["solimp"])}" '
             f'margin="0" gap="0"/></default><worldbody>']
    for k, s in enumerate(spec["statics"]):
        if s["shape"] == "halfspace":
            n = np.asarray(s["normal"], float) / np.linalg.norm(s["normal"])
            parts.append(f'<geom name="s{k}" type="plane" size="0 0 1" pos="{f(n * s["offset"])}" quat="{f(z_to(n))}"/>')
        else:
            parts.append(f'<geom name="s{k}" type="box" size="{f(s["half_extents"])}" pos="{f(s["pos"])}" '
                         f'quat="{f(s["quat"])}"/>')
    for i, b in enumerate(spec["bodies"]):
        geom = (f'<geom type="sphere" size="{b["radius"]:.17g}"/>' if b["shape"] == "sphere"
                else f'<geom type="box" size="{f(b["half_extents"])}"/>')
        inertial = f'<inertial pos="0 0 0" mass="{b["mass"]:.17g}" diaginertia="{f(b["inertia"])}"/>'
        if b["joint"] == "free":
            parts.append(f'<body name="b{i}" pos="{f(b["pos"])}" quat="{f(b["quat"])}"><freejoint/>{inertial}{geom}</body>')
        else:
            parts.append(f'<body name="b{i}" pos="{f(b["origin"])}"><joint type="slide" axis="{f(b["axis"])}"/>'
                         f'{inertial}{geom}</body>')
    parts.append("</worldbody></mujoco>")
    return "".join(parts)


def run(spec: dict, **params) -> dict:
    import mujoco

    P = merge_params("MuJoCo", DEFAULTS, params)
    e, h, T = float(spec["e"]), float(spec["h"]), float(spec["T"])
    cs = contact_settings(e, h, P)
    mjcf = xml(spec, P, cs)
    model = mujoco.MjModel.from_xml_string(mjcf)
    data = mujoco.MjData(model)
    adr = _initial_state(spec, model, data)
    N = n_steps(h, T)
    nq, nv = model.nq, model.nv
    if P["use_rollout"]:
        qpos, qvel, cpu = _rollout(model, data, N)
    else:
        qpos, qvel = np.empty((N + 1, nq)), np.empty((N + 1, nv))
        qpos[0], qvel[0] = data.qpos, data.qvel
        step = mujoco.mj_step
        c0 = time.process_time()
        for k in range(1, N + 1):
            step(model, data)
            qpos[k], qvel[k] = data.qpos, data.qvel
        cpu = time.process_time() - c0
    sl = slice(None, None, max(1, int(spec.get("stride", 1))))
    bodies = []
    for b, (qa, va) in zip(spec["bodies"], adr):
        if b["joint"] == "free":
            quat = qpos[:, qa + 3:qa + 7]
            wb = qvel[:, va + 3:va + 6]
            bodies.append({"pos": qpos[sl, qa:qa + 3], "quat": quat[sl], "vel": qvel[sl, va:va + 3],
                           "omega_world": np.einsum("nij,nj->ni", quat_to_mats(quat), wb)[sl]})
        else:
            bodies.append({"q": qpos[sl, qa], "u": qvel[sl, va]})
    settings = {"timestep": h, "contact_model": "soft spring-damper, solref direct format -k -b",
                "damping_map": P["damping_map"], "omega_h": cs["h_omega"], "stiffness_k": cs["k"],
                "damping_b": cs["b"], "zeta": cs["zeta"], "solref": [-cs["k"], -cs["b"]], "solimp": cs["solimp"],
                "expected_e_continuous": cs["expected_e_continuous"], "integrator": P["integrator"],
                "solver": P["solver"], "iterations": int(P["iterations"]), "tolerance": P["tolerance"], "condim": 1,
                "margin": 0.0, "penetration_estimate_per_mps": 1.0 / cs["omega"],
                "loop": "mujoco.rollout" if P["use_rollout"] else "python mj_step loop", "xml": mjcf}
    res = {"peer": "mujoco", "scene": spec["name"], "t": (np.arange(N + 1) * h)[sl], "bodies": bodies,
           "cpu_seconds": cpu, "settings": settings, "version": mujoco.__version__}
    if int(P["timing_repeats"]) > 0:
        res["timing"] = _timed(spec, model, data, N, int(P["timing_repeats"]))
    return res


def _initial_state(spec, model, data) -> list:
    """Set the spec's initial state in `data` (forward kinematics done); each body's (qpos, qvel) address."""
    import mujoco

    adr = []
    for i, b in enumerate(spec["bodies"]):
        j = model.body_jntadr[i + 1]
        qa, va = model.jnt_qposadr[j], model.jnt_dofadr[j]
        adr.append((qa, va))
        if b["joint"] == "free":
            data.qvel[va:va + 3] = b["v"]
            data.qvel[va + 3:va + 6] = b["w"]  # a free joint's angular velocity is in the body frame
        else:
            data.qpos[qa] = b["q0"]
            data.qvel[va] = b["u0"]
    mujoco.mj_forward(model, data)
    return adr


def _rollout(model, data, N):
    """N steps from `data`'s state by mujoco.rollout (a C loop): qpos, qvel (N + 1 rows), CPU seconds."""
    import mujoco
    from mujoco import rollout

    nq, nv = model.nq, model.nv
    kind = mujoco.mjtState.mjSTATE_FULLPHYSICS
    init = np.empty(mujoco.mj_stateSize(model, kind))
    mujoco.mj_getState(model, data, init, kind)
    rollout.rollout(model, data, init[None], nstep=1)  # warm-up: one-time initialisation is not timed
    out = np.empty((1, N, len(init)))
    c0 = time.process_time()
    rollout.rollout(model, data, init[None], nstep=N, state=out)
    cpu = time.process_time() - c0
    # the FULLPHYSICS state starts with time, qpos, qvel
    qpos = np.vstack([init[1:1 + nq][None], out[0, :, 1:1 + nq]])
    qvel = np.vstack([init[1 + nq:1 + nq + nv][None], out[0, :, 1 + nq:1 + nq + nv]])
    return qpos, qvel, cpu


def _timed(spec, model, data, N, repeats) -> dict:
    """The whole run's wall time by mujoco.rollout (best of `repeats`, s), and per step the best of
    `repeats` Python mj_step loops (us) with the number of contacts mj_step found at its start."""
    import mujoco
    from mujoco import rollout

    kind = mujoco.mjtState.mjSTATE_FULLPHYSICS
    mujoco.mj_resetData(model, data)
    _initial_state(spec, model, data)
    init = np.empty(mujoco.mj_stateSize(model, kind))
    mujoco.mj_getState(model, data, init, kind)
    out = np.empty((1, N, len(init)))
    walls = []
    for _ in range(repeats + 1):  # the first: warm-up
        w0 = time.perf_counter()
        rollout.rollout(model, data, init[None], nstep=N, state=out)
        walls.append(time.perf_counter() - w0)
    best, ncon = np.full(N, np.inf), np.zeros(N, dtype=np.int64)
    step, clock = mujoco.mj_step, time.perf_counter
    for _ in range(repeats):
        mujoco.mj_resetData(model, data)
        _initial_state(spec, model, data)
        us = np.empty(N)
        for k in range(N):
            t0 = clock()
            step(model, data)
            us[k] = clock() - t0
            ncon[k] = data.ncon  # the contacts of this step's collision (at the state it started from)
        best = np.minimum(best, us * 1e6)
    return {"repeats": repeats, "wall_seconds": min(walls[1:]), "step_us": best, "contacts": ncon,
            "timer": "whole run: mujoco.rollout; per step: time.perf_counter around mj_step in a Python loop"}
