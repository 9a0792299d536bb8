"""The compiled step's paid position lift (src/step.cpp Stepper::correct_positions, stepper.correct_positions):
a persistent penetration between flat faces (a box's vertices in the ground, a box's face in another's, deeper
than the step's own approach h |gamma_minus| + tol) in a step whose budget does not cover the lift is removed in
full and paid with the velocities of the bodies in contact, so that T + V ends where the law's step ended
(docs/theory.md §2.5). The compiled step takes those steps itself, bit for bit the Python step (§2.8): q, u, the
step's result (u_law, the law's u_{k+1} the ledger measures, §5.2) and, through the run loop (src/run.cpp), the
run's arrays and ledger."""

from __future__ import annotations

import numpy as np
import pytest

import moreau_sim as ms
import moreau_sim.compiled as compiled
import moreau_sim.stepper as stepper
from moreau_sim.contacts import pair_distances
from moreau_sim.energy import kinetic, potential
from moreau_sim.law import ENERGY_ROUNDOFF
from moreau_sim.options import StepImpl

from helpers import scene

STEPS = 4
# (scene, depth [m], the pose its last free joint rests in (None: the scene's q0)): box_drop's box (0.4 m high)
# flat on the ground and 4 mm into it; box_stack_5's top box 3 mm into the one below it. Both tumbling (TUMBLE).
CASES = {"box in the ground": ("box_drop", 0.004, (0.0, 0.0, 0.2, 0.0, 0.0, 0.0, 1.0)),
         "box in a box": ("box_stack_5", 0.003, None)}
TUMBLE = (0.5, 0.3, -0.2, 0.5, -0.3, 1.0)


@pytest.fixture(scope="module", autouse=True)
def _compiled():
    assert compiled.available(), compiled.unavailable_reason()


def _model(name: str, impl: StepImpl, e: float, h: float):
    return ms.build_model(scene(name, restitution=e, dt=h, step_impl=impl.value))


def _start(model, depth: float, rest, speed: float = 1.0) -> ms.State:
    """The scene's start with its last free joint's box (at its resting pose `rest`, if given) lowered by `depth` [m]
    into what it rests on, tumbling (speed times TUMBLE)."""
    q, u = model.q0.copy(), np.zeros(model.nv)
    if rest is not None:
        q[-7:] = rest
    q[-5] -= depth  # the last free joint's z (x, y, z, quaternion)
    u[-6:] = speed * np.array(TUMBLE)
    return ms.State(0.0, q, u)


def _steps(name: str, depth: float, rest, impl: StepImpl, e: float, h: float, speed: float = 1.0):
    """STEPS steps from _start: (model, data, the results)."""
    model = _model(name, impl, e, h)
    data = ms.make_data(model)
    st, out = _start(model, depth, rest, speed), []
    for _ in range(STEPS):
        r = ms.step(model, data, st)
        out.append(r)
        st = r.state
    return model, data, out


