"""Persistent contacts are not impacts (docs/theory.md §5.2): a contact step whose contacts were all closed in the
step before and are at rest to the law's accuracy (ledger.at_rest) books no impact figures; the budget is
unchanged and closes; a resting contact that is struck is booked as an impact; both run loops agree bit for bit.

Exact references: a ball at rest on the ground under gravity g dissipates in its first contact step (a new
contact: the one impact) D = L = (1 - e)/(2(1 + e)) m g^2 h^2 and then nothing (every later step is persistent,
W_c = 0, T + V constant); the touching cradle's one impact is §4.2's closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim import compiled_run
from moreau_sim.law import outcome
from moreau_sim.ledger import REST_ACCURACY, at_rest, law_kept
from moreau_sim.testing import assert_budget_closes, assert_dissipation_follows_law, assert_no_energy_gain

from helpers import inline_scene, scene

G = 9.81  # [m/s^2] the scenes' gravity
R = 0.1  # [m] models/ball.urdf's radius (1 kg)


def _ball(name: str, z: float) -> str:
    return f"""
[[bodies]]
name = "{name}"
urdf = "{{models}}/ball.urdf"
root_joint = "prismatic"
axis = [0, 0, 1]
q0 = [{z!r}]
"""


def _balls(tmp_path, heights: list[float], e: float, h: float, duration: float) -> ms.Scene:
    """Balls (r = 0.1 m, 1 kg) on vertical prismatic joints at the given centre heights [m], at rest, over the
    ground (a half-space at z = 0)."""
    bodies = "".join(_ball(f"ball{i}", z) for i, z in enumerate(heights))
    toml = f"""[scene]
name = "resting_balls"
[simulation]
restitution = {e!r}
dt = {h!r}
duration = {duration!r}
{bodies}
[[statics]]
name = "ground"
shape = "halfspace"
normal = [0, 0, 1]
offset = 0.0
"""
    return inline_scene(toml, tmp_path, "resting_balls")


def _both(sc: ms.Scene) -> ms.Trajectory:
    """The run through the Python loop and, where it takes the scene, the compiled loop: the same arrays and
    ledger bit for bit."""
    ref = ms.simulate(ms.build_model(sc), progress=False, python_run=True)
    new = ms.simulate(ms.build_model(sc), progress=False)
    if compiled_run.unsupported(ms.build_model(sc), None) is None:
        assert new.meta["run"]["loop"] == "compiled"
    for k in set(ref.arrays) | set(new.arrays):
        a, b = np.asarray(ref.arrays[k]), np.asarray(new.arrays[k])
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), k
    assert ref.meta["ledger"] == new.meta["ledger"]
    return ref


# ---- the predicate at its edge -----------------------------------------------------------------------------------

def test_at_rest_at_the_edge_of_its_accuracy():
    """|gamma| <= REST_ACCURACY rho is at rest, the next float above is not, for gamma^k and gamma^{k+1} of
    either sign; rho = |W|'(|u_k| + |u_free - u_k|) (here 2 * 0.75 + 1 * 1 = 2.5, exact)."""
    W = np.array([[2.0], [-1.0]])
    u_k, u_free = np.array([0.25, 1.0]), np.array([-0.25, 1.0])
    bound = REST_ACCURACY * 2.5
    above = np.nextafter(bound, np.inf)
    zero = np.zeros(1)
    for g in (bound, -bound):
        assert at_rest(W, u_k, u_free, np.array([g]), zero) and at_rest(W, u_k, u_free, zero, np.array([g]))
    for g in (above, -above):
        assert not at_rest(W, u_k, u_free, np.array([g]), zero)
        assert not at_rest(W, u_k, u_free, zero, np.array([g]))
    assert at_rest(W, np.zeros(2), np.zeros(2), zero, zero)  # rho = 0: only exact zeros rest (the cradle)
    assert not at_rest(W, np.zeros(2), np.zeros(2), np.array([5e-324]), zero)
    assert not at_rest(W, u_k, u_free, np.array([np.nan]), zero)


def test_a_step_the_cap_or_a_paid_lift_changed_is_not_persistent():
    """law_kept: u_{k+1} must be law.outcome(v, u_k, e) bit for bit; one ulp off (what an energy cap or a lift
    paid with the velocities leaves) is not the law's."""
    v, u_k, e = np.array([0.0, 0.3]), np.array([-0.1, 0.3]), 0.5
    u_next = outcome(v, u_k, e)
    assert law_kept(v, u_k, u_next, e)
    assert not law_kept(v, u_k, np.nextafter(u_next, np.inf), e)


