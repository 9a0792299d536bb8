"""Two implementations, one truth: the impact at a located event compiled (src/impact.hpp,
compiled_events.CompiledImpact) against its Python one (event_rules._impact): the detection at q, the constraints,
the Zeno rule and law.impact with Pinocchio's M^-1 in the same floating-point operations in the same order
(docs/theory.md §2.8), so that the adaptive and event-driven runs give the same arrays bit for bit either way.

Every bundled scene whose events the compiled impact takes (compiled_events.impact_unsupported is None) runs the
adaptive integrator, and a few the event-driven one, with the compiled impact and with the Python one
(Rules.impact = None), over the byte-identity runs' durations; how many impacts ran compiled is counted and asserted
> 0 where the scene has impacts that coal's rows describe, so that "equal because nothing ran compiled" shows.
Through the compiled path the ball's impact instants and the touching cradle's velocities after its impact are their
closed forms (docs/theory.md §4.1, §4.2), and a corner (the set-valued law, §3) is handed back to Python and still
exact. The adaptive integrator's event location in free flight compiled (src/locate.hpp) likewise: runs both ways,
and random step ends bit for bit.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import moreau_sim.compiled as compiled
from moreau_sim import compiled_events
from moreau_sim.actuation import refuse_driven
from moreau_sim.adaptive import DEFAULT_ORDER, AdaptiveRun
from moreau_sim.data import make_data
from moreau_sim.drive import refuse as refuse_drives
from moreau_sim.driver import drive
from moreau_sim.errors import SceneError, SimulationError
from moreau_sim.event_driven import EventDrivenRun
from moreau_sim.event_rules import sample_grid
from moreau_sim.gaps import UnsupportedModel, feature_list
from moreau_sim.model import build_model, initial_state
from moreau_sim.scene import load_scene
from moreau_sim.testing.references import ball_impact_times, cradle_simultaneous

SCENE_DIR = Path(__file__).resolve().parent.parent / "scenes"
SCENES = sorted(SCENE_DIR.glob("*.toml"))
HEAVY = ("quadruped", "solo", "panda", "column_of_beads_100", "box_stack_10", "heavy_on_light_box_10000",
         "heavy_on_light_ball_1000", "heavy_on_light_box_1000")
# scenes with impacts whose rows are coal's: some must run compiled
MUST_COMPILE = {"bouncing_ball", "zeno_ball", "newton_cradle_5", "newton_cradle_5_gapped", "box_drop", "rocking_block",
                "pendulum_wall", "pendulum_limit", "fast_impact", "slider_crank_clearance"}
INTEGRATORS = ("adaptive", "event-driven")
# the event-driven integrator (slower: solve_ivp between events) on these, over 0.5 s (1 s: the pendulum's first impact)
EVENT_DRIVEN = {"bouncing_ball": 0.5, "zeno_ball": 0.5, "box_drop": 0.5, "rocking_block": 0.5, "newton_cradle_5": 0.5,
                "newton_cradle_5_gapped": 0.5, "pendulum_wall": 1.0, "pendulum_limit": 0.5, "fast_impact": 0.5,
                "blocks_corner": 0.5, "corner_point": 0.5}
RUNS = [(p, "adaptive") for p in SCENES] + [(SCENE_DIR / f"{n}.toml", "event-driven") for n in EVENT_DRIVEN]


class _Counted:
    """A CompiledImpact that counts the events it took."""

    def __init__(self, inner):
        self.inner, self.taken = inner, 0

    @property
    def reasons(self):
        return self.inner.reasons

    def takes(self, coal_rows: bool) -> bool:
        return self.inner.takes(coal_rows)

    def __call__(self, *args):
        got = self.inner(*args)
        self.taken += got is not None
        return got


def _run(scene, integrator: str, compiled_impact: bool):
    """The run of `scene` with `integrator` and the compiled impact (or the Python one): (arrays, the counting
    CompiledImpact or None, impacts)."""
    model = build_model(scene.with_options(integrator=integrator))
    refuse_driven(model, integrator)
    refuse_drives(model, integrator)
    data = make_data(model)
    state = initial_state(model, data)
    t_end, grid = sample_grid(model, state, None, None)
    o = model.options
    if integrator == "adaptive":
        run = AdaptiveRun(model, data, o.restitution, o.rtol, o.atol, DEFAULT_ORDER, 1.0, 10 ** 6, state=state,
                          t_end=t_end)
    else:
        run = EventDrivenRun(model, data, o.restitution, 1e-12, 1e-12, "DOP853", 1e-2, 100_000, state=state,
                             t_end=t_end)
    counted = None
    if not compiled_impact:
        run.rules = dataclasses.replace(run.rules, impact=None)
    elif run.rules.impact is not None:
        counted = _Counted(run.rules.impact)
        run.rules = dataclasses.replace(run.rules, impact=counted)
    try:
        traj = drive(run, model, data, grid=grid, capacity=len(grid))
    except Exception as exc:  # a run that fails fails alike both ways, up to the same sample
        traj = getattr(exc, "trajectory", None)
        if traj is None:
            raise
    return traj.arrays, counted, run.s.ev.impacts


def _refusal(path) -> str | None:
    """Why the compiled impact does not take the scene's events (None: it does)."""
    model = build_model(load_scene(path))
    try:
        feats = feature_list(model)
    except UnsupportedModel as exc:
        return str(exc)
    return compiled_events.impact_unsupported(model, make_data(model), feats)


