"""Fault injection at every solver call: the library call is patched to fail (a failed status, an
exception) or to answer NaN, and the run must stop with a SimulationError naming the step (or
event-driven phase) and the time, carrying the samples so far as a trajectory marked failed
that saves and loads as FILE.partial.npz does. The libraries themselves are not mocked elsewhere."""

from __future__ import annotations

import math
import re

import numpy as np
import piqp
import pytest
import scipy.integrate
import scipy.optimize

import moreau_sim as ms
from moreau_sim import adaptive, event_driven, qp

from helpers import run

_DENSE_SOLVER = piqp.DenseSolver  # the real one (the tests patch the module's attribute)


class _Result:
    """piqp's result with x and z_l replaced by NaN (an answer "solved" with NaN in it)."""

    def __init__(self, real):
        self.info = real.info
        self.x = np.full_like(real.x, np.nan)
        self.z_l = np.full_like(real.z_l, np.nan)


def faulty_piqp(mode: str, when=lambda c: True):
    """A piqp.DenseSolver whose solve() fails ("fail": max iterations reached) or answers NaN with
    status solved ("nan") on the problems where when(c) (c: the linear term given to setup)."""
    class Solver:
        def __init__(self):
            self._real = _DENSE_SOLVER()
            self.settings = self._real.settings
            self._hit = False

        def setup(self, P, c, *args):
            self._hit = bool(when(np.asarray(c)))
            return self._real.setup(P, c, *args)

        def solve(self):
            status = self._real.solve()
            if not self._hit:
                return status
            return piqp.PIQP_MAX_ITER_REACHED if mode == "fail" else piqp.PIQP_SOLVED

        @property
        def result(self):
            real = self._real.result
            return _Result(real) if self._hit and mode == "nan" else real
    return Solver


def raising(exc: Exception):
    def f(*args, **kwargs):
        raise exc
    return f


def nan_root(f, a, b, *args, **kwargs):
    return math.nan


def failed_ivp(*args, **kwargs):
    sol = scipy.integrate.solve_ivp(*args, **kwargs)
    sol.status, sol.message = -1, "Required step size is less than spacing between numbers."
    return sol


def zero_c(c):  # the position correction's QP: v0 = 0, so piqp's linear term -M v0 is 0
    return not np.any(c)


def zero_c_and_retry():
    """zero_c, and the next problem after a hit too: qp.solve retries a primal piqp stopped at its iteration
    limit in the dual form (docs/theory.md §2.11), whose linear term is not 0; both fail, as a solver that fails."""
    hit = [False]

    def when(c):
        now = hit[0] or zero_c(c)
        hit[0] = zero_c(c)
        return now
    return when


# (id, patch target, replacement, scene, options, what the message says)
TS = dict(integrator="time-stepping")
FAULTS = [
    ("impact QP fails", (qp.piqp, "DenseSolver"), faulty_piqp("fail"), "bouncing_ball", TS,
     "impact QP failed with status PIQP_MAX_ITER_REACHED"),
    ("impact QP answers NaN", (qp.piqp, "DenseSolver"), faulty_piqp("nan"), "bouncing_ball", TS,
     "impact QP failed with status NON_FINITE_SOLUTION"),
    ("correction QP fails", (qp.piqp, "DenseSolver"), faulty_piqp("fail", zero_c_and_retry()), "bouncing_ball",
     dict(restitution=0.0, dt=1e-2), "position-correction QP failed with status PIQP_MAX_ITER_REACHED"),
    ("correction QP answers NaN", (qp.piqp, "DenseSolver"), faulty_piqp("nan", zero_c), "bouncing_ball",
     dict(restitution=0.0, dt=1e-2), "position-correction QP failed with status NON_FINITE_SOLUTION"),
    ("corner law QP fails", (qp.piqp, "DenseSolver"), faulty_piqp("fail"), "corner_point", TS,
     "corner projection QP failed: PIQP_MAX_ITER_REACHED"),
    ("corner law QP answers NaN", (qp.piqp, "DenseSolver"), faulty_piqp("nan"), "corner_point", TS,
     "corner projection QP failed: NON_FINITE_SOLUTION"),
    ("LU of the active set raises", (qp, "_lu_solve"), raising(ValueError("array must not contain infs or NaNs")),
     "resting_box", TS, "ValueError: array must not contain infs or NaNs"),
    ("event-driven solve_ivp raises", (event_driven, "solve_ivp"), raising(RuntimeError("ODE failure")),
     "bouncing_ball", dict(integrator="event-driven"), "RuntimeError: ODE failure"),
    ("event-driven solve_ivp fails", (event_driven, "solve_ivp"), failed_ivp, "bouncing_ball",
     dict(integrator="event-driven"), "solve_ivp failed: Required step size"),
    ("event-driven event root raises", (scipy.optimize, "brentq"), raising(RuntimeError("failed to converge")),
     "bouncing_ball", dict(integrator="event-driven"), "RuntimeError: failed to converge"),
    ("event-driven impact QP fails", (qp.piqp, "DenseSolver"), faulty_piqp("fail"), "bouncing_ball",
     dict(integrator="event-driven"), "impact QP failed: PIQP_MAX_ITER_REACHED"),
    ("event-driven contact-force QP answers NaN", (qp.piqp, "DenseSolver"), faulty_piqp("nan"), "resting_box",
     dict(integrator="event-driven"), "QP failed"),
    ("adaptive event root raises", (adaptive, "brentq"), raising(RuntimeError("failed to converge")),
     "bouncing_ball", dict(integrator="adaptive"), "RuntimeError: failed to converge"),
    ("adaptive event root answers NaN", (adaptive, "brentq"), nan_root, "bouncing_ball",
     dict(integrator="adaptive"), "non-finite"),
    ("adaptive error estimate is NaN", (adaptive.AdaptiveRun, "_error"), lambda self, *a: math.nan,
     "bouncing_ball", dict(integrator="adaptive"), "error estimate of an extrapolated step"),
    ("adaptive impact QP fails", (qp.piqp, "DenseSolver"), faulty_piqp("fail"), "bouncing_ball",
     dict(integrator="adaptive"), "impact QP failed: PIQP_MAX_ITER_REACHED"),
]


