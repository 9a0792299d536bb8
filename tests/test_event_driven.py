"""The event-driven reference against the closed forms of docs/theory.md §4, then its own
invariants (energy ledger, rest, Lie-group chart) on the scenes without a closed form."""

import re

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
from moreau_sim.adaptive import simulate_adaptive
from moreau_sim.event_driven import EventDrivenRun, UnsupportedModel, simulate_event_driven
from moreau_sim.testing.references import (
    ball_apex_gaps,
    ball_apex_times,
    ball_first_impact,
    ball_impact_times,
    cradle_sequential,
    zeno_time,
)
from moreau_sim.trajectory import ARRAYS

from helpers import BUNDLED, REFUSED, ROOT, inline_scene, lowest_corner_height, scene

G, D0 = 9.81, 0.9  # gravity [m/s^2]; the ball's initial gap [m] (centre at 1 m, r = 0.1 m)
T0 = ball_first_impact(D0, G)  # first impact time [s]


def ref(name: str, **kw) -> ms.Trajectory:
    opts = {k: kw.pop(k) for k in ("restitution", "duration") if k in kw}
    return simulate_event_driven(ms.build_model(scene(name, **opts)), **kw)


@pytest.mark.parametrize("e", [0.5, 0.8, 1.0])
def test_ball_impact_times_and_apex_heights(e):
    n = 6
    tn = np.array(ball_impact_times(e, n + 1, D0, G))  # t_k = t0 (1 + 2 e + ... + 2 e^k) (docs/theory.md §4)
    apex_t = np.array(ball_apex_times(e, n, D0, G))  # apex after bounce k: t_{k-1} + e^k t0
    tr = ref("bouncing_ball", restitution=e, duration=float(tn[n]) + 0.01, t_eval=np.r_[0.0, apex_t])
    assert tr.complete and tr.meta["integrator"] == "event-driven"
    assert np.abs(tr.log_t[:n + 1] - tn).max() < 1e-8
    assert np.abs(tr.gap[1:, 0] - np.array(ball_apex_gaps(e, n, D0))).max() < 1e-8
    assert np.abs(tr.u[1:, 0]).max() < 1e-8  # at the apex the ball is at rest
    assert np.allclose(tr.log_gamma_plus[:n], -e * tr.log_gamma_minus[:n], rtol=0, atol=1e-12)


@pytest.mark.parametrize("e", [0.5, 0.8])
def test_ball_zeno_time_and_rest(e):
    t_inf = zeno_time(e, D0, G)
    tr = ref("bouncing_ball", restitution=e, duration=t_inf + 0.5)
    assert tr.complete
    (z,) = tr.meta["zeno"]  # one accumulation point, declared just before it
    assert abs(z["t_accumulation"] - t_inf) < 1e-8 and t_inf - 1e-5 < z["t"] < t_inf
    after = tr.t > t_inf + 1e-6
    assert np.abs(tr.u[after]).max() < 1e-12 and np.abs(tr.gap[after]).max() < 1e-12  # resting
    assert np.all(tr.n_contacts[after] == 1)  # the persistent contact
    E = tr.kinetic_energy + tr.potential_energy
    assert abs(E[-1] - 1.0 * G * 0.1) < 1e-12  # all kinetic energy gone, centre at r
    assert abs(E[-1] - E[0] - tr.contact_work.sum()) < 1e-10  # the ledger: energy lost = impact losses


@pytest.mark.parametrize("e, expected", [(1.0, [-0.6, 0.4, 0.4, 0.4, 0.4]), (0.5, [-0.2, 0.3, 0.3, 0.3, 0.3])])
def test_touching_cradle_simultaneous(e, expected):
    tr = ref("newton_cradle_5", restitution=e, duration=0.5)
    assert tr.complete and tr.meta["run"]["impacts"] == 1
    assert np.abs(tr.u[-1] - expected).max() < 1e-12
    assert np.abs(tr.log_t).max() == 0.0  # the impact is at t = 0
    # balls 1-4 keep touching, idle (zero force, zero relative acceleration: docs/theory.md §7), not held
    assert np.abs(tr.gap[1:, 1:]).max() < 1e-15 and np.all(tr.n_contacts[1:] == 0)
    assert abs(tr.u[-1].sum() - 1.0) < 1e-12  # momentum


def test_gapped_cradle_sequential():
    tr = ref("newton_cradle_5_gapped", restitution=1.0, duration=0.5)
    assert tr.complete
    assert np.abs(tr.u[-1] - [0, 0, 0, 0, 1]).max() < 1e-12
    assert np.allclose(tr.log_t, [0.001, 0.002, 0.003, 0.004], rtol=0, atol=1e-12)  # 1 mm gaps at 1 m/s
    assert list(tr.log_pair) == [0, 1, 2, 3]


