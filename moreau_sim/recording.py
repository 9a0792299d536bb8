"""One Recorder for every integrator: samples, the percussion log and corner branches, filling
the arrays of trajectory.py's schema; and the run metadata every trajectory file carries.

Columns grow in place by at most BLOCK_ROWS rows (compact: memory is proportional to what was recorded)."""

from __future__ import annotations

import datetime
import platform
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import numpy as np

from . import trajectory
from .contacts import Contacts, pair_distances
from .data import Data
from .energy import kinetic, potential
from .model import Model
from .state import State
from .trajectory import Trajectory

BLOCK_ROWS = 1 << 14  # the most rows a full column grows by at a time (see _Columns)
LOG_RELATIVE = 1e-9  # a percussion is logged when P_i > LOG_RELATIVE * max(P) of its step (and > 0)


def versions() -> dict[str, str]:
    """Python's and the libraries' versions (recorded in every output)."""
    out = {"python": platform.python_version()}
    for dist in ("moreau-sim", "pin", "coal", "piqp", "numpy", "scipy"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out


def run_metadata(model: Model, status: str, run: dict, **extra) -> dict:
    """The `meta` of a trajectory: format, status, scene (name, path, TOML and URDF texts), options,
    model summary, the names and units of q and u, versions, `run` statistics, and any `extra`
    entries (e.g. integrator)."""
    sc = model.scene
    meta = {
        "format": trajectory.FORMAT,
        "status": status,
        **{k: v for k, v in extra.items() if k == "integrator"},
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "scene": {"name": sc.name, "description": sc.description, "path": str(sc.path) if sc.path else None,
                  "toml": sc.source,
                  "urdf": {b.name: Path(b.urdf).read_text(encoding="utf-8") for b in sc.bodies}},
        "options": model.options.to_dict(),
        "model": model.describe(),
        **model.coordinates(),  # q_names, u_names, q_units, u_units
        "versions": versions(),
        **{k: v for k, v in extra.items() if k != "integrator"},
        "run": run,
    }
    return meta


@dataclass(frozen=True, slots=True)
class PercussionRow:
    """One logged contact percussion: the step (time-stepping: the step number; event-driven: the
    index of the next sample), t [s], the contact (pair, kind, feature), its gap g [m], P [N s],
    gamma_minus and gamma_plus [m/s], its point on A [m] and normal, and whether it is a new
    impact (the contact did not push in the previous step)."""

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


class _Columns:
    """Arrays of one schema group, `n` rows used. A full column grows in place (ndarray.resize:
    realloc, which for large arrays remaps pages instead of copying them) by as many rows as it
    has, at most BLOCK_ROWS at a time, and is cut to its n rows when the recording ends (fit):
    the memory stays ~ the rows recorded, with no copy and at most BLOCK_ROWS rows to spare. A row
    counts (commit) only once written: an interrupt never leaves a half-written row."""

    def __init__(self, schema: dict, sizes: dict, capacity: int):
        self.shapes = {k: tuple(sizes.get(d, d) for d in shape) for k, (_, shape) in schema.items()}
        self.cols = {k: np.empty((max(capacity, 1),) + self.shapes[k], dtype) for k, (dtype, _) in schema.items()}
        self.n = 0

    def free(self) -> int:
        """Index of the next row (growing the columns if full); call commit() once it is written."""
        i = self.n
        if i == len(next(iter(self.cols.values()))):
            self._resize(i + min(max(i, 64), BLOCK_ROWS))
        return i

    def commit(self) -> None:
        self.n += 1

    def _resize(self, rows: int) -> None:
        for k in self.cols:
            try:  # in place; refused (ValueError) while a view of the array is alive: then copied
                self.cols[k].resize((rows,) + self.cols[k].shape[1:])
            except ValueError:
                a = self.cols[k]
                b = np.empty((rows,) + a.shape[1:], a.dtype)
                b[:min(rows, self.n)] = a[:min(rows, self.n)]
                self.cols[k] = b

    def fit(self) -> None:
        """Release the rows not used (at the end of a recording)."""
        if len(next(iter(self.cols.values()))) > max(self.n, 1):
            self._resize(max(self.n, 1))

    def load(self, arrays: dict[str, np.ndarray]) -> None:
        """Start from rows recorded earlier (a checkpoint's arrays)."""
        n = len(arrays[next(iter(self.cols))])
        if n > len(next(iter(self.cols.values()))):
            self._resize(n)
        for k, a in self.cols.items():
            a[:n] = arrays[k]
        self.n = n

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: a[:self.n] for k, a in self.cols.items()}