# ---- the ledger on resting contacts --------------------------------------------------------------------------------

@pytest.mark.parametrize("h", [1e-3, 5e-4])
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_resting_ball_books_one_impact(tmp_path, e, h):
    """A ball placed at rest on the ground: its first contact step is the one impact, D = L =
    (1 - e)/(2(1 + e)) m g^2 h^2; every later step is persistent (no dissipation booked, W_c = 0), T + V stays
    E_0, and the budget closes to round-off."""
    n = 400
    traj = _both(_balls(tmp_path, [R], e, h, n * h))
    L = ms.ledger(traj)
    one = (1.0 - e) / (2.0 * (1.0 + e)) * G * G * h * h
    assert L.contact_steps == n and len(L.impacts) == 1 and L.impacts[0].step == 1
    assert abs(L.impacts[0].dissipated - one) <= 1e-12 * (one + G * G * h * h)
    assert abs(L.dissipation - one) <= 1e-12 * (one + G * G * h * h)  # main: n times it
    assert abs(L.law - one) <= 1e-12 * (one + G * G * h * h)
    assert L.contact_work == 0.0 and np.all(traj.q == R)
    assert_budget_closes(traj, rtol=1e-12)
    # the contact force is still logged: the impact's row, then one row for the stretch of n - 1 persistent steps
    # with their percussions summed, P = m g h a step (not an impact after the first)
    assert traj.log_impact.tolist() == [True, False] and traj.log_steps.tolist() == [1, n - 1]
    assert np.allclose(traj.log_P / traj.log_steps, G * h, rtol=1e-12, atol=0.0)
    assert np.allclose(traj.log_duration, traj.log_steps * h, rtol=1e-12, atol=0.0)
    assert traj.log_step.tolist() == [1, 2] and traj.log_t[1] == 1.5 * h


@pytest.mark.parametrize("h", [1e-3, 5e-4])
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_touching_cradle_books_its_one_impact(e, h):
    """The touching cradle: the one impact of §4.2, then contacts that stay closed with P = 0 (persistent); the
    ledger's dissipation is the impact's closed form, the budget closes to round-off."""
    traj = _both(scene("newton_cradle_5", restitution=e, dt=h, duration=0.25))
    L = ms.ledger(traj)
    (imp,) = L.impacts
    loss = 0.5 * (1 - e * e) * np.sum((np.eye(5)[0] - 0.2) ** 2)
    assert abs(imp.dissipated - loss) <= 1e-15 and abs(L.dissipation - loss) <= 1e-15
    assert L.contact_steps == round(0.25 / h)  # the balls that move together stay closed
    assert_budget_closes(traj, rtol=1e-12)
    assert_no_energy_gain(traj, rtol=1e-12)


@pytest.mark.parametrize("h", [1e-2, 5e-3])
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("name", ["resting_box", "alternating_stack_10", "box_stack_5"])
def test_resting_stacks_book_one_impact(name, e, h):
    """Boxes placed at rest on the ground and on each other (rotations, many contacts, the QP's answers, |gamma|
    ~1e-13 m/s): the first step is the one impact, the whole stack's kick g h taken up by the ground,
    D = (1 - e)/(2(1 + e)) M g^2 h^2 (M: the stack's mass); every later step is persistent (main booked that
    again every step); the budget closes to round-off."""
    sc = scene(name, restitution=e, dt=h)
    n = 60
    traj = _both(sc.with_options(duration=n * h))
    L = ms.ledger(traj)
    mass = sum(float(i.mass) for tree in ms.build_model(sc).forest.trees for i in tree.model.inertias)
    one = (1.0 - e) / (2.0 * (1.0 + e)) * mass * G * G * h * h
    assert L.contact_steps == n and len(L.impacts) == 1 and L.impacts[0].step == 1
    assert abs(L.dissipation - one) <= 1e-12 * L.scale and abs(L.law - one) <= 1e-12 * L.scale
    assert_budget_closes(traj, rtol=1e-12)
    assert_dissipation_follows_law(traj, rtol=1e-12)
    assert_no_energy_gain(traj, rtol=1e-12)


# ---- the log of a rest: one row per contact ------------------------------------------------------------------------

