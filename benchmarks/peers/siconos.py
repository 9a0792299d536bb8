"""Siconos runner of the neutral spec (benchmarks.spec); runs in Debian's Python.

Siconos (Debian `python3-siconos`) is importable only from Debian's own interpreter, so the host
(benchmarks.peers.run) always runs this module in a subprocess of SICONOS_PYTHON; this module
imports nothing but numpy and benchmarks.spec.

Method: the same class as moreau-sim - Moreau-Jean time stepping, MoreauJeanOSI(theta = 1/2), the
Newton impact law NewtonImpactNSL(e) per contact, one LCP per step (Lemke by default). Two spec
shapes are expressible:
- spheres on slide joints along one common line, with half-space statics: one 1-dof
  LagrangianLinearTIDS per sphere, contacts LagrangianLinearTIR(H, b). Siconos switches a contact
  on from the predicted gap with no tolerance (a gap of 1.1e-16 m from 0.2 * 3 is a gap), so by
  default each sphere keeps its absolute coordinate and the gaps are exactly what the spec's
  floating-point positions give (moreau-sim's input too: the cradle_rounding point);
  exact_gaps=True writes the spheres in displacement coordinates with every initial gap rounded
  to 1e-12 m (the work-precision cradle: Siconos given exact touching);
- one free box over the half-space z >= 0: Siconos' mechanics toolbox, a RigidBodyDS (Newton-Euler,
  quaternion) with Bullet contact detection (SiconosBulletCollisionManager, all margins 0),
  Newton loop SICONOS_TS_NONLINEAR. With this manager NewtonImpactNSL + LCP throws in Siconos 4.4
  (it builds 3-D contact relations), so the law is NewtonImpactFrictionNSL(e, 0, mu = 0) solved
  as FrictionContact(3) (NSGS): with mu = 0 the same frictionless Newton law.
Anything else raises NotExpressible.

simulation="event-driven" (spheres only) runs Siconos' event-driven simulation instead:
EventDriven with LsodarOSI (its default tolerances), an LCP for the impacts
(SICONOS_OSNSP_ED_IMPACT) and one for the accelerations (SICONOS_OSNSP_ED_SMOOTH_ACC), impacts
located by Lsodar's root finding, time events every h (the samples; h is then no step size).
"""

from __future__ import annotations

import subprocess
import time

import numpy as np

from ..spec import NotExpressible, merge_params, min_corner_height, n_steps, quat_to_mats

DEFAULTS = {
    "theta": 0.5,
    "lcp_solver": "lemke",  # lemke | pgs | enum | pivot
    "lcp_tolerance": 1e-12,
    "lcp_max_iterations": 100000,  # NSGS needs > 1000 on the resting box (mu = 0)
    # spheres: False = absolute coordinates, each gap exactly as the spec's floating-point positions
    # give it (what moreau-sim sees); True = displacement coordinates with every initial gap rounded
    # to 1e-12 m (a touching cradle exactly touching, a 1 mm gap exactly 1e-3)
    "exact_gaps": False,
    "simulation": "time-stepping",  # or "event-driven" (spheres only; module doc)
    # free box only (Siconos' Bullet contact detection)
    "contact_breaking_threshold": 0.02,
    "perturbation_iterations": 3,
    "inside_margin": 0.0,
    # > 0: also time the stepping loop (time stepping only; `timing` in the result): that many whole
    # runs as they are, and as many with a timer around each step; the best of them per step
    "timing_repeats": 0,
}


def version() -> str:
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

    ids = {"lemke": sn.SICONOS_LCP_LEMKE, "pgs": sn.SICONOS_LCP_PGS, "enum": sn.SICONOS_LCP_ENUM,
           "pivot": sn.SICONOS_LCP_PIVOT}
    if P["lcp_solver"] not in ids:
        raise ValueError(f"lcp_solver must be one of {sorted(ids)}, got {P['lcp_solver']!r}")
    lcp = sk.LCP(ids[P["lcp_solver"]])
    try:
        opts = lcp.numericsSolverOptions()
        opts.iparam[sn.SICONOS_IPARAM_MAX_ITER] = int(P["lcp_max_iterations"])
        opts.dparam[sn.SICONOS_DPARAM_TOL] = float(P["lcp_tolerance"])
    except Exception:  # noqa: BLE001 - older bindings: keep the solver's defaults
        pass
    return lcp


