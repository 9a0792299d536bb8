"""The loop: steps, recorder, progress, stop conditions, errors naming the step and time."""

from __future__ import annotations

import datetime
import os
import platform
import time
from importlib import metadata
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .contacts import pair_distances
from .energy import kinetic, potential
from .errors import SimulationError
from .model import Data, Model, build_model, initial_state, make_data
from .scene import Integrator, Scene, load_scene
from .state import State
from .stepper import step
from .trajectory import Trajectory

LOG_RELATIVE = 1e-9  # a percussion is logged when P_i > LOG_RELATIVE * max(P) of its step (and > 0)
# An impact ("log_impact") is a logged percussion of a contact that was not closed in the previous step.
# [s] the progress bar appears on runs longer than this (MOREAU_SIM_PROGRESS_DELAY overrides it)
_PROGRESS_DELAY = float(os.environ.get("MOREAU_SIM_PROGRESS_DELAY", "2.0"))


def versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for dist in ("moreau-sim", "pin", "coal", "piqp", "numpy", "scipy"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out


class _Recorder:
    def __init__(self, model: Model, data: Data, n_save: int):
        self.model, self.data = model, data
        nq, nv, npairs = model.nq, model.nv, len(model.pairs)
        self.t = np.empty(n_save)
        self.q = np.empty((n_save, nq))
        self.u = np.empty((n_save, nv))
        self.ke = np.empty(n_save)
        self.pe = np.empty(n_save)
        self.work = np.empty(n_save)
        self.corr = np.empty(n_save)
        self.gap = np.empty((n_save, npairs))
        self.nc = np.empty(n_save, dtype=np.int64)
        self.n = 0
        self.log: list[tuple] = []
        self.branches: list[tuple] = []  # (step, t, chosen, [(u_plus, distance, global_min)])

    def sample(self, s: State, work: float, corr: float, n_contacts: int) -> None:
        i, m, d = self.n, self.model, self.data
        self.t[i] = s.t
        self.q[i] = s.q
        self.u[i] = s.u
        self.ke[i] = kinetic(m, d, s.q, s.u)
        self.pe[i] = potential(m, d, s.q)
        self.work[i] = work
        self.corr[i] = corr
        self.gap[i] = pair_distances(m, d, s.q)
        self.nc[i] = n_contacts
        self.n += 1

    def arrays(self) -> dict[str, np.ndarray]:
        n = self.n
        log = self.log
        cols = list(zip(*log)) if log else [()] * 11
        return {
            "t": self.t[:n], "q": self.q[:n], "u": self.u[:n], "kinetic_energy": self.ke[:n],
            "potential_energy": self.pe[:n], "contact_work": self.work[:n], "correction_energy": self.corr[:n], "gap": self.gap[:n],
            "n_contacts": self.nc[:n],
            "log_step": np.array(cols[0], dtype=np.int64), "log_t": np.array(cols[1], float),
            "log_pair": np.array(cols[2], dtype=np.int64), "log_feature": np.array(cols[3], dtype=np.int64),
            "log_gap": np.array(cols[4], float), "log_P": np.array(cols[5], float),
            "log_gamma_minus": np.array(cols[6], float), "log_gamma_plus": np.array(cols[7], float),
            "log_point": np.array(cols[8], float).reshape(-1, 3),
            "log_normal": np.array(cols[9], float).reshape(-1, 3),
            "log_impact": np.array(cols[10], dtype=bool),
            **self._branch_arrays(),
        }

    def _branch_arrays(self) -> dict[str, np.ndarray]:
        b, nv = self.branches, self.model.nv
        cands = [c for *_, cs in b for c in cs]
        counts = [len(cs) for *_, cs in b]
        return {
            "branch_step": np.array([x[0] for x in b], dtype=np.int64), "branch_t": np.array([x[1] for x in b], float),
            "branch_chosen": np.array([x[2] for x in b], dtype=np.int64),
            "branch_start": np.cumsum([0] + counts[:-1], dtype=np.int64) if b else np.zeros(0, np.int64),
            "branch_count": np.array(counts, dtype=np.int64),
            "candidate_u_plus": np.array([c[0] for c in cands], float).reshape(-1, nv),
            "candidate_distance": np.array([c[1] for c in cands], float),
            "candidate_global_min": np.array([c[2] for c in cands], dtype=bool),
        }


def _meta(model: Model, status: str, steps: int, wall: float) -> dict:
    sc = model.scene
    return {
        "format": "moreau-sim trajectory 1",
        "status": status,
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "scene": {"name": sc.name, "description": sc.description, "path": str(sc.path) if sc.path else None,
                  "toml": sc.source,
                  "urdf": {b.name: Path(b.urdf).read_text(encoding="utf-8") for b in sc.bodies}},
        "options": sc.options.to_dict(),
        "model": model.describe(),
        "versions": versions(),
        "run": {"steps": steps, "wall_seconds": wall, "us_per_step": 1e6 * wall / steps if steps else None},
    }


def simulate(model: Model, *, data: Data | None = None, state: State | None = None,
             progress: bool = True) -> Trajectory:
    """Run the scene's options (restitution, dt, duration) from `state` (default: the scene's
    initial state). Returns a complete :class:`Trajectory` or raises :class:`SimulationError`
    (naming the step and time) whose ``.trajectory`` holds the samples up to the failure,
    marked ``status = "failed: ..."``."""
    data = data or make_data(model)
    state = state or initial_state(model)
    opts = model.scene.options
    if opts.integrator is Integrator.EVENT_DRIVEN:
        from .reference import simulate_event_driven  # late: reference imports this module

        return simulate_event_driven(model, data=data, state=state)
    h, e, n, every = opts.dt, opts.restitution, opts.n_steps, opts.save_every
    rec = _Recorder(model, data, 1 + n // every + 1)
    rec.sample(state, 0.0, 0.0, 0)
    t0 = state.t
    prev_closed: set = set()
    work = corr = 0.0
    wall0 = time.perf_counter()
    bar = tqdm(total=n, delay=_PROGRESS_DELAY, disable=not progress, unit="step", mininterval=0.5, leave=False)
    k = 0
    try:
        for k in range(n):
            r = step(model, data, state, h, e, t_next=t0 + (k + 1) * h)
            if r.qp is not None and not r.qp.ok:
                raise SimulationError(f"step {k + 1} (t = {state.t:.6g} s -> {r.state.t:.6g} s): the impact QP "
                                      f"failed with status {r.qp.status} after {r.qp.iterations} iterations "
                                      f"({r.contacts.m} closed contacts)", step=k + 1, t=state.t)
            if not (np.isfinite(r.state.q).all() and np.isfinite(r.state.u).all()):
                raise SimulationError(f"step {k + 1} (t = {state.t:.6g} s -> {r.state.t:.6g} s): the state became "
                                      "non-finite (NaN or inf)", step=k + 1, t=state.t)
            work += r.contact_work
            corr += r.correction_energy
            closed = set()
            if r.contacts.m:
                c = r.contacts
                closed = set(zip(c.pair.tolist(), c.feature.tolist()))
                cut = LOG_RELATIVE * float(r.P.max())
                tm = state.t + 0.5 * h
                for i in np.flatnonzero((r.P > cut) & (r.P > 0)):
                    key = (int(c.pair[i]), int(c.feature[i]))
                    rec.log.append((k + 1, tm, key[0], key[1], float(c.g[i]), float(r.P[i]),
                                    float(r.gamma_minus[i]), float(r.gamma_plus[i]), c.point_a[i], c.normal[i],
                                    key not in prev_closed))
            prev_closed = closed
            if r.branch is not None:
                sol, chosen, u_plus = r.branch
                rec.branches.append((k + 1, state.t + 0.5 * h, chosen,
                                     [(up, c.distance, c.global_min) for up, c in zip(u_plus, sol.candidates)]))
            state = r.state
            if (k + 1) % every == 0 or k == n - 1:
                rec.sample(state, work, corr, r.contacts.m)
                work = corr = 0.0
            if (k & 1023) == 1023:
                bar.update(1024)
    except SimulationError as exc:
        wall = time.perf_counter() - wall0
        exc.trajectory = Trajectory(rec.arrays(), _meta(model, f"failed: {exc}", k, wall))
        raise
    finally:
        bar.close()
    wall = time.perf_counter() - wall0
    return Trajectory(rec.arrays(), _meta(model, "complete", n, wall))


def run(scene: Scene | str | Path, *, dt: float | None = None, duration: float | None = None,
        restitution: float | None = None, progress: bool = False, **options) -> Trajectory:
    """Load (if a path), override options (dt [s], duration [s], restitution, any other
    :class:`~moreau_sim.scene.Options` field), build and simulate. Returns the Trajectory."""
    sc = scene if isinstance(scene, Scene) else load_scene(scene)
    sc = sc.with_options(dt=dt, duration=duration, restitution=restitution, **options)
    return simulate(build_model(sc), progress=progress)


def summary(traj: Trajectory) -> dict:
    """The figures the CLI prints: steps, impacts, energies, penetration, timing."""
    a, run_ = traj.arrays, traj.meta.get("run", {})
    E = a["kinetic_energy"] + a["potential_energy"]
    gaps = a["gap"]
    return {
        "scene": traj.meta.get("scene", {}).get("name"),
        "status": traj.meta.get("status"),
        "steps": run_.get("steps"),
        "samples": int(len(a["t"])),
        "t_end": float(a["t"][-1]) if len(a["t"]) else None,
        "impacts": traj.impacts,
        "branching_steps": int(len(a["branch_step"])),
        "percussions_logged": int(len(a["log_P"])),
        "energy_start": float(E[0]) if len(E) else None,
        "energy_end": float(E[-1]) if len(E) else None,
        "energy_max_increase": float(np.max(E - E[0])) if len(E) else None,
        "contact_work_total": float(a["contact_work"].sum()),
        "correction_energy_total": float(a["correction_energy"].sum()),
        "min_gap": float(gaps.min()) if gaps.size else None,
        "wall_seconds": run_.get("wall_seconds"),
        "us_per_step": run_.get("us_per_step"),
    }