def test_gapped_cradle_e_half_matches_binary_impacts():
    """e = 0.5: repeated binary impacts; the order is fixed by the geometry, so the result is the
    reference's sweep of left-to-right binary Newton impacts (moreau_sim.testing.references)."""
    v = cradle_sequential(0.5)
    tr = ref("newton_cradle_5_gapped", restitution=0.5, duration=0.5)
    assert np.abs(tr.u[-1] - v).max() < 2e-2  # ordering differences only (peers/README.md)
    assert abs(tr.u[-1].sum() - 1.0) < 1e-12
    assert np.all(np.diff(tr.u[-1]) >= -1e-12)  # nobody approaches any more


def test_rocking_block_ledger_and_rest():
    tr = ref("rocking_block", duration=0.4)
    assert tr.complete and tr.meta["run"]["impacts"] > 10 and len(tr.meta["zeno"]) >= 2
    E = tr.kinetic_energy + tr.potential_energy
    ledger = E - E[0] - np.cumsum(tr.contact_work)
    assert np.abs(ledger).max() < 1e-9  # smooth phases (pivoting, flight) conserve energy exactly
    assert np.all(np.diff(E) <= 1e-9)
    assert tr.n_contacts[1] == 1  # it starts pivoting on one corner (a persistent contact)
    x, z, th = tr.q[-1]
    assert abs(z - 0.2) < 1e-9 and abs(th) < 1e-8 and np.abs(tr.u[-1]).max() < 1e-9  # flat at rest
    assert np.abs(tr.q[:, 0]).max() < 1e-12  # frictionless: the centre of mass stays on its vertical
    assert tr.gap.min() > -1e-9


def test_rocking_block_agrees_with_stepper_at_small_step():
    te = np.array([0.05, 0.1])
    tr = ref("rocking_block", duration=0.1, t_eval=te)
    ts = ms.simulate(ms.build_model(scene("rocking_block", dt=1e-4, duration=0.1)), progress=False)
    qs = ts.q[np.searchsorted(ts.t, te - 1e-12)]
    assert np.abs(qs - tr.q).max() < 1e-3  # first order: ~1e-4 m at h = 1e-4
    hits = ts.log_t[ts.log_impact & (ts.log_feature == tr.log_feature[0])]  # the other corner's first hit
    assert abs(tr.log_t[0] - hits[0]) < 2e-4


def test_pendulum_tolerance_convergence():
    te = np.linspace(0, 2.0, 9)
    a = ref("pendulum_wall", duration=2.0, t_eval=te)
    b = ref("pendulum_wall", duration=2.0, t_eval=te, rtol=1e-10, atol=1e-10)
    assert a.complete and len(a.log_t) == 2
    assert np.abs(a.q - b.q).max() < 1e-9 and np.abs(a.log_t - b.log_t).max() < 1e-10
    E = a.kinetic_energy + a.potential_energy
    assert np.abs(E - E[0] - np.cumsum(a.contact_work)).max() < 1e-9


def test_free_body_in_a_lie_group_chart():
    """box_drop (free root: translation + quaternion) through the chart q = q_b (+) delta."""
    te = np.linspace(0, 0.6, 7)
    tr = ref("box_drop", duration=0.6, t_eval=te)
    assert tr.complete and tr.meta["reference"]["lie_group_chart"] and tr.meta["run"]["impacts"] >= 3
    quat = tr.q[:, 3:]
    assert np.abs(np.linalg.norm(quat, axis=1) - 1).max() < 1e-12
    E = tr.kinetic_energy + tr.potential_energy
    assert np.abs(E - E[0] - np.cumsum(tr.contact_work)).max() < 1e-9
    assert tr.gap.min() > -1e-9
    # free fall before the first impact: the exact parabola
    t1 = tr.log_t[0]
    k = np.flatnonzero(te < t1)
    assert np.abs(tr.q[k, 2] - (0.6 - 0.5 * G * te[k] ** 2)).max() < 1e-12
    model = ms.build_model(scene("box_drop"))
    assert np.abs(pin.difference(model.pin, model.q0, tr.q[0])).max() == 0.0


