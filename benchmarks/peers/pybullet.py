"""PyBullet runner of the neutral spec (benchmarks.spec).

PyBullet's restitution is per body and a contact multiplies the two values: every body and every
static gets sqrt(e), so that every pair's product is e (body-body and body-ground alike).
Friction (lateral, rolling, spinning) and damping (linear, angular, joint) are 0, sleeping is
off; a free body is a btMultiBody floating base (or a btRigidBody with maximal_coordinates=True),
a slide body a prismatic link on a fixed base; masses and principal inertias from the spec.

Two configurations (param `config`):
- "default": Bullet's defaults for everything else: restitutionVelocityThreshold 0.2 m/s
  (restitution zeroed below it), speculative contacts within contactBreakingThreshold 0.02 m,
  contact ERP (Baumgarte position correction, which adds energy), split impulse.
- "tuned": restitutionVelocityThreshold = 0, contactBreakingThreshold = 0, contactERP = erp =
  frictionERP = 0: clean bounces, but resting contact is lost (bodies drift into the floor since
  nothing corrects penetration).
Each engine parameter can be overridden individually (the keys of BULLET_DEFAULTS).
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..spec import merge_params, n_steps, quat_to_mats

DEFAULTS = {
    "config": "default",
    "restitution_velocity_threshold": None,  # None: the config's value, else Bullet's default
    "contact_breaking_threshold": None,
    "contact_erp": None,
    "erp": None,
    "friction_erp": None,
    "use_split_impulse": None,
    "split_impulse_penetration_threshold": None,
    "num_solver_iterations": None,
    "solver_residual_threshold": None,
    "contact_slop": None,
    "maximal_coordinates": False,  # free bodies as btRigidBody instead of btMultiBody
}

CONFIGS = {
    "default": {},  # leave Bullet's defaults untouched
    "tuned": {"restitution_velocity_threshold": 0.0, "contact_breaking_threshold": 0.0, "contact_erp": 0.0,
              "erp": 0.0, "friction_erp": 0.0},
}

# Bullet / PyBullet 3.2.x defaults (btContactSolverInfo, PhysicsServerCommandProcessor), reported
# in the settings: pybullet cannot read most of them back.
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
}

ENGINE_KEYS = {
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


def version() -> str:
    import importlib.metadata as md

    try:
        return md.version("pybullet")
    except md.PackageNotFoundError:
        import pybullet

        return f"api {pybullet.getAPIVersion()}"


def run(spec: dict, **params) -> dict:
    import pybullet as p

    P = merge_params("PyBullet", DEFAULTS, params)
    if P["config"] not in CONFIGS:
        raise ValueError(f"config must be one of {sorted(CONFIGS)}, got {P['config']!r}")
    e, h, T = float(spec["e"]), float(spec["h"]), float(spec["T"])
    if not 0.0 <= e <= 1.0:
        raise ValueError(f"restitution e={e} outside [0, 1]")
    eng = dict(CONFIGS[P["config"]])
    for k in ENGINE_KEYS:
        if P[k] is not None:
            eng[k] = P[k]
    # Bullet keeps contactBreakingThreshold in a process-global variable that survives
    # disconnect/connect: a "tuned" run would leak 0 into every later run. Always set it.
    eng.setdefault("contact_breaking_threshold", BULLET_DEFAULTS["contact_breaking_threshold"])
    se = math.sqrt(e)
    mc = bool(P["maximal_coordinates"])
    cid = p.connect(p.DIRECT)
    try:
        p.resetSimulation(physicsClientId=cid)
        p.setGravity(*spec["gravity"], physicsClientId=cid)
        kw = {ENGINE_KEYS[k]: v for k, v in eng.items()}
        for k in ("use_split_impulse", "num_solver_iterations"):
            if ENGINE_KEYS[k] in kw:
                kw[ENGINE_KEYS[k]] = int(kw[ENGINE_KEYS[k]])
        p.setPhysicsEngineParameter(fixedTimeStep=h, numSubSteps=0, physicsClientId=cid, **kw)

        def dyn(b, link):
            p.changeDynamics(b, link, restitution=se, lateralFriction=0.0, rollingFriction=0.0,
                             spinningFriction=0.0, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0,
                             physicsClientId=cid)
            if P["config"] == "tuned" or P["contact_breaking_threshold"] is not None:
                # the per-body speculative distance (contactProcessingThreshold) follows the global one
                p.changeDynamics(b, link, contactProcessingThreshold=eng["contact_breaking_threshold"],
                                 physicsClientId=cid)
            p.changeDynamics(b, link, activationState=p.ACTIVATION_STATE_DISABLE_SLEEPING, physicsClientId=cid)

        for s in spec["statics"]:
            if s["shape"] == "halfspace":
                n = np.asarray(s["normal"], float) / np.linalg.norm(s["normal"])
                col = p.createCollisionShape(p.GEOM_PLANE, planeNormal=list(n), physicsClientId=cid)
                sid = p.createMultiBody(0, col, -1, list(n * s["offset"]), physicsClientId=cid)
            else:
                col = p.createCollisionShape(p.GEOM_BOX, halfExtents=list(s["half_extents"]), physicsClientId=cid)
                q = s["quat"]
                sid = p.createMultiBody(0, col, -1, list(s["pos"]), [q[1], q[2], q[3], q[0]], physicsClientId=cid)
            dyn(sid, -1)
        ids = []
        for b in spec["bodies"]:
            col = (p.createCollisionShape(p.GEOM_SPHERE, radius=b["radius"], physicsClientId=cid)
                   if b["shape"] == "sphere" else
                   p.createCollisionShape(p.GEOM_BOX, halfExtents=list(b["half_extents"]), physicsClientId=cid))
            if b["joint"] == "free":
                q = b["quat"]
                bid = p.createMultiBody(b["mass"], col, -1, list(b["pos"]), [q[1], q[2], q[3], q[0]],
                                        useMaximalCoordinates=mc, physicsClientId=cid)
                p.changeDynamics(bid, -1, localInertiaDiagonal=list(b["inertia"]), physicsClientId=cid)
                R = quat_to_mats(np.asarray(q, float))[0]
                p.resetBaseVelocity(bid, list(b["v"]), list(R @ np.asarray(b["w"], float)), physicsClientId=cid)
                dyn(bid, -1)
            else:
                bid = p.createMultiBody(0, -1, -1, list(b["origin"]), linkMasses=[b["mass"]],
                                        linkCollisionShapeIndices=[col], linkVisualShapeIndices=[-1],
                                        linkPositions=[[0, 0, 0]], linkOrientations=[[0, 0, 0, 1]],
                                        linkInertialFramePositions=[[0, 0, 0]],
                                        linkInertialFrameOrientations=[[0, 0, 0, 1]], linkParentIndices=[0],
                                        linkJointTypes=[p.JOINT_PRISMATIC], linkJointAxis=[list(b["axis"])],
                                        physicsClientId=cid)
                p.changeDynamics(bid, 0, localInertiaDiagonal=list(b["inertia"]), physicsClientId=cid)
                p.setJointMotorControl2(bid, 0, p.VELOCITY_CONTROL, force=0, physicsClientId=cid)
                p.resetJointState(bid, 0, b["q0"], b["u0"], physicsClientId=cid)
                dyn(bid, 0)
            ids.append(bid)
        N = n_steps(h, T)
        rec = [dict(pos=np.empty((N + 1, 3)), quat=np.empty((N + 1, 4)), vel=np.empty((N + 1, 3)),
                    omega_world=np.empty((N + 1, 3))) if b["joint"] == "free" else
               dict(q=np.empty(N + 1), u=np.empty(N + 1)) for b in spec["bodies"]]

        def record(k):
            for b, bid, r in zip(spec["bodies"], ids, rec):
                if b["joint"] == "free":
                    pos, q = p.getBasePositionAndOrientation(bid, physicsClientId=cid)
                    v, w = p.getBaseVelocity(bid, physicsClientId=cid)
                    r["pos"][k], r["quat"][k] = pos, (q[3], q[0], q[1], q[2])
                    r["vel"][k], r["omega_world"][k] = v, w
                else:
                    js = p.getJointState(bid, 0, physicsClientId=cid)
                    r["q"][k], r["u"][k] = js[0], js[1]

        record(0)
        step = p.stepSimulation
        c0 = time.process_time()
        for k in range(1, N + 1):
            step(physicsClientId=cid)
            record(k)
        cpu = time.process_time() - c0
        readback = p.getPhysicsEngineParameters(physicsClientId=cid)
    finally:
        p.disconnect(physicsClientId=cid)
    sl = slice(None, None, max(1, int(spec.get("stride", 1))))
    effective = {**BULLET_DEFAULTS, **eng, "maximal_coordinates": mc}
    settings = {"config": P["config"], "fixedTimeStep": h, "numSubSteps": 0, "engine_parameters_set": kw,
                "effective_parameters": effective, "restitution_each_body_and_static": se, "pair_product": e,
                "friction": 0.0, "damping": 0.0, "sleeping": "disabled",
                "free_bodies": "btRigidBody (maximal coordinates)" if mc else "btMultiBody floating base",
                "slide_bodies": "prismatic link on a fixed base",
                "readback": {k: readback[k] for k in ("fixedTimeStep", "numSolverIterations", "numSubSteps")
                             if k in readback},
                "cpu_note": "loop includes one stepSimulation + state queries per step"}
    return {"peer": "pybullet", "scene": spec["name"], "t": (np.arange(N + 1) * h)[sl],
            "bodies": [{k: v[sl] for k, v in r.items()} for r in rec], "cpu_seconds": cpu, "settings": settings,
            "version": version()}