def _same(ref: dict, got: dict) -> None:
    assert set(ref) == set(got)
    for key in ref:
        x, y = np.asarray(ref[key]), np.asarray(got[key])
        assert x.shape == y.shape and x.tobytes() == y.tobytes(), (key, x.shape, y.shape)


def test_the_compiled_impact_is_available():
    assert compiled.available(), compiled.unavailable_reason()
    model = build_model(load_scene(SCENE_DIR / "bouncing_ball.toml"))
    data = make_data(model)
    assert compiled_events.impact_unsupported(model, data, feature_list(model)) is None
    py = build_model(load_scene(SCENE_DIR / "bouncing_ball.toml").with_options(step_impl="python"))
    assert compiled_events.impact_unsupported(py, make_data(py), feature_list(py)) == "step_impl python"
    moving = build_model(load_scene(SCENE_DIR / "vibrating_paddle.toml"))
    assert compiled_events.impact_unsupported(moving, make_data(moving), feature_list(moving)) == \
        "moving statics or driven joints"


@pytest.mark.parametrize("path, integrator", [pytest.param(p, i, id=f"{p.stem}-{i}", marks=[pytest.mark.slow] if (
    p.stem, i) == ("block_on_step", "adaptive") else []) for p, i in RUNS])
def test_same_runs_with_the_compiled_impact(path, integrator):
    """The adaptive run of every bundled scene the compiled impact takes, and the event-driven run of a few: the same
    arrays bit for bit with the compiled impact and with the Python one; some impacts compiled where the scene has
    them (and every impact either compiled or counted as handed back)."""
    why = _refusal(path)
    if why is not None:  # refused by name: moving statics / drives, or a pair the event integrators do not take
        assert why == "moving statics or driven joints" or "the feature integrators" in why, why
        return
    scene = load_scene(path)
    longest = EVENT_DRIVEN[path.stem] if integrator == "event-driven" else 1.0
    duration = min(scene.options.duration, 0.3 if any(h in path.stem for h in HEAVY) else longest)
    scene = scene.with_options(duration=duration)
    try:
        ref, _, impacts_ref = _run(scene, integrator, False)
    except SceneError as exc:  # refused alike both ways
        with pytest.raises(SceneError) as again:
            _run(scene, integrator, True)
        assert str(again.value) == str(exc)
        return
    got, counted, impacts = _run(scene, integrator, True)
    assert impacts == impacts_ref
    if counted is None:  # the adaptive run has no features for this model (AdaptiveRun.unsupported): fixed steps
        assert integrator == "adaptive" and scene.name not in MUST_COMPILE
        _same(ref, got)
        return
    print(f"{scene.name} {integrator}: {impacts} impacts, {counted.taken} compiled, handed back {counted.reasons}")
    if scene.name in MUST_COMPILE:
        assert counted.taken > 0
    assert counted.taken + sum(counted.reasons.values()) == impacts  # every impact tried compiled, or counted back
    _same(ref, got)