def _same(a, b) -> bool:
    return a is None and b is None or (a is not None and b is not None and a.tobytes() == b.tobytes())


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("h", [1e-3, 1e-2])
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_paid_lift_compiled_and_identical(case, e, h):
    """The first step pays a lift (u_law set): the compiled step takes it and every step after it (nothing handed
    back), with the Python step's q, u, P, gamma_plus, correction energy and u_law bit for bit; the penetration is
    gone (no deeper than h |gamma_plus| + tol at the step's end), and T + V did not rise beyond the step's round-off
    (stepper._roundoff: the paid lift's own promise, §2.5)."""
    name, depth, rest = CASES[case]
    _, _, ref = _steps(name, depth, rest, StepImpl.PYTHON, e, h)
    model, data, got = _steps(name, depth, rest, StepImpl.COMPILED, e, h)
    counts = compiled.counts(data)
    assert counts["contact"] + counts["flight"] == STEPS, dict(counts)
    for a, b in zip(ref, got):
        assert _same(a.state.q, b.state.q) and _same(a.state.u, b.state.u)
        assert _same(a.P, b.P) and _same(a.gamma_plus, b.gamma_plus) and _same(a.u_law, b.u_law)
        assert a.correction_energy == b.correction_energy and a.contact_work == b.contact_work
    first = got[0]
    assert first.u_law is not None  # the lift was paid with the velocities
    tol = model.options.contact_tolerance
    start = _start(model, depth, rest)
    assert pair_distances(model, data, start.q).min() < -(h * np.abs(first.gamma_minus).max() + tol)  # persistent
    # lifted: what is left is not persistent by the rule's own measure (at most what the step's own motion makes,
    # h |gamma_plus| + tol: the linearized lift's second-order rest, 1.5e-7 m of the 4 mm at e = 1, h = 1e-2)
    assert pair_distances(model, data, first.state.q).min() >= -(h * np.abs(first.gamma_plus).max() + tol)
    T0, V0 = kinetic(model, data, start.q, start.u), potential(model, data, start.q)
    T1, V1 = kinetic(model, data, first.state.q, first.state.u), potential(model, data, first.state.q)
    assert (T1 + V1) - (T0 + V0) <= ENERGY_ROUNDOFF * (((T0 + abs(V0)) + T1) + abs(V1))


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("h", [1e-3, 1e-2])
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_a_lift_the_velocities_cannot_pay_keeps_the_budget_rule(case, e, h, monkeypatch):
    """Tumbling at a tenth of the speed the box has too little kinetic energy to pay the lift: the payment is tried
    (stepper._scaled) and refused by its round-off test, and the budget rule takes the step (a partial lift worth at
    most the step's dissipation, none where it dissipated nothing): no u_law, no gain beyond round-off, and the
    compiled step takes these steps too, bit for bit the Python step (alpha from the tried payment's dE, §2.5)."""
    name, depth, rest = CASES[case]
    tried = []
    scaled = stepper._scaled
    monkeypatch.setattr(stepper, "_scaled", lambda *a: tried.append(1) or scaled(*a))
    _, _, ref = _steps(name, depth, rest, StepImpl.PYTHON, e, h, 0.1)
    assert tried
    model, data, got = _steps(name, depth, rest, StepImpl.COMPILED, e, h, 0.1)
    counts = compiled.counts(data)
    assert counts["contact"] + counts["flight"] == STEPS, dict(counts)
    for a, b in zip(ref, got):
        assert _same(a.state.q, b.state.q) and _same(a.state.u, b.state.u) and a.u_law is b.u_law is None
        assert a.correction_energy == b.correction_energy
    start, first = _start(model, depth, rest, 0.1), got[0]
    T0, V0 = kinetic(model, data, start.q, start.u), potential(model, data, start.q)
    T1, V1 = kinetic(model, data, first.state.q, first.state.u), potential(model, data, first.state.q)
    assert (T1 + V1) - (T0 + V0) <= ENERGY_ROUNDOFF * (((T0 + abs(V0)) + T1) + abs(V1))


@pytest.mark.parametrize("case", CASES)
def test_paid_lift_in_place_and_its_result(case):
    """ms.step_in_place takes the paid step compiled too, and its StepView's result carries the step's u_law."""
    name, depth, rest = CASES[case]
    _, _, ref = _steps(name, depth, rest, StepImpl.PYTHON, 0.5, 1e-3)
    model = _model(name, StepImpl.COMPILED, 0.5, 1e-3)
    data = ms.make_data(model)
    st = _start(model, depth, rest)
    q, u = st.q.copy(), st.u.copy()
    view = ms.step_in_place(model, data, 0.0, q, u)
    assert compiled.counts(data)["contact"] == 1
    assert _same(q, ref[0].state.q) and _same(u, ref[0].state.u)
    assert _same(view.result().u_law, ref[0].u_law) and view.result().u_law is not None


def _arrays_differ(a, b) -> list[str]:
    keys = set(a.arrays) | set(b.arrays)
    return sorted(k for k in keys if k not in a.arrays or k not in b.arrays
                  or a.arrays[k].dtype != b.arrays[k].dtype or a.arrays[k].shape != b.arrays[k].shape
                  or a.arrays[k].tobytes() != b.arrays[k].tobytes())


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_paid_lift_in_the_compiled_run(case, e):
    """ms.simulate from the penetrating start: the compiled run loop (src/run.cpp) takes the paid step and books
    its impact on the law's u_{k+1} (u_law, docs/theory.md §5.2) as the Recorder does: the Python run's arrays,
    ledger and status bit for bit."""
    name, depth, rest = CASES[case]
    out = []
    for python_run in (True, False):
        model = _model(name, StepImpl.COMPILED, e, 1e-3)
        sc = model.scene.with_options(duration=20 * 1e-3)
        model = ms.build_model(sc)
        out.append(ms.simulate(model, state=_start(model, depth, rest), progress=False, python_run=python_run))
    ref, new = out
    assert ref.meta["run"]["loop"] == "python" and new.meta["run"]["loop"] == "compiled"
    assert new.meta["run"]["python_steps"] == 0, new.meta["run"]
    assert _arrays_differ(ref, new) == []
    assert ref.meta["ledger"] == new.meta["ledger"]
    assert ref.meta["status"] == new.meta["status"]