class Recorder:
    """Samples (t, q, u, T, V, contact work and correction energy since the previous sample, pair
    gaps, closed contacts), percussion rows and corner branches of one run."""

    def __init__(self, model: Model, data: Data, n_samples: int = 1):
        self.model, self.data = model, data
        sizes = {"nq": model.nq, "nv": model.nv, "pairs": len(model.pairs)}
        self._samples = _Columns(trajectory.SAMPLES, sizes, n_samples)
        self._log = _Columns(trajectory.LOG, sizes, 64)
        self._branches = _Columns(trajectory.BRANCHES, sizes, 4)
        self._candidates = _Columns(trajectory.CANDIDATES, sizes, 8)

    @property
    def n(self) -> int:
        """Samples recorded so far."""
        return self._samples.n

    def sample(self, state: State, work: float, corr: float, n_contacts: int) -> None:
        m, d = self.model, self.data
        q, u = state.q, state.u
        i = self._samples.free()
        c = self._samples.cols
        c["t"][i] = state.t
        c["q"][i] = q
        c["u"][i] = u
        c["kinetic_energy"][i] = kinetic(m, d, q, u)
        c["potential_energy"][i] = potential(m, d, q)
        c["contact_work"][i] = work
        c["correction_energy"][i] = corr
        c["gap"][i] = pair_distances(m, d, q)
        c["n_contacts"][i] = n_contacts
        self._samples.commit()

    def finite(self) -> bool:
        """Whether the last sample's energies and gaps are finite (an overflow shows there first)."""
        i, c = self._samples.n - 1, self._samples.cols
        return bool(np.isfinite(c["kinetic_energy"][i]) and np.isfinite(c["potential_energy"][i])
                    and np.isfinite(c["gap"][i]).all())

    def log(self, row: PercussionRow) -> None:
        i = self._log.free()
        c = self._log.cols
        for name in PercussionRow.__slots__:
            c[f"log_{name}"][i] = getattr(row, name)
        self._log.commit()

    def log_percussions(self, step: int, t: float, contacts: Contacts, P: np.ndarray, gamma_minus: np.ndarray,
                        gamma_plus: np.ndarray, previous: set) -> set:
        """Log the percussions of a step above LOG_RELATIVE of its largest; a row is a new impact
        when its contact (pair, kind, feature) is not in `previous`. Returns this step's contacts."""
        if not contacts.m:
            return set()
        cut = LOG_RELATIVE * float(P.max())
        for i in np.flatnonzero((P > cut) & (P > 0)):
            key = (int(contacts.pair[i]), int(contacts.kind[i]), int(contacts.feature[i]))
            self.log(PercussionRow(step, t, *key, float(contacts.g[i]), float(P[i]), float(gamma_minus[i]),
                                   float(gamma_plus[i]), contacts.point_a[i], contacts.normal[i], key not in previous))
        return contacts.keys()

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

    def _groups(self) -> tuple[_Columns, ...]:
        return self._samples, self._log, self._branches, self._candidates

    def restore(self, arrays: dict[str, np.ndarray]) -> None:
        """Continue a recording from its arrays (a checkpoint's, checkpoint.py)."""
        for g in self._groups():
            g.load(arrays)

    def arrays(self) -> dict[str, np.ndarray]:
        out = {**self._samples.arrays(), **self._log.arrays(), **self._branches.arrays(), **self._candidates.arrays()}
        return {k: out[k] for k in trajectory.ARRAYS}

    def trajectory(self, meta: dict, *, final: bool = True) -> Trajectory:
        """The arrays so far (views) with `meta`; `final`: the recording ends, unused rows are released."""
        if final:
            for g in self._groups():
                g.fit()
        return Trajectory(self.arrays(), meta)
