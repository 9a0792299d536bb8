"""The compiled step's StepResult (compiled.result, compiled._CompiledResult): its state made at once, every other
field made from the step's StepOut where it is first read. Read at once, read steps later or never, in any order,
each field is the Python step's on the same state, bit for bit, with the dtype, shape and writeability of the
arrays made all at once from the StepOut (compiled._Context.arrays, as result() made them before); it is a
StepResult to dataclasses, copy, pickle and ==. And the detection's warm start the compiled Stepper holds
between steps (Data.warm_start_pairs, hold_warm_start): read from it where asked, sent again only where data's set
changed."""

from __future__ import annotations

import copy
import dataclasses
import pickle

import numpy as np
import pytest

import moreau_sim as ms
import moreau_sim.compiled as compiled
from moreau_sim.contacts import NO_CONTACTS, Contacts
from moreau_sim.options import StepImpl
from moreau_sim.results import StepResult

from helpers import scene

FIELDS = [f.name for f in dataclasses.fields(StepResult)]
QP_ARRAYS = ("M", "W", "v0", "b", "v", "lam")
# (scene, steps, start): "scene" its q0 at rest; "tumbling": the last free joint's box lowered 4 mm into what it rests
# on and tumbling (a paid position lift, u_law: tests/test_compiled_lift.py); "impact": a few steps before the
# run's first contact (the ball on the paddle)
CASES = {"box_drop": ("box_drop", 30, "tumbling"), "box_stack_5": ("box_stack_5", 40, "scene"),
         "vibrating_paddle": ("vibrating_paddle", 30, "impact"), "driven_paddle": ("driven_paddle", 30, "impact"),
         "solo12_stand": ("solo12_stand", 12, "scene")}


@pytest.fixture(scope="module", autouse=True)
def _compiled():
    assert compiled.available(), compiled.unavailable_reason()


def _models(name: str, e: float, h: float) -> dict:
    return {impl: ms.build_model(scene(name, restitution=e, dt=h, step_impl=impl.value)) for impl in StepImpl}


def _start(model, how: str) -> ms.State:
    st = ms.initial_state(model)
    if how == "scene":
        return st
    if how == "impact":  # the run's states until its first contact step (a data of its own), 5 steps back
        data, states = ms.make_data(model), [st]
        while not ms.step(model, data, states[-1]).contacts.m:
            states.append(ms.step(model, data, states[-1]).state)
        return states[max(0, len(states) - 6)]
    q, u = st.q.copy(), np.zeros(model.nv)
    q[-7:] = (0.0, 0.0, 0.2, 0.0, 0.0, 0.0, 1.0)
    q[-5] -= 0.004
    u[-6:] = (0.5, 0.3, -0.2, 0.5, -0.3, 1.0)
    return ms.State(0.0, q, u)


def _same_array(x, y) -> bool:
    return (x is None and y is None) or (x is not None and y is not None and x.dtype == y.dtype
                                         and x.shape == y.shape and x.tobytes() == y.tobytes())


def _eager(ctx, r, t1: float, tau) -> dict:
    """The fields of the StepOut r's StepResult made all at once from its named arrays (ctx.arrays), as
    compiled.result made them before its fields were lazy: {field: value} (qp: {name: value})."""
    f = ctx.arrays(r)
    if r.outcome is compiled._module.Outcome.FLIGHT:
        return {"state": (t1, f["q_next"], f["u_next"]), "contacts": None, "P": compiled._EMPTY,
                "gamma_minus": compiled._EMPTY, "gamma_plus": compiled._EMPTY, "contact_work": 0.0, "qp": None,
                "branch": None, "correction_energy": 0.0, "u_free": f["u_next"], "tau": tau,
                "obstacle_work": r.obstacle_work, "u_law": None, "drive_work_free": 0.0}
    admissible = r.projection is compiled._module.Projection.ADMISSIBLE
    qp = {"status": r.projection.name, "ok": True, "iterations": 0, "polished": not admissible, "v": f["v"],
          "lam": f["lam"], "M": f["M"], "W": f["W"], "v0": f["v_free"], "b": f["b"], "active": None}
    return {"state": (t1, f["q_next"], f["u_next"]), "contacts": {k: f[k] for k in Contacts.ARRAYS}, "P": f["P"],
            "gamma_minus": f["gamma_minus"], "gamma_plus": f["gamma_plus"], "contact_work": r.contact_work, "qp": qp,
            "branch": None, "correction_energy": r.correction_energy, "u_free": f["u_free"], "tau": tau,
            "obstacle_work": r.obstacle_work, "u_law": f["u_law"] if r.paid else None,
            "drive_work_free": r.drive_work_free}