@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("e", [0.0, 0.5, 0.8, 1.0])
def test_ball_impact_times_through_the_compiled_impact(e, integrator):
    """The ball dropped from a 0.9 m gap: every impact through the compiled impact, at the closed form's instants
    t_k = t0 (1 + 2 e + ... + 2 e^k) (docs/theory.md §4.1); e = 0: one impact, then at rest on the ground."""
    T = 2.5
    scene = load_scene(SCENE_DIR / "bouncing_ball.toml").with_options(restitution=e, duration=T, rtol=1e-10,
                                                                      atol=1e-12)
    got, counted, impacts = _run(scene, integrator, True)
    ref = np.array(ball_impact_times(e, 1 if e == 0.0 else 6))  # e < 1: well before the accumulation (§7)
    ref = ref[ref < T - 1e-3]
    n = len(ref)
    assert impacts >= n and counted.taken == impacts and not counted.reasons
    tol = 1e-9 if integrator == "adaptive" else 1e-8
    assert np.abs(got["log_t"][:n] - ref).max() < tol
    if e == 0.0:
        assert impacts == 1 and abs(got["u"][-1, 0]) < 1e-12


@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("e", [0.0, 0.5, 0.8, 1.0])
def test_cradle_velocities_through_the_compiled_impact(e, integrator):
    """The touching cradle struck at 1 m/s: one impact, through the compiled impact, leaving the simultaneous law's
    velocities u_1 = (1 + e)/5 - e, u_2..5 = (1 + e)/5 [m/s] (docs/theory.md §4.2); momentum 1 kg m/s kept."""
    scene = load_scene(SCENE_DIR / "newton_cradle_5.toml").with_options(restitution=e, duration=0.3, rtol=1e-10,
                                                                        atol=1e-12)
    got, counted, impacts = _run(scene, integrator, True)
    assert impacts == 1 and counted.taken == 1 and not counted.reasons
    assert np.abs(got["u"][-1] - np.array(cradle_simultaneous(e))).max() < 1e-12
    assert abs(got["u"][-1].sum() - 1.0) < 1e-12


@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_a_corner_is_handed_back_and_exact(e, integrator):
    """The particle striking the convex corner of a block with u- = (1, 0.5) (docs/theory.md §3): the compiled
    detection sees a vertex at a box's edge and hands the event back; the Python set-valued law gives the unique
    global minimizer v = (1, 0), u+ = (1, -0.5 e), and the run is the one without the compiled impact, bit for bit."""
    scene = load_scene(SCENE_DIR / "corner_point_asymmetric.toml").with_options(restitution=e, duration=0.2)
    ref, _, _ = _run(scene, integrator, False)
    got, counted, impacts = _run(scene, integrator, True)
    assert impacts >= 1 and counted.taken == 0 and sum(counted.reasons.values()) == impacts
    assert np.abs(got["u"][-1] - [1.0, -0.5 * e]).max() < 1e-12
    _same(ref, got)


# ---- the event location in free flight (src/locate.hpp, compiled_events.locator) ----------------------------------
LOCATE_SCENES = ["bouncing_ball", "zeno_ball", "newton_cradle_5", "newton_cradle_5_gapped", "box_drop", "rocking_block",
                 "pendulum_wall", "column_of_beads", "fast_impact"]