@pytest.mark.parametrize("target,replacement,name,options,words", [f[1:] for f in FAULTS], ids=[f[0] for f in FAULTS])
def test_a_solver_fault_is_a_named_stop_with_the_samples_so_far(monkeypatch, tmp_path, target, replacement, name,
                                                                 options, words):
    monkeypatch.setattr(*target, replacement)
    if target == (qp.piqp, "DenseSolver"):  # piqp first (below COLD_START_ROWS it only backs up the active set)
        monkeypatch.setattr(qp, "COLD_START_ROWS", 0)
    with pytest.raises(ms.SimulationError) as info:
        run(name, duration=1.0, step_impl="python", **options)
    exc = info.value
    msg = str(exc)
    unit = "phase" if options.get("integrator") == "event-driven" else "step"
    assert re.match(rf"{unit} \d+ \(t = [^)]* s\S*( -> [^)]* s)?\): ", msg), msg
    assert words in msg and "\n" not in msg
    assert exc.step >= 1 and math.isfinite(exc.t)
    traj = exc.trajectory
    assert traj is not None and not traj.complete and traj.meta["status"] == f"failed: {msg}"
    assert len(traj.t) >= 1 and np.isfinite(traj.q).all()  # the samples before the fault, all finite
    monkeypatch.undo()  # save and load with the real libraries
    back = ms.load_trajectory(traj.save(tmp_path / "run.partial.npz"))
    assert back.meta["status"].startswith("failed: ") and len(back.t) == len(traj.t)


def test_a_nan_lu_is_never_used(monkeypatch):
    """The active set's LU answering NaN: the active set gives up and piqp's (finite) answer is kept."""
    monkeypatch.setattr(qp, "_lu_solve", lambda A, rhs: np.full(len(rhs), np.nan))
    traj = run("resting_box", duration=0.2, step_impl="python")
    assert traj.complete and np.isfinite(traj.q).all() and np.isfinite(traj.arrays["log_P"]).all()


def test_a_nan_slack_drops_no_row(monkeypatch):
    """qp._active_set on a NaN residual: no answer (None). The row to drop was index -1 where none had a
    negative step: Python's active set then cleared the last row's multiplier, src/step.cpp's wrote before its
    arrays (a run crashed with "free(): invalid pointer")."""
    assert qp._active_set(np.eye(2), np.array([np.nan, 1.0]), 1e-12) is None


@pytest.mark.parametrize("step_impl", ["compiled", "python"])
def test_a_blow_up_under_the_compiled_step_is_a_named_stop(step_impl):
    """solo12_stand at h = 5e-3 (five times its dt): the PD torques overflow within 6 steps. Both steps stop with
    one line naming the step and the failed QP, the samples before it kept; the compiled step crashed the process
    before (its active set on the non-finite problem wrote outside its arrays), it now hands the step to Python
    (src/step.cpp project: qp.solve's NON_FINITE_INPUT). The stop took 4 min of CPU: the blown-up robot's thousands
    of rows gave constraints' duplicate screen 31 million candidate pairs, compared one by one (now at once per row,
    the same mask)."""
    with pytest.raises(ms.SimulationError) as info:
        run("solo12_stand", duration=0.1, dt=5e-3, restitution=0.5, step_impl=step_impl)
    msg = str(info.value)
    assert re.match(r"step \d+ \(t = [^)]* s -> [^)]* s\): ", msg) and "NON_FINITE_INPUT" in msg, msg
    traj = info.value.trajectory
    assert traj is not None and traj.meta["status"] == f"failed: {msg}" and np.isfinite(traj.q).all()
