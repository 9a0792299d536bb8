#!/usr/bin/python3
"""Siconos runner for the moreau-sim impact scenes (run with Debian's /usr/bin/python3).

Siconos (Debian `python3-siconos`) is only importable from Debian's Python, so the uniform
entry point (scripts/peers/__init__.py) runs this file as a subprocess and reads the JSON it
prints on stdout.

Method (shared/notes/peers.md): the same class as moreau-sim — Moreau–Jean time stepping,
MoreauJeanOSI(theta = 1/2), Newton impact law NewtonImpactNSL(e) per contact, one LCP per
step (Lemke by default). Bodies are LagrangianLinearTIDS, contacts LagrangianLinearTIR(H, b)
with exact gaps: Siconos switches a contact on from the predicted gap with no tolerance, so
the cradle is written in displacement coordinates (q_i = x_i - x_i(0)) and each relation
carries the initial gap exactly in b (0.0 or the requested gap), never 0.2*i rounding.

box_drop is built with Siconos' own Bullet-based contact detection
(siconos.mechanics.collision.bullet) on a RigidBodyDS (Newton–Euler, quaternion); see
`_box_drop` for its settings (it uses mu = 0 friction contact instead of NewtonImpactNSL).

Usage:  /usr/bin/python3 scripts/peers/siconos_runner.py bouncing_ball --e 0.8 --h 1e-3 --T 3
"""
from __future__ import annotations

import subprocess
import sys
import time

import numpy as np

try:
    from . import _common as C
except ImportError:  # run as a script
    import _common as C

PEER = "siconos"

PEER_DEFAULTS = {
    "theta": 0.5,
    "lcp_solver": "lemke",  # lemke | pgs | enum | pivot
    "lcp_tolerance": 1e-12,
    "lcp_max_iterations": 100000,  # NSGS needs > 1000 on the resting box (mu = 0)
    # box_drop only (Siconos' Bullet contact detection)
    "contact_breaking_threshold": 0.02,
    "perturbation_iterations": 3,
    "inside_margin": 0.0,
}


def version():
    import siconos

    v = getattr(siconos, "version", None) or getattr(siconos, "__version__", "?")
    try:
        deb = subprocess.run(["dpkg-query", "-W", "-f=${Version}", "python3-siconos"],
                             capture_output=True, text=True, timeout=10).stdout.strip()
    except Exception:  # noqa: BLE001
        deb = ""
    return f"{v} (Debian python3-siconos {deb})" if deb else str(v)


def _lcp(P):
    import siconos.kernel as sk
    import siconos.numerics as sn

    ids = {
        "lemke": sn.SICONOS_LCP_LEMKE,
        "pgs": sn.SICONOS_LCP_PGS,
        "enum": sn.SICONOS_LCP_ENUM,
        "pivot": sn.SICONOS_LCP_PIVOT,
    }
    name = P["lcp_solver"]
    if name not in ids:
        raise ValueError(f"lcp_solver must be one of {sorted(ids)}, got {name!r}")
    lcp = sk.LCP(ids[name])
    try:
        opts = lcp.numericsSolverOptions()
        opts.iparam[sn.SICONOS_IPARAM_MAX_ITER] = int(P["lcp_max_iterations"])
        opts.dparam[sn.SICONOS_DPARAM_TOL] = float(P["lcp_tolerance"])
    except Exception:  # noqa: BLE001 - older bindings: keep solver defaults
        pass
    return lcp


def _simulate(sim, record, N):
    """Step N times; `record(k)` stores the state after step k. Returns CPU seconds."""
    c0 = time.process_time()
    k = 0
    while k < N and sim.hasNextEvent():
        sim.computeOneStep()
        sim.nextStep()
        k += 1
        record(k)
    cpu = time.process_time() - c0
    if k != N:
        raise RuntimeError(f"simulation stopped after {k} of {N} steps")
    return cpu


