"""The stress suite: every stress scene at a CI size against the bound stated in its
description and in docs/stability.md; large steps over the bundled scenes; the swept-contact
prototype against tunnelling (moreau_sim/tunnelling.py).

Known failures are pinned with strict xfail (the reason names the cause; docs/stability.md has
the numbers): an xfail that starts passing fails the suite, so the mark is removed with the fix.
"""

import dataclasses

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
from moreau_sim.testing.references import cradle_simultaneous, zeno_rest_bound, zeno_time
from moreau_sim.tunnelling import motion_bounds, pair_distance, swept_contacts

from helpers import SCENES, run, scene

G = 9.81
CORRECTIONS = ("none", "projection")


def energy(traj):
    return traj.kinetic_energy + traj.potential_energy


def rotation_drift(q0, q):
    """Angle [rad] between the orientations of free-body quaternions [qx qy qz qw]."""
    q0, q = np.asarray(q0), np.asarray(q)
    dot = np.abs((q0 * q).sum(axis=-1)).clip(0.0, 1.0)
    return 2.0 * np.arccos(dot)


def free_drift(model, traj):
    """(largest position drift [m], largest orientation drift [rad]) of every body over the run
    (free bodies: centre and quaternion; 1-dof bodies: their coordinate)."""
    dpos, drot = 0.0, 0.0
    for b in model.bodies:
        q = traj.q[:, b.q_slice]
        if b.root_joint is ms.RootJoint.FREE:
            dpos = max(dpos, float(np.abs(q[:, :3] - q[0, :3]).max()))
            drot = max(drot, float(rotation_drift(q[0, 3:], q[:, 3:]).max()))
        elif q.shape[1]:
            dpos = max(dpos, float(np.abs(q - q[0]).max()))
    return dpos, drot


# ----------------------------------------------------------------------------------------- 1. zeno_ball
D0_ZENO = 0.5  # zeno_ball: initial gap [m] (centre at 0.6 m, r = 0.1 m)


@pytest.mark.parametrize("e,h,correction", [(0.5, 1e-3, "none"), (0.5, 1e-3, "projection"),
                                            (0.8, 1e-3, "none"), (0.8, 1e-3, "projection"),
                                            (0.95, 1e-3, "none"), (0.95, 1e-3, "projection"),
                                            (0.8, 1e-2, "none"), (0.8, 1e-2, "projection")])
def test_zeno_ball_rests_near_t_inf_and_stays_still(e, h, correction):
    t_inf = zeno_time(e, D0_ZENO)
    bound = zeno_rest_bound(e, h, D0_ZENO)  # the scene's stated bound (zeno_ball.toml)
    traj = run("zeno_ball", restitution=e, dt=h, duration=t_inf + bound + 10.0 + 10 * h,
               position_correction=correction)
    speed = np.abs(traj.u[:, 0])
    moving = np.flatnonzero(speed > 1e-12)
    t_rest = traj.t[moving[-1] + 1]
    assert abs(t_rest - t_inf) <= bound, (t_rest - t_inf, bound)
    rest = traj.t >= t_rest
    assert traj.t[-1] - t_rest >= 10.0
    z = traj.q[rest, 0]
    assert np.ptp(z) <= 1e-12  # no creep
    assert -h * h * G <= z.min() - 0.1 <= 1e-15  # resting penetration below h^2 g, not lifted off
    assert not np.any(traj.log_impact & (traj.log_t > t_rest))


# ------------------------------------------------------------------- 2. resting_box, box_stack_5/10
@pytest.mark.parametrize("h,duration", [(1e-2, 60.0), (1e-3, 3.0)])
@pytest.mark.parametrize("correction", CORRECTIONS)
def test_resting_box_does_not_drift(h, duration, correction):
    """resting_box.toml: drift <= 1e-9 m and 1e-9 rad, penetration <= 1e-9 m and not growing,
    T + V never above its start by more than 1e-12 J."""
    model = ms.build_model(scene("resting_box", dt=h, duration=duration, position_correction=correction))
    traj = ms.simulate(model, progress=False)
    dpos, drot = free_drift(model, traj)
    assert dpos <= 1e-9 and drot <= 1e-9, (dpos, drot)
    pen = -traj.gap.min(axis=1)
    assert pen.max() <= 1e-9
    half = len(pen) // 2
    assert pen[half:].max() <= pen[:half].max() + 1e-12  # not growing
    assert np.max(energy(traj) - energy(traj)[0]) <= 1e-12


@pytest.mark.parametrize("name", ["box_stack_5", "box_stack_10", pytest.param("alternating_stack_10",
                                                                               marks=pytest.mark.slow)])