def test_trajectory_schema_and_round_trip(tmp_path):
    tr = ref("bouncing_ball", restitution=0.8, duration=1.0)
    assert set(tr.arrays) == set(ARRAYS)
    n = len(tr.t)
    assert tr.q.shape == (n, 1) and tr.u.shape == (n, 1) and tr.gap.shape == (n, 1)
    assert np.allclose(np.diff(tr.t), 1e-3)  # default samples: every scene dt
    k = len(tr.log_t)
    assert tr.log_point.shape == (k, 3) and tr.log_impact.all() and tr.candidate_u_plus.shape == (0, 1)
    assert np.all(tr.t[np.minimum(tr.log_step, n - 1)] >= tr.log_t)  # log_step: the next sample
    back = ms.load_trajectory(tr.save(tmp_path / "ref.npz"))
    assert back.meta["integrator"] == "event-driven" and np.array_equal(back.q, tr.q)
    assert ms.summary(back)["impacts"] == k


def test_unsupported_pair_is_named():
    """A pair type without per-feature gaps (a moving box against a static cylinder) is refused by
    name, with the list of what is supported."""
    b = ms.SceneBuilder("box_on_cylinder", restitution=0.5, duration=0.1, folder=ROOT)
    b.add_body("box", "models/cube.urdf", position=(0.0, 0.0, 0.3))
    b.add_cylinder("post", 0.05, 0.2, position=(0.0, 0.0, 0.1))
    with pytest.raises(UnsupportedModel, match=re.escape("pair 'box/cube_0|post' (Box vs Cylinder)")):
        simulate_event_driven(ms.build_model(b.build()))


@pytest.mark.parametrize("name", BUNDLED)
def test_every_bundled_scene_runs_or_is_refused_by_name(name):
    """Each bundled scene runs 10 ms event-driven without energy gain, or is refused with
    UnsupportedModel naming the pair (REFUSED, precisely)."""
    model = ms.build_model(scene(name))
    if name in REFUSED:
        exc, message = REFUSED[name]
        with pytest.raises(exc, match=re.escape(message)):
            simulate_event_driven(model, t_end=0.01)
        return
    tr = simulate_event_driven(model, t_end=0.01)
    assert tr.meta["status"] == "complete" and tr.t[-1] == pytest.approx(0.01, abs=1e-15)
    E = tr.total_energy
    assert (E - E[0]).max() <= 1e-12 * (1.0 + np.abs(E).max())


@pytest.mark.parametrize("name, T", [("heavy_on_light_box_100", 1.0), ("box_stack_5", 0.5)])
def test_box_stacks_stay_at_rest(name, T):
    """Boxes resting on boxes (aligned: corners on corners; yawed: the octagon's edge crossings)
    stay at rest: q drifts <= 1e-9 over T, no impact, T + V never above its start."""
    tr = ref(name, duration=T)
    assert np.abs(tr.q - tr.q[0]).max() <= 1e-9
    assert tr.meta["run"]["impacts"] == 0
    E = tr.total_energy
    assert (E - E[0]).max() <= 1e-12 * abs(E[0])


@pytest.mark.parametrize("e", [0.0, pytest.param(0.5, marks=pytest.mark.slow), 1.0])
@pytest.mark.parametrize("case, rpy, z_rest", [("flat", (0.0, 0.0, 0.0), 0.15),
                                               ("edge", (np.pi / 4, 0.0, 0.6), 0.1 + 0.05 * np.sqrt(2))])
def test_cube_dropped_on_a_cube(case, rpy, z_rest, e):
    """A cube dropped 5 cm onto a cube resting on the ground, face down and aligned (corners on
    corners, the first impact 4 corners at once) or edge down across the lower cube's top face
    (an edge-on-face segment contact whose ends are edge crossings): T + V never rises, e = 1
    keeps it, e < 1 ends at rest in the closed-form equilibrium (z = 0.15 m, or 0.1 + 0.05 sqrt(2)
    m balanced on the edge: frictionless and symmetric) after the Zeno rule ends the bounces."""
    b = ms.SceneBuilder("cube_on_cube", restitution=e, duration=0.5, folder=ROOT)
    b.add_body("low", "models/cube.urdf", position=(0.0, 0.0, 0.05))
    b.add_body("top", "models/cube.urdf", position=(0.01, 0.003, z_rest + 0.05), rpy=rpy)
    b.add_halfspace("ground")
    tr = simulate_event_driven(ms.build_model(b.build()))
    E = tr.total_energy
    assert (E - E[0]).max() <= 1e-12 * E[0]
    if e == 1.0:
        assert E[-1] == pytest.approx(E[0], rel=1e-12)
    else:
        assert E[-1] == pytest.approx(G * (0.05 + z_rest), rel=1e-12)  # 1 kg each, at rest
        assert np.abs(tr.u[-1]).max() <= 1e-9


