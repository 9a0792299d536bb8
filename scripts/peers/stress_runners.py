#!/usr/bin/env python3
"""Peer runners for the stress scenes (issue 5), built from a neutral scene *spec*.

The spec (a JSON-able dict, made from a moreau-sim scene by scripts/peers/stress_spec.py) holds
rigid bodies that are spheres or boxes on a free joint or on one prismatic ("slide") joint, and
static half-spaces and boxes - enough for zeno_ball, resting_box, the box stacks, heavy_on_light,
fast_impact, spinning_box, the bead columns and the cradles (not the slider-crank: a chain).

    spec = {"name", "e", "h", "T", "gravity": [3], "stride": k,
            "bodies": [{"name", "shape": "sphere" | "box", "radius" | "half_extents": [3],
                        "mass", "inertia": [3] (principal, body frame),
                        "joint": "free", "pos": [3], "quat": [w x y z], "v": [3] (world),
                                 "w": [3] (body frame)
                        | "joint": "slide", "axis": [3] (unit), "origin": [3], "q0", "u0"}],
            "statics": [{"name", "shape": "halfspace", "normal": [3], "offset"}
                        | {"name", "shape": "box", "half_extents": [3], "pos": [3], "quat": [w x y z]}],
            "pairs": [[a, b]]: colliding pairs, a a body index, b a body index or "s<k>" (static k)}

Result: {"peer", "scene", "t", "bodies": [free: {"pos", "quat" (w x y z), "vel", "omega_world"} |
slide: {"q", "u"}], "cpu_seconds", "settings", "version"}.

Settings follow the peers' own runners (shared/notes/peers.md): MuJoCo's contact model and
stiffness rule come from mujoco_runner (solref -k -b, omega_h = 0.2, Schwager-Poschel damping);
PyBullet's configs "default" / "tuned" from pybullet_runner, with every body and static given
restitution sqrt(e) so that every pair's product is e (the runner's ground-1/body-e rule cannot
serve body-body and body-ground contacts at once); Siconos as in siconos_runner
(MoreauJeanOSI(1/2), NewtonImpactNSL(e), LCP Lemke), for specs of spheres on collinear slide
joints only, with the gaps written in the bodies' absolute coordinates exactly as the scene
file's floating-point positions give them (no exact-gap rebuilding: the cradle_rounding point).
MuJoCo and PyBullet collide every pair of geoms that touch (the spec's pair list only removes
pairs that cannot touch geometrically in these scenes).

Usage (spec JSON on stdin, result JSON on stdout):
    /work/peersenv/bin/python scripts/peers/stress_runners.py mujoco [--params '{"omega_h": 0.1}'] < spec.json
    /usr/bin/python3 scripts/peers/stress_runners.py siconos < spec.json
"""
from __future__ import annotations

import json
import math
import os
import sys
import time
import traceback

import numpy as np

_HERE = os.path.dirname(os.path.abspath(__file__))
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)

import _common as C  # noqa: E402


def _quat_mat(q):
    return C.quat_to_mats(np.asarray(q, float)[None])[0]


def _z_to(n):
    """Quaternion (w x y z) rotating +z onto the unit vector n."""
    n = np.asarray(n, float) / np.linalg.norm(n)
    z = np.array([0.0, 0.0, 1.0])
    c = float(z @ n)
    if c > 1 - 1e-15:
        return np.array([1.0, 0.0, 0.0, 0.0])
    if c < -1 + 1e-15:
        return np.array([0.0, 1.0, 0.0, 0.0])
    a = np.cross(z, n)
    s = math.sqrt(2 * (1 + c))
    return np.array([s / 2, a[0] / s, a[1] / s, a[2] / s])


def _params(defaults, params, peer):
    """The peer's default settings updated with `params`; unknown names are an error."""
    unknown = sorted(set(params) - set(defaults))
    if unknown:
        raise ValueError(f"unknown {peer} parameter(s) {unknown}")
    return {**defaults, **params}


