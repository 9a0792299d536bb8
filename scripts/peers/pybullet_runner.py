#!/usr/bin/env python3
"""PyBullet runner for the moreau-sim impact scenes.

PyBullet's restitution is per body and the two values of a contact pair are multiplied
(shared/notes/peers.md): the ground gets 1 and the body e; cradle balls get sqrt(e) each.
Default linear/angular damping (0.04) is switched off; friction is 0 (lateral, rolling,
spinning) for the frictionless scenes.

Two configurations (param `config`):
- "default": Bullet's defaults for everything else: restitutionVelocityThreshold 0.2 m/s
  (restitution zeroed below it), speculative contacts within contactBreakingThreshold
  0.02 m, contact ERP (Baumgarte position correction, which adds energy), split impulse.
- "tuned": restitutionVelocityThreshold = 0, contactBreakingThreshold = 0, contactERP = 0
  and erp = 0 (peers.md: gives clean bounces, but loses resting contact: bodies then drift
  into the floor since nothing corrects penetration).
Each of these can be overridden individually (restitution_velocity_threshold,
contact_breaking_threshold, contact_erp, erp, use_split_impulse, num_solver_iterations,
contact_slop, maximal_coordinates).

Usage:  python scripts/peers/pybullet_runner.py bouncing_ball --e 0.8 --h 1e-3 --T 3 --param config=tuned
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

PEER = "pybullet"

PEER_DEFAULTS = {
    "config": "default",
    "restitution_velocity_threshold": None,
    "contact_breaking_threshold": None,
    "contact_erp": None,
    "erp": None,
    "friction_erp": None,
    "use_split_impulse": None,
    "split_impulse_penetration_threshold": None,
    "num_solver_iterations": None,
    "solver_residual_threshold": None,
    "contact_slop": None,
    "maximal_coordinates": False,
}

CONFIGS = {
    # None = leave Bullet's default untouched (the value read back is reported)
    "default": {},
    "tuned": {
        "restitution_velocity_threshold": 0.0,
        "contact_breaking_threshold": 0.0,
        "contact_erp": 0.0,
        "erp": 0.0,
        "friction_erp": 0.0,
    },
}

# Bullet / PyBullet 3.2.x defaults (btContactSolverInfo and PhysicsServerCommandProcessor),
# reported so the benchmark can print them; pybullet cannot read most of them back.
BULLET_DEFAULTS = {
    "restitution_velocity_threshold": 0.2,
    "contact_breaking_threshold": 0.02,
    "contact_erp": 0.2,
    "erp": 0.2,
    "friction_erp": 0.2,
    "use_split_impulse": 1,
    "split_impulse_penetration_threshold": -0.04,
    "num_solver_iterations": 50,
    "solver_residual_threshold": 1e-7,
    "contact_slop": 1e-5,
    "maximal_coordinates": False,
}

_ENGINE_KEYS = {
    "restitution_velocity_threshold": "restitutionVelocityThreshold",
    "contact_breaking_threshold": "contactBreakingThreshold",
    "contact_erp": "contactERP",
    "erp": "erp",
    "friction_erp": "frictionERP",
    "use_split_impulse": "useSplitImpulse",
    "split_impulse_penetration_threshold": "splitImpulsePenetrationThreshold",
    "num_solver_iterations": "numSolverIterations",
    "solver_residual_threshold": "solverResidualThreshold",
    "contact_slop": "contactSlop",
}


def _import_pybullet():
    """pybullet prints its build-time banner on stderr at import (harmless)."""
    import pybullet

    return pybullet


def version():
    import importlib.metadata as md
    try:
        return md.version("pybullet")
    except md.PackageNotFoundError:
        p = _import_pybullet()
        return f"api {p.getAPIVersion()}"


def run(scene: str, *, e: float, h: float, T: float, **params) -> dict:
    p = _import_pybullet()
    P = C.merge_params(scene, PEER_DEFAULTS, params)
    if P["config"] not in CONFIGS:
        raise ValueError(f"config must be one of {sorted(CONFIGS)}, got {P['config']!r}")
    if not 0.0 <= e <= 1.0:
        raise ValueError(f"restitution e={e} outside [0, 1]")
    eng = dict(CONFIGS[P["config"]])
    for k in _ENGINE_KEYS:
        if P[k] is not None:
            eng[k] = P[k]
    # Bullet keeps contactBreakingThreshold in a process-global variable
    # (gContactBreakingThreshold) that survives disconnect/connect: a "tuned" run would leak
    # 0 into every later run of this process. Always set it explicitly.
    eng.setdefault("contact_breaking_threshold", BULLET_DEFAULTS["contact_breaking_threshold"])
    effective = dict(BULLET_DEFAULTS)
    effective.update(eng)
    effective["maximal_coordinates"] = bool(P["maximal_coordinates"])

    cid = p.connect(p.DIRECT)
    try:
        return _run(p, cid, scene, e, h, T, P, eng, effective)
    finally:
        p.disconnect(physicsClientId=cid)


def _run(p, cid, scene, e, h, T, P, eng, effective):
    g = 0.0 if scene == "newton_cradle_5" else P["g"]
    p.resetSimulation(physicsClientId=cid)
    p.setGravity(0, 0, -g, physicsClientId=cid)
    kw = {_ENGINE_KEYS[k]: v for k, v in eng.items()}
    for k in ("use_split_impulse", "num_solver_iterations"):
        if _ENGINE_KEYS[k] in kw:
            kw[_ENGINE_KEYS[k]] = int(kw[_ENGINE_KEYS[k]])
    p.setPhysicsEngineParameter(fixedTimeStep=h, numSubSteps=0, physicsClientId=cid, **kw)
    mc = bool(P["maximal_coordinates"])

    def body_dyn(b, rest):
        p.changeDynamics(b, -1, restitution=rest, lateralFriction=0.0, rollingFriction=0.0,
                         spinningFriction=0.0, linearDamping=0.0, angularDamping=0.0,
                         physicsClientId=cid)
        if P["config"] == "tuned" or P["contact_breaking_threshold"] is not None:
            # per-body speculative distance (contactProcessingThreshold) follows the global one
            p.changeDynamics(b, -1, contactProcessingThreshold=eng["contact_breaking_threshold"],
                             physicsClientId=cid)
        # keep bodies awake: no sleeping/deactivation in a benchmark
        p.changeDynamics(b, -1, activationState=p.ACTIVATION_STATE_DISABLE_SLEEPING,
                         physicsClientId=cid)

    def ground():
        col = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=cid)
        gid = p.createMultiBody(0, col, -1, [0, 0, 0], physicsClientId=cid)
        body_dyn(gid, 1.0)
        return gid

    bodies = []
    if scene == "bouncing_ball":
        ground()
        col = p.createCollisionShape(p.GEOM_SPHERE, radius=P["r"], physicsClientId=cid)
        b = p.createMultiBody(P["m"], col, -1, [0, 0, P["z0"]], useMaximalCoordinates=mc,
                              physicsClientId=cid)
        body_dyn(b, e)
        bodies = [b]
        restitutions = {"ground": 1.0, "ball": e, "pair_product": e}
    elif scene == "newton_cradle_5":
        n = int(P["n"])
        col = p.createCollisionShape(p.GEOM_SPHERE, radius=P["r"], physicsClientId=cid)
        se = math.sqrt(e)
        for i in range(n):
            b = p.createMultiBody(P["m"], col, -1, [i * (2 * P["r"] + P["gap"]), 0, 0],
                                  useMaximalCoordinates=mc, physicsClientId=cid)
            body_dyn(b, se)
            bodies.append(b)
        p.resetBaseVelocity(bodies[0], [P["v0"], 0, 0], [0, 0, 0], physicsClientId=cid)
        restitutions = {"ball": se, "pair_product": se * se}
    elif scene == "box_drop":
        ground()
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=list(P["half_extents"]),
                                     physicsClientId=cid)
        q = C.rpy_to_quat(P["rpy"])  # wxyz
        b = p.createMultiBody(P["m"], col, -1, [0, 0, P["z0"]], [q[1], q[2], q[3], q[0]],
                              useMaximalCoordinates=mc, physicsClientId=cid)
        body_dyn(b, e)
        bodies = [b]
        restitutions = {"ground": 1.0, "box": e, "pair_product": e}
    else:
        raise ValueError(scene)

    N = C.n_steps(h, T)
    nb = len(bodies)
    pos = np.empty((N + 1, nb, 3))
    orn = np.empty((N + 1, nb, 4))
    lin = np.empty((N + 1, nb, 3))
    getpo = p.getBasePositionAndOrientation
    getv = p.getBaseVelocity
    step = p.stepSimulation
    for j, b in enumerate(bodies):
        pp, oo = getpo(b, physicsClientId=cid)
        pos[0, j], orn[0, j] = pp, oo
        lin[0, j] = getv(b, physicsClientId=cid)[0]
    c0 = time.process_time()
    for k in range(1, N + 1):
        step(physicsClientId=cid)
        for j, b in enumerate(bodies):
            pp, oo = getpo(b, physicsClientId=cid)
            pos[k, j] = pp
            orn[k, j] = oo
            lin[k, j] = getv(b, physicsClientId=cid)[0]
    cpu = time.process_time() - c0

    readback = p.getPhysicsEngineParameters(physicsClientId=cid)
    stride = max(1, int(P["stride"]))
    sl = slice(None, None, stride)
    settings = {
        "config": P["config"], "fixedTimeStep": h, "numSubSteps": 0,
        "engine_parameters_set": kw, "effective_parameters": effective,
        "restitution": restitutions, "friction": 0.0, "linear_damping": 0.0,
        "angular_damping": 0.0, "sleeping": "disabled",
        "body_type": "btRigidBody (maximal coordinates)" if mc else "btMultiBody floating base",
        "readback": {k: readback[k] for k in ("fixedTimeStep", "numSolverIterations", "numSubSteps")
                     if k in readback},
        "cpu_note": "loop includes one stepSimulation + state queries per step",
    }
    settings.update({k: P[k] for k in C.SCENE_DEFAULTS[scene]})
    res = {"peer": PEER, "scene": scene, "e": e, "h": h, "T": T, "settings": settings,
           "t": (np.arange(N + 1) * h)[sl], "cpu_seconds": cpu, "version": version()}
    if scene == "bouncing_ball":
        res["z"] = pos[sl, 0, 2]
        res["vz"] = lin[sl, 0, 2]
    elif scene == "newton_cradle_5":
        res["x"] = pos[sl, :, 0]
        res["vx"] = lin[sl, :, 0]
        res["vx_final"] = lin[-1, :, 0].copy()
    else:
        quat = orn[:, 0][:, [3, 0, 1, 2]]  # xyzw -> wxyz
        res["pos"] = pos[sl, 0]
        res["quat"] = quat[sl]
        res["vel"] = lin[sl, 0]
        res["min_corner_z"] = C.min_corner_height(pos[:, 0], quat, P["half_extents"])[sl]
    return res


if __name__ == "__main__":
    sys.exit(C.cli(PEER, run))
