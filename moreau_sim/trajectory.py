"""Recorded arrays + metadata, and the self-describing NPZ file format (docs/output.md).
The schema below is the one list of arrays; recording.Recorder fills it for every integrator.

Arrays (n = saved samples, k = logged contact percussions):
  t (n,) [s]; q (n, nq); u (n, nv); kinetic_energy, potential_energy (n,) [J];
  contact_work (n,) [J]: sum of the step ledger W_c over the steps since the previous sample;
  correction_energy (n,) [J]: the change of T + V made by the position correction over those steps;
  gap (n, gaps) [m]: signed distance of each collision pair at the sample; in a scene of more than model.GAP_PAIRS
  pairs (Model.gaps_per_geometry: meta model "gap_columns" = "geometries") one column per geometry, its
  nearest partner's distance, +inf where none is within meta model "gap_reach" [m] (contacts.geometry_gaps);
  n_contacts (n,): closed contacts in the step that produced the sample;
  the energy ledger (docs/theory.md §5, ledger.py), summed over the steps since the previous sample:
  smooth_error (n,) [J]: the change of T + V of the contact-free part of each step,
  dissipation (n,) [J]: T- - T+ of the impacts (the law's frame: u- = v_free at q_m),
  law_dissipation (n,) [J]: the law's prediction of it, (1 - e^2)/2 |v_free - v|_M^2 - P.b;
  actuator_work, obstacle_work (n,) [J] (only in runs with joint torques or moving statics): the work of
  the torques, h tau.(u_k + u_{k+1})/2, and of the statics' prescribed motion, -P.dg/dt (§5.5);
  impacts (steps with a new impact), i of them: impact_step, impact_t [s] (step midpoint),
  impact_contacts (pushing contacts), impact_T_minus, impact_T_plus, impact_dissipation, impact_law [J];
  log_step, log_t [s] (step midpoint time), log_pair, log_kind (contacts.FeatureKind value),
  log_feature (index within the kind), log_gap [m], log_P [N s],
  log_gamma_minus, log_gamma_plus [m/s], log_point (k, 3) [m], log_normal (k, 3),
  log_impact (bool: the contact did not push in the previous step, i.e. a new impact),
  log_steps, log_duration [s] (the fixed steps the row covers and the time they span: one step and its h,
  or a stretch of persistent steps whose log_P it sums; an impact at a located instant: 1 and 0);
  branching steps (a corner impact with several admissible outcomes, docs/theory.md §3), b of them:
  branch_step, branch_t [s] (step midpoint), branch_chosen (index among the step's candidates),
  branch_start, branch_count (its candidates' rows in candidate_*); candidate_u_plus (c, nv),
  candidate_distance (c,) [J] (1/2 |v - v_free|_M^2), candidate_global_min (c,) bool.
  meta: one JSON string: scene (name, path, TOML source, URDF texts), options, model summary,
  package versions, status (protocol.RunStatus: "complete"; "flagged" when the run ran to its end
  but broke an invariant, listed in "invariants", docs/theory.md §10; or "failed: ..." and the
  reason), run statistics, and "ledger": the per-run figures no array holds (largest energy rise
  of any step, largest law difference).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import mmap
import os
import tempfile
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from moreau_sim import interrupts

# 5: a gap per geometry above model.GAP_PAIRS pairs; 4: log_steps; 3: the ledger arrays; 2: log_kind + log_feature
# (1: one feature id)
FORMAT = "moreau-sim trajectory 5"

# name -> (dtype, trailing shape); "nq", "nv", "gaps" are the model's sizes (gaps: len(Model.gap_names))
SAMPLES = {"t": (float, ()), "q": (float, ("nq",)), "u": (float, ("nv",)), "kinetic_energy": (float, ()),
           "potential_energy": (float, ()), "contact_work": (float, ()), "correction_energy": (float, ()),
           "gap": (float, ("gaps",)), "n_contacts": (np.int64, ()), "smooth_error": (float, ()),
           "dissipation": (float, ()), "law_dissipation": (float, ())}
LOG = {"log_step": (np.int64, ()), "log_t": (float, ()), "log_pair": (np.int64, ()), "log_kind": (np.int64, ()),
       "log_feature": (np.int64, ()), "log_gap": (float, ()), "log_P": (float, ()), "log_gamma_minus": (float, ()),
       "log_gamma_plus": (float, ()), "log_point": (float, (3,)), "log_normal": (float, (3,)), "log_impact": (bool, ()),
       "log_steps": (np.int64, ()), "log_duration": (float, ())}
BRANCHES = {"branch_step": (np.int64, ()), "branch_t": (float, ()), "branch_chosen": (np.int64, ()),
            "branch_start": (np.int64, ()), "branch_count": (np.int64, ())}
CANDIDATES = {"candidate_u_plus": (float, ("nv",)), "candidate_distance": (float, ()),
              "candidate_global_min": (bool, ())}
IMPACTS = {"impact_step": (np.int64, ()), "impact_t": (float, ()), "impact_contacts": (np.int64, ()),
           "impact_T_minus": (float, ()), "impact_T_plus": (float, ()), "impact_dissipation": (float, ()),
           "impact_law": (float, ())}
# per sample, only in runs with joint torques or moving statics (absent elsewhere: those files are unchanged):
# the work of the actuators and of the statics' prescribed motion over the steps since the previous sample [J]
EXTERNAL = {"actuator_work": (float, ()), "obstacle_work": (float, ())}
ARRAYS = tuple(SAMPLES) + tuple(LOG) + tuple(BRANCHES) + tuple(CANDIDATES) + tuple(IMPACTS)
LEDGER_ARRAYS = ("smooth_error", "dissipation", "law_dissipation") + tuple(IMPACTS)  # absent before format 3
_FORMAT1_OFFSETS = ((30_000, 4), (20_000, 3), (10_000, 2))  # format 1 feature ids: SWEPT, CORNER, PATCH


def _from_format1(arrays: dict) -> None:
    """Split a format-1 log_feature (WITNESS = -1, PATCH + k, CORNER + f, SWEPT) into log_kind and
    log_feature (FeatureKind values, as contacts.FeatureKind)."""
    f = arrays["log_feature"].astype(np.int64)
    kind = np.zeros_like(f)
    feature = f.copy()
    kind[f == -1], feature[f == -1] = 1, 0
    for offset, k in _FORMAT1_OFFSETS:
        sel = (f >= offset) & (kind == 0)
        kind[sel], feature[sel] = k, f[sel] - offset
    arrays["log_kind"], arrays["log_feature"] = kind, feature


def log_before_format_4(k: int) -> dict[str, np.ndarray]:
    """The log columns a file or checkpoint of format 3 or earlier lacks, for its k rows: each row was one step's
    (log_steps 1), of a length it did not record (log_duration NaN)."""
    return {"log_steps": np.ones(k, np.int64), "log_duration": np.full(k, np.nan)}


def _without_ledger(arrays: dict) -> None:
    """A file of format 1 or 2 has no ledger: its per-sample terms read as NaN (not measured) and it
    has no impact rows; ledger.ledger() says so instead of reporting zeros."""
    n = len(arrays["t"])
    for k in LEDGER_ARRAYS:
        if k not in arrays:
            dtype = SAMPLES[k][0] if k in SAMPLES else IMPACTS[k][0]
            arrays[k] = np.full(n, np.nan) if k in SAMPLES else np.zeros(0, dtype)


@dataclass(eq=False)
class Trajectory:
    """A simulation's record. ``arrays`` holds the names of ARRAYS; ``meta`` a JSON-able dict."""

    arrays: dict[str, np.ndarray]
    meta: dict = field(default_factory=dict)

    def __getattr__(self, name):
        arrays = self.__dict__.get("arrays", {})
        if name in arrays:
            return arrays[name]
        raise AttributeError(name)

    def __dir__(self):  # every array is an attribute (traj.gap, traj.log_P, ...): list them too
        return sorted(set(super().__dir__()) | set(self.__dict__.get("arrays", {})))

    @property
    def t(self) -> np.ndarray:
        """(n,) sample times [s]."""
        return self.arrays["t"]

    @property
    def q(self) -> np.ndarray:
        """(n, nq) generalized coordinates at the samples (Model.coordinate_names gives their order)."""
        return self.arrays["q"]

    @property
    def u(self) -> np.ndarray:
        """(n, nv) generalized velocities at the samples."""
        return self.arrays["u"]

    def __repr__(self) -> str:
        a, m = self.arrays, self.meta
        t = a.get("t", np.zeros(0))
        span = f"t = {t[0]:g} .. {t[-1]:g} s" if len(t) else "no samples"
        return (f"Trajectory({m.get('scene', {}).get('name', '?')!r}, {m.get('status', '?')}, {len(t)} samples, "
                f"{span}, nq = {a['q'].shape[1] if 'q' in a else '?'}, "
                f"{len(a.get('log_P', ()))} percussions logged)")

    @property
    def complete(self) -> bool:
        return self.meta.get("status") == "complete"

    @property
    def total_energy(self) -> np.ndarray:
        return self.arrays["kinetic_energy"] + self.arrays["potential_energy"]

    @property
    def impacts(self) -> int:
        """Number of new impacts (a contact starting to push)."""
        return int(np.count_nonzero(self.arrays["log_impact"]))

    def save(self, path: str | Path) -> Path:
        """Write an NPZ atomically (a temporary file renamed into place: never half-written)."""
        path = Path(path)

        def write(tmp: Path) -> None:
            with tmp.open("wb") as fh:
                meta = {**self.meta, "checksum": checksum(self.arrays)}  # lets a reader detect damaged data
                _write_npz(fh, {"meta": np.array(json.dumps(meta)), **self.arrays})

        _remove_orphans(path)
        return atomic_write(path, write)