def _simulate(sim, record, N, h=None, step_us=None, active=None):
    """Step N times (time stepping), or with h go event by event to the end (event-driven);
    `record(k)` stores the state after step k, or at the time event k h (impacts are events too,
    not recorded). Returns CPU and wall seconds of the loop. With arrays `step_us` and `active` (time stepping only) it
    also stores each step's wall time (perf_counter around computeOneStep + nextStep, us) and the
    number of interactions in the step's index set 1 (the contacts its LCP carries)."""
    c0, w0 = time.process_time(), time.perf_counter()
    k = 0
    while (h is not None or k < N) and sim.hasNextEvent():
        if h is None and step_us is not None:
            t0 = time.perf_counter()
            sim.computeOneStep()
            t1 = time.perf_counter()
            active[k] = len(sim.indexSet(1).interactions())
            t2 = time.perf_counter()
            sim.nextStep()
            step_us[k] = (t1 - t0 + time.perf_counter() - t2) * 1e6
        elif h is None:
            sim.computeOneStep()
            sim.nextStep()
        else:
            sim.advanceToEvent()
            sim.processEvents()
            if not (k < N and abs(sim.startingTime() - (k + 1) * h) <= 1e-9 * h):
                continue
        k += 1
        record(k)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    if k != N:
        raise RuntimeError(f"simulation stopped after {k} of {N} steps or time events")
    return cpu, wall


def run(spec: dict, **params) -> dict:
    P = merge_params("Siconos", DEFAULTS, params)
    e = float(spec["e"])
    if not 0.0 <= e <= 1.0:
        raise ValueError(f"restitution e={e} outside [0, 1]")
    if P["simulation"] not in ("time-stepping", "event-driven"):
        raise ValueError(f"simulation must be 'time-stepping' or 'event-driven', got {P['simulation']!r}")
    bodies = spec["bodies"]
    if all(b["joint"] == "slide" and b["shape"] == "sphere" for b in bodies):
        sim = _spheres
    elif len(bodies) == 1 and bodies[0]["joint"] == "free" and bodies[0]["shape"] == "box":
        if P["simulation"] == "event-driven":
            raise NotExpressible("the Siconos runner's event-driven simulation takes spheres only")
        sim = _box
    else:
        raise NotExpressible("the Siconos runner takes spheres on collinear slide joints, or one free box over a "
                             "half-space")
    repeats = int(P["timing_repeats"])
    if repeats <= 0:
        return sim(spec, P)
    if P["simulation"] != "time-stepping":
        raise ValueError("timing_repeats times the time-stepping loop only")
    return _timed(sim, spec, P, repeats)


def _timed(sim, spec, P, repeats):
    """`sim`'s result with `timing`: the whole run's wall time (the loop with its recording, best of
    `repeats` runs, s) and per step the best of `repeats` timed runs (us) with the number of
    contacts in its LCP. Each run builds the simulation anew, after one untimed run; the timed runs
    are separate so that the per-step timer does not weigh on the whole-run figure."""
    N = n_steps(float(spec["h"]), float(spec["T"]))
    sim(spec, P)  # warm-up: the process's first run pays for first calls and allocations
    walls = []
    for _ in range(repeats):
        res = sim(spec, P)
        walls.append(res["wall_seconds"])
    best = np.full(N, np.inf)
    active = np.zeros(N, dtype=np.int64)
    for _ in range(repeats):
        step_us = np.empty(N)
        sim(spec, P, (step_us, active))
        best = np.minimum(best, step_us)
    res["timing"] = {"repeats": repeats, "wall_seconds": min(walls), "step_us": best, "contacts": active,
                     "timer": "time.perf_counter around computeOneStep + nextStep (the runner's Python loop)"}
    return res


def _settings_ed(P, e, h):
    return {"integrator": "LsodarOSI (default tolerances)",
            "simulation": "EventDriven (impact LCP + acceleration LCP, impacts located by Lsodar's root finding)",
            "nonsmooth_law": f"NewtonImpactNSL(e={e})", "lcp_solver": P["lcp_solver"],
            "lcp_tolerance": P["lcp_tolerance"], "time_events_every": h}


def _settings(P, e, h):
    return {"integrator": f"MoreauJeanOSI(theta={P['theta']})",
            "simulation": "TimeStepping (one LCP per step, velocity-level Newton impact law)",
            "nonsmooth_law": f"NewtonImpactNSL(e={e})", "lcp_solver": P["lcp_solver"],
            "lcp_tolerance": P["lcp_tolerance"], "lcp_max_iterations": P["lcp_max_iterations"], "timestep": h}