def tilted_drop(e: float, dt: float) -> ms.Model:
    """A cube (0.1 m, 1 kg) released at rest tilted, its lowest vertex over a static box's top face (z = 0)."""
    b = ms.SceneBuilder("tilted_drop", restitution=e, duration=0.29, dt=dt, folder=ROOT)
    b.add_body("cube", "models/cube.urdf", position=(0.01, -0.02, 0.3), rpy=TILT)
    b.add_box("table", (1.0, 1.0, 0.2), position=(0.0, 0.0, -0.1))
    return ms.build_model(b.build())


TILT = (0.3, 0.2, 0.1)


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_tilted_box_dropped_on_a_static_box(e):
    """Box on box: the first impact (one vertex on the face) at the closed-form time
    sqrt(2 h0 / g) with the closed-form percussion (1 + e) g t / (1/m + (r x n)' I^-1 (r x n));
    no energy gained (e = 1: none lost); the fixed midpoint step converges to it as h -> 0
    (h = 1e-4, 1e-5): impact times within 2 h, the state between the first two impacts and
    after them closer at the smaller h."""
    tr = simulate_event_driven(tilted_drop(e, 1e-3))
    h0 = 0.3 - lowest_corner_height(TILT, half=(0.05, 0.05, 0.05))
    t1 = np.sqrt(2 * h0 / G)
    R = pin.rpy.rpyToMatrix(*TILT)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * 0.05 @ R.T
    rn = np.cross(corners[np.argmin(corners[:, 2])], [0.0, 0.0, 1.0])
    k = 1.0 + rn @ np.linalg.solve(R @ np.eye(3) * (0.1 ** 2 / 6) @ R.T, rn)  # 1/m + ..., m = 1 kg
    log_t, log_P = tr.arrays["log_t"], tr.arrays["log_P"]
    assert log_t[0] == pytest.approx(t1, abs=1e-12)
    assert log_P[0] == pytest.approx((1 + e) * G * t1 / k, rel=1e-9)
    E = tr.total_energy
    assert (E - E[0]).max() <= 1e-12 * E[0]
    if e == 1.0:
        assert E[-1] == pytest.approx(E[0], rel=1e-12)
    impacts = np.unique(log_t)
    between = np.searchsorted(tr.t, 0.5 * (impacts[0] + impacts[1]))
    after = np.searchsorted(tr.t, 0.28)
    errs = []
    for h in (1e-4, 1e-5):
        ts = ms.simulate(tilted_drop(e, h), progress=False)
        t_fix = np.unique(ts.arrays["impact_t"])[:2]
        assert np.all(np.abs(t_fix - impacts[:2]) <= 2 * h)
        errs.append([np.abs(ts.u[np.argmin(np.abs(ts.t - tr.t[i]))] - tr.u[i]).max() for i in (between, after)])
    assert errs[1][0] < errs[0][0] / 10 and errs[1][1] < errs[0][1]


def test_bad_sample_times():
    with pytest.raises(ValueError, match="t_eval"):
        ref("bouncing_ball", duration=1.0, t_eval=[0.5, 0.2])


@pytest.mark.parametrize("name", ["rocking_block", "newton_cradle_5", "pendulum_wall", "box_drop"])
def test_feature_gaps_rows_and_drift_against_finite_differences(name):
    """The analytic gaps' first and second time derivatives along a motion (q, u, a):
    g' = w' u and g'' = w' a + drift, by central differences of q(t) = q (+) (t u + t^2/2 a)."""
    model = ms.build_model(scene(name))
    integ = EventDrivenRun(model, ms.make_data(model), 0.5, 1e-12, 1e-12, "DOP853", 1e-2, 10)
    rng = np.random.default_rng(1)
    q = pin.integrate(model.pin, model.q0, 0.05 * rng.standard_normal(model.nv))
    u, a = rng.standard_normal(model.nv), rng.standard_normal(model.nv)
    gaps = integ.rules.gaps.features
    fs = gaps(q, u)
    eps = 1e-4
    g = [gaps(pin.integrate(model.pin, q, s * u + 0.5 * s * s * a), u, rows=False).g for s in (-eps, eps)]
    assert np.allclose((g[1] - g[0]) / (2 * eps), fs.gamma, rtol=0, atol=1e-7)
    assert np.allclose((g[1] - 2 * fs.g + g[0]) / eps ** 2, fs.W.T @ a + fs.drift, rtol=0, atol=1e-5)


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_corner_point_takes_the_set_valued_law(e):
    """The point mass striking a convex corner (docs/theory.md §3.4, §4.4) at t = 0: with
    u- = (1, 0.5) the stationary points are v in {(1, 0), (0, 0.5), (0, 0)}, (1, 0) the unique
    global minimizer, u+ = (1, -0.5 e); with u- = (1, 1) two tie, (0, 1) and (1, 0)."""
    tr = ref("corner_point_asymmetric", restitution=e, duration=0.1)
    assert tr.log_t.tolist() == [0.0] and np.allclose(tr.u[-1], [1.0, -0.5 * e], rtol=0, atol=1e-12)
    v = (np.asarray(tr.candidate_u_plus) + e * np.array([1.0, 0.5])) / (1.0 + e)
    assert sorted(map(tuple, np.round(v, 9).tolist())) == [(0.0, 0.0), (0.0, 0.5), (1.0, 0.0)]
    assert tr.candidate_global_min.tolist().count(True) == 1 and tr.branch_chosen.tolist() == [0]
    loss = 0.5 * (1 - e * e) * 0.5 ** 2  # (1 - e^2)/2 |u- - v|_M^2
    assert tr.total_energy[-1] == pytest.approx(tr.total_energy[0] - loss, abs=1e-14)
    tr = ref("corner_point", restitution=e, duration=0.1)
    v = (np.asarray(tr.candidate_u_plus) + e) / (1.0 + e)
    assert sorted(map(tuple, np.round(v, 9).tolist())) == [(0.0, 0.0), (0.0, 1.0), (1.0, 0.0)]
    assert tr.candidate_global_min.tolist().count(True) == 2


