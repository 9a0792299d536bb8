"""stepper.step_in_place (the step without its result objects) against stepper.step: the same q_{k+1}, u_{k+1}
bit for bit, both step implementations, on every bundled scene; its StepView's result() is step()'s."""

from __future__ import annotations

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim.options import StepImpl

from helpers import BUNDLED, SCENES

STEPS = 40  # steps of each scene (from its start; the scenes that start in contact are in contact)


@pytest.mark.parametrize("impl", [StepImpl.COMPILED, StepImpl.PYTHON])
@pytest.mark.parametrize("name", BUNDLED)
def test_in_place_equals_step(name, impl):
    model = ms.build_model(ms.load_scene(SCENES / f"{name}.toml").with_options(step_impl=impl.value))
    st = ms.initial_state(model)
    ref_data, data = ms.make_data(model), ms.make_data(model)
    q, u, t = st.q.copy(), st.u.copy(), st.t
    for k in range(STEPS):
        r = ms.step(model, ref_data, st, t_next=st.t + model.options.dt)
        view = ms.step_in_place(model, data, t, q, u)
        assert np.array_equal(q, r.state.q) and np.array_equal(u, r.state.u), f"step {k + 1}"
        assert view.t == r.state.t and view.n_contacts == r.contacts.m and view.ok == (r.qp is None or r.qp.ok)
        got = view.result()
        assert np.array_equal(got.P, r.P) and np.array_equal(got.state.u, r.state.u)
        st, t = r.state, view.t


def test_a_view_outlives_the_next_step():
    """The compiled step's arrays are its own buffers, one per step: a StepView read after more steps is still
    its own step's."""
    model = ms.build_model(ms.load_scene(SCENES / "zeno_ball.toml").with_options(step_impl="compiled"))
    data = ms.make_data(model)
    st = ms.initial_state(model)
    q, u = st.q.copy(), st.u.copy()
    views, states = [], []
    for k in range(5):
        views.append(ms.step_in_place(model, data, st.t + k * model.options.dt, q, u))
        states.append((q.copy(), u.copy()))
    for v, (qk, uk) in zip(views, states):
        assert np.array_equal(v.result().state.q, qk) and np.array_equal(v.result().state.u, uk)