@pytest.mark.parametrize("h,duration", [(1e-2, 2.0), (1e-3, 0.2)])
def test_box_stack_stays_put(name, h, duration):
    """box_stack_N.toml: drift <= 1e-6 m / 1e-6 rad, penetration <= 1e-6 m, T + V <= E0 + 1e-9 J."""
    model = ms.build_model(scene(name, dt=h, duration=duration))
    traj = ms.simulate(model, progress=False)
    dpos, drot = free_drift(model, traj)
    assert dpos <= 1e-6 and drot <= 1e-6, (dpos, drot)
    assert -traj.gap.min() <= 1e-6
    assert np.max(energy(traj) - energy(traj)[0]) <= 1e-9


# ------------------------------------------------------------------------------ 3. heavy_on_light
@pytest.mark.parametrize("ratio", [100, 1000])
@pytest.mark.parametrize("h,duration", [(1e-2, 10.0), (1e-3, 3.0)])
@pytest.mark.parametrize("correction", CORRECTIONS)
def test_heavy_ball_on_light_ball(ratio, h, duration, correction):
    """heavy_on_light_ball_R.toml: drift and penetration <= 1e-9 m, T + V <= E0 + 1e-11 |E0|
    (the potential energy of 1000 kg at 0.3 m is 2943 J: its round-off alone is ~1e-12 of it)."""
    model = ms.build_model(scene(f"heavy_on_light_ball_{ratio}", dt=h, duration=duration,
                                 position_correction=correction))
    traj = ms.simulate(model, progress=False)
    dpos, _ = free_drift(model, traj)
    assert dpos <= 1e-9
    assert -traj.gap.min() <= 1e-9
    E = energy(traj)
    assert np.max(E - E[0]) <= 1e-11 * abs(E[0])


@pytest.mark.parametrize("ratio,h,duration", [(100, 1e-2, 10.0), (100, 1e-3, 5.5), (1000, 1e-3, 2.0),
                                                (1000, 1e-2, 10.0), (10000, 1e-2, 10.0)])
def test_heavy_box_on_light_box(ratio, h, duration):
    """heavy_on_light_box_R.toml: drift <= 1e-6 m / 1e-6 rad, penetration <= 1e-6 m. (1:1000 at h = 1e-2
    tipped over at 6-9 s until the polish's refinement step, docs/theory.md §1.5.)"""
    model = ms.build_model(scene(f"heavy_on_light_box_{ratio}", dt=h, duration=duration))
    traj = ms.simulate(model, progress=False)
    dpos, drot = free_drift(model, traj)
    assert dpos <= 1e-6 and drot <= 1e-6, (dpos, drot)
    assert -traj.gap.min() <= 1e-6


# --------------------------------------------------------------------------------- 4. large steps
BUNDLED_ORIGINAL = ["block_on_step", "blocks_corner", "bouncing_ball", "box_drop", "corner_point",
                    "corner_point_asymmetric", "newton_cradle_5", "newton_cradle_5_gapped", "pendulum_wall",
                    "rocking_block"]
LARGE_STEP_CASES = [(n, h, c, b) for n in BUNDLED_ORIGINAL for h in (2e-2, 5e-2)
                    for c, b in (("none", "explicit"), ("projection", "midpoint"))
                    if not (n == "pendulum_wall" and b == "explicit")]


def test_large_steps_explicit_bias_gains_energy():
    """Pins bias = "midpoint" (default): with the explicit Coriolis terms the double pendulum gains
    2.9 % of E0 at h = 2e-2 and 17 % at 5e-2; with the midpoint rule it stays within 1 %."""
    for h, low in ((2e-2, 0.02), (5e-2, 0.1)):
        E = energy(run("pendulum_wall", dt=h, bias="explicit", position_correction="none"))
        assert np.max(E - E[0]) >= low * abs(E[0])
        E = energy(run("pendulum_wall", dt=h, bias="midpoint"))
        assert np.max(E - E[0]) <= 1e-2 * abs(E[0])


# the runs that break an invariant they check of themselves (docs/theory.md §10): none since the edge crossings of
# two boxes (§6.2; block_on_step at 2e-2 without correction, whose block rotating off its step deepened beyond its
# allowance through the step's edge, was flagged)
LARGE_STEP_FLAGGED: dict = {}


def invariants_broken(traj) -> set:
    return {v["invariant"] for v in traj.meta.get("invariants", [])}