def test_blocks_corner_outcomes():
    """The paper's two blocks meeting vertex to vertex (e = 1, docs/theory.md §4.4): the outcomes
    u+ in {(-0.2, -1, 2.4), (-1, -0.2, -2.4), (1, 1, 0)}, the first two the global minimizers; the
    run goes on with the first, keeps its energy, and agrees with the fixed step's limit."""
    tr = ref("blocks_corner")
    cands = np.round(np.asarray(tr.candidate_u_plus), 9) + 0.0
    assert sorted(map(tuple, cands.tolist())) == [(-1.0, -0.2, -2.4), (-0.2, -1.0, 2.4), (1.0, 1.0, 0.0)]
    assert tr.candidate_global_min.tolist() == [True, True, False]
    assert np.allclose(tr.u[1], [-0.2, -1.0, 2.4], rtol=0, atol=1e-12)
    E = tr.total_energy
    assert np.abs(E - E[0]).max() <= 1e-13
    errs = [np.abs(ms.simulate(ms.build_model(scene("blocks_corner", dt=h)), progress=False).q[-1] - tr.q[-1]).max()
            for h in (1e-3, 1e-4)]
    assert errs[1] < errs[0] / 5 and errs[1] < 2e-4  # first order in h towards the located impacts


def test_block_on_step_is_the_fixed_steps_limit():
    """A block landing with a corner on a step's edge (docs/theory.md §3, §7): the corner law at
    t = 0, then rocking, tipping and sliding on the step's top face (box features ending at their
    regions' ends, §7.1). The fixed step's error shrinks in proportion to h towards this run."""
    tr = ref("block_on_step", duration=0.6)
    assert tr.complete and len(tr.branch_t) == 1 and tr.branch_t[0] == 0.0
    errs = [np.abs(ms.simulate(ms.build_model(scene("block_on_step", duration=0.6, dt=h)), progress=False).q[-1]
                   - tr.q[-1]).max() for h in (1e-3, 1e-4)]
    assert errs[1] < errs[0] / 5 and errs[1] < 2e-4
    E = tr.total_energy
    assert (np.diff(E) <= 1e-12).all()  # never a gain


@pytest.mark.parametrize("integrator", ["event-driven", "adaptive"])
def test_a_fast_marble_does_not_pass_a_thin_plate(integrator):
    """fast_impact: 50 m/s onto a 1 cm plate (docs/theory.md §7: a step lets no point travel half
    the thinnest pair's extent, so no gap crosses a thin obstacle between two checks). The
    impact at the closed-form instant z(t) = 0.51 m, u+ = -e u-, and the marble stays above."""
    model = ms.build_model(scene("fast_impact", integrator=integrator))
    tr = simulate_event_driven(model) if integrator == "event-driven" else simulate_adaptive(model)
    g, z0, v0, e = 9.81, 0.656, 50.0, 0.5
    t1 = (-v0 + np.sqrt(v0 ** 2 + 2 * g * (z0 - 0.51))) / g  # z0 - v0 t - g t^2 / 2 = 0.51
    assert tr.log_t.tolist() == pytest.approx([t1], abs=1e-9) and tr.log_pair.tolist() == [0]
    assert tr.log_gamma_plus[0] == pytest.approx(-e * tr.log_gamma_minus[0], abs=1e-9)
    assert tr.q[:, 0].min() > 0.51 - 1e-9