def run(scene: str, *, e: float, h: float, T: float, **params) -> dict:
    import siconos.kernel as sk

    P = C.merge_params(scene, PEER_DEFAULTS, params)
    if not 0.0 <= e <= 1.0:
        raise ValueError(f"restitution e={e} outside [0, 1]")
    N = C.n_steps(h, T)
    T_sim = N * h
    settings = {
        "integrator": f"MoreauJeanOSI(theta={P['theta']})",
        "simulation": "TimeStepping (one LCP per step, velocity-level Newton impact law)",
        "nonsmooth_law": f"NewtonImpactNSL(e={e})",
        "lcp_solver": P["lcp_solver"], "lcp_tolerance": P["lcp_tolerance"],
        "lcp_max_iterations": P["lcp_max_iterations"], "timestep": h,
    }
    if scene == "box_drop":
        return _box_drop(e, h, T, N, P, settings)

    nsds = sk.NonSmoothDynamicalSystem(0.0, T_sim)
    if scene == "bouncing_ball":
        ball = sk.LagrangianLinearTIDS(np.array([P["z0"]]), np.array([0.0]),
                                       np.array([[P["m"]]]))
        ball.setFExtPtr(np.array([-P["m"] * P["g"]]))
        nsds.insertDynamicalSystem(ball)
        # gap = z - r
        rel = sk.LagrangianLinearTIR(np.array([[1.0]]), np.array([-P["r"]]))
        nsds.link(sk.Interaction(sk.NewtonImpactNSL(e), rel), ball)
        dss = [ball]
        settings["model"] = "1-dof LagrangianLinearTIDS (centre height), gap = z - r"
    elif scene == "newton_cradle_5":
        n = int(P["n"])
        dss = []
        for i in range(n):
            ds = sk.LagrangianLinearTIDS(np.array([0.0]),
                                         np.array([P["v0"] if i == 0 else 0.0]),
                                         np.array([[P["m"]]]))
            nsds.insertDynamicalSystem(ds)
            dss.append(ds)
        gap = float(P["gap"])
        for i in range(n - 1):
            # gap_i = q_{i+1} - q_i + gap (displacement coordinates: exact initial gap)
            rel = sk.LagrangianLinearTIR(np.array([[-1.0, 1.0]]), np.array([gap]))
            nsds.link(sk.Interaction(sk.NewtonImpactNSL(e), rel), dss[i], dss[i + 1])
        settings["model"] = ("5 x 1-dof LagrangianLinearTIDS in displacement coordinates, "
                             "relations gap_i = q_{i+1} - q_i + gap (exact)")
    else:
        raise ValueError(f"unknown scene {scene!r}")

    osi = sk.MoreauJeanOSI(float(P["theta"]))
    td = sk.TimeDiscretisation(0.0, h)
    sim = sk.TimeStepping(nsds, td, osi, _lcp(P))

    nd = len(dss)
    q = np.empty((N + 1, nd))
    v = np.empty((N + 1, nd))
    for j, ds in enumerate(dss):
        q[0, j] = ds.q()[0]
        v[0, j] = ds.velocity()[0]

    def record(k):
        for j, ds in enumerate(dss):
            q[k, j] = ds.q()[0]
            v[k, j] = ds.velocity()[0]

    cpu = _simulate(sim, record, N)
    stride = max(1, int(P["stride"]))
    sl = slice(None, None, stride)
    settings.update({k: P[k] for k in C.SCENE_DEFAULTS[scene]})
    res = {"peer": PEER, "scene": scene, "e": e, "h": h, "T": T, "settings": settings,
           "t": (np.arange(N + 1) * h)[sl], "cpu_seconds": cpu, "version": version()}
    if scene == "bouncing_ball":
        res["z"] = q[sl, 0]
        res["vz"] = v[sl, 0]
    else:
        x0 = np.array([i * (2 * P["r"] + P["gap"]) for i in range(nd)])
        res["x"] = q[sl] + x0
        res["vx"] = v[sl]
        res["vx_final"] = v[-1].copy()
    return res


