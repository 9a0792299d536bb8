"""coal's cached GJK guess (contacts.fresh_guesses, src/step.cpp's mirror; docs/theory.md §6).

Exactly touching shapes leave coal a cached guess of ~5e-12 m; from it coal 3.0.3 reported a
6-14 mm overlap as no collision (boxes on a slope went 1.4-2.6 cm into it, whatever the step) and a
resting pair's distance as -DBL_MAX, written into trajectories. Every guess shorter than GUESS_MIN
is now rescaled to unit length before each call, and a failed distance is NaN, never data. A box pair's
contact deeper than the boxes can overlap (coal's EPA failing) is redone at coal's defaults.
"""

import math

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim.contacts import FeatureKind
from moreau_sim.errors import SimulationError

from helpers import MODELS, scene

# configurations where a pair rests exactly (gap ~ -5e-12 m) and coal's distance, warm-started from the
# guess the touching start q0 leaves, was -1.8e308 (heavy_on_light_box_10000 adaptive at t = 0.13 s;
# alternating_stack_10 event-driven at t = 0.49 s, its two lowest cubes, the others at q0)
RESTING = {
    "heavy_on_light_box_10000": [
        -1.149993468083452e-09, -7.247299404420154e-11, 0.05000000000018612, 8.056853766195464e-13,
        3.599574583477699e-12, 2.046281600181504e-17, 1.0, 1.1499934680834516e-13, 7.247299404420162e-15,
        0.15000000000006164, -1.2771293041684921e-12, 1.043627704925907e-12, 5.445016822843862e-25, 1.0],
    "alternating_stack_10": [
        -7.617580609327788e-10, -1.1472959756756821e-10, 0.050000000000096904, 8.192363629249161e-13,
        3.0892400600975516e-12, 9.603490252256703e-18, 1.0, 5.667377964323764e-12, 6.0478007281195975e-12,
        0.15000000000044644, 3.506603220473601e-12, 6.939121940491311e-13, -3.384744432756086e-21, 1.0],
}


@pytest.mark.parametrize("name", sorted(RESTING))
def test_a_distance_after_touching_shapes_is_the_true_distance(name):
    """pair_distances at the touching start, then at the resting configuration: every distance is
    within 1e-10 m of 0 (the pairs touch), as a fresh query gives it; none is a sentinel."""
    model = ms.build_model(scene(name))
    q = model.q0.copy()
    q[:len(RESTING[name])] = RESTING[name]
    data = ms.make_data(model)
    ms.pair_distances(model, data, model.q0)  # touching: leaves coal a guess of ~5e-12 m
    g = ms.pair_distances(model, data, q)
    fresh = ms.pair_distances(model, ms.make_data(model), q)
    assert np.isfinite(g).all() and g.min() > -1e100
    touching = np.abs(fresh) < 1e-9
    assert touching[0] and np.abs(g[touching]).max() < 1e-10
    assert np.abs(g[~touching] - fresh[~touching]).max(initial=0.0) < 1e-12


@pytest.mark.parametrize("tiny", [0.0, 1e-300, 5e-12, 1e-7, math.nan, math.inf])
def test_a_degenerate_guess_is_rescaled_before_the_call(tiny):
    """A guess of length 0, subnormal, tiny, NaN or inf: the distance of a ball 0.25 m above the ground is
    0.25 m (the guess is reset to its direction, or to (1, 0, 0)), as from a fresh query."""
    model = ms.build_model(scene("bouncing_ball"))
    data = ms.make_data(model)
    q = np.array([0.35])  # the ball's height [m]: 0.25 m above the ground
    for req in (*data.geom.distanceRequests, *data.geom.collisionRequests):
        req.cached_gjk_guess = np.array([0.0, 0.0, tiny])
    expected = ms.pair_distances(model, ms.make_data(model), q)
    assert np.allclose(expected, [0.25], rtol=0, atol=1e-12)
    assert np.array_equal(ms.pair_distances(model, data, q), expected)
    for req in data.geom.distanceRequests:
        n = float(np.linalg.norm(req.cached_gjk_guess))
        assert math.isfinite(n) and n > 1e-3