@pytest.mark.parametrize("h", [1e-3, 5e-4])
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_a_rest_is_one_log_row_with_its_steps_percussions_summed(tmp_path, e, h):
    """The resting ball's log: the impact's row (step 1), then one row for the n - 1 persistent steps, whose P is
    the sum of those steps' percussions as the step computes them, added in step order, bit for bit; its
    duration the sum of their h, its point, normal, gap and gammas those of its first step (step 2)."""
    n = 300
    sc = _balls(tmp_path, [R], e, h, n * h)
    traj = _both(sc)
    model = ms.build_model(sc)
    data, state = ms.make_data(model), ms.initial_state(model)
    P, first = [], None
    for k in range(n):
        r = ms.step(model, data, state, h=h, e=e, t_next=(k + 1) * h)
        P.append(float(r.P[0]))
        if k == 1:
            first = r
        state = r.state
    total, duration = P[1], h
    for p in P[2:]:
        total += p
        duration += h
    assert traj.log_steps.tolist() == [1, n - 1] and traj.log_step.tolist() == [1, 2]
    assert traj.log_P[0] == P[0] and traj.log_P[1] == total and traj.log_duration.tolist() == [h, duration]
    assert traj.log_gap[1] == first.contacts.g[0] and traj.log_gamma_plus[1] == first.gamma_plus[0]
    assert traj.log_point[1].tobytes() == first.contacts.point_a[0].tobytes()
    assert abs(traj.log_P[1] - (n - 1) * G * h) <= 1e-12 * n * G * h  # the weight's impulse over the rest


@pytest.mark.parametrize("name", ["resting_box", "alternating_stack_10", "box_stack_5"])
def test_a_resting_stack_logs_its_rest_in_stretches(name):
    """A stack at rest: the first step's rows (all new impacts), then stretches of persistent steps, one row per
    contact each, that tile steps 2..n (a stretch ends where the pushing contacts change: of a face's four
    corners on a plane the QP's answer leaves the weight on any three); the impulse of the rest on the ground is
    the stack's weight times its duration."""
    n, h = 60, 1e-2
    sc = scene(name, dt=h).with_options(duration=n * h)
    traj = _both(sc)
    m = int((traj.log_step == 1).sum())
    assert m > 0 and traj.log_impact[:m].all() and not traj.log_impact[m:].any()
    step, steps = traj.log_step[m:], traj.log_steps[m:]
    starts = np.unique(step)
    assert starts[0] == 2 and len(starts) < n - 1  # fewer stretches than steps
    for a, b in zip(starts, list(starts[1:]) + [n + 1]):
        assert (steps[step == a] == b - a).all()  # each stretch's rows cover its steps, up to the next stretch
    mass = sum(float(i.mass) for tree in ms.build_model(sc).forest.trees for i in tree.model.inertias)
    ground = [i for i, p in enumerate(ms.build_model(sc).pairs) if p.name.endswith("|ground")]
    on_ground = np.isin(traj.log_pair[m:], ground)
    assert abs(traj.log_P[m:][on_ground].sum() - mass * G * (n - 1) * h) <= 1e-9 * mass * G * n * h


# ---- a resting contact that is struck --------------------------------------------------------------------------------

@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_a_struck_resting_contact_is_an_impact(tmp_path, e):
    """Ball A rests on the ground; ball B falls d = 0.05 m onto it. The step where B arrives (t* = sqrt(2 d/g)
    after the start, within a step) is booked as an impact, with D = L, and the ground contact under A (persistent
    until then) transmits it: its percussion in that step exceeds its resting m g h many times."""
    h, d = 1e-3, 0.05
    sc = _balls(tmp_path, [R, 3 * R + d], e, h, 0.15)
    traj = _both(sc)
    L = ms.ledger(traj)
    t_star = math.sqrt(2 * d / G)
    struck = [r for r in L.impacts if r.step > 1]
    assert struck and abs(struck[0].t - t_star) <= h
    assert abs(struck[0].difference) <= 1e-12 * L.scale and struck[0].contacts == 2  # B on A, A on the ground
    assert struck[0].dissipated > 0.0 if e < 1 else abs(struck[0].dissipated) <= 1e-12 * L.scale
    k = struck[0].step
    pairs = [p.name for p in ms.build_model(sc).pairs]
    pair = next(i for i, p in enumerate(pairs) if p.startswith("ball0/") and p.endswith("|ground"))
    ground = (traj.log_step == k) & (traj.log_pair == pair)
    assert ground.sum() == 1 and not traj.log_impact[ground][0]  # the same contact, closed before
    rest = np.flatnonzero((traj.log_pair == pair) & (traj.log_step < k))[-1]  # its rest until then: one row
    assert traj.log_step[rest] == 2 and traj.log_step[rest] + traj.log_steps[rest] == k
    assert traj.log_P[ground][0] > 10 * G * h
    assert_budget_closes(traj, rtol=1e-12)
    assert_dissipation_follows_law(traj, rtol=1e-12)