def _box_drop(e, h, T, N, P, settings):
    """Free box on the ground with Siconos' mechanics toolbox: RigidBodyDS (Newton–Euler,
    quaternion q = (x, y, z, qw, qx, qy, qz), twist = (v, omega)), contact detection by
    SiconosBulletCollisionManager (box vs SiconosPlane, all margins 0), MoreauJeanOSI(1/2),
    Newton loop SICONOS_TS_NONLINEAR (as siconos.io.mechanics_run does).

    Frictionless: with this collision manager, NewtonImpactNSL + LCP throws std::exception
    in Siconos 4.4 (the manager builds 3-D contact relations), so the contact law is
    NewtonImpactFrictionNSL(e, 0, mu = 0) solved as FrictionContact(3) (NSGS) — with mu = 0
    it is the same frictionless Newton law."""
    import siconos.kernel as sk
    import siconos.numerics as sn
    from siconos.mechanics.collision import (RigidBodyDS, SiconosBox, SiconosContactor,
                                             SiconosContactorSet, SiconosPlane)
    from siconos.mechanics.collision.bullet import (SiconosBulletCollisionManager,
                                                    SiconosBulletOptions)

    m = float(P["m"])
    hx, hy, hz = (float(x) for x in P["half_extents"])
    q0 = C.rpy_to_quat(P["rpy"])
    inertia = np.diag([m / 3 * (hy * hy + hz * hz), m / 3 * (hx * hx + hz * hz),
                       m / 3 * (hx * hx + hy * hy)])
    body = RigidBodyDS([0.0, 0.0, float(P["z0"])] + [float(x) for x in q0], [0.0] * 6, m,
                       inertia)
    body.setUseContactorInertia(False)
    box = SiconosBox(2 * hx, 2 * hy, 2 * hz)
    box.setInsideMargin(float(P["inside_margin"]))
    box.setOutsideMargin(0.0)
    cset = SiconosContactorSet()
    cset.append(SiconosContactor(box, [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], 0))
    body.setContactors(cset)
    body.setFExtPtr([0.0, 0.0, -m * float(P["g"])])

    nsds = sk.NonSmoothDynamicalSystem(0.0, N * h)
    nsds.insertDynamicalSystem(body)
    opts = SiconosBulletOptions()
    opts.contactBreakingThreshold = float(P["contact_breaking_threshold"])
    opts.perturbationIterations = int(P["perturbation_iterations"])
    opts.minimumPointsPerturbationThreshold = int(P["perturbation_iterations"])
    man = SiconosBulletCollisionManager(opts)
    man.insertNonSmoothLaw(sk.NewtonImpactFrictionNSL(e, 0.0, 0.0, 3), 0, 0)
    plane = SiconosPlane()
    pset = SiconosContactorSet()
    pset.append(SiconosContactor(plane, [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], 0))
    man.insertStaticContactorSet(pset, [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])

    osi = sk.MoreauJeanOSI(float(P["theta"]))
    fc = sk.FrictionContact(3)
    try:
        so = fc.numericsSolverOptions()
        so.iparam[sn.SICONOS_IPARAM_MAX_ITER] = int(P["lcp_max_iterations"])
        so.dparam[sn.SICONOS_DPARAM_TOL] = float(P["lcp_tolerance"])
    except Exception:  # noqa: BLE001
        pass
    sim = sk.TimeStepping(nsds, sk.TimeDiscretisation(0.0, h))
    sim.insertIntegrator(osi)
    sim.insertNonSmoothProblem(fc)
    sim.insertInteractionManager(man)
    sim.setNewtonOptions(sk.SICONOS_TS_NONLINEAR)
    sim.setNewtonMaxIteration(20)
    sim.setNewtonTolerance(1e-10)

    qq = np.empty((N + 1, 7))
    vv = np.empty((N + 1, 6))
    qq[0] = body.q()
    vv[0] = body.twist()

    def record(k):
        qq[k] = body.q()
        vv[k] = body.twist()

    cpu = _simulate(sim, record, N)
    stride = max(1, int(P["stride"]))
    sl = slice(None, None, stride)
    settings.update({
        "model": "RigidBodyDS (Newton-Euler, quaternion) + SiconosBulletCollisionManager",
        "nonsmooth_law": f"NewtonImpactFrictionNSL(e={e}, mu=0) (frictionless)",
        "osnspb": "FrictionContact(3), NSGS", "newton": "SICONOS_TS_NONLINEAR, 20 it, tol 1e-10",
        "bullet_contactBreakingThreshold": opts.contactBreakingThreshold,
        "bullet_perturbationIterations": int(P["perturbation_iterations"]),
        "box_inside_margin": float(P["inside_margin"]), "box_outside_margin": 0.0,
        "inertia_diag": np.diag(inertia).tolist(),
    })
    settings.update({k: P[k] for k in C.SCENE_DEFAULTS["box_drop"]})
    return {"peer": PEER, "scene": "box_drop", "e": e, "h": h, "T": T, "settings": settings,
            "t": (np.arange(N + 1) * h)[sl], "cpu_seconds": cpu, "version": version(),
            "pos": qq[sl, 0:3], "quat": qq[sl, 3:7], "vel": vv[sl, 0:3],
            "min_corner_z": C.min_corner_height(qq[:, 0:3], qq[:, 3:7], (hx, hy, hz))[sl]}


if __name__ == "__main__":
    sys.exit(C.cli(PEER, run))