def _adaptive(name: str, *, locate: bool = True, phase: bool = False, tol: tuple | None = None, q0=None, u0=None,
              **options):
    """The adaptive run of scene `name` to its end or its error, its event location compiled (locate) or Python's,
    its free-flight steps in one call (phase, src/phase.hpp) or with the calls one by one; tol: (rtol, atol) below
    what the scene's options accept; q0, u0: another start (the start checks passed at the scene's). Returns
    (trajectory, error message or None, what the compiled call answered each time: with phase the one call's status,
    with a landing's kind as (status, 0 a gap / 1 a return); else the compiled location's status)."""
    model = build_model(load_scene(SCENE_DIR / f"{name}.toml").with_options(integrator="adaptive", **options))
    data = make_data(model)
    state = initial_state(model, data)
    if q0 is not None:
        state = dataclasses.replace(state, q=np.array(q0, float), u=np.array(u0, float))
    t_end, grid = sample_grid(model, state, None, None)
    o = model.options
    rtol, atol = tol or (o.rtol, o.atol)
    run = AdaptiveRun(model, data, o.restitution, rtol, atol, DEFAULT_ORDER, 1.0, 10 ** 6, state=state, t_end=t_end)
    calls = []
    if not locate:
        run.locate = None
    if phase:
        assert run.phase is not None or name in NO_PHASE
        if run.phase is not None:
            whole = run.phase

            def counted_phase(*args):
                got = whole(*args)
                calls.append(got[0] if got[7] is None else (got[0], got[7][1]))
                return got
            run.phase = counted_phase
    else:
        run.phase = None
        if run.locate is not None:
            inner = run.locate

            def counted(*args):
                got = inner(*args)
                calls.append(got[0])
                return got
            run.locate = counted
    try:
        return drive(run, model, data, grid=grid, capacity=len(grid)), None, calls
    except SimulationError as exc:
        return exc.trajectory, str(exc), calls


@pytest.mark.parametrize("name", LOCATE_SCENES)
def test_same_runs_with_the_compiled_event_location(name):
    """The adaptive run with the compiled event location and with the Python one: the same arrays bit for bit; the
    compiled one answered (a model with box features keeps the Python location: none there)."""
    ref, err_ref, none = _adaptive(name, locate=False, duration=1.0)
    got, err_got, answers = _adaptive(name, duration=1.0)
    assert err_ref is None and err_got is None
    assert none == []
    assert sum(a >= 0 for a in answers) > 0
    _same(ref.arrays, got.arrays)


# no free-flight step in one call: a free body (a Lie group: box_drop), features the compiled gaps do not take
# (a sphere against a box: pendulum_wall, fast_impact)
NO_PHASE = {"box_drop", "pendulum_wall", "fast_impact"}


@pytest.mark.parametrize("e", [0.5, 1.0])
@pytest.mark.parametrize("name", LOCATE_SCENES)
def test_same_runs_with_the_free_flight_step_in_one_call(name, e):
    """The adaptive run with its free-flight steps in one call (src/phase.hpp: the step sizes, the step's end, the
    event location, the landing) and with those calls one by one: the same arrays bit for bit and the same counts
    (steps refused and landed, step ends evaluated); the call answered where the model qualifies."""
    ref, err_ref, _ = _adaptive(name, duration=1.0, restitution=e)
    got, err_got, calls = _adaptive(name, phase=True, duration=1.0, restitution=e)
    assert err_ref is None and err_got is None
    taken = [c for c in calls if (c[0] if isinstance(c, tuple) else c).name in ("ACCEPTED", "LANDED")]
    assert (len(taken) > 0) is (name not in NO_PHASE)
    _same(ref.arrays, got.arrays)
    for k in ("steps", "steps_extrapolated", "steps_refused", "steps_landed", "events", "impacts", "nfev"):
        assert got.meta["run"][k] == ref.meta["run"][k], k


def test_free_flight_step_in_one_call_at_its_edges():
    """The one call's two ways out before a step is accepted, as the calls one by one take them: no step size passing
    the error test (the cradle at rtol = atol = 1e-30, its swing not a polynomial in t: down to H_MIN, then fixed
    steps, the same fallback at the same instant) and an error estimate that is not finite (the ball at rtol = atol =
    0: d / 0; the same error at the same step)."""
    ref, err_ref, _ = _adaptive("newton_cradle_5", duration=0.5, rtol=1e-30, atol=1e-30)
    got, err_got, statuses = _adaptive("newton_cradle_5", phase=True, duration=0.5, rtol=1e-30, atol=1e-30)
    S = compiled_events.phase_statuses()  # (the extension loaded by now)
    assert err_ref is None and err_got is None and S.REFUSED in statuses
    assert got.meta["fallbacks"] == ref.meta["fallbacks"]
    assert got.meta["fallbacks"][0]["reason"] == "the error test refused every step size"
    _same(ref.arrays, got.arrays)
    with np.errstate(divide="ignore", invalid="ignore"):  # (the Python estimate's d / 0)
        ref, err_ref, _ = _adaptive("bouncing_ball", duration=0.5, tol=(0.0, 0.0))
    got, err_got, statuses = _adaptive("bouncing_ball", phase=True, duration=0.5, tol=(0.0, 0.0))
    assert statuses == [S.NONFINITE] and err_got == err_ref and "error estimate of an extrapolated step" in err_got
    _same(ref.arrays, got.arrays)