@pytest.mark.parametrize("name,h,correction,bias", LARGE_STEP_CASES)
def test_large_steps_are_stable(name, h, correction, bias):
    """The bundled scenes at h = 2e-2 and 5e-2 (their own duration): the run completes with a finite
    state; T + V never above its start by more than 1e-9 |E0| (pendulum_wall, whose Coriolis terms
    are integrated to O(h): 1 % of E0); penetration <= 2 h reach max|u| + h^2 g (a contact closes
    within a step; reach: the largest lever arm of a vertex)."""
    model = ms.build_model(scene(name, dt=h, position_correction=correction, bias=bias))
    traj = ms.simulate(model, progress=False)
    flagged = LARGE_STEP_FLAGGED.get((name, h, correction, bias), set())
    assert traj.meta["status"] == ("flagged" if flagged else "complete") and invariants_broken(traj) == flagged
    assert np.isfinite(traj.q).all() and np.isfinite(traj.u).all()
    E = energy(traj)
    allowed = (1e-2 if name == "pendulum_wall" else 1e-9) * max(1.0, abs(E[0]))
    assert np.max(E - E[0]) <= allowed, np.max(E - E[0])
    if traj.gap.size:
        assert -traj.gap.min() <= 2 * h * model.reach * np.abs(traj.u).max() + h * h * G


# -------------------------------------------------------------------------------- 5. fast_impact
PLATE_TOP, PLATE_BOTTOM, MARBLE_R = 0.5, 0.49, 0.01


def marble_runs(q0s, **options):
    """min z of the marble's centre over 12 ms (it reaches the plate at ~3 ms) per start height."""
    base = scene("fast_impact", duration=0.012, **options)
    out = []
    for q0 in q0s:
        sc = dataclasses.replace(base, bodies=(dataclasses.replace(base.bodies[0], q0=(float(q0),)),))
        traj = ms.simulate(ms.build_model(sc), progress=False)
        out.append(traj.q[:, 0].min())
    return np.array(out)


def test_fast_impact_does_not_tunnel():
    """fast_impact.toml's bound: the marble's centre never gets below the plate (tunnelling =
    "swept", the default: the step looks along the motion when a body outruns the thinnest pair)."""
    traj = run("fast_impact")
    assert traj.q[:, 0].min() >= PLATE_BOTTOM - MARBLE_R


PHASES = 0.606 + 0.05 * np.arange(20) / 20  # start heights spread over one step's travel (5 cm)


def test_fast_impact_tunnelling_rate_with_midpoint_activation():
    """Measured: the midpoint lands in the 3 cm overlap window with probability 3/5, and in its upper
    half (normal pointing up) with 1.5/5: the marble passes at 1 - 0.3 = 70 % of phases."""
    zmin = marble_runs(PHASES, tunnelling="none")
    rate = np.mean(zmin < PLATE_BOTTOM - MARBLE_R)
    assert 0.6 <= rate <= 0.8, rate  # the failure tunnelling = "swept" (default) removes


@pytest.mark.parametrize("e,correction", [(0.0, "projection"), (0.5, "none"), (0.5, "projection"),
                                          (0.9, "none")])
def test_swept_contacts_stop_the_tunnelling(e, correction):
    zmin = marble_runs(PHASES, restitution=e, position_correction=correction)  # default: tunnelling = "swept"
    assert zmin.min() >= PLATE_BOTTOM + 0.5 * 0.01 - MARBLE_R  # never past the plate's mid-plane


def test_swept_test_leaves_ordinary_runs_unchanged():
    for name, T in (("bouncing_ball", 2.0), ("box_drop", 0.8), ("pendulum_wall", 0.5)):
        a = ms.simulate(ms.build_model(scene(name, duration=T, tunnelling="none")), progress=False)
        b = ms.simulate(ms.build_model(scene(name, duration=T, tunnelling="swept")), progress=False)
        # the sweep forced at every step changes nothing either
        c = ms.simulate(ms.build_model(scene(name, duration=T, tunnelling="always")), progress=False)
        assert np.array_equal(a.q, c.q) and np.array_equal(a.u, c.u), name
        assert np.array_equal(a.q, b.q) and np.array_equal(a.u, b.u), name


def test_swept_contacts_find_the_passage_through_the_plate():
    model = ms.build_model(scene("fast_impact"))
    data = ms.make_data(model)
    q0, q1 = np.array([0.54]), np.array([0.46])  # from 3 cm above the plate to past it
    assert pair_distance(model, data, q0, 0).min_distance > 0 and pair_distance(model, data, q1, 0).min_distance > 0
    found = swept_contacts(model, data, q0, q1)
    assert [c.pair for c in found] == [0]  # the plate, not the ground
    c = found[0]
    assert c.tunnels and c.converged
    assert abs(c.s - 0.03 / 0.08) <= 1e-9 / 0.08  # where the bottom meets the top (to tol / mu)
    np.testing.assert_allclose(c.normal, [0, 0, 1], atol=1e-12)
    assert abs(c.q[0] - (PLATE_TOP + MARBLE_R)) <= 1e-9
    assert swept_contacts(model, data, q0, np.array([0.52])) == []  # stops 1 cm short


