"""The position correction's rows that contradict (moreau_sim.stepper.correct_positions, docs/theory.md §2.5):
a cube pushed deep into another has linearized rows no dq meets; the step corrects to the least uniform residual
t* instead of stopping the run, and gains no energy."""

import numpy as np
import pinocchio as pin
import pytest
from scipy.optimize import linprog

import moreau_sim as ms
from moreau_sim import energy, stepper
from moreau_sim.contacts import pair_distances
from moreau_sim.invariants import FIXED_RTOL

from helpers import ROOT


@pytest.mark.parametrize("a, b", [(0.3, 0.1), (1e-3, 1e-3), (0.05, 0.0)])
@pytest.mark.parametrize("tol", [0.0, 1e-9])
def test_shortfall_of_a_wedge_is_half_the_overlap(a, b, tol):
    """One dof wedged between two walls: dq >= a and -dq >= b; the least t with dq + t >= a, -dq + t >= b is
    t* = (a + b) / 2 (at dq = (a - b) / 2), on both rows. b = 0: the second row is met, so it is not relaxed
    (-dq >= 0): t* = a. A third row that is met stays unshifted."""
    W = np.array([[1.0, -1.0, 1.0]])
    g = np.array([-a, -b, 1.0])
    s = stepper.shortfall(W, g, tol)
    t = (a + b) / 2 if b > 0.0 else a
    expect = np.array([t + tol, (t + tol) if b > 0.0 else 0.0, 0.0])
    np.testing.assert_allclose(s, expect, rtol=0.0, atol=1e-12)


def two_cubes(e: float, h: float):
    b = ms.SceneBuilder("cube_in_cube", folder=f"{ROOT}/scenes", restitution=e, dt=h, duration=10 * h,
                        step_impl="python")
    b.add_body("a", "../models/cube.urdf", root_joint="free", position=(0.0, 0.0, 0.05))
    b.add_body("b", "../models/cube.urdf", root_joint="free", position=(0.0, 0.0, 0.3))
    b.add_halfspace("ground")
    return ms.build_model(b.build())


@pytest.mark.parametrize("e", [0.0, 0.5])
@pytest.mark.parametrize("h", [1e-3, 1e-2])
@pytest.mark.parametrize("dz, yaw, vz", [(0.02, 0.2, -0.5), (0.05, 0.3, -2.0), (0.0, 0.785, 0.0)])
def test_a_cube_inside_another_steps_without_gain(e, h, dz, yaw, vz):
    """0.1 m cube b placed 2-5 cm above cube a's centre (50-80 % overlap), turned: its linearized rows contradict
    (scipy's LP finds no dq), so piqp's "infeasible" is right. The step returns (it stopped the run with
    PIQP_PRIMAL_INFEASIBLE), T + V does not rise beyond round-off, and no gap is left below what the step's own
    motion makes: the closed pair is not deeper after the step than without any correction."""
    model = two_cubes(e, h)
    data = ms.make_data(model)
    q = model.q0.copy()
    q[:7] = [0.0, 0.0, 0.05, 0.0, 0.0, 0.0, 1.0]
    q[7:10] = [0.0, 0.0, 0.05 + dz]
    q[10:14] = pin.Quaternion(pin.rpy.rpyToMatrix(0.0, 0.0, yaw)).coeffs()
    u = np.zeros(model.nv)
    u[8] = vz
    state = ms.State(0.0, q, u)
    pb = stepper.assemble(model, data, state, h=h, e=e)
    imp = stepper.solve_impact(pb, model.options)
    g = imp.contacts.g + 0.5 * h * imp.gamma_plus
    lp = linprog(np.zeros(model.nv), A_ub=-imp.W.T, b_ub=g, bounds=[(None, None)] * model.nv, method="highs")
    assert lp.status == 2  # infeasible: the rows contradict
    E0 = energy.total(model, data, q, u)
    r = ms.step(model, data, state)
    E1 = energy.total(model, data, r.state.q, r.state.u)
    assert E1 <= E0 + 1e-12 * max(1.0, abs(E0))
    q_plain = pin.integrate(model.pin, pb.q_m, 0.5 * h * r.state.u)  # the step without a correction
    d_step = pair_distances(model, data, r.state.q, near=True)
    d_plain = pair_distances(model, data, q_plain, near=True)
    assert d_step.min() >= d_plain.min() - model.options.contact_tolerance


@pytest.mark.slow
def test_the_27_cube_pile_runs_without_gain():
    """benchmarks.scaling's pile of 27 cubes dropped into a bin (e = 0.1, h = 1e-3, 0.8 s): it stopped at
    t = 0.639 s on a correction whose rows contradict. It now runs to the end; T + V never rises above its start
    beyond the fixed step's stated bound (invariants.FIXED_RTOL of it), and what penetration is left is flagged
    by the run's invariant checks, never silent: the status says complete only if none is."""
    from benchmarks.scaling import pile

    # the compiled step (the default; the Python step's run bit for bit, tests/test_compiled_pairs.py), 1/20 of its time
    model = ms.build_model(pile(27).with_options(step_impl="compiled"))
    tr = ms.simulate(model, progress=False)
    E = tr.total_energy
    assert tr.t[-1] == pytest.approx(0.8)
    assert (E - E[0]).max() <= FIXED_RTOL * abs(E[0])
    found = {v["invariant"] for v in tr.meta.get("invariants") or []}
    assert found <= {"penetration"}
    assert (tr.meta["status"] == "complete") == (not found)