class Summary(dict):
    """The figures of a run (simulate.summary): a dict (its keys as before, JSON-able) that prints
    as a few readable lines."""

    def __str__(self) -> str:
        def g(key, fmt=".6g", unit=""):
            v = self.get(key)
            return "n/a" if v is None else f"{v:{fmt}}{unit}"

        count = (f"{self['events']} events" if self.get("steps") is None
                 else f"{self['steps']} steps" + (f", {self['events']} events" if self.get("events") else ""))
        lines = [f"{self.get('scene')}: {self.get('status')}, {self.get('integrator')}, {count}, "
                 f"{self.get('samples')} samples to t = {g('t_end', 'g', ' s')}",
                 f"  impacts {self.get('impacts')}, percussions logged {self.get('percussions_logged')}, "
                 f"corner impacts with several outcomes {self.get('branching_steps')}",
                 f"  energy {g('energy_start', unit=' J')} -> {g('energy_end', unit=' J')} (contact work "
                 f"{g('contact_work_total', unit=' J')}, max rise {g('energy_max_increase', '.3g', ' J')})",
                 f"  min gap {g('min_gap', '.3g', ' m')}, wall time {g('wall_seconds', '.3f', ' s')}, "
                 f"CPU {g('cpu_seconds', '.3f', ' s')}"]
        return "\n".join(lines + [f"  {k} = {v:.6g}" if isinstance(v, float) else f"  {k} = {v}"
                                  for k, v in self.items() if k not in _SHOWN and v is not None])