def test_swept_contacts_on_a_rotating_chain():
    """pendulum_wall: the second bob swings into the wall within a large motion; the reported first
    contact is touching (gap ~ 0) and no point moved faster than the motion bound."""
    model = ms.build_model(scene("pendulum_wall"))
    data = ms.make_data(model)
    q0 = np.array([np.pi / 2, 0.0])  # horizontal, bobs at x = -0.5, -1.0: far from the wall at 0.45
    q1 = np.array([-np.pi / 2, 0.0])  # swung through to the wall's side
    found = swept_contacts(model, data, q0, q1)
    assert found and all(c.converged for c in found)
    for c in found:
        assert abs(pair_distance(model, data, c.q, c.pair).min_distance) <= 1e-6
        assert 0.0 < c.s < 1.0
    mu = motion_bounds(model, data, q0, q1)
    dq = pin.difference(model.pin, q0, q1)
    ss = np.linspace(0, 1, 201)
    for g, go in enumerate(model.geom.geometryObjects):
        if go.parentJoint == 0:
            continue
        pts = []
        for s in ss:
            q = pin.integrate(model.pin, q0, s * dq)
            pin.updateGeometryPlacements(model.pin, data.pin, model.geom, data.geom, q)
            pts.append(data.geom.oMg[g].translation.copy())
        speed = np.linalg.norm(np.diff(pts, axis=0), axis=1) / (ss[1] - ss[0])
        assert speed.max() <= mu[g] * (1 + 1e-9)


# ------------------------------------------------------------------------------- 6. spinning_box
@pytest.mark.parametrize("h", [1e-3, 1e-2])
@pytest.mark.parametrize("bias", ["midpoint"])
def test_spinning_box_free_flight_energy(h, bias):
    """spinning_box.toml: |T - T0|/T0 <= 1e-9 in free flight (t < 10 s; measured 1.5e-14 at h = 1e-3
    and 1.2e-13 at 1e-2: asserted <= 3e-13); the flip happens; the landing never raises T; angular
    momentum (world) drifts by <= 10 (h / 1 s)^2 of itself (measured 4.15 h^2)."""
    traj = run("spinning_box", dt=h, bias=bias)
    T = traj.kinetic_energy
    flight = traj.t < 10.0
    assert not np.any(traj.log_t < 10.0)  # no contact in free flight
    assert np.abs(T[flight] - T[0]).max() <= 3e-13 * T[0]
    assert np.sum(np.diff(np.sign(traj.u[flight, 4])) != 0) >= 2  # the Dzhanibekov flips
    assert T[~flight].max() <= T[flight][-1] * (1 + 1e-12)
    inertia = np.diag([0.0108333333333333, 0.00833333333333333, 0.00416666666666667])
    L = np.array([pin.Quaternion(q[6], q[3], q[4], q[5]).toRotationMatrix() @ (inertia @ u[3:6])
                  for q, u in zip(traj.q[flight], traj.u[flight])])
    assert np.linalg.norm(L - L[0], axis=1).max() <= 10 * h * h * np.linalg.norm(L[0])


@pytest.mark.parametrize("h,low", [(1e-3, 1e-2), (1e-2, 0.1)])
def test_spinning_box_explicit_bias_gains_energy(h, low):
    """Pins bias = "midpoint": the explicit gyroscopic term h(q_m, u_k) gains +2.9 % of T in 10 s of
    free flight at h = 1e-3 and +36 % at 1e-2 (the test above holds T to 1e-9 with the default)."""
    traj = run("spinning_box", dt=h, bias="explicit")
    T = traj.kinetic_energy[traj.t < 10.0]
    assert T.max() - T[0] >= low * T[0]


# ---------------------------------------------------------------------------- 7. column_of_beads
@pytest.mark.parametrize("name,duration,correction", [
    ("column_of_beads", 1.5, "none"), ("column_of_beads", 1.5, "projection"), ("column_of_beads_100", 0.4, "none"),
    ("column_of_beads_100", 0.4, "projection")])