@pytest.mark.slow
@pytest.mark.parametrize("name", ["alternating_stack_10", "heavy_on_light_box_100", "heavy_on_light_box_1000",
                                  "heavy_on_light_box_10000"])
def test_resting_stacks_run_to_the_end(name):
    """Every bundled resting stack over its full duration: one persistent phase whose contact
    forces (~R m g) are refined (docs/theory.md §1.5), so round-off does not tilt the boxes until
    a corner's feature flips: complete, q drifts <= 1e-6 m, no impact, T + V never above its start
    (issue 23: each aborted with "100 events without time advancing")."""
    tr = ref(name)
    assert tr.complete and tr.t[-1] == scene(name).options.duration
    assert np.abs(tr.q - tr.q[0]).max() <= 1e-6
    assert tr.meta["run"]["impacts"] == 0
    E = tr.total_energy
    assert (E - E[0]).max() <= 1e-12 * np.abs(E).max()


@pytest.mark.slow
@pytest.mark.parametrize("integrator", ["event-driven", "adaptive"])
def test_elastic_ball_for_400_s(integrator):
    """bouncing_ball at e = 1 for 400 s (467 impacts): every impact at t_n = t_0 (2n + 1), T + V
    constant to round-off. Past t = 64 s one ulp of absolute time moves the ball (4.2 m/s at
    impact) by 6e-14 m > G_RES/2: an event near a phase's start must be located in the phase's
    own time (issue 23: "100 events without time advancing" at t = 64.68 s). The times' bound:
    1e-12 s, plus the rounding of the phases' start times, at most one ulp of t per phase and
    four phases per bounce (impact, rise, apex region, ...), accumulated."""
    tr = ms.run(ROOT / "scenes" / "bouncing_ball.toml", integrator=integrator, restitution=1.0, duration=400.0,
                dt=0.01, **({"rtol": 1e-12, "atol": 1e-12} if integrator == "adaptive" else {}))  # 40,001 samples
    assert tr.complete
    n = np.arange(int((400.0 / T0 - 1.0) / 2.0) + 1)
    exact = T0 * (2 * n + 1)
    assert len(tr.log_t) == len(exact) == 467
    assert (np.abs(tr.log_t - exact) <= 1e-12 + 4 * np.cumsum(np.spacing(exact))).all()
    E = tr.total_energy
    assert np.abs(E - E[0]).max() <= 1e-13 * abs(E[0])


@pytest.mark.parametrize("integrator", ["event-driven", "adaptive"])
def test_a_light_ball_lifts_off_a_sphere_under_a_small_separating_acceleration(integrator, tmp_path):
    """A ball of 1 mg at the top of a static sphere (R = 0.6 m to its centre), v0^2 = g R (1 + 1e-4):
    the contact separates at once with a normal acceleration 1e-4 g, so the closed-form motion
    is the parabola x = v0 t, z = R - g t^2/2 (no contact ever). The ball is light so that the
    multiplier a persistent contact would need (-1e-4 g m = -1e-9 N) is within the release
    threshold LAM_EPS: the decision must come from the relative acceleration's own test
    (event_rules.ACC_TOL), not from a later release (docs/theory.md §7)."""
    urdf = tmp_path / "light_ball.urdf"
    urdf.write_text((ROOT / "models" / "ball.urdf").read_text().replace('mass value="1.0"', 'mass value="1e-6"')
                    .replace("0.004", "4e-9"))
    R = 0.6
    v0 = np.sqrt(G * R * (1.0 + 1e-4))
    b = ms.SceneBuilder("light_ball_on_sphere", restitution=0.5, dt=1e-3, duration=0.2)
    b.add_body("ball", urdf, root_joint="translation", axes=[[1, 0, 0], [0, 0, 1]], position=[0.0, 0.0, R],
               q0=[0.0, 0.0], u0=[v0, 0.0])
    b.add_sphere("dome", 0.5, position=[0.0, 0.0, 0.0])
    tr = ms.run(b.build(), integrator=integrator)
    assert tr.complete
    assert np.abs(tr.q[:, 0] - v0 * tr.t).max() <= 1e-12
    assert np.abs(tr.q[:, 1] + 0.5 * G * tr.t ** 2).max() <= 1e-12
    assert (tr.gap[1:] > 0.0).all() and len(tr.log_t) == 0 and tr.n_contacts.max() == 0