_SHOWN = {"scene", "status", "integrator", "steps", "events", "samples", "t_end", "impacts", "percussions_logged",
          "branching_steps", "energy_start", "energy_end", "contact_work_total", "energy_max_increase", "min_gap",
          "wall_seconds", "cpu_seconds"}


def atomic_write(path: str | Path, write) -> Path:
    """Write `path` atomically: write(tmp) fills a temporary file beside it (NAME.PID.XXXX.tmp, which
    _remove_orphans recognises once its writer is gone), renamed into place with the usual file mode;
    removed when writing fails. Ctrl-C and SIGTERM wait until the file is in place (interrupts.held). Every file
    the package writes goes through here."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with interrupts.held():
        fd, tmp = tempfile.mkstemp(prefix=f"{path.name}.{os.getpid()}.", suffix=".tmp", dir=path.parent)
        try:
            os.close(fd)
            write(Path(tmp))
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file the usual mode
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    return path


_PIECE = 1 << 20  # [bytes] written (and compressed) at a time by _write_npz


def _write_npz(fh, arrays: dict[str, np.ndarray]) -> None:
    """The layout of np.savez_compressed (NAME.npy per array, ZIP_DEFLATED), written from each
    array's buffer in _PIECE bytes: savez copies 16 MiB twice per piece, which shows on the peak
    memory of a long run's save."""
    with zipfile.ZipFile(fh, mode="w", compression=zipfile.ZIP_DEFLATED, allowZip64=True) as zf:
        for name, a in arrays.items():
            a = a if a.flags.c_contiguous else np.ascontiguousarray(a)  # (ascontiguousarray makes 0-d 1-d)
            with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array_header_1_0(f, np.lib.format.header_data_from_array_1_0(a))
                for piece in _pieces(a):
                    f.write(piece)