def test_column_of_beads(name, duration, correction):
    """column_of_beads(_100).toml: T + V <= E0 + 1e-12 |E0|, penetration <= h sqrt(2 g z_top), no
    positive contact work (beyond round-off), the cascade reaches the upper beads (100: the
    lowest ten)."""
    traj = run(name, duration=duration, position_correction=correction)
    h = 5e-4
    E = energy(traj)
    assert np.max(E - E[0]) <= 1e-12 * abs(E[0])
    assert -traj.gap.min() <= h * np.sqrt(2 * G * traj.q[0].max())
    assert traj.contact_work.max() <= 1e-12 * abs(E[0])
    hit = {int(p) for p in traj.log_pair}
    assert len(hit) >= 10


@pytest.mark.parametrize("e,h", [(0.9, 5e-4), (0.3, 5e-4), (0.9, 1e-3)])  # (e = 0.5 does not come to rest:
# the top bead keeps a bounce of 2/3 h g on the one below, whose slow-impact test sees no gravity, §2.3)
def test_column_of_beads_rests_at_the_contact_tolerance(e, h):
    """column_of_beads.toml run to rest: every gap ends within the contact tolerance (1e-9 m) of zero
    - the correction lifts contacts that end a step at rest in full, beyond the step's dissipation
    (docs/theory.md §2.5) - with T + V never above E0, and the ledger E_end - E_0 = sum(W_c +
    correction) balanced (translations under gravity are exact): the lift's energy is booked, not
    physics."""
    traj = run("column_of_beads", restitution=e, dt=h, duration=3.0)
    assert np.abs(traj.u[-1]).max() <= 1e-12  # at rest
    rest = traj.t >= traj.t[-1] - 0.5
    assert -traj.gap[rest].min() <= 1e-9
    E = energy(traj)
    assert np.max(E - E[0]) <= 1e-12 * abs(E[0])
    assert abs(E[-1] - E[0] - traj.contact_work.sum() - traj.correction_energy.sum()) <= 1e-10 * abs(E[0])


# ----------------------------------------------------------------------------- 8. cradle_rounding
@pytest.mark.parametrize("name", ["cradle_rounding", "cradle_rounding_perturbed", "newton_cradle_5"])
@pytest.mark.parametrize("e", [1.0, 0.5, 0.0])
def test_cradle_rounding_gives_the_exact_touching_result(name, e):
    traj = run(name, restitution=e, duration=0.05)
    np.testing.assert_allclose(traj.u[-1], cradle_simultaneous(e), rtol=0, atol=1e-14)


def test_cradle_random_1e16_perturbations(tmp_path):
    """20 random variants: every ball moved by k 1e-16 m, k uniform in -3..3 (seeded)."""
    text = (SCENES / "cradle_rounding.toml").read_text().replace("../models", str(SCENES.parent / "models"))
    rng = np.random.default_rng(5)
    base = [0.1 + 0.2 * i for i in range(5)]
    for v in range(20):
        t = text
        for x in base:
            t = t.replace(f"q0 = [{x!r}]", f"q0 = [{float(x + int(rng.integers(-3, 4)) * 1e-16)!r}]", 1)
        p = tmp_path / f"cradle_{v}.toml"
        p.write_text(t)
        traj = ms.run(p, duration=0.05)
        np.testing.assert_allclose(traj.u[-1], cradle_simultaneous(1.0), rtol=0, atol=1e-14)


# ---------------------------------------------------------------------- 9. slider_crank_clearance
@pytest.mark.parametrize("correction,bias", [("none", "explicit"), ("projection", "midpoint")])
def test_slider_crank_clearance(correction, bias):
    """slider_crank_clearance.toml at h = 1e-5 (0.05 s, 5000 steps: about 0.8 of a crank turn):
    finite, T + V <= E0 + 1e-4 |E0| (stated; measured: never above E0, asserted to 1e-12 |E0|),
    max_i P_i/h <= 2e4 N (measured 6.3e3 N), the slider strikes the guide (impacts on both half-spaces)."""
    traj = run("slider_crank_clearance", duration=0.05, position_correction=correction, bias=bias)
    h = 1e-5
    # without the correction the slider's corner sliding on the guide drifts into it step after step (2.4 um over
    # 96 steps, allowed 0.18 um): flagged; the correction's paid lift holds it (docs/theory.md §2.5, §10)
    if correction == "none":
        assert traj.meta["status"] == "flagged" and invariants_broken(traj) == {"penetration"}
    else:
        assert traj.complete, traj.meta.get("invariants")
    assert np.isfinite(traj.q).all() and np.isfinite(traj.u).all()
    E = energy(traj)
    assert np.max(E - E[0]) <= 1e-12 * abs(E[0])
    assert traj.log_P.max() / h <= 2e4
    assert set(traj.log_pair.tolist()) == {0, 1}
    assert traj.q[-1, 0] > 3.0  # the crank kept turning (more than half a turn)