# ------------------------------------------------------------------------------------------ MuJoCo
def run_mujoco(spec, **params):
    import mujoco

    import mujoco_runner as MR

    P = _params(MR.PEER_DEFAULTS, params, "MuJoCo")
    e, h, T = float(spec["e"]), float(spec["h"]), float(spec["T"])
    cs = MR._contact_settings(e, h, P)
    f = lambda v: " ".join(f"{float(x):.17g}" for x in v)  # noqa: E731
    parts = [f'<mujoco><option timestep="{h:.17g}" gravity="{f(spec["gravity"])}" integrator="{P["integrator"]}" '
             f'solver="{P["solver"]}" iterations="{int(P["iterations"])}" tolerance="{P["tolerance"]:.17g}"/>',
             f'<default><geom condim="1" solref="{-cs["k"]:.17g} {-cs["b"]:.17g}" solimp="{f(cs["solimp"])}" '
             f'margin="0" gap="0"/></default><worldbody>']
    for k, s in enumerate(spec["statics"]):
        if s["shape"] == "halfspace":
            n = np.asarray(s["normal"], float) / np.linalg.norm(s["normal"])
            parts.append(f'<geom name="s{k}" type="plane" size="0 0 1" pos="{f(n * s["offset"])}" quat="{f(_z_to(n))}"/>')
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
    xml = "".join(parts)
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    adr = []
    for i, b in enumerate(spec["bodies"]):
        j = model.body_jntadr[i + 1]
        qa, va = model.jnt_qposadr[j], model.jnt_dofadr[j]
        adr.append((qa, va))
        if b["joint"] == "free":
            data.qvel[va:va + 3] = b["v"]
            data.qvel[va + 3:va + 6] = b["w"]  # MuJoCo: a free joint's angular velocity is in the body frame
        else:
            data.qpos[qa] = b["q0"]
            data.qvel[va] = b["u0"]
    mujoco.mj_forward(model, data)
    N = C.n_steps(h, T)
    from mujoco import rollout

    spec_state = mujoco.mjtState.mjSTATE_FULLPHYSICS
    init = np.empty(mujoco.mj_stateSize(model, spec_state))
    mujoco.mj_getState(model, data, init, spec_state)
    rollout.rollout(model, data, init[None], nstep=1)
    out = np.empty((1, N, len(init)))
    c0 = time.process_time()
    rollout.rollout(model, data, init[None], nstep=N, state=out)
    cpu = time.process_time() - c0
    nq, nv = model.nq, model.nv
    qpos = np.vstack([init[1:1 + nq][None], out[0, :, 1:1 + nq]])
    qvel = np.vstack([init[1 + nq:1 + nq + nv][None], out[0, :, 1 + nq:1 + nq + nv]])
    t = np.arange(N + 1) * h
    sl = slice(None, None, max(1, int(spec.get("stride", 1))))
    bodies = []
    for b, (qa, va) in zip(spec["bodies"], adr):
        if b["joint"] == "free":
            quat = qpos[:, qa + 3:qa + 7]
            R = C.quat_to_mats(quat)
            wb = qvel[:, va + 3:va + 6]
            bodies.append({"pos": qpos[sl, qa:qa + 3], "quat": quat[sl], "vel": qvel[sl, va:va + 3],
                           "omega_world": np.einsum("nij,nj->ni", R, wb)[sl]})
        else:
            bodies.append({"q": qpos[sl, qa], "u": qvel[sl, va]})
    settings = {"contact_model": "soft spring-damper, solref direct -k -b (mujoco_runner)",
                "omega_h": cs["h_omega"], "stiffness_k": cs["k"], "damping_b": cs["b"], "zeta": cs["zeta"],
                "solimp": cs["solimp"], "integrator": P["integrator"], "solver": P["solver"],
                "iterations": int(P["iterations"]), "tolerance": P["tolerance"], "condim": 1}
    return {"peer": "mujoco", "scene": spec["name"], "t": t[sl], "bodies": bodies, "cpu_seconds": cpu,
            "settings": settings, "version": mujoco.__version__}