def _pieces(a: np.ndarray):
    """The bytes of a C-contiguous array in _PIECE-byte memoryviews, without a copy. Pages of a
    read-only file map under `a` (a spilling recording's arrays, columns.Columns) are handed
    back once read, so streaming such an array through costs no memory."""
    data = memoryview(a.reshape(-1).view(np.uint8))
    mm = _read_only_map(a)
    start = 0
    if mm is not None:
        start = a.__array_interface__["data"][0] - np.frombuffer(mm, np.uint8).__array_interface__["data"][0]
    for i in range(0, len(data), _PIECE):
        yield data[i:i + _PIECE]
        if mm is not None and hasattr(mmap, "MADV_DONTNEED"):  # page-aligned from below; the kernel rounds up
            lo = (start + i) // mmap.PAGESIZE * mmap.PAGESIZE
            mm.madvise(mmap.MADV_DONTNEED, lo, start + i + _PIECE - lo)


def _read_only_map(a: np.ndarray) -> mmap.mmap | None:
    """The mmap under `a` when `a` reads a shared read-only file map (np.frombuffer of an
    ACCESS_READ mmap), else None. MADV_DONTNEED on such a map only drops pages that the file
    holds: on any other memory it would lose data."""
    b = a
    while isinstance(b, np.ndarray):
        b = b.base
    if isinstance(b, memoryview) and b.readonly and isinstance(b.obj, mmap.mmap):
        return b.obj
    return None


def _remove_orphans(path: Path) -> None:
    """Delete temporary files of earlier saves to `path` whose writer process is gone (killed
    during its save): NAME.PID.XXXX.tmp."""
    for tmp in path.parent.glob(f"{path.name}.*.tmp"):
        pid = tmp.name[len(path.name) + 1:].split(".", 1)[0]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            tmp.unlink(missing_ok=True)
        except OSError:  # alive but another user's: leave it
            pass


def checksum(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 of the arrays (names, dtypes, shapes and bytes, in schema order)."""
    h = hashlib.sha256()
    for k in ARRAYS + tuple(EXTERNAL):
        if k in arrays:
            a = np.ascontiguousarray(arrays[k])
            h.update(f"{k}|{a.dtype.str}|{a.shape}|".encode())
            for piece in _pieces(a):  # the bytes of tobytes(), without a copy
                h.update(piece)
    return h.hexdigest()


def load_trajectory(path: str | Path, *, verify: bool = True) -> Trajectory:
    """Read an NPZ written by :meth:`Trajectory.save`. Raises ValueError naming the file, also
    when `verify` and its arrays do not match the checksum recorded at save (damaged data)."""
    path = Path(path)
    with read_npz(path) as z:
        old = "log_kind" not in z.files
        optional = LEDGER_ARRAYS + ("log_steps", "log_duration") + (("log_kind",) if old else ())
        missing = [k for k in ARRAYS + ("meta",) if k not in z.files and k not in optional]
        if missing:
            raise ValueError(f"{path}: not a moreau-sim trajectory (missing {missing})")
        meta = json.loads(str(z["meta"]))
        arrays = {k: z[k] for k in ARRAYS + tuple(EXTERNAL) if k in z.files}
        if verify:
            verify_checksum(path, meta, arrays)
        if old:
            _from_format1(arrays)
        _without_ledger(arrays)
        if "log_steps" not in arrays:
            arrays.update(log_before_format_4(len(arrays["log_P"])))
    return Trajectory(arrays, meta)


def verify_checksum(path: Path, meta: dict, arrays) -> None:
    """ValueError naming `path` when `arrays` (a dict, or an open NPZ) do not match the checksum
    in `meta` (damaged data; a file without one passes)."""
    if "checksum" in meta and checksum(arrays) != meta["checksum"]:
        raise ValueError(f"{path}: damaged: its arrays do not match the checksum written with them")


@contextlib.contextmanager
def read_npz(path: Path):
    """A trajectory NPZ open (np.load: each array read when asked for, so one at a time can be in
    memory); any error reading it, also inside the with block, a ValueError naming the file."""
    try:
        with np.load(path, allow_pickle=False) as z:
            yield z
    except ValueError as exc:
        if str(path) in str(exc):
            raise
        why = "not a NumPy .npz archive" if "pickle" in str(exc) else str(exc)  # np.load's allow_pickle advice
        raise ValueError(f"{path}: not a moreau-sim trajectory NPZ ({why})") from None
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error, KeyError) as exc:  # truncated or corrupted
        raise ValueError(f"{path}: cannot read trajectory: {type(exc).__name__}: {exc}") from None