def slope(h: float, spin: float | None = None):
    """Issue 23's scene: three 0.1 m cubes 0.5 m apart at 1.0-1.4 m sliding down a slope of two static
    boxes 2 x 1 x 0.1 m tilted 0.25 rad, e = 0.3, 1.5 s. spin [rad/s]: a fourth cube, 50 m up and 10 m away
    (it touches nothing), spinning at this rate."""
    b = ms.SceneBuilder("slope3", restitution=0.3, dt=h, duration=1.5)
    if spin is not None:
        b.add_body("spinner", MODELS / "cube.urdf", root_joint="free", position=[10.0, 0.0, 50.0],
                   u0=[0.0, 0.0, 0.0, 0.0, 0.0, spin])
    th = 0.25
    b.add_box("slope_a", [2.0, 1.0, 0.1], position=[0.0, 0.0, 0.5], rpy=[0.0, th, 0.0])
    b.add_box("slope_b", [2.0, 1.0, 0.1], position=[-2.0 * np.cos(th), 0.0, 0.5 + 2.0 * np.sin(th)],
              rpy=[0.0, th, 0.0])
    for i in range(3):
        b.add_body(f"box{i}", MODELS / "cube.urdf", root_joint="free", position=[-0.5 * i, 0.0, 1.0 + 0.2 * i])
    b.add_halfspace("ground")
    return b.build()


@pytest.mark.parametrize("shift", [0.0, 10.0])
def test_a_static_is_no_lever_arm(shift):
    """Model.reach, the lever arm that turns |u|_inf into a vertex's travel in a step (the corner margin of
    contacts.detect, docs/theory.md §6.3), is the moving vertices' (at least 1 m): the slabs' far ends, 3.2 m from
    the origin (13 m shifted), do not move with u. Counted, they made the slope's corner margin at h = 2e-3 12 cm
    while a cube spun at 19 rad/s; a cube sliding off a slab's end then had its rear vertices, 9.6 cm behind
    the end face, at a corner of the slab that the end face separates, no row pushed, and it sank 6.9 mm."""
    b = ms.SceneBuilder("far_slab", dt=1e-3, duration=0.01)
    b.add_box("slab", [2.0, 1.0, 0.1], position=[shift + 2.0, 0.0, 0.5], rpy=[0.0, 0.25, 0.0])
    b.add_body("cube", MODELS / "cube.urdf", root_joint="free", position=[0.0, 0.0, 1.0])
    model = ms.build_model(b.build())
    assert model.reach == 1.0  # max(1 m, the cube's half diagonal 0.087 m)


def test_the_slope_runs_compiled_bit_for_bit():
    """The slope's slabs are boxes turned on the universe: the compiled step takes them (the run's steps handed back
    to Python: corners, edge crossings, paid lifts), and the run's arrays are the Python run's, bit for bit, through
    the cubes' landings, tumbles and slides off the slab's end at h = 2e-3 (1.5 s)."""
    runs = {impl: ms.simulate(ms.build_model(slope(2e-3).with_options(step_impl=impl)), progress=False)
            for impl in ("compiled", "python")}
    got, ref = runs["compiled"], runs["python"]
    assert got.meta["run"]["loop"] == "compiled" and got.meta["run"]["python_steps"] <= 30, got.meta["run"]
    assert got.complete and ref.complete
    assert got.arrays.keys() == ref.arrays.keys()
    for k, v in ref.arrays.items():
        assert np.asarray(got.arrays[k]).tobytes() == np.asarray(v).tobytes(), k


@pytest.mark.parametrize("spin", [0.0, 60.0])
def test_a_body_elsewhere_makes_no_corner(spin):
    """A pair's corner margin is how far its own two bodies can move in the step (Forest.joint_travel), not the
    fastest body's of the scene: a cube spinning at 60 rad/s 50 m above the slope made the margin h |u|_inf reach =
    12 cm at h = 2e-3 for every pair, a cube sliding off a slab's end had its rear vertices, 9.6 cm behind the
    end face, at a corner the end face separates, and it sank 4.9 mm into the slab (flagged). Now the slope
    holds with the spinner at rest or spinning, its deepest gap within one step's impact transient."""
    h = 2e-3
    traj = ms.run(slope(h, spin))
    assert traj.complete, traj.meta.get("invariants")
    assert -float(traj.arrays["gap"].min()) <= h * math.sqrt(2 * 9.81 * 1.4)