@pytest.mark.parametrize("integrator", ["event-driven", "adaptive"])
def test_lift_off_instant_from_a_sphere_sampled_to_1e_10_s(integrator):
    """A ball (1 kg, translations in x-z) riding a static sphere (R = 0.6 m to its centre) from the
    top with v0^2 = g R / 2 leaves it at cos theta* = 5/6, at t* = int_0^theta* dtheta / theta'
    (theta'^2 = v0^2/R^2 + 2 g (1 - cos theta)/R). Sampled every 1e-10 s from t* - 2e-9 to t* + 2e-9 s:
    one persistent contact before t*, none after (the release is located where the multiplier
    reaches -LAM_EPS = -1e-9 N, 2.7e-11 s after t*), so the located lift-off instant is t* to
    1e-10 s; before it the ball is on the circle. A lift-off is a C^2 event: an error dt in its
    instant moves the motion by O(dt^2) only, so only its sampled instant shows it (the adaptive
    integrator's event location with xtol 1e-6 instead of 1e-13 of the step put it 2.1e-10 s late)."""
    from scipy.integrate import quad

    R = 0.6
    v0 = np.sqrt(0.5 * G * R)
    th = np.arccos((2.0 + v0 * v0 / (G * R)) / 3.0)
    t_star = quad(lambda x: 1.0 / np.sqrt(v0 * v0 / R ** 2 + 2.0 * G * (1.0 - np.cos(x)) / R), 0.0, th,
                  epsabs=1e-14, epsrel=1e-14, limit=200)[0]
    b = ms.SceneBuilder("ball_on_sphere", restitution=0.5, dt=1e-3, duration=t_star + 1e-7)
    b.add_body("ball", ROOT / "models" / "ball.urdf", root_joint="translation", axes=[[1, 0, 0], [0, 0, 1]],
               position=[0.0, 0.0, R], q0=[0.0, 0.0], u0=[v0, 0.0])
    b.add_sphere("dome", 0.5, position=[0.0, 0.0, 0.0])
    model = ms.build_model(b.build())
    k = np.r_[-20:0, 1:21]
    t_eval = np.r_[0.0, t_star + 1e-10 * k]
    run = simulate_event_driven if integrator == "event-driven" else simulate_adaptive
    tr = run(model, t_eval=t_eval)
    assert tr.complete
    assert (tr.n_contacts[1:21] == 1).all() and (tr.n_contacts[21:] == 0).all()
    x, z = tr.q[1:21, 0], R + tr.q[1:21, 1]
    assert np.abs(np.hypot(x, z) - R).max() <= 1e-9


# ---- idle contacts (docs/theory.md §7, "Idle contacts"): touching, carrying nothing, not in C
RESTING_BALL = """
[scene]
name = "resting_ball"
[simulation]
restitution = 0.5
dt = 1e-3
duration = 1.0
gravity = [0, 0, {g}]
[[bodies]]
name = "ball"
urdf = "{{models}}/ball.urdf"
root_joint = "prismatic"
axis = [0, 0, 1]
q0 = [0.1]
[[statics]]
name = "ground"
shape = "halfspace"
normal = [0, 0, 1]
offset = 0.0
"""


@pytest.mark.parametrize("factor, persistent", [(0.99, False), (1.01, True)])
def test_idle_contact_threshold_edge(tmp_path, factor, persistent):
    """A 1 kg ball resting exactly on the ground under gravity g: its force m g changes its own relative
    acceleration by g, so it is idle just below IDLE_TOL (1 + g) and persistent just above."""
    from moreau_sim.event_rules import IDLE_TOL, EventState, make_rules, resolve

    g = factor * IDLE_TOL
    model = ms.build_model(inline_scene(RESTING_BALL.format(g=-g), tmp_path))
    data = ms.make_data(model)
    st = ms.initial_state(model, data)
    res = resolve(make_rules(model, data, 0.5), EventState(), 0.0, st.q, st.u, frozenset())
    assert res.C == ((0,) if persistent else ()) and not res.records


@pytest.mark.parametrize("integrate", [simulate_event_driven, simulate_adaptive])
def test_idle_resting_ball_is_in_free_flight(tmp_path, integrate):
    """Idle (gravity just below IDLE_TOL), the ball falls freely, g(t) = -g t^2 / 2: the bound on an idle
    contact's drift (docs/theory.md §7), until its rate returns below -2 V_TOL (at 2 V_TOL / g = 2000 s)."""
    from moreau_sim.event_rules import IDLE_TOL

    g = 0.99 * IDLE_TOL
    model = ms.build_model(inline_scene(RESTING_BALL.format(g=-g), tmp_path))
    tr = integrate(model, t_end=1.0)
    assert tr.complete and tr.meta["run"]["impacts"] == 0 and tr.meta["run"]["nfev_constrained"] == 0
    assert np.abs(tr.gap[:, 0] + 0.5 * g * tr.t ** 2).max() < 1e-16
    assert np.abs(tr.u[:, 0] + g * tr.t).max() < 1e-14  # (the dense output of a 1 s step)