def _check(a: StepResult, b: StepResult, ref: dict, order: list[str]) -> None:
    """The compiled step's result b, its fields read in `order`, against the Python step's a on the same state and
    against ref (_eager): values bit for bit, dtypes, shapes, writeability, types."""
    got = {name: getattr(b, name) for name in order}
    assert all(getattr(b, name) is got[name] for name in FIELDS)  # made once, kept
    t1, q1, u1 = ref["state"]
    assert b.state.t == a.state.t == t1
    for x, y, z in ((a.state.q, b.state.q, q1), (a.state.u, b.state.u, u1)):
        assert _same_array(x, y) and _same_array(y, z) and y.flags.writeable == z.flags.writeable
    for name in ("P", "gamma_minus", "gamma_plus", "u_free", "tau", "u_law"):
        x, y, z = getattr(a, name), getattr(b, name), ref[name]
        assert _same_array(x, y) and _same_array(y, z), name
        assert y is None or (y.flags.writeable == z.flags.writeable and y.flags.c_contiguous == z.flags.c_contiguous)
    if ref["qp"] is None:  # flight: u_free is u_{k+1} itself, as the Python step's
        assert b.u_free is b.state.u and a.u_free is a.state.u
    for name in ("contact_work", "correction_energy", "obstacle_work", "drive_work_free"):
        x, y = getattr(a, name), getattr(b, name)
        assert type(y) is float and x == y == ref[name], name
    assert a.branch is b.branch is None
    assert b.contacts.corners == ()
    for k in Contacts.ARRAYS:
        x, y = getattr(a.contacts, k), getattr(b.contacts, k)
        assert _same_array(x, y), k
        if ref["contacts"] is not None:
            z = ref["contacts"][k]
            assert _same_array(y, z) and y.flags.writeable == z.flags.writeable and y.strides == z.strides, k
        else:
            assert b.contacts is NO_CONTACTS
    assert (a.qp is None) == (b.qp is None) == (ref["qp"] is None)
    if b.qp is not None:
        for k, z in ref["qp"].items():
            y = getattr(b.qp, k)
            if isinstance(z, np.ndarray):
                assert _same_array(y, z) and y.strides == z.strides and y.flags.writeable == z.flags.writeable, k
            else:
                assert y == z and type(y) is type(z), k
        for k in QP_ARRAYS:
            assert _same_array(getattr(a.qp, k), getattr(b.qp, k)), k
        assert (a.qp.status, a.qp.ok, a.qp.polished) == (b.qp.status, b.qp.ok, b.qp.polished)


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("h", [1e-3, 2e-3])
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_lazy_fields_are_the_python_steps(case, e, h):
    """From the same states, every field of the compiled step's result, read at once (every other step, in the
    dataclass's order) or after the run's last step (the others, in reverse order), is the Python step's and the
    one the StepOut's arrays made at once give; the steps cover flight and contact, a paid lift (u_law), torques
    (tau), moving statics and driven joints (obstacle_work, drive_work_free)."""
    name, steps, how = CASES[case]
    models = _models(name, e, h)
    mp, mc = models[StepImpl.PYTHON], models[StepImpl.COMPILED]
    dp, dc = ms.make_data(mp), ms.make_data(mc)
    st = _start(mp, how)
    later, seen = [], []
    for k in range(steps):
        a = ms.step(mp, dp, st)
        b = ms.step(mc, dc, st)
        assert type(b) is compiled._CompiledResult  # the compiled step took it (every step here: counts below)
        ref = _eager(b._ctx, b._r, b.state.t, b.tau)
        seen.append(b)
        if k % 2:
            _check(a, b, ref, FIELDS)
        else:
            later.append((a, b, ref))
        st = a.state
    for a, b, ref in later:  # read after the next steps: the StepOut's buffers are the step's own
        _check(a, b, ref, FIELDS[::-1])
    c = compiled.counts(dc)
    assert c["flight"] + c["contact"] == steps, dict(c)
    if how == "tumbling":
        assert any(b.u_law is not None for b in seen)
    if name == "solo12_stand":
        assert all(b.tau is not None for b in seen)
    if name.endswith("paddle"):
        assert any(b.obstacle_work != 0.0 for b in seen)
    if name == "driven_paddle":
        assert any(b.drive_work_free != 0.0 for b in seen)