@pytest.mark.slow
def test_penetration_on_the_slope_shrinks_with_the_step():
    """The deepest gap of the slope scene is the impact transient of one step, h v: below h sqrt(2 g z0)
    (the fastest a cube released at z0 = 1.4 m can move) and shrinking with h. Before the rescale a
    missed contact left -1.43 cm at h = 1e-3 and -2.58 cm at 3e-4. Every run holds its invariants (no
    contact beyond its allowance for 3 steps: before the edge crossings of docs/theory.md §6.2 and the paid
    lift of §2.5, a cube tipping over a slab's end sank 1.8 mm into it), its ledger balances and the law's
    D = L holds on the law's velocity (§5.2), and no step gains."""
    v_max = math.sqrt(2 * 9.81 * 1.4)
    deepest = {}
    for h in (2e-3, 1e-3, 5e-4, 3e-4):
        traj = ms.run(slope(h))
        assert traj.complete, traj.meta.get("invariants")
        deepest[h] = -float(traj.arrays["gap"].min())
        assert 0.0 < deepest[h] <= h * v_max, (h, deepest[h])
        led = ms.ledger(traj)
        assert abs(led.residual) <= 1e-11 * led.scale and led.max_law_difference <= 1e-12 * led.scale
        assert led.max_step_rise <= 1e-14 * led.scale
    assert deepest[1e-3] > deepest[5e-4] > deepest[3e-4]


def test_a_failed_distance_stops_the_run_naming_the_pair(monkeypatch):
    """A distance coal cannot compute is NaN and stops the run (step, time, pair): never a sentinel in
    the records, never a silent complete run."""
    import moreau_sim.recording as recording
    real = recording.record_gaps

    def failing(model, data, q):
        g = real(model, data, q)
        if q[-1] < 0.9:
            g[0] = np.nan
        return g
    monkeypatch.setattr(recording, "record_gaps", failing)
    with pytest.raises(SimulationError) as info:  # the Python loop (the compiled one hands a NaN gap's step to it)
        ms.simulate(ms.build_model(scene("bouncing_ball", duration=1.0)), progress=False, python_run=True)
    msg = str(info.value)
    assert "step " in msg and "ball/ball_0|ground" in msg and "undefined" in msg
    traj = info.value.trajectory
    assert not traj.complete and np.isfinite(traj.arrays["gap"]).all()


# a cube rocking on its lower edge on a slab tilted 0.25 rad, 1.8e-10 m above it (a pose of
# test_impact_energy's slab run, h = 3e-4, e = 0.3, with a vertex rule of docs/theory.md §6.2 tried)
ON_THE_SLAB = [-0.4808969820523014, -2.7864846508458923e-33, 0.7272654451703974, -4.960553815815112e-19,
               0.11236223685229516, -2.0363398838928048e-18, 0.9936673123986463]


def test_a_box_pair_deeper_than_the_boxes_overlap_is_redone():
    """Where the cube's two lowest vertices are 1.8e-10 m from the slab, coal's EPA at data.GJK_TOLERANCE gives the
    pair a depth of 0.2 m (more than a 0.1 m cube can go into anything) and its patch corners took that gap: the
    run stopped with the cube 'sunk 0.2 m'. Deeper than box_box.depth_floor (4 times the boxes' penetration depth in
    closed form, box_box.overlap, + tol) the contact is redone at coal's defaults: every contact is then the
    vertices' own gap, and both steps take the same step from there."""
    b = ms.SceneBuilder("on_the_slab", restitution=0.3, dt=3e-4, duration=0.01)
    b.add_box("slope", [3.0, 1.0, 0.1], position=[0.0, 0.0, 0.5], rpy=[0.0, 0.25, 0.0])
    b.add_body("box", MODELS / "cube.urdf", root_joint="free", position=ON_THE_SLAB[:3], rpy=[0.0, 0.2252, 0.0])
    sc = b.build()
    q = np.array(ON_THE_SLAB)
    model = ms.build_model(sc)
    c = ms.detect(model, ms.make_data(model), q)
    assert c.m == 2 and (c.kind == FeatureKind.VERTEX).all()
    np.testing.assert_allclose(c.g, 1.809e-10, rtol=1e-3, atol=0)
    steps = []
    for impl in ("python", "compiled"):
        model = ms.build_model(sc.with_options(step_impl=impl))
        steps.append(ms.step(model, ms.make_data(model), ms.State(0.0, q, np.zeros(6))))
    assert steps[0].contacts.g.min() > -1e-9
    assert np.array_equal(steps[0].state.q, steps[1].state.q) and np.array_equal(steps[0].state.u, steps[1].state.u)