def _spheres(spec, P, timing=()):
    import siconos.kernel as sk

    e, h, T = float(spec["e"]), float(spec["h"]), float(spec["T"])
    bodies = spec["bodies"]
    g = np.asarray(spec["gravity"], float)
    N = n_steps(h, T)
    nsds = sk.NonSmoothDynamicalSystem(0.0, N * h)
    dss = []
    for b in bodies:
        ax = np.asarray(b["axis"], float)
        s0 = 0.0 if P["exact_gaps"] else float(b["q0"])
        ds = sk.LagrangianLinearTIDS(np.array([s0]), np.array([float(b["u0"])]), np.array([[b["mass"]]]))
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
                raise NotExpressible("the Siconos runner takes half-space statics only for spheres")
            n = np.asarray(s["normal"], float) / np.linalg.norm(s["normal"])
            b0 = float(n @ oa) - float(s["offset"]) - A["radius"]
            if P["exact_gaps"]:
                b0 = round(b0 + float(n @ axa) * float(A["q0"]), 12)
            rel = sk.LagrangianLinearTIR(np.array([[float(n @ axa)]]), np.array([b0]))
            nsds.link(sk.Interaction(sk.NewtonImpactNSL(e), rel), dss[a])
            relations.append(f"body {a} - static {o[1:]}")
            continue
        B = bodies[o]
        axb, ob = np.asarray(B["axis"], float), np.asarray(B["origin"], float)
        if np.abs(axa - axb).max() > 1e-12 or np.linalg.norm(np.cross(ob - oa, axa)) > 1e-12:
            raise NotExpressible("the Siconos runner takes spheres on one common line only")
        ca = oa + float(A["q0"]) * axa
        cb = ob + float(B["q0"]) * axb
        sig = 1.0 if float((cb - ca) @ axa) > 0 else -1.0
        # gap = sig ((ob - oa).axis + s_b - s_a) - r_a - r_b, in the spec's absolute coordinates
        b0 = sig * float((ob - oa) @ axa) - A["radius"] - B["radius"]
        if P["exact_gaps"]:
            b0 = round(b0 + sig * (float(B["q0"]) - float(A["q0"])), 12)
        rel = sk.LagrangianLinearTIR(np.array([[-sig, sig]]), np.array([b0]))
        nsds.link(sk.Interaction(sk.NewtonImpactNSL(e), rel), dss[a], dss[o])
        relations.append(f"body {a} - body {o}")
    event_driven = P["simulation"] == "event-driven"
    if event_driven:
        sim = sk.EventDriven(nsds, sk.TimeDiscretisation(0.0, h))
        sim.insertIntegrator(sk.LsodarOSI())
        sim.insertNonSmoothProblem(_lcp(P), sk.SICONOS_OSNSP_ED_IMPACT)
        sim.insertNonSmoothProblem(_lcp(P), sk.SICONOS_OSNSP_ED_SMOOTH_ACC)
    else:
        sim = sk.TimeStepping(nsds, sk.TimeDiscretisation(0.0, h), sk.MoreauJeanOSI(float(P["theta"])), _lcp(P))
    q, v = np.empty((N + 1, len(dss))), np.empty((N + 1, len(dss)))

    def record(k):
        for j, ds in enumerate(dss):
            q[k, j] = ds.q()[0]
            v[k, j] = ds.velocity()[0]

    record(0)
    cpu, wall = _simulate(sim, record, N, h if event_driven else None, *timing)
    if P["exact_gaps"]:
        q += np.array([float(b["q0"]) for b in bodies])
    sl = slice(None, None, max(1, int(spec.get("stride", 1))))
    coords = ("displacement coordinates, initial gaps rounded to 1e-12 m" if P["exact_gaps"] else
              "absolute coordinates, gaps from the spec's floating-point positions")
    settings = (_settings_ed(P, e, h) if event_driven else _settings(P, e, h)) | {
        "model": f"1-dof LagrangianLinearTIDS per sphere ({coords}), LagrangianLinearTIR",
                                     "exact_gaps": bool(P["exact_gaps"]), "relations": len(relations)}
    return {"peer": "siconos", "scene": spec["name"], "t": (np.arange(N + 1) * h)[sl],
            "bodies": [{"q": q[sl, j], "u": v[sl, j]} for j in range(len(dss))], "cpu_seconds": cpu,
            "wall_seconds": wall,
            "settings": settings, "version": version()}