STRUCK_ROW = """
[scene]
name = "struck_row"
[simulation]
restitution = {e}
dt = 1e-3
duration = 0.01
gravity = [0, 0, 0]
""" + "".join(f"""
[[bodies]]
name = "ball{i}"
urdf = "{{models}}/ball.urdf"
root_joint = "prismatic"
axis = [1, 0, 0]
q0 = [{x}]
u0 = [{1.0 if i == 0 else 0.0}]
""" for i, x in enumerate((-0.001, 0.2, 0.4, 0.6000000000000001, 0.8))) + """
[collisions]
exclude = [["ball0", "ball2"], ["ball0", "ball3"], ["ball0", "ball4"], ["ball1", "ball3"], ["ball1", "ball4"],
           ["ball2", "ball4"]]
"""


@pytest.mark.parametrize("integrate", [simulate_event_driven, simulate_adaptive])
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_idle_contacts_take_part_in_the_next_impact(tmp_path, integrate, e):
    """Four touching balls at rest carry nothing: no constrained phase before ball 0 (1 mm away at 1 m/s)
    strikes them at t = 1 ms, where their closed contacts join the impact: the simultaneous result of
    docs/theory.md §4.2; after it the touching balls fly together, again without a constrained phase."""
    model = ms.build_model(inline_scene(STRUCK_ROW.replace("{e}", str(e)), tmp_path))
    tr = integrate(model, t_end=0.01, t_eval=np.linspace(0.0, 0.01, 11))
    assert tr.complete and tr.meta["run"]["impacts"] == 1 and abs(tr.log_t[0] - 1e-3) < 1e-15
    expected = np.r_[(1 + e) / 5 - e, np.full(4, (1 + e) / 5)]
    assert np.abs(tr.u[-1] - expected).max() < 1e-14
    assert np.abs(np.diff(tr.q[:, 1:], axis=1) - 0.2).max() < 1e-15  # the touching balls stay touching
    assert tr.meta["run"]["nfev_constrained"] == 0


@pytest.mark.parametrize("integrate", [simulate_event_driven, simulate_adaptive])
def test_touching_cradle_after_the_strike_is_free_flight(integrate):
    tr = integrate(ms.build_model(scene("newton_cradle_5", restitution=1.0)), t_end=1.0)
    assert np.abs(tr.u[-1] - [-0.6, 0.4, 0.4, 0.4, 0.4]).max() < 1e-15
    assert np.abs(np.diff(tr.q[:, 1:], axis=1) - 0.2).max() < 1e-14
    assert tr.meta["run"]["nfev_constrained"] == 0


def test_slider_crank_corners_idle_after_their_accumulation_point():
    """After the accumulation point at 9.13 ms the slider's two corners touch the guide at zero force
    (idle, docs/theory.md §7): both integrators let them separate and agree through the next 17 impacts
    (held bilaterally, the event-driven run kept them and missed those impacts, 1 cm off)."""
    model = ms.build_model(scene("slider_crank_clearance", duration=0.05))
    grid = np.linspace(0.0, 0.05, 51)
    a = simulate_event_driven(model, t_eval=grid)
    b = simulate_adaptive(model, t_eval=grid)
    assert a.meta["run"]["impacts"] == b.meta["run"]["impacts"] == 29
    assert np.abs(a.q - b.q).max() < 1e-7 and np.abs(a.log_t - b.log_t).max() < 1e-9


def test_a_zero_multiplier_of_dependent_rows_is_not_idle():
    """A box resting flat on the ground: four corner rows of rank 3, the acceleration QP puts m g / 2 on two
    of the corners and 0 on the others; forces of dependent rows are not unique, so none is idle and all
    four stay in C (docs/theory.md §7, "Idle contacts")."""
    from moreau_sim.event_rules import EventState, make_rules, resolve

    model = ms.build_model(scene("resting_box"))
    data = ms.make_data(model)
    st = ms.initial_state(model, data)
    res = resolve(make_rules(model, data, 0.5), EventState(), 0.0, st.q, st.u, frozenset())
    assert len(res.C) == 4 and not res.records
