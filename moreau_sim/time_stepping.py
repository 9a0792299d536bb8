"""The time-stepping integrator: fixed midpoint Moreau steps (stepper.step, docs/theory.md §2)
behind the step protocol (protocol.py, §9); the driver (driver.py) records, samples and checkpoints.
"""

from __future__ import annotations

import numpy as np

from .data import Data
from .model import Model
from .protocol import FixedStep, Report, Status
from .recording import run_metadata
from .state import State
from .stepper import step


class TimeStepping:
    """Steps of the scene's dt from `state` for the scene's n_steps; every save_every-th step
    (and the last) is a sample."""

    unit = "step"
    grid = False

    def __init__(self, model: Model, data: Data, state: State):
        opts = model.options
        self.model, self.data = model, data
        self.h, self.e, self.n, self.every = opts.dt, opts.restitution, opts.n_steps, opts.save_every
        self.t0 = state.t
        self.t_end = state.t + self.n * self.h
        self.state = state
        self.k = 0  # steps done
        self.loop_meta: dict = {"loop": "python"}  # meta["run"]: the run loop (compiled_run.runner sets it)

    def step(self, t_sample: float = np.inf) -> Report:
        k, state, h, e = self.k, self.state, self.h, self.e
        r = step(self.model, self.data, state, h=h, e=e, t_next=self.t0 + (k + 1) * h)
        if r.qp is not None and not r.qp.ok:
            return Report(Status.FAILED, state.t, message=(
                f"step {k + 1} (t = {state.t:.6g} s -> {r.state.t:.6g} s): the impact QP failed with status "
                f"{r.qp.status} after {r.qp.iterations} iterations ({r.contacts.m} closed contacts)"))
        if not r.state.finite():
            return Report(Status.FAILED, state.t, message=(
                f"step {k + 1} (t = {state.t:.6g} s -> {r.state.t:.6g} s): the state became non-finite (NaN or inf)"))
        self.k, self.state = k + 1, r.state
        last = k == self.n - 1
        return Report(Status.FINISHED if last else Status.RUNNING, r.state.t, r.state,
                      (FixedStep(k + 1, state.t + 0.5 * h, state, r, h, e),), r.contact_work, r.correction_energy,
                      due=(k + 1) % self.every == 0 or last, n_contacts=r.contacts.m)

    def position(self) -> tuple[int, float]:
        return self.k + 1, self.state.t

    def progress(self) -> tuple[float, float, str]:
        return self.k, self.n, "step"

    def state_dict(self) -> dict:
        s = self.state
        return {"steps": self.k, "t0": self.t0, "t": s.t, "q": s.q.tolist(), "u": s.u.tolist()}

    def load_state_dict(self, d: dict) -> None:
        self.k, self.t0 = int(d["steps"]), float(d["t0"])
        self.state = State(float(d["t"]), np.array(d["q"], float), np.array(d["u"], float))

    def meta(self, status: str, wall: float, points: int) -> dict:
        """meta["run"]["steps"]: the steps recorded (a step whose sample failed is not one); "loop": the run
        loop, "compiled" (with "python_steps": the steps the Python run took in it) or "python" (and "why")."""
        return run_metadata(self.model, status, {"steps": points, "wall_seconds": wall,
                                                 "us_per_step": 1e6 * wall / points if points else None,
                                                 **self.loop_meta})