@pytest.mark.parametrize("v", [1e-8, 1e-7, 1e-6])
def test_free_flight_step_in_one_call_lands_on_a_return(v):
    """A ball within G_RES of the ground rising at v [m/s], too slowly to leave G_RES (apex v^2 / 2g): its gap is
    watched by its return (its rate below -2 V_TOL), and the one call lands on that return, one step and no Newton
    (AdaptiveRun._land's), as the calls one by one do: the same arrays and counts."""
    from moreau_sim.kinematics import G_RES

    start = {"q0": [0.1 + 0.25 * G_RES], "u0": [v]}  # (the ball's radius 0.1 m)
    ref, err_ref, _ = _adaptive("bouncing_ball", duration=0.5, **start, restitution=0.5)
    got, err_got, statuses = _adaptive("bouncing_ball", phase=True, duration=0.5, **start, restitution=0.5)
    assert err_ref is None and err_got is None
    landed = [st for st in statuses if isinstance(st, tuple)]
    assert landed == [(compiled_events.phase_statuses().LANDED, 1)] and got.meta["run"]["events"] == 1
    _same(ref.arrays, got.arrays)
    for k in ("steps", "steps_refused", "steps_landed", "nfev", "impacts"):
        assert got.meta["run"][k] == ref.meta["run"][k], k


@pytest.mark.parametrize("name", ["bouncing_ball", "newton_cradle_5", "column_of_beads"])
def test_first_event_is_bit_identical(name):
    """AdaptiveRun._first_event on random step ends in free flight (gaps crossing within the step, features near
    contact coming back, none): the compiled location gives Python's (tau, kind, feature) bit for bit."""
    from moreau_sim.adaptive_carried import End as _End

    model = build_model(load_scene(SCENE_DIR / f"{name}.toml").with_options(integrator="adaptive"))
    data = make_data(model)
    run = AdaptiveRun(model, data, model.options.restitution, 1e-10, 1e-12, DEFAULT_ORDER, 1.0, 10 ** 6, t_end=1.0)
    assert run.locate is not None
    fast = run.locate
    run.is_box = np.zeros(8, bool)  # up to 8 synthetic features, none a box's
    rng = np.random.default_rng(11)
    z, kinds = np.zeros(model.nv), set()
    for trial in range(400):
        nf = int(rng.integers(1, 8))
        nw = int(rng.integers(0, nf + 1))
        H = float(10.0 ** rng.uniform(-5, -1))
        g0, g1 = rng.uniform(-1e-4, 1e-2, nf) * (rng.random(nf) < 0.8), rng.uniform(-1e-2, 1e-2, nf)
        gam0, gam1 = rng.normal(0.0, 1.0, nf), rng.normal(0.0, 1.0, nf)
        gdd0, gdd1 = rng.normal(0.0, 10.0, nf), rng.normal(0.0, 10.0, nf)
        if trial % 3 == 0:  # returns: rates near the -2 V_TOL threshold
            gam0, gam1 = rng.normal(0.0, 1e-8, nf), rng.normal(-1e-8, 1e-8, nf)
        e0 = _End(0.25, z, z, z, z[:0], g0, gam0, gdd0, z[:0], np.zeros(nf, bool))
        e1 = _End(0.25 + H, z, z, z, z[:0], g1, gam1, gdd1, z[:0], np.zeros(nf, bool))
        watched = list(range(nf))
        run.locate = None
        ref = run._first_event(e0, e1, nw, (), watched)
        run.locate = fast
        got = run._first_event(e0, e1, nw, (), watched)
        assert (ref is None) is (got is None), (trial, ref, got)
        if ref is not None:
            kinds.add(ref[1])
            same_tau = np.float64(ref[0]).tobytes() == np.float64(got[0]).tobytes()
            assert ref[1:] == got[1:] and same_tau, (trial, ref, got)
    assert kinds == {"gap", "return"}