def _box(spec, P, timing=()):
    import siconos.kernel as sk
    import siconos.numerics as sn
    from siconos.mechanics.collision import RigidBodyDS, SiconosBox, SiconosContactor, SiconosContactorSet, SiconosPlane
    from siconos.mechanics.collision.bullet import SiconosBulletCollisionManager, SiconosBulletOptions

    e, h, T = float(spec["e"]), float(spec["h"]), float(spec["T"])
    (b,) = spec["bodies"]
    ground = [s for s in spec["statics"] if s["shape"] == "halfspace"]
    if (len(spec["statics"]) != 1 or len(ground) != 1 or float(ground[0]["offset"]) != 0.0
            or np.abs(np.asarray(ground[0]["normal"], float) - [0, 0, 1]).max() > 0):
        raise NotExpressible("the Siconos runner takes a free box over the one half-space z >= 0 only")
    N = n_steps(h, T)
    m = float(b["mass"])
    hx, hy, hz = (float(x) for x in b["half_extents"])
    body = RigidBodyDS([float(x) for x in b["pos"]] + [float(x) for x in b["quat"]],
                       [float(x) for x in b["v"]] + [float(x) for x in b["w"]], m, np.diag(b["inertia"]))
    body.setUseContactorInertia(False)
    box = SiconosBox(2 * hx, 2 * hy, 2 * hz)
    box.setInsideMargin(float(P["inside_margin"]))
    box.setOutsideMargin(0.0)
    cset = SiconosContactorSet()
    cset.append(SiconosContactor(box, [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], 0))
    body.setContactors(cset)
    body.setFExtPtr([m * float(x) for x in spec["gravity"]])
    nsds = sk.NonSmoothDynamicalSystem(0.0, N * h)
    nsds.insertDynamicalSystem(body)
    opts = SiconosBulletOptions()
    opts.contactBreakingThreshold = float(P["contact_breaking_threshold"])
    opts.perturbationIterations = int(P["perturbation_iterations"])
    opts.minimumPointsPerturbationThreshold = int(P["perturbation_iterations"])
    man = SiconosBulletCollisionManager(opts)
    man.insertNonSmoothLaw(sk.NewtonImpactFrictionNSL(e, 0.0, 0.0, 3), 0, 0)
    pset = SiconosContactorSet()
    pset.append(SiconosContactor(SiconosPlane(), [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], 0))
    man.insertStaticContactorSet(pset, [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    fc = sk.FrictionContact(3)
    try:
        so = fc.numericsSolverOptions()
        so.iparam[sn.SICONOS_IPARAM_MAX_ITER] = int(P["lcp_max_iterations"])
        so.dparam[sn.SICONOS_DPARAM_TOL] = float(P["lcp_tolerance"])
    except Exception:  # noqa: BLE001
        pass
    sim = sk.TimeStepping(nsds, sk.TimeDiscretisation(0.0, h))
    sim.insertIntegrator(sk.MoreauJeanOSI(float(P["theta"])))
    sim.insertNonSmoothProblem(fc)
    sim.insertInteractionManager(man)
    sim.setNewtonOptions(sk.SICONOS_TS_NONLINEAR)
    sim.setNewtonMaxIteration(20)
    sim.setNewtonTolerance(1e-10)
    qq, vv = np.empty((N + 1, 7)), np.empty((N + 1, 6))
    qq[0], vv[0] = body.q(), body.twist()

    def record(k):
        qq[k] = body.q()
        vv[k] = body.twist()

    cpu, wall = _simulate(sim, record, N, None, *timing)
    sl = slice(None, None, max(1, int(spec.get("stride", 1))))
    omega_world = np.einsum("nij,nj->ni", quat_to_mats(qq[:, 3:7]), vv[:, 3:6])  # the twist's omega: body frame
    settings = _settings(P, e, h) | {
        "model": "RigidBodyDS (Newton-Euler, quaternion) + SiconosBulletCollisionManager",
        "nonsmooth_law": f"NewtonImpactFrictionNSL(e={e}, mu=0) (frictionless)",
        "osnspb": "FrictionContact(3), NSGS", "newton": "SICONOS_TS_NONLINEAR, 20 it, tol 1e-10",
        "bullet_contactBreakingThreshold": opts.contactBreakingThreshold,
        "bullet_perturbationIterations": int(P["perturbation_iterations"]),
        "box_inside_margin": float(P["inside_margin"]), "box_outside_margin": 0.0,
        "min_corner_z_final": float(min_corner_height(qq[-1:, 0:3], qq[-1:, 3:7], (hx, hy, hz))[0])}
    return {"peer": "siconos", "scene": spec["name"], "t": (np.arange(N + 1) * h)[sl],
            "bodies": [{"pos": qq[sl, 0:3], "quat": qq[sl, 3:7], "vel": vv[sl, 0:3], "omega_world": omega_world[sl]}],
            "cpu_seconds": cpu, "wall_seconds": wall, "settings": settings, "version": version()}