def test_flight_and_contact_outcomes_are_covered():
    """box_drop from its own start: steps in flight (no contact) and, by the end, in contact, both lazy."""
    models = _models("box_drop", 0.5, 1e-3)
    mp, mc = models[StepImpl.PYTHON], models[StepImpl.COMPILED]
    dp, dc = ms.make_data(mp), ms.make_data(mc)
    st = ms.initial_state(mp)
    kinds = set()
    for _ in range(700):
        a, b = ms.step(mp, dp, st), ms.step(mc, dc, st)
        ref = _eager(b._ctx, b._r, b.state.t, b.tau)
        _check(a, b, ref, FIELDS)
        kinds.add(b.qp is None)
        st = a.state
    assert kinds == {True, False}


def test_it_is_a_step_result():
    """dataclasses.fields / replace / asdict, copy, deepcopy, pickle and == see a StepResult: the copies are plain
    StepResults of the same fields."""
    m = ms.build_model(scene("box_stack_5", step_impl="compiled"))
    d = ms.make_data(m)
    r = ms.step(m, d, ms.initial_state(m))
    r = ms.step(m, d, r.state)
    assert isinstance(r, StepResult) and type(r) is not StepResult and r.contacts.m > 0
    assert [f.name for f in dataclasses.fields(r)] == FIELDS
    for other in (copy.copy(r), copy.deepcopy(r), pickle.loads(pickle.dumps(r)),
                  dataclasses.replace(r, correction_energy=r.correction_energy)):
        assert type(other) is StepResult
        for name in FIELDS:
            x, y = getattr(r, name), getattr(other, name)
            if isinstance(x, np.ndarray):
                assert _same_array(x, y), name
            elif name in ("contacts", "state"):
                assert all(_same_array(np.asarray(getattr(x, k)), np.asarray(getattr(y, k)))
                           for k in (Contacts.ARRAYS if name == "contacts" else ("q", "u"))), name
            elif name == "qp":
                assert all(_same_array(getattr(x, k), getattr(y, k)) for k in QP_ARRAYS)
            else:
                assert x == y, name
    plain = copy.copy(r)
    assert r == plain and plain == r and r == r and r != 1
    assert dataclasses.replace(r, contact_work=1.0).contact_work == 1.0
    assert dataclasses.asdict(r).keys() == set(FIELDS)
    assert repr(r) == repr(plain) and repr(r).startswith("StepResult(")
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.P = None


class _Spy:
    """A compiled Stepper that records the warm starts sent to it (Stepper.warm's setter)."""

    def __init__(self, stepper):
        self._s, self.sent = stepper, []

    @property
    def warm(self):
        return self._s.warm

    @warm.setter
    def warm(self, pairs):
        self.sent.append(list(pairs))
        self._s.warm = pairs

    def __getattr__(self, name):
        return getattr(self._s, name)

    def __setattr__(self, name, value):
        if name in ("_s", "sent", "warm"):
            object.__setattr__(self, name, value)
        else:
            setattr(self._s, name, value)


def test_warm_start_held_by_the_stepper():
    """Between compiled steps the Stepper holds the detection's warm start (nothing sent or read back); a read of
    data.warm_start_pairs gives the Python step's set, after which data's set is sent at the next step, changed in
    place or replaced: the run stays the Python step's bit for bit."""
    models = _models("box_stack_5", 0.0, 1e-2)
    mp, mc = models[StepImpl.PYTHON], models[StepImpl.COMPILED]
    dp, dc = ms.make_data(mp), ms.make_data(mc)
    ctx = compiled._context(mc, dc)
    assert ctx.boxes
    spy = ctx.stepper = _Spy(ctx.stepper)
    st, dp_before = ms.initial_state(mp), set()
    for k in range(60):
        before = len(spy.sent)
        a, b = ms.step(mp, dp, st), ms.step(mc, dc, st)
        assert _same_array(a.state.q, b.state.q) and _same_array(a.state.u, b.state.u)
        assert dc.warm_start_holder is spy  # held: not read back
        if k % 3 == 0:
            assert len(spy.sent) == before + (k == 0)  # sent at the first step only, and after a read (below)
        if k % 3 == 1:
            assert dc.warm_start_pairs == dp.warm_start_pairs and dc.warm_start_holder is None
        if k % 3 == 2:
            assert len(spy.sent) == before + 1 and spy.sent[-1] == sorted(dp_before)
        if k % 9 == 4:  # changed in place (a set read from data is its own)
            dc.warm_start_pairs.clear()
            dp.warm_start_pairs.clear()
        elif k % 9 == 7:
            dc.warm_start_pairs = {0}
            dp.warm_start_pairs = {0}
        dp_before = set(dp.warm_start_pairs)
        st = a.state
    c = compiled.counts(dc)
    assert c["contact"] > 40 and c["flight"] + c["contact"] == 60, dict(c)