# ---------------------------------------------------------------------------------------- PyBullet
def run_pybullet(spec, **params):
    import pybullet as p

    import pybullet_runner as PR

    P = _params(PR.PEER_DEFAULTS, params, "PyBullet")
    if P["config"] not in PR.CONFIGS:
        raise ValueError(f"config must be one of {sorted(PR.CONFIGS)}")
    eng = dict(PR.CONFIGS[P["config"]])
    for k in PR._ENGINE_KEYS:
        if P[k] is not None:
            eng[k] = P[k]
    eng.setdefault("contact_breaking_threshold", PR.BULLET_DEFAULTS["contact_breaking_threshold"])
    e, h, T = float(spec["e"]), float(spec["h"]), float(spec["T"])
    se = math.sqrt(e)
    cid = p.connect(p.DIRECT)
    try:
        p.resetSimulation(physicsClientId=cid)
        p.setGravity(*spec["gravity"], physicsClientId=cid)
        kw = {PR._ENGINE_KEYS[k]: v for k, v in eng.items()}
        for k in ("use_split_impulse", "num_solver_iterations"):
            if PR._ENGINE_KEYS[k] in kw:
                kw[PR._ENGINE_KEYS[k]] = int(kw[PR._ENGINE_KEYS[k]])
        p.setPhysicsEngineParameter(fixedTimeStep=h, numSubSteps=0, physicsClientId=cid, **kw)

        def dyn(b, link):
            p.changeDynamics(b, link, restitution=se, lateralFriction=0.0, rollingFriction=0.0,
                             spinningFriction=0.0, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0,
                             physicsClientId=cid)
            if P["config"] == "tuned" or P["contact_breaking_threshold"] is not None:
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
                                        physicsClientId=cid)
                p.changeDynamics(bid, -1, localInertiaDiagonal=list(b["inertia"]), physicsClientId=cid)
                R = _quat_mat(q)
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
        N = C.n_steps(h, T)
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
    finally:
        p.disconnect(physicsClientId=cid)
    sl = slice(None, None, max(1, int(spec.get("stride", 1))))
    eff = dict(PR.BULLET_DEFAULTS)
    eff.update(eng)
    settings = {"config": P["config"], "restitution_each_body_and_static": se, "pair_product": e,
                "engine": eff, "friction": 0.0, "damping": 0.0, "slide_joints": "prismatic link on a fixed base"}
    return {"peer": "pybullet", "scene": spec["name"], "t": (np.arange(N + 1) * h)[sl],
            "bodies": [{k: v[sl] for k, v in r.items()} for r in rec], "cpu_seconds": cpu, "settings": settings,
            "version": PR.version()}


