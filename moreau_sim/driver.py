"""The one loop over time of every integrator (docs/theory.md §9; protocol.py): sampling,
recording and the energy ledger (recording.py, §5), progress, Ctrl-C/SIGTERM
(errors.named_stops), checkpoints and resume (checkpoint.py), spilling to disk, the invariant hook.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from tqdm import tqdm

from . import checkpoint as ckpt
from . import compiled
from .checkpoint import Checkpoint
from .data import Data, make_data, spares
from .errors import SimulationError, named_stops
from .model import Model
from .protocol import FixedStep, Impact, Integrator, Report, RunStatus, Status
from .recording import LOG_RELATIVE, PercussionRow, Recorder
from .state import State
from .trajectory import Trajectory

# [s] the progress bar appears on runs longer than this (MOREAU_SIM_PROGRESS_DELAY overrides it)
_PROGRESS_DELAY = float(os.environ.get("MOREAU_SIM_PROGRESS_DELAY", "2.0"))
PROGRESS_EVERY = 0.5  # [s of wall time] the bar is refreshed at most this often, whatever a step costs
_BAR = "{percentage:3.0f}%|{bar}| {n:.6g}/{total:.6g} {unit} [{elapsed}<{remaining}]"

# The invariant hook: check(where, state, report, recorder) at the initial state (where "start",
# report None), at every accepted point ("point"), every sample ("sample", after it is recorded) and
# once at the end ("end", the final state);
# the recorder's figures (Recorder.energies, .last_sample) are there to read. A dict (or a list of
# them) it returns is a violation, kept in meta["invariants"], and the run ends "flagged" instead of "complete"
# (protocol.RunStatus); a check that must stop the run raises SimulationError. A hook with
# state_dict()/load_state_dict() carries its figures through a checkpoint (invariants.Invariants).
Check = Callable[[str, State, "Report | None", Recorder], "dict | None"]


def drive(integ: Integrator, model: Model, data: Data, *, grid: np.ndarray | None = None,
          progress: bool = False, checkpoint: Checkpoint | None = None, spill: str | Path | None = None,
          check: Check | None = None, capacity: int = 1, fast: Callable | None = None) -> Trajectory:
    """Run `integ` from its state to its end. grid: the output instants [s] of an
    integrator that samples through dense output (else it marks its samples, Report.due);
    checkpoint: save every so often at accepted points and/or resume (bit-identical); spill: a
    folder for the recorded rows (recording.Recorder); check: the invariant hook (above);
    capacity: the expected number of samples; fast: fast(integ, rec, loop, check) -> a runner of compiled
    steps or None (compiled_run.runner: runner.advance(t_stop) takes steps until a poll, -> (t, finished), or
    None where the next step is the Python run's). Returns the Trajectory, or raises SimulationError
    (SimulationInterrupted on Ctrl-C) with .trajectory up to the stop."""
    rec = Recorder(model, data, capacity, spill=spill)
    loop = _Loop(integ, rec, grid, check)
    wall_before = cpu_before = 0.0
    resume = checkpoint is not None and checkpoint.resume and Path(checkpoint.path).exists()
    if resume:
        loop_state, wall_before, cpu_before = ckpt.load(Path(checkpoint.path), model, rec, data, integ)
        loop.load(loop_state)
    wall0, cpu0 = time.perf_counter(), time.process_time()

    def clock() -> tuple[float, float]:
        """The run's wall and CPU time so far [s] (a resumed run's before its checkpoint included)."""
        return wall_before + time.perf_counter() - wall0, cpu_before + time.process_time() - cpu0

    def partial(status: str) -> Trajectory:
        return rec.trajectory(loop.meta(status, *clock()))

    every = checkpoint.every if checkpoint is not None else None
    next_ck = np.inf if every is None else loop.t_ck + every
    done, total, unit = integ.progress()
    bar = (tqdm(total=total, initial=done, delay=_PROGRESS_DELAY, unit=unit, leave=False, bar_format=_BAR,
                mininterval=PROGRESS_EVERY) if progress else _NO_BAR)
    refresh = time.perf_counter() + PROGRESS_EVERY if progress else np.inf
    at: list = [None]  # while a step's report is recorded: the position of that step (errors name it)
    with named_stops(lambda: at[0] or integ.position(), partial, unit=integ.unit):
        try:
            if not resume:
                loop.start(integ.state)
            runner = None if fast is None else fast(integ, rec, loop, check)
            while True:
                got = None if runner is None else runner.advance(next_ck)
                if got is None:
                    before = integ.position()
                    rep = integ.step(grid[loop.gi] if grid is not None and loop.gi < len(grid) else np.inf)
                    if rep.status is Status.FAILED:
                        raise SimulationError(rep.message, step=before[0], t=rep.t)
                    at[0] = before
                    loop.account(rep)
                    at[0] = None
                    if runner is not None:
                        runner.python_step()
                    got = rep.t, rep.status is Status.FINISHED
                t, finished = got
                if finished:
                    _show(bar, integ, wall0)
                    break
                if t >= next_ck:
                    loop.t_ck = t
                    next_ck = t + every
                    ckpt.save(Path(checkpoint.path), rec, loop.meta("checkpoint", *clock()), integ=integ,
                              loop=loop.state_dict(), data=data)
                if time.perf_counter() >= refresh:  # ~50 ns a step: the bar moves with wall time, not steps
                    _show(bar, integ, wall0)
                    refresh = time.perf_counter() + PROGRESS_EVERY
        finally:
            bar.close()
        loop.end(integ.state)  # in named_stops: a strict violation at the end leaves with the samples
    done = RunStatus.FLAGGED if loop.violations else RunStatus.COMPLETE
    traj = rec.trajectory(loop.meta(done.value, *clock()))
    if checkpoint is not None and not checkpoint.keep:
        Path(checkpoint.path).unlink(missing_ok=True)
    return traj


SPARE_NV = 64  # a model with at most this many velocities keeps the Datas of its runs for its next ones (run_data)


@contextlib.contextmanager
def run_data(model: Model, data: Data | None = None) -> Iterator[Data]:
    """The Data of one run of `model`, as a new one starts it (Data.reset): `data` reset, else one of the model's
    spares (data.spares) reset, else a new one. A spare or new Data goes back to the model's spares at the run's
    end where the model is small (SPARE_NV): on a short run of a small model, making a Data (its Pinocchio Datas,
    coal's requests and results, the compiled Stepper) costs as much as the run (docs/theory.md §2.8)."""
    reset = compiled.guess_reset()
    if data is not None:
        yield data.reset(reset)
        return
    spare = spares(model)
    try:
        d = spare.pop().reset(reset) if spare else make_data(model)
    except IndexError:  # (another thread took the last one)
        d = make_data(model)
    try:
        yield d
    finally:
        if model.nv <= SPARE_NV:
            spare.append(d)


class _NoBar:
    """The bar of a run without progress (a disabled tqdm costs ~10 us to make, per run)."""

    disable = True

    def close(self) -> None:
        pass


_NO_BAR = _NoBar()


def _show(bar: tqdm | _NoBar, integ: Integrator, wall0: float) -> None:
    """Move the bar to the integrator's progress (once the run has lasted the bar's delay)."""
    if not bar.disable and time.perf_counter() - wall0 >= _PROGRESS_DELAY:
        bar.n = integ.progress()[0]
        bar.refresh()


class _Loop:
    """What the driver carries between accepted points: the contact work and correction energy
    since the last sample, the next grid instant, the last fixed step's contacts (the log's
    new-impact test), the invariant violations."""

    def __init__(self, integ: Integrator, rec: Recorder, grid: np.ndarray | None, check: Check | None):
        self.integ, self.rec, self.grid, self.check = integ, rec, grid, check
        self.work = self.corr = 0.0
        self.gi = 0
        self.previous: set = set()
        self.violations: list[dict] = []
        self.t_ck = integ.t0  # [s] the last checkpoint (or the start)
        self.points = 0  # the accepted points recorded

    def start(self, state: State) -> None:
        """The initial sample(s) (before any impact)."""
        if self.grid is None:
            self._sample(state, 0)
        while self.grid is not None and self.gi < len(self.grid) and self.grid[self.gi] <= state.t:
            self._sample(state, 0)
            self.gi += 1
        self._check("start", state, None)

    def account(self, rep: Report) -> None:
        """Record one step's report: its records, work, samples; then the invariant hook."""
        self.work += rep.work
        self.corr += rep.corr
        rec = self.rec
        for r in rep.records:
            if type(r) is FixedStep:
                res = r.result
                if r.fresh:
                    self.previous = set()
                index = rec.n if r.index is None else r.index
                self.previous = rec.log_percussions(index, r.t, res.contacts, res.P, res.gamma_minus,
                                                    res.gamma_plus, self.previous, h=r.h)
                rec.account_step(index, r.t, r.before, res, r.h, r.e)
                if res.branch is not None:
                    sol, chosen, u_plus = res.branch
                    rec.branch(index, r.t, chosen, [(up, c.distance, c.global_min)
                                                    for up, c in zip(u_plus, sol.candidates)])
            else:
                self._impact(r)
        if rep.due:
            self._sample(rep.state, rep.n_contacts)
        grid = self.grid
        for seg in rep.segments:
            end = self.gi  # the grid instants t < until (<= if closed) not yet sampled: grid[gi:end]
            until, closed, at, n = seg.until, seg.closed, grid.item, len(grid)  # (item: a Python float, cheaper)
            while end < n and (at(end) < until or (closed and at(end) <= until)):
                end += 1
            if end == self.gi:
                continue
            tgs = grid[self.gi:end]
            if seg.batch is not None:  # all the step's samples in one call, recorded at once where they may be
                Q, U, T, V, G = seg.batch(tgs)
                if self._block(tgs, Q, U, T, V, G, seg.n_contacts):
                    continue
                for i, tg in enumerate(tgs.tolist()):
                    self._sample(State(tg, Q[i], U[i]), seg.n_contacts, (float(T[i]), float(V[i]), G[i]))
                    self.gi += 1
                continue
            for tg in tgs.tolist():
                q, u = seg.dense(tg)
                self._sample(State(tg, q, u), seg.n_contacts)
                self.gi += 1
        if self.check is not None and rep.state is not None:
            self._check("point", rep.state, rep)
        self.points += 1

    def end(self, state: State) -> None:
        """The hook once more at the run's end (where "end"): what had not yet persisted long enough."""
        self._check("end", state, None)

    def _impact(self, r: Impact) -> None:
        rec = self.rec
        c, P = r.contacts, r.P
        if r.branch is not None:
            cand, chosen, ups = r.branch
            rec.branch(rec.n, r.t, chosen, [(up, k.distance, k.global_min) for up, k in zip(ups, cand.candidates)])
        cut = LOG_RELATIVE * float(P.max(initial=0.0))
        for i in np.flatnonzero((P > cut) & (P > 0)):  # step: the index of the next sample
            rec.log(PercussionRow(rec.n, r.t, int(c.pair[i]), int(c.kind[i]), int(c.feature[i]), float(c.g[i]),
                                  float(P[i]), float(r.gamma_minus[i]), float(r.gamma_plus[i]), c.point_a[i],
                                  c.normal[i], True))
        rec.account_impact(r.t, r.q, r.u_minus, r.u_plus, r.M, r.v, r.e, P)

    def _block(self, t: np.ndarray, Q: np.ndarray, U: np.ndarray, T: np.ndarray, V: np.ndarray, G: np.ndarray,
               n_contacts: int) -> bool:
        """A step's samples (at the instants t, with their figures: Segment.batch's) recorded and checked at once:
        the rows and figures _sample would give them one by one (Recorder.block, Invariants.samples). False (nothing
        done) where they go one by one: a hook of the caller's (it reads each sample), something non-finite, or
        a check that may find something (it is then found at its sample, as _sample finds it)."""
        check = self.check
        together = None if check is None else getattr(check, "samples", None)
        if check is not None and together is None:
            return False
        b = self.rec.block(t, Q, U, T, V, G, self.work, self.corr, n_contacts)
        if b is None or (together is not None and not together(b, self.rec)):
            return False
        self.rec.write_block(b)
        self.work = self.corr = 0.0
        self.gi += len(t)
        return True

    def _sample(self, state: State, n_contacts: int, figures: tuple | None = None) -> None:
        """A sample with the work and correction energy since the previous one (figures: its (T, V,
        gaps) already evaluated, Recorder.sample); nothing non-finite is ever complete."""
        if not state.finite():
            raise SimulationError(f"the state at t = {state.t:.6g} s became non-finite (NaN or inf)")
        self.rec.sample(state, self.work, self.corr, n_contacts, figures)
        self.work = self.corr = 0.0
        if not self.rec.finite():
            raise SimulationError(f"the energies or gaps at t = {state.t:.6g} s became non-finite (an overflow: "
                                  "check gravity, masses and initial velocities)")
        self._check("sample", state, None)

    def _check(self, where: str, state: State, rep: Report | None) -> None:
        if self.check is not None:
            v = self.check(where, state, rep, self.rec)
            if isinstance(v, list):
                self.violations += v
            elif v is not None:
                self.violations.append(v)

    def meta(self, status: str, wall: float, cpu: float) -> dict:
        """The integrator's meta with the run's CPU time [s] (time.process_time of the loop: from the initial state
        to the last, recording and checks included, building the model and the run's set-up not) in meta["run"]."""
        meta = self.integ.meta(status, wall, self.points)
        meta["run"]["cpu_seconds"] = cpu
        return {**meta, "invariants": self.violations} if self.violations else meta

    def state_dict(self) -> dict:
        carried = getattr(self.check, "state_dict", None)
        return {"work": self.work, "corr": self.corr, "gi": self.gi, "previous": sorted(self.previous),
                "violations": self.violations, "t_ck": self.t_ck, "points": self.points,
                "check": carried() if carried is not None else None}

    def load(self, d: dict) -> None:
        self.work, self.corr, self.gi = float(d["work"]), float(d["corr"]), int(d["gi"])
        self.previous = {tuple(p) for p in d["previous"]}
        self.violations, self.t_ck, self.points = list(d["violations"]), float(d["t_ck"]), int(d["points"])
        if d.get("check") is not None and hasattr(self.check, "load_state_dict"):
            self.check.load_state_dict(d["check"])
