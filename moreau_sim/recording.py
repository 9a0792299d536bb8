"""One Recorder for every integrator: samples, the percussion log, corner branches and the energy
ledger (docs/theory.md §5), filling the arrays of trajectory.py's schema (in columns.Columns); and the run
metadata every trajectory file carries."""

from __future__ import annotations

import datetime
import functools
import math
import pickle
import platform
import weakref
from collections import ChainMap
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import numpy as np
import pinocchio as pin

from . import trajectory
from .columns import Columns
from .contacts import Contacts, record_gaps
from .data import Data
from .energy import kinetic, potential, total
from .errors import SimulationError
from .ledger import at_rest, impact_terms, law_kept
from .model import Model
from .sums import ordered
from .state import State
from .trajectory import Trajectory

FINITE_FLOATS = 96  # a block's finiteness (_finite) is checked on Python floats up to this many entries
LOG_RELATIVE = 1e-9  # a percussion is logged when P_i > LOG_RELATIVE * max(P) of its step (and > 0)


def versions() -> dict[str, str]:
    """Python's and the libraries' versions (recorded in every output; a new dict each call)."""
    return dict(_versions())


@functools.cache
def _versions() -> dict[str, str]:
    """The versions, read once per process: the libraries are imported once, and reading their metadata
    (3-7 ms) was a whole run's largest fixed cost (a 1000-step run: 3 µs a step; a short adaptive run: more
    than it integrates in)."""
    out = {"python": platform.python_version()}
    for dist in ("moreau-sim", "pin", "coal", "piqp", "numpy", "scipy"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out


def run_metadata(model: Model, status: str, run: dict, **extra) -> dict:
    """The `meta` of a trajectory: format, status, scene (name, path, TOML, URDF and SRDF texts), options,
    model summary, the names and units of q and u, versions, `run` statistics, and any `extra`
    entries (e.g. integrator). What depends on the model alone is computed once per model (_model_meta) and
    copied into each trajectory's meta."""
    meta = {
        "format": trajectory.FORMAT,
        "status": status,
        **{k: v for k, v in extra.items() if k == "integrator"},
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        **_model_meta(model),  # scene, options, model, q_names, u_names, q_units, u_units
        "versions": versions(),
        **{k: v for k, v in extra.items() if k != "integrator"},
        "run": run,
    }
    return meta


_MODEL_META: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # model -> its part of the meta, pickled


def _model_meta(model: Model) -> dict:
    """The part of run_metadata that depends on the model alone (the scene's texts as the model was built from
    them, its options, summary and coordinates), made on a model's first run (a Model never changes) and kept
    pickled: each call returns a new copy (each trajectory's meta is its own), unpickled in a fifth of the time a
    copy of its nested dicts and lists takes in Python."""
    fixed = _MODEL_META.get(model)
    if fixed is None:
        sc = model.scene
        texts: dict[str, str] = {}

        def text(path) -> str:
            """A file's text, read once however many bodies name it: one string for them all, which the pickle
            keeps once (a column of 10,000 beads of one URDF: one text in each trajectory's meta, not 10,000)."""
            key = str(path)
            if key not in texts:
                texts[key] = Path(path).read_text(encoding="utf-8")
            return texts[key]

        fixed = {
            "scene": {"name": sc.name, "description": sc.description, "path": str(sc.path) if sc.path else None,
                      "toml": sc.source,
                      "urdf": {b.name: text(b.urdf) for b in sc.bodies},
                      "srdf": {b.name: text(b.srdf) for b in sc.bodies if b.srdf}},
            "options": model.options.to_dict(),
            "model": model.describe(),
            **model.coordinates(),  # q_names, u_names, q_units, u_units
        }
        fixed = _MODEL_META[model] = pickle.dumps(fixed, pickle.HIGHEST_PROTOCOL)
    return pickle.loads(fixed)


@dataclass(frozen=True, slots=True)
class PercussionRow:
    """One logged contact percussion: the step (time-stepping: the step number; event-driven: the
    index of the next sample), t [s], the contact (pair, kind, feature), its gap g [m], P [N s],
    gamma_minus and gamma_plus [m/s], its point on A [m] and normal, whether it is a new
    impact (the contact did not push in the previous step), and the steps it covers and their time
    [s] (a step: 1 and h; an impact at a located instant: 1 and 0; a stretch of persistent steps is one
    row: its first step's, with P, steps and duration summed over the stretch; docs/theory.md §5.2)."""

    step: int
    t: float
    pair: int
    kind: int
    feature: int
    gap: float
    P: float
    gamma_minus: float
    gamma_plus: float
    point: np.ndarray
    normal: np.ndarray
    impact: bool
    steps: int = 1
    duration: float = 0.0


_LOG_COLUMNS = tuple((f"log_{name}", name) for name in PercussionRow.__slots__)  # (column, field)


def _finite(Q: np.ndarray, U: np.ndarray, G: np.ndarray) -> bool:
    """Whether every entry of Q, U and G is finite: up to FINITE_FLOATS entries on Python floats (cheaper than
    numpy's calls there), else through numpy's sums (NaN and inf propagate through a sum; one that overflows only
    says False)."""
    if Q.size + U.size + G.size <= FINITE_FLOATS:
        return all(map(math.isfinite, Q.ravel().tolist() + U.ravel().tolist() + G.ravel().tolist()))
    return math.isfinite(float(Q.sum()) + float(U.sum()) + float(G.sum()))


class SampleBlock:
    """The samples of one step as Recorder.block figures them, not yet written (Recorder.write_block): instants t
    (k,) [s], Q, U, T, V (arrays), E = T + V [J] and the smooth error each books [J] (lists of floats), pair gaps G
    [m]; the first's contact work, correction energy and work done on the system [J] (the others': 0); n_contacts;
    the ledger's largest rise of one stretch once they are recorded (Recorder._rise)."""

    __slots__ = ("t", "Q", "U", "T", "V", "E", "G", "smooth", "work", "corr", "n_contacts", "rise", "external")

    def __init__(self, t, Q, U, T, V, E, G, smooth, work, corr, n_contacts, rise, external):
        self.t, self.Q, self.U, self.T, self.V, self.E, self.G = t, Q, U, T, V, E, G
        self.smooth, self.work, self.corr, self.n_contacts, self.rise = smooth, work, corr, n_contacts, rise
        self.external = external


class Recorder:
    """Samples (t, q, u, T, V, contact work and correction energy since the previous sample, pair
    gaps, closed contacts), percussion rows, corner branches and the energy ledger of one run.

    The ledger (docs/theory.md §5, ledger.py): the integrator reports each fixed step
    (account_step) and each impact located in time (account_impact); the energy change between
    the states they leave and the next reported or sampled state is contact-free motion and counts
    as smooth error.

    spill: a folder for temporary files that hold all but the last columns.SPILL_BYTES of rows of each group
    (Columns): memory for one block of rows instead of the whole record, and the trajectory's
    arrays are read-only maps of those files."""

    def __init__(self, model: Model, data: Data, n_samples: int = 1, *, spill: str | Path | None = None):
        self.model, self.data = model, data
        gaps = len(model.geometries) if model.gaps_per_geometry else len(model.pairs)  # len(model.gap_names)
        sizes = {"nq": model.nq, "nv": model.nv, "gaps": gaps}
        self._far = model.gaps_per_geometry  # +inf where no partner is near: not an overflow
        self._external = (model.actuation is not None or model.prescribed is not None
                          or model.drive is not None)  # the EXTERNAL columns
        schema = {**trajectory.SAMPLES, **trajectory.EXTERNAL} if self._external else trajectory.SAMPLES
        self._samples = Columns(schema, sizes, n_samples, spill)
        self._act = self._obs = 0.0  # actuator and obstacle work since the previous sample [J] (§5.5)
        self._log = Columns(trajectory.LOG, sizes, 64, spill)
        self._branches = Columns(trajectory.BRANCHES, sizes, 4, spill)
        self._candidates = Columns(trajectory.CANDIDATES, sizes, 8, spill)
        self._impacts = Columns(trajectory.IMPACTS, sizes, 16, spill)
        self._smooth = self._diss = self._law = 0.0  # ledger terms since the previous sample [J]
        self._E: float | None = None  # T + V at the last state the ledger accounted [J]
        self._at: tuple | None = None  # that state's (q, u) arrays (a step starting there reuses _E)
        self._TV = (0.0, 0.0)  # that state's (T, V) [J] (a sample of it reuses them)
        self._gap_sum = (-1, math.nan)  # (row, sum of its gaps) of the last sample (finite())
        self._new_impact = False  # the last log_percussions logged a new impact
        self._held = False  # every contact of the last log_percussions was closed in the step before it
        self._pending: list[PercussionRow] = []  # the rows of the step log_percussions saw, for account_step
        self._rise = (-np.inf, np.nan)  # (largest T + V increase of one step [J], t [s])
        self._law_difference = (0.0, np.nan)  # (largest |D - L| of a contact step [J], t [s])
        self._contact_steps = 0
        # [J] sum over contact steps of max(-S_k, 0): what a capped step (docs/theory.md §2.10) may leave in the
        # ledger's residual (it closes the budget up to -S_k); read by the invariant checks
        self.smooth_deficit = 0.0

    @property
    def n(self) -> int:
        """Samples recorded so far."""
        return self._samples.n

    def sample(self, state: State, work: float, corr: float, n_contacts: int, figures: tuple | None = None) -> None:
        """Record a sample of `state`; figures: its (T [J], V [J], pair gaps [m]) as this would evaluate them,
        already evaluated (compiled_events.sampler: none here then)."""
        m, d = self.model, self.data
        q, u = state.q, state.u
        if m.prescribed is not None:
            m.prescribed.place(m.geom, state.t)  # the gaps at the sample's time
        i = self._samples.free()
        c = self._samples.cols
        c["t"][i] = state.t
        c["q"][i] = q
        c["u"][i] = u
        if figures is not None:
            T, V, _ = figures
        elif self._at is not None and self._at[0] is q and self._at[1] is u:
            T, V = self._TV  # the state the last step left, already evaluated by account_step
        else:
            T, V = kinetic(m, d, q, u), potential(m, d, q)
        c["kinetic_energy"][i], c["potential_energy"][i] = T, V
        c["contact_work"][i] = work
        c["correction_energy"][i] = corr
        g = c["gap"][i] = record_gaps(m, d, q) if figures is None else figures[2]
        # their sum: finite when every gap is (an overflow of finite gaps, or inf - inf, only sends to the full tests)
        gs = self._gap_sum = (self._samples.n, sum(c["gap"][i].tolist()))
        # coal failed at a finite state (not an overflow, which finite() reports): stop, uncommitted, no sentinel
        if not math.isfinite(gs[1]) and np.isnan(g).any() and math.isfinite(T + V) and state.finite():
            k = int(np.flatnonzero(np.isnan(g))[0])
            what = f"a pair of geometry {m.gap_names[k]}" if m.gaps_per_geometry else f"pair {m.pairs[k].name}"
            raise SimulationError(f"the distance of {what} at t = {state.t:.6g} s is undefined "
                                  "(coal's GJK/EPA query failed)")
        c["n_contacts"][i] = n_contacts
        self._smooth_until(T + V, state.t)  # 0 right after a step
        c["smooth_error"][i], c["dissipation"][i], c["law_dissipation"][i] = self._smooth, self._diss, self._law
        if self._external:
            c["actuator_work"][i], c["obstacle_work"][i] = self._act, self._obs
        self._samples.commit()
        self._smooth = self._diss = self._law = self._act = self._obs = 0.0
        self._E, self._at, self._TV = T + V, (q, u), (T, V)

    def block(self, t: np.ndarray, Q: np.ndarray, U: np.ndarray, T: np.ndarray, V: np.ndarray, G: np.ndarray,
              work: float, corr: float, n_contacts: int) -> "SampleBlock | None":
        """The k samples of one step at the instants t (k,) [s], given with their figures (Q (k, nq), U (k, nv), T, V
        (k,) [J], pair gaps G (k, pairs) [m]: compiled_events.sampler's), as k calls of sample() would record them
        (work, corr [J]: the first's contact work and correction energy, the others' are 0), figured out but not yet
        written (write_block): what the invariant checks read of them in one pass (Invariants.samples). None where
        sample() must take them one by one: moving statics (placed at each sample's time), or anything non-finite
        (sample() and the driver's checks name the sample and the cause)."""
        if self.model.prescribed is not None or not len(t):
            return None
        Es = [a + b for a, b in zip(T.tolist(), V.tolist())]  # each sample's T + V as sample() adds them
        if not (all(map(math.isfinite, Es)) and _finite(Q, U, G)):
            return None
        # the smooth error of each and the ledger's largest rise, as sample() books them one after the other
        # (_smooth_until), on Python floats: the same operations
        diffs = [b - a for a, b in zip(Es, Es[1:])]  # from each sample to the next
        prev = self._E
        if prev is None:  # nothing accounted yet: the first books what the ledger holds, no rise
            changes, smooth, first = diffs, [self._smooth], 1
        elif math.isfinite(prev):
            d0 = Es[0] - prev
            changes, smooth, first = [d0] + diffs, [self._smooth + d0], 0
        else:
            return None
        smooth += [0.0 + d for d in diffs]  # (sample() adds each change to a _smooth reset to 0.0)
        rise = self._rise
        if changes:  # the first of the largest changes, if above the ledger's (a later equal one does not replace it)
            d = max(changes)
            if d > rise[0]:
                rise = (d, float(t[first + changes.index(d)]))
        external = self._act + self._obs if self._external else 0.0
        return SampleBlock(t, Q, U, T, V, Es, G, smooth, work, corr, n_contacts, rise, external)

    def write_block(self, b: "SampleBlock") -> None:
        """Record the samples of block() (its rows written, then counted at once: an interrupt leaves none of them)."""
        k = len(b.t)
        cols = self._samples
        i = cols.reserve(k)
        c, j = cols.cols, i + k
        c["t"][i:j] = b.t
        c["q"][i:j] = b.Q
        c["u"][i:j] = b.U
        c["kinetic_energy"][i:j] = b.T
        c["potential_energy"][i:j] = b.V
        c["gap"][i:j] = b.G
        c["n_contacts"][i:j] = b.n_contacts
        c["smooth_error"][i:j] = b.smooth
        firsts = [("contact_work", b.work), ("correction_energy", b.corr), ("dissipation", self._diss),
                  ("law_dissipation", self._law)]
        if self._external:
            firsts += [("actuator_work", self._act), ("obstacle_work", self._obs)]
        for name, first in firsts:  # the first sample's: what the steps since the previous one did; then 0
            col = c[name]
            col[i] = first
            col[i + 1:j] = 0.0
        cols.commit(k)
        self._gap_sum = (-1, math.nan)
        self._smooth = self._diss = self._law = self._act = self._obs = 0.0
        self._rise = b.rise
        T, V = float(b.T[-1]), float(b.V[-1])
        self._E, self._at, self._TV = T + V, (b.Q[-1], b.U[-1]), (T, V)

    def energies(self, state: State) -> tuple[float, float] | None:
        """(T, V) [J] of `state` when it is the last state the ledger evaluated (a fixed step's end,
        a sample), else None (the invariant checks read them instead of evaluating them again)."""
        at = self._at
        return self._TV if at is not None and at[0] is state.q and at[1] is state.u else None

    def last_sample(self) -> tuple[float, float, float, float, float, float, np.ndarray]:
        """The last sample's T, V, contact work, correction energy, smooth error, the work done on the
        system (actuator + obstacle work, §5.5; 0 in a passive run) [J] and pair gaps [m] (a view of its row)."""
        i, c = self._samples.last, self._samples.cols
        external = float(c["actuator_work"][i] + c["obstacle_work"][i]) if self._external else 0.0
        return (float(c["kinetic_energy"][i]), float(c["potential_energy"][i]), float(c["contact_work"][i]),
                float(c["correction_energy"][i]), float(c["smooth_error"][i]), external, c["gap"][i])

    def _smooth_until(self, E: float, t: float) -> None:
        """Contact-free motion from the last accounted state to a state of T + V = E [J] at t [s]:
        smooth error, and a rise that counts as one step's (event-driven, adaptive: a smooth stretch)."""
        if self._E is not None:
            self._smooth += E - self._E
            if E - self._E > self._rise[0]:
                self._rise = (E - self._E, float(t))

    def account_step(self, step: int, t: float, before: State, r, h: float, e: float) -> None:
        """The ledger of one midpoint Moreau step (docs/theory.md §5, ledger.py) from `before` to the
        StepResult r, of size h [s] and restitution e; t [s]: the step's midpoint. Call it after
        log_percussions (a step with a new impact gets an impact row; a step whose contacts it found all closed
        before may be persistent, §5.2: no D, L)."""
        m, d = self.model, self.data
        q0, u0, q1, u1 = before.q, before.u, r.state.q, r.state.u
        if self._at is not None and self._at[0] is q0 and self._at[1] is u0:
            E0 = self._E
        else:
            E0 = total(m, d, q0, u0)
            self._smooth_until(E0, before.t)
        T1, V1 = kinetic(m, d, q1, u1), potential(m, d, q1)
        E1 = T1 + V1
        # the work done on the system (§5.5): torques over the step's mean velocity, the moving statics' push
        tau = r.tau
        act = 0.0 if tau is None else 0.5 * h * float(ordered(tau, u0 + u1))  # summed in index order (§2.8)
        self._act += act
        self._obs += r.obstacle_work
        # a rise the position correction made and booked (the lift of bodies at rest, docs/theory.md
        # §2.5) is in the ledger's correction term, not a gain of the physics; nor is the work done on it
        rise = E1 - E0 - max(r.correction_energy, 0.0) - act - r.obstacle_work
        if rise > self._rise[0]:
            self._rise = (rise, float(r.state.t))
        res = r.qp
        if res is None or res.M is None:
            self._log_step(False)
            self._smooth += E1 - E0 - act - r.obstacle_work  # a contact-free step is smooth motion only (§2.13)
        else:  # the projection's problem: M, v_free = v0, b; and the step's own u_free
            # the law's u_{k+1}: before a lift the correction paid with the velocities, booked as correction (§2.5)
            u_law = u1 if r.u_law is None else r.u_law
            # a persistent contact step (§5.2): every contact closed before and at rest; no impact to book
            persistent = self._held and r.branch is None and at_rest(res.W, u0, r.u_free, r.gamma_minus,
                                                                     r.gamma_plus) and law_kept(res.v, u0, u1, e)
            self._log_step(persistent)
            if not persistent:
                T_minus, T_plus, law = impact_terms(res.M, res.v0, res.v, u0, u_law, e, r.P, res.b)
            q_free = pin.integrate(m.pin, pin.integrate(m.pin, q0, 0.5 * h * u0), 0.5 * h * r.u_free)
            act_free = 0.0 if tau is None else 0.5 * h * float(ordered(tau, u0 + r.u_free))  # the torques' work
            # contacts that left the smooth motion as it was, bit for bit (u_{k+1} = u_free, q_{k+1} = q_free, e.g.
            # closed without a push, §5.3): its energy is E1's
            same = r.u_free.tobytes() == u1.tobytes() and q_free.tobytes() == q1.tobytes()
            S = (E1 if same else total(m, d, q_free, r.u_free)) - E0 - act_free - r.drive_work_free
            self._smooth += S
            if S < 0.0:
                self.smooth_deficit -= S
            if persistent:
                self._contact_steps += 1
            else:  # a moving static's push (§2.9): the impact's dissipation is counted in its frame, T- - T+ + W_o
                self._add_impact(step, t, T_minus, T_plus, law, int(np.count_nonzero(r.P > 0)), self._new_impact,
                                 r.obstacle_work)
        self._E, self._at, self._TV = E1, (q1, u1), (T1, V1)

    def account_impact(self, t: float, q: np.ndarray, u_minus: np.ndarray, u_plus: np.ndarray, M: np.ndarray,
                       v: np.ndarray, e: float, P: np.ndarray) -> None:
        """The ledger of an impact located at t [s] (event-driven and adaptive runs): the law of
        docs/theory.md §1 at q, u- -> u+ with v the projection and M = M(q)."""
        m, d = self.model, self.data
        self._log.keep = 0  # an impact between steps ends a stretch of persistent ones (_log_step)
        V = potential(m, d, q)  # (energy.total's terms; V once for both)
        self._smooth_until(kinetic(m, d, q, u_minus) + V, t)
        T_minus, T_plus, law = impact_terms(M, u_minus, v, u_minus, u_plus, e, P, None)
        self._add_impact(self._samples.n, t, T_minus, T_plus, law, int(np.count_nonzero(P > 0)), True)
        self._E, self._at = kinetic(m, d, q, u_plus) + V, None

    def _add_impact(self, step: int, t: float, T_minus: float, T_plus: float, law: float, contacts: int,
                    new: bool, given: float = 0.0) -> None:
        """given: the work a moving static did in the step [J], added to both the dissipation and the law's
        figure (their difference is unchanged; the dissipation is then the one in the static's frame, >= 0)."""
        dissipated = T_minus - T_plus
        if given:
            dissipated, law = dissipated + given, law + given
        self._contact_steps += 1
        self._diss += dissipated
        self._law += law
        diff = abs(dissipated - law)
        if diff > self._law_difference[0]:
            self._law_difference = (diff, float(t))
        if new:
            i = self._impacts.free()
            c = self._impacts.cols
            c["impact_step"][i], c["impact_t"][i], c["impact_contacts"][i] = step, t, contacts
            c["impact_T_minus"][i], c["impact_T_plus"][i] = T_minus, T_plus
            c["impact_dissipation"][i], c["impact_law"][i] = dissipated, law
            self._impacts.commit()

    def ledger_meta(self) -> dict:
        """The per-run ledger figures no array holds (meta["ledger"] of the trajectory; a time is None
        when there was no such step: JSON has no NaN)."""
        rise, t_rise = self._rise if np.isfinite(self._rise[0]) else (0.0, np.nan)
        t_diff = self._law_difference[1]
        return {"max_step_rise": float(rise), "t_step_rise": None if np.isnan(t_rise) else float(t_rise),
                "max_law_difference": float(self._law_difference[0]),
                "t_law_difference": None if np.isnan(t_diff) else float(t_diff), "contact_steps": self._contact_steps}

    def finite(self) -> bool:
        """Whether the last sample's energies and gaps are finite (an overflow shows there first)."""
        i, c = self._samples.last, self._samples.cols
        if not (math.isfinite(c["kinetic_energy"][i]) and math.isfinite(c["potential_energy"][i])):
            return False
        n, gs = self._gap_sum
        if n == self._samples.n - 1 and math.isfinite(gs):
            return True
        g = c["gap"][i]
        return bool(np.isfinite(g).all() or (self._far and not np.isnan(g).any() and not np.isneginf(g).any()))

    def log(self, row: PercussionRow) -> None:
        """Write one row to the log (it ends any stretch of persistent steps)."""
        self._write(row)
        self._log.keep = 0

    def _write(self, row: PercussionRow) -> None:
        i = self._log.free()
        c = self._log.cols
        for column, name in _LOG_COLUMNS:
            c[column][i] = getattr(row, name)
        self._log.commit()

    def _log_step(self, persistent: bool) -> None:
        """Log the rows log_percussions kept for this step (account_step, once it knows whether the step is
        persistent). A persistent step whose rows have the contacts, in order, of the stretch of persistent steps
        the log ends with adds its P to the stretch's rows and one to their log_steps, instead of new rows
        (docs/theory.md §5.2): at rest, a step's percussions are the weight's, and a stretch is one row per
        contact whatever its length. The stretch is the log's last log.keep rows (0: none), which a spill
        leaves in memory."""
        rows, self._pending = self._pending, []
        k = len(rows)
        log = self._log
        i0 = log.last - k + 1  # the stretch's first row in log.cols
        c = log.cols
        if persistent and k and log.keep == k and all(
                (c["log_pair"][i0 + j], c["log_kind"][i0 + j], c["log_feature"][i0 + j]) ==
                (row.pair, row.kind, row.feature) for j, row in enumerate(rows)):
            for j, row in enumerate(rows):
                c["log_P"][i0 + j] += row.P
                c["log_steps"][i0 + j] += 1
                c["log_duration"][i0 + j] += row.duration
            return
        log.keep = k if persistent else 0  # a new stretch: its rows stay in memory as they are written
        for row in rows:
            self._write(row)

    def log_percussions(self, step: int, t: float, contacts: Contacts, P: np.ndarray, gamma_minus: np.ndarray,
                        gamma_plus: np.ndarray, previous: set, *, h: float) -> set:
        """The percussions of a step above LOG_RELATIVE of its largest, logged by the account_step that
        follows (a stretch of persistent steps is one row per contact, _log_step); a row is a new impact
        when its contact (pair, kind, feature) is not in `previous`. Returns this step's contacts."""
        self._new_impact = False
        if not contacts.m:
            self._held = False
            return set()
        cut = max(LOG_RELATIVE * float(P.max()), 0.0)
        keys = list(zip(contacts.pair.tolist(), contacts.kind.tolist(), contacts.feature.tolist()))
        self._held = all(key in previous for key in keys)
        for i, p in enumerate(P.tolist()):
            if p > cut:
                key = keys[i]
                self._new_impact |= key not in previous
                self._pending.append(PercussionRow(step, t, *key, float(contacts.g[i]), p, float(gamma_minus[i]),
                                       float(gamma_plus[i]), contacts.point_a[i], contacts.normal[i],
                                       key not in previous, 1, h))
        return set(keys)

    def branch(self, step: int, t: float, chosen: int, candidates: list[tuple]) -> None:
        """A step with several admissible corner outcomes: candidates [(u_plus, distance, global_min)]."""
        start = self._candidates.n
        for u_plus, distance, global_min in candidates:
            j = self._candidates.free()
            c = self._candidates.cols
            c["candidate_u_plus"][j], c["candidate_distance"][j], c["candidate_global_min"][j] = \
                u_plus, distance, global_min
            self._candidates.commit()
        i = self._branches.free()
        b = self._branches.cols
        b["branch_step"][i], b["branch_t"][i], b["branch_chosen"][i] = step, t, chosen
        b["branch_start"][i], b["branch_count"][i] = start, len(candidates)
        self._branches.commit()

    def _groups(self) -> tuple[Columns, ...]:
        return self._samples, self._log, self._branches, self._candidates, self._impacts

    def carried(self, state: State) -> dict:
        """What the recording carries from one step to the next besides its arrays (the ledger's
        running terms), as JSON for a checkpoint (checkpoint.py); `state`: the run's current state."""
        return {"smooth": float(self._smooth), "diss": float(self._diss), "law": float(self._law),
                "act": float(self._act), "obs": float(self._obs),
                "E": None if self._E is None else float(self._E),
                "at_state": self._at is not None and self._at[0] is state.q and self._at[1] is state.u,
                "TV": [float(x) for x in self._TV], "new_impact": bool(self._new_impact),
                "rise": [None if not np.isfinite(x) else x for x in self._rise],
                "law_difference": [None if np.isnan(x) else x for x in self._law_difference],
                "contact_steps": self._contact_steps, "smooth_deficit": float(self.smooth_deficit),
                "rest": self._log.keep}

    def restore(self, arrays: Mapping[str, np.ndarray], carried: dict, state: State) -> None:
        """Continue a recording from its arrays (a dict or an open NPZ) and carried() (a
        checkpoint's) at `state`."""
        c = carried
        self._log.keep = int(c.get("rest", 0))  # the stretch of persistent steps the log ends with (_log_step)
        if "log_steps" not in arrays:  # a checkpoint of format 3
            arrays = ChainMap(arrays, trajectory.log_before_format_4(len(arrays["log_P"])))
        for g in self._groups():
            g.load(arrays)
        self._gap_sum = (-1, math.nan)
        self._smooth, self._diss, self._law, self._E = c["smooth"], c["diss"], c["law"], c["E"]
        self._act, self._obs = c.get("act", 0.0), c.get("obs", 0.0)
        self._at = (state.q, state.u) if c["at_state"] else None
        self._TV, self._new_impact, self._contact_steps = tuple(c["TV"]), c["new_impact"], c["contact_steps"]
        self.smooth_deficit = c.get("smooth_deficit", 0.0)
        rise, t_rise = c["rise"]
        self._rise = (-np.inf if rise is None else rise, np.nan if t_rise is None else t_rise)
        diff, t_diff = c["law_difference"]
        self._law_difference = (diff, np.nan if t_diff is None else t_diff)

    def arrays(self) -> dict[str, np.ndarray]:
        out = {**self._samples.arrays(), **self._log.arrays(), **self._branches.arrays(), **self._candidates.arrays(),
               **self._impacts.arrays()}
        return {k: out[k] for k in trajectory.ARRAYS + tuple(trajectory.EXTERNAL) if k in out}

    def trajectory(self, meta: dict, *, final: bool = True) -> Trajectory:
        """The arrays so far (views) with `meta` (and its "ledger" entry, ledger_meta()); `final`:
        the recording ends, its unused rows are released."""
        if final:
            for g in self._groups():
                g.fit()
        arrays = self.arrays()
        meta = {**meta, "ledger": self.ledger_meta()}
        m = self.model
        if not m.listed and isinstance(meta.get("model"), dict):  # the meta lists no pair of a pair table: name the
            n = len(m.pairs)                                      # pairs its log holds
            logged = np.unique(arrays["log_pair"]).tolist()
            meta["model"] = {**meta["model"], "logged_pairs": {str(k): m.pairs[k].name for k in logged if k < n}}
        traj = Trajectory(arrays, meta)
        if final:
            for g in self._groups():
                g.close()
        return traj