# ----------------------------------------------------------------------------------------- Siconos
def run_siconos(spec, **params):
    import siconos.kernel as sk

    import siconos_runner as SR

    P = {k: SR.PEER_DEFAULTS[k] for k in ("theta", "lcp_solver", "lcp_tolerance", "lcp_max_iterations")}
    unknown = sorted(set(params) - set(P))
    if unknown:
        raise ValueError(f"unknown Siconos parameter(s) {unknown}")
    P.update(params)
    e, h, T = float(spec["e"]), float(spec["h"]), float(spec["T"])
    bodies = spec["bodies"]
    if any(b["joint"] != "slide" or b["shape"] != "sphere" for b in bodies):
        raise ValueError("the Siconos stress runner takes spheres on slide joints only (LagrangianLinearTIR gaps)")
    g = np.asarray(spec["gravity"], float)
    N = C.n_steps(h, T)
    nsds = sk.NonSmoothDynamicalSystem(0.0, N * h)
    dss = []
    for b in bodies:
        ax = np.asarray(b["axis"], float)
        ds = sk.LagrangianLinearTIDS(np.array([float(b["q0"])]), np.array([float(b["u0"])]), np.array([[b["mass"]]]))
        ds.setFExtPtr(np.array([b["mass"] * float(g @ ax)]))
        nsds.insertDynamicalSystem(ds)
        dss.append(ds)
    relations = []
    for a, o in spec["pairs"]:
        A = bodies[a]
        axa, oa = np.asarray(A["axis"], float), np.asarray(A["origin"], float)
        if isinstance(o, str):  # a static half-space: gap = n.(origin + s axis) - offset - r
            s = spec["statics"][int(o[1:])]
            if s["shape"] != "halfspace":
                raise ValueError("the Siconos stress runner takes half-space statics only")
            n = np.asarray(s["normal"], float) / np.linalg.norm(s["normal"])
            rel = sk.LagrangianLinearTIR(np.array([[float(n @ axa)]]),
                                         np.array([float(n @ oa) - float(s["offset"]) - A["radius"]]))
            nsds.link(sk.Interaction(sk.NewtonImpactNSL(e), rel), dss[a])
            relations.append(f"body {a} - static {o[1:]}")
            continue
        B = bodies[o]
        axb, ob = np.asarray(B["axis"], float), np.asarray(B["origin"], float)
        if np.abs(axa - axb).max() > 1e-12 or np.linalg.norm(np.cross(ob - oa, axa)) > 1e-12:
            raise ValueError("the Siconos stress runner takes spheres on one common line only")
        ca = oa + float(A["q0"]) * axa
        cb = ob + float(B["q0"]) * axb
        sig = 1.0 if float((cb - ca) @ axa) > 0 else -1.0
        # gap = sig ((ob - oa).axis + s_b - s_a) - r_a - r_b, in the scene's absolute coordinates
        rel = sk.LagrangianLinearTIR(np.array([[-sig, sig]]),
                                     np.array([sig * float((ob - oa) @ axa) - A["radius"] - B["radius"]]))
        nsds.link(sk.Interaction(sk.NewtonImpactNSL(e), rel), dss[a], dss[o])
        relations.append(f"body {a} - body {o}")
    osi = sk.MoreauJeanOSI(float(P["theta"]))
    sim = sk.TimeStepping(nsds, sk.TimeDiscretisation(0.0, h), osi, SR._lcp(P))
    q = np.empty((N + 1, len(dss)))
    v = np.empty((N + 1, len(dss)))

    def record(k):
        for j, ds in enumerate(dss):
            q[k, j] = ds.q()[0]
            v[k, j] = ds.velocity()[0]

    record(0)
    cpu = SR._simulate(sim, record, N)
    sl = slice(None, None, max(1, int(spec.get("stride", 1))))
    settings = {"integrator": f"MoreauJeanOSI(theta={P['theta']})", "nonsmooth_law": f"NewtonImpactNSL(e={e})",
                "lcp_solver": P["lcp_solver"], "model": "1-dof LagrangianLinearTIDS per sphere (absolute "
                "coordinates), LagrangianLinearTIR gaps from the scene's floating-point positions",
                "relations": len(relations)}
    return {"peer": "siconos", "scene": spec["name"], "t": (np.arange(N + 1) * h)[sl],
            "bodies": [{"q": q[sl, j], "u": v[sl, j]} for j in range(len(dss))], "cpu_seconds": cpu,
            "settings": settings, "version": SR.version()}


RUNNERS = {"mujoco": run_mujoco, "pybullet": run_pybullet, "siconos": run_siconos}


def main(argv=None):
    import argparse

    ap = argparse.ArgumentParser(description="Run a stress-scene spec (JSON on stdin) in a peer.")
    ap.add_argument("peer", choices=sorted(RUNNERS))
    ap.add_argument("--params", default="{}", help="peer parameters as a JSON object")
    a = ap.parse_args(argv)
    spec = json.load(sys.stdin)
    sys.stdout.flush()
    json_fd = os.dup(1)
    os.dup2(2, 1)  # C libraries print on stdout: keep fd 1 for the JSON only
    try:
        res = RUNNERS[a.peer](spec, **json.loads(a.params))
    except Exception as exc:  # noqa: BLE001
        traceback.print_exc(file=sys.stderr)
        print(f"PEER-ERROR {a.peer}/{spec.get('name')}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    with os.fdopen(json_fd, "w") as out:
        out.write(json.dumps(C.to_jsonable(res)))
        out.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
