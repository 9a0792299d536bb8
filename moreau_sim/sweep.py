"""Parameter sweeps: a grid of :class:`~moreau_sim.scene.Options` over one scene, one simulation
per point, one table of summary metrics (docs/sweeps.md).

    params = [parse_param("restitution=0:1:11"), parse_param("dt=1e-2,1e-3")]
    res = run_sweep("scenes/bouncing_ball.toml", params, "out/sweep")   # 22 runs
    res.table                     # out/sweep/sweep.csv: one row per point
    res.computed, res.skipped, res.failed

Output layout of ``out_dir``:
  sweep.csv        one row per point: id, the swept options, status, message, the figures of
                   :func:`moreau_sim.simulate.summary`, energy_lost [J], npz (path relative to out_dir)
  sweep.parquet    the same table, written only when pyarrow is importable
  runs/ID.npz      the trajectory of point ID that ran to its end (complete or flagged);
                   runs/ID.failed.npz the samples of a failed one

A point's id is a hash of the scene file text, its URDF files and the point's full effective
options, so the same simulation has the same id in any sweep. Resume: a point whose
runs/ID.npz ran to its end (meta status "complete", or "flagged": it broke an invariant,
docs/theory.md §10, and would again) is not recomputed; its row is taken from the existing
table, or rebuilt from the NPZ when the table lost it. Failed points are run again.
Runs execute in a local process pool or on a Dask cluster; the results come back to this
process, which alone writes the NPZ files (atomically, as each run finishes) and the table
(atomically, at most once a second and at the end, including on an interruption).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import csv
import dataclasses
import enum
import hashlib
import itertools
import json
import math
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

try:
    import fcntl
except ImportError:  # not POSIX: no lock
    fcntl = None

from .errors import MoreauSimError, SceneError, SimulationError, SimulationInterrupted
from .invariants import flagged, one_line
from .model import build_model
from .options import Options
from .scene import Scene, load_scene
from .simulate import simulate, summary
from .trajectory import Trajectory, atomic_write, load_trajectory

__all__ = ["Kind", "Param", "Status", "SWEEPABLE", "SweepError", "SweepResult", "TABLE", "WALL_COLUMNS",
           "grid", "parse_param", "point_id", "run_sweep"]

TABLE = "sweep.csv"
PARQUET = "sweep.parquet"
RUNS = "runs"
_FLUSH_INTERVAL = 1.0  # [s] minimum time between two rewrites of the table during a sweep


class SweepError(MoreauSimError, RuntimeError):
    """A sweep cannot run: Dask not installed or its scheduler unreachable, an unreadable table."""


class Kind(enum.Enum):
    """How a sweepable option's values are written on the command line."""

    FLOAT = "float"  # a number; ranges a:b:n allowed
    INT = "int"  # an integer
    VECTOR = "vector"  # [x,y,z]
    CHOICE = "choice"  # one of an enum's values


def _kind(default) -> tuple[Kind, type[enum.Enum] | None]:
    if isinstance(default, enum.Enum):
        return Kind.CHOICE, type(default)
    if isinstance(default, tuple):
        return Kind.VECTOR, None
    if isinstance(default, int) and not isinstance(default, bool):
        return Kind.INT, None
    return Kind.FLOAT, None


# Every field of Options (new ones included), with its kind, read from its default.
FIELDS: dict[str, tuple[Kind, type[enum.Enum] | None]] = {
    f.name: _kind(getattr(Options(), f.name)) for f in dataclasses.fields(Options)}
SWEEPABLE = tuple(FIELDS)  # the names a --param may take


class Status(enum.Enum):
    """Outcome of one point."""

    COMPLETE = "complete"
    FLAGGED = "flagged"  # ran to its end but broke an invariant (invariants.py): the violations in the message
    FAILED = "failed"  # SimulationError: message in the row, samples up to it in runs/ID.failed.npz


_FINISHED = {Status.COMPLETE.value, Status.FLAGGED.value}  # a point that ran to its end: not recomputed


WALL_COLUMNS = ("wall_seconds", "cpu_seconds", "us_per_step")  # differ between identical runs; all others do not
_TEXT_COLUMNS = {"id", "status", "message", "scene", "npz"}  # the other result columns are numbers


@dataclass(frozen=True)
class Param:
    """One swept option: its name (an Options field) and values (float, int, enum value string,
    or a gravity 3-tuple [m/s^2]; SI units as in Options). ``text`` is the --param as given."""

    name: str
    values: tuple
    text: str = ""


@dataclass(frozen=True)
class SweepResult:
    """What :func:`run_sweep` did. ``rows`` are the table rows of this grid's points, in grid
    order (the table file may hold rows of earlier sweeps too). computed + skipped + failed is
    the number of distinct points: skipped had run to their end already, failed raised
    SimulationError now, computed ran to their end now; flagged: how many of those computed
    broke an invariant (status flagged)."""

    out_dir: Path
    table: Path
    parquet: Path | None
    rows: tuple[dict, ...]
    computed: int
    skipped: int
    failed: int
    flagged: int = 0


# ---------------------------------------------------------------------------------------------
# --param parsing and the grid


def _split(spec: str) -> list[str]:
    """Split at commas outside [...] brackets."""
    parts, depth, cur = [], 0, ""
    for ch in spec:
        depth += (ch == "[") - (ch == "]")
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += ch
    parts.append(cur)
    return [p.strip() for p in parts]


def _float(s: str, where: str) -> float:
    try:
        x = float(s)
    except ValueError:
        raise SceneError(f"{where}: {s!r} is not a number") from None
    if not math.isfinite(x):
        raise SceneError(f"{where}: {s!r} is not finite")
    return x


def _value(name: str, s: str, where: str):
    kind, choices = FIELDS[name]
    if kind is Kind.FLOAT:
        return _float(s, where)
    if kind is Kind.INT:
        try:
            return int(s)
        except ValueError:
            raise SceneError(f"{where}: {s!r} is not an integer") from None
    if kind is Kind.VECTOR:
        inner = s[1:-1] if s.startswith("[") and s.endswith("]") else None
        parts = inner.split(",") if inner is not None else []
        if len(parts) != 3:
            raise SceneError(f"{where}: {s!r} is not a vector [x,y,z]")
        return tuple(_float(p.strip(), where) for p in parts)
    allowed = [m.value for m in choices]
    if s not in allowed:
        raise SceneError(f"{where}: {s!r} is not one of {allowed}")
    return s


def _range(spec: str, where: str) -> tuple[float, ...]:
    parts = spec.split(":")
    if len(parts) != 3:
        raise SceneError(f"{where}: a range is A:B:N (N points from A to B inclusive)")
    a, b = _float(parts[0], where), _float(parts[1], where)
    try:
        n = int(parts[2])
    except ValueError:
        raise SceneError(f"{where}: N = {parts[2]!r} must be an integer >= 1") from None
    if n < 1 or (n == 1 and a != b):
        raise SceneError(f"{where}: N = {n} points cannot span {a:g} to {b:g}" if n == 1 else
                         f"{where}: N = {n} must be >= 1")
    # a + (b - a) i / (n - 1): 0:1:11 gives 0.3, not linspace's 0.30000000000000004
    return tuple(a + (b - a) * i / (n - 1) for i in range(n - 1)) + (b,)


def _probe(name: str, value) -> None:
    """Validate one value on its own (cross-field checks are made per point against the scene)."""
    probe = {name: value}
    other = {"dt": "duration", "duration": "dt"}.get(name)
    if other and value > 0:  # duration/dt is judged per point, not against a default
        probe[other] = value
    Options().replace(**probe)


def parse_param(text: str, *, flag: str = "--param") -> Param:
    """Parse ``NAME=A:B:N`` (N points from A to B inclusive, equal spacing; real-valued options)
    or ``NAME=V1,V2,...`` (one value is a fixed override). NAME is an Options field; gravity
    values are written ``[x,y,z]``, enum options by value (``qp_form=primal,dual``).
    Raises :class:`SceneError` naming the --param: unknown option, bad or out-of-range value."""
    where = f"{flag} {text}"
    name, sep, spec = text.partition("=")
    name, spec = name.strip(), spec.strip()
    if not sep or not name or not spec:
        raise SceneError(f"{where}: expected NAME=A:B:N or NAME=V1,V2,...")
    if name not in FIELDS:
        raise SceneError(f"{where}: unknown option {name!r}; options: {', '.join(SWEEPABLE)}")
    if ":" in spec:
        if FIELDS[name][0] is not Kind.FLOAT:
            raise SceneError(f"{where}: a range A:B:N is only for real-valued options, not {name}")
        values = _range(spec, where)
    else:
        values = tuple(_value(name, s, where) for s in _split(spec))
    if len(set(values)) != len(values):
        raise SceneError(f"{where}: repeated values")
    for v in values:
        try:
            _probe(name, v)
        except SceneError as exc:
            raise SceneError(f"{where}: {str(exc).replace('options: ', '', 1)}") from None
    return Param(name, values, text)



def parse_settings(texts: Iterable[str], *, flag: str = "--set") -> dict[str, Any]:
    """``NAME=VALUE`` overrides, one value each (the command line's --set) -> {name: value}.
    Raises :class:`SceneError` naming the flag, as :func:`parse_param` does, or a grid given."""
    out = {}
    for text in texts:
        p = parse_param(text, flag=flag)
        if len(p.values) != 1:
            raise SceneError(f"{flag} {text}: one value, not {len(p.values)} (a grid is `moreau-sim sweep`)")
        out[p.name] = p.values[0]
    return out

def grid(params: Sequence[Param]) -> tuple[dict[str, Any], ...]:
    """The cartesian product of the params' values, the first param varying slowest.
    No params: one point (the scene as it is). Raises SceneError on a name given twice."""
    names = [p.name for p in params]
    for n in names:
        if names.count(n) > 1:
            raise SceneError(f"--param {n} given more than once")
    return tuple(dict(zip(names, combo)) for combo in itertools.product(*(p.values for p in params)))


def point_id(scene: Scene) -> str:
    """Deterministic id of a simulation: sha256 of the scene text, its URDF texts and its full
    options (16 hex digits)."""
    urdfs = [Path(b.urdf).read_text(encoding="utf-8") for b in scene.bodies]
    key = json.dumps([scene.source, urdfs, scene.options.to_dict()], sort_keys=True)
    return hashlib.sha256(key.encode()).hexdigest()[:16]


# ---------------------------------------------------------------------------------------------
# one point (runs in a worker process) and the row made of it


@dataclass(frozen=True)
class _Outcome:
    status: Status
    message: str | None
    trajectory: Trajectory | None


def _simulate_point(scene: Scene) -> _Outcome:
    """The task of a worker: build and simulate; a SimulationError is a result, not an error."""
    try:
        traj = simulate(build_model(scene), progress=False)
    except SimulationInterrupted:  # Ctrl-C or SIGTERM stops the sweep, not only this point
        raise KeyboardInterrupt from None
    except SimulationError as exc:
        return _Outcome(Status.FAILED, str(exc), exc.trajectory)
    if flagged(traj.meta):
        return _Outcome(Status.FLAGGED, one_line(traj.meta["invariants"]), traj)
    return _Outcome(Status.COMPLETE, None, traj)


def _param_cell(name: str, value):
    return json.dumps(list(value)) if FIELDS[name][0] is Kind.VECTOR else value


def _row(pid: str, point: dict, status: Status, message: str | None, traj: Trajectory | None,
         npz: str | None) -> dict:
    s = summary(traj) if traj is not None else {}
    s.pop("status", None)  # "failed: <message>": ours is split in two columns
    lost = s["energy_start"] - s["energy_end"] if s.get("energy_end") is not None else None
    return {"id": pid, **{k: _param_cell(k, v) for k, v in point.items()}, "status": status.value,
            "message": message, **s, "energy_lost": lost, "npz": npz}


# ---------------------------------------------------------------------------------------------
# the table: CSV (floats written with repr, so they read back bitwise), Parquet if pyarrow is there


def _cell(col: str, text: str):
    if text == "":
        return None
    if col in FIELDS:
        kind = FIELDS[col][0]
        return float(text) if kind is Kind.FLOAT else int(text) if kind is Kind.INT else text
    if col in _TEXT_COLUMNS:
        return text
    for number in (int, float):  # ints are written without '.', floats with repr: both read back exactly
        try:
            return number(text)
        except ValueError:
            pass
    return text


def _read_table(path: Path) -> dict[str, dict]:
    if not path.is_file():
        return {}
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            if reader.fieldnames is None or "id" not in reader.fieldnames:
                raise SweepError(f"{path}: not a sweep table (no 'id' column)")
            return {r["id"]: {c: _cell(c, v or "") for c, v in r.items()} for r in reader}
    except (OSError, UnicodeDecodeError, ValueError, csv.Error) as exc:
        raise SweepError(f"{path}: cannot read the sweep table: {exc}") from None


class _Table:
    """The rows of a sweep directory, keyed by id, rewritten atomically."""

    def __init__(self, out_dir: Path, params: Sequence[str], old: dict[str, dict], order: Sequence[str]):
        self.path, self.parquet = out_dir / TABLE, out_dir / PARQUET
        self.old, self.order = old, list(order)
        self.rows: dict[str, dict] = {}
        others = sorted({c for r in old.values() for c in r if c in FIELDS} - set(params))
        self.params = ["id", *params, *others]
        self.last_write = -math.inf

    @property
    def columns(self) -> list[str]:
        """id, swept options, then every other column of the rows (summary figures...) in order."""
        rows = itertools.chain(self.rows.values(), self.old.values())
        keys = dict.fromkeys(k for r in rows for k in r if k not in FIELDS and k != "id")
        rank = {"status": 0, "message": 1, "energy_lost": 3, "npz": 4}
        return [*self.params, *sorted(keys, key=lambda k: rank.get(k, 2))]

    def all_rows(self) -> list[dict]:
        ids = [i for i in self.order if i in self.rows] + [i for i in self.old if i not in self.order]
        columns = self.columns
        return [{c: (self.rows.get(i) or self.old[i]).get(c) for c in columns} for i in ids]

    def flush(self, force: bool = False) -> None:
        if not force and time.monotonic() - self.last_write < _FLUSH_INTERVAL:
            return
        rows, columns = self.all_rows(), self.columns

        def write_csv(tmp):
            with open(tmp, "w", newline="", encoding="utf-8") as fh:
                w = csv.DictWriter(fh, columns)
                w.writeheader()
                w.writerows({c: "" if v is None else v for c, v in r.items()} for r in rows)

        atomic_write(self.path, write_csv)
        if force and _pyarrow() is not None:
            pa, pq = _pyarrow()
            atomic_write(self.parquet, lambda tmp: pq.write_table(pa.Table.from_pylist(rows), tmp))
        self.last_write = time.monotonic()


def _pyarrow():
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return None
    return pa, pq


def _npz_finished(path: Path) -> str | None:
    """The status (complete or flagged) if `path` is a trajectory NPZ whose run ran to its end and
    whose arrays match the checksum written with them, else None (a damaged file is recomputed,
    never passed as finished)."""
    if not path.is_file():
        return None
    try:
        status = load_trajectory(path, verify=True).meta.get("status")
    except ValueError:  # unreadable, truncated, damaged, not ours: recompute
        return None
    return status if status in _FINISHED else None


# ---------------------------------------------------------------------------------------------
# executors: each yields (index, _Outcome) as runs finish


def _serial(tasks: list[tuple[int, Scene]]) -> Iterator[tuple[int, _Outcome]]:
    for i, sc in tasks:
        yield i, _simulate_point(sc)


def _pool(tasks: list[tuple[int, Scene]], workers: int) -> Iterator[tuple[int, _Outcome]]:
    # forkserver (spawn where absent): no fork of a process that may run threads (tqdm, Dask)
    method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
    ex = cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context(method), initializer=_die_with_parent,
                                initargs=(os.getpid(),))
    done = False
    try:
        futs = {ex.submit(_simulate_point, sc): i for i, sc in tasks}
        for f in cf.as_completed(futs):
            yield futs[f], f.result()
        done = True
    finally:
        if done:
            ex.shutdown(wait=True)
        else:  # a stop (Ctrl-C, SIGTERM, an error): end the workers now, not after their points (docs/sweeps.md)
            procs = list((getattr(ex, "_processes", None) or {}).values())  # Python 3.14: ex.terminate_workers()
            for proc in procs:
                proc.terminate()
            for proc in procs:
                proc.join(5)
            ex.shutdown(wait=True, cancel_futures=True)  # the pool sees its workers gone and frees its queues


def _die_with_parent(parent: int) -> None:
    """Worker initializer: exit as soon as the sweeping process is gone (killed), instead of
    finishing its point for nobody. SIGTERM ends it at once and Ctrl-C is left to the sweeping
    process, which ends its workers (docs/sweeps.md)."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch():
        while True:
            time.sleep(0.5)
            try:
                os.kill(parent, 0)
                with open(f"/proc/{parent}/stat", "rb") as fh:  # a killed parent not yet reaped is a zombie
                    if fh.read().rsplit(b")", 1)[-1].split()[0] == b"Z":
                        os._exit(1)
            except ProcessLookupError:
                os._exit(1)
            except OSError:
                pass

    threading.Thread(target=watch, daemon=True, name="moreau-sim parent watch").start()


def _import_distributed():
    try:
        import distributed
    except ImportError:
        raise SweepError("--dask needs the optional dependency dask[distributed]: "
                         "pip install 'moreau-sim[sweep]'") from None
    return distributed


def _dask(tasks: list[tuple[int, Scene]], address: str) -> Iterator[tuple[int, _Outcome]]:
    distributed = _import_distributed()
    try:
        client = distributed.Client(address, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise SweepError(f"--dask {address}: cannot connect to the Dask scheduler: {exc}") from None
    futs = {}
    try:
        futs = {client.submit(_simulate_point, sc, pure=False): i for i, sc in tasks}
        for f in distributed.as_completed(list(futs), loop=client.loop):
            yield futs[f], f.result()
    finally:
        if pending := [f for f in futs if not f.done()]:
            client.cancel(pending)
        client.close()


@contextlib.contextmanager
def locked(out_dir: Path):
    """Hold out_dir/.sweep.lock: two sweeps writing one directory would overwrite each other's table."""
    with open(out_dir / ".sweep.lock", "w") as fh:
        if fcntl is not None:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                raise SweepError(f"{out_dir}: another sweep is writing this directory") from None
        yield


def _workers(workers: int | None) -> int:
    if workers is None:
        return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if workers < 1:
        raise SceneError(f"--workers {workers}: must be >= 1")
    return workers


# ---------------------------------------------------------------------------------------------


def _point_scene(scene: Scene, point: dict) -> Scene:
    try:
        return scene.with_options(**point)
    except SceneError as exc:
        desc = " ".join(f"{k}={_param_cell(k, v)}" for k, v in point.items())
        raise SceneError(f"--param point {desc}: {str(exc).replace('options: ', '', 1)}") from None


def _resume(table: _Table, out_dir: Path, ids, points, scenes) -> list[tuple[int, Scene]]:
    """Fill `table` with the rows of points that ran to their end in out_dir (complete or flagged);
    return the others (index, scene)."""
    todo, seen = [], set()
    for i, (pid, point, sc) in enumerate(zip(ids, points, scenes)):
        if pid in seen:  # the same simulation twice in one grid
            continue
        seen.add(pid)
        npz = out_dir / RUNS / f"{pid}.npz"
        status = _npz_finished(npz)
        if status is None:
            todo.append((i, sc))
            continue
        old = table.old.get(pid)
        if old is not None and old.get("status") == status:
            table.rows[pid] = {**old, **{k: _param_cell(k, v) for k, v in point.items()}}
        else:  # finished, but its row was never written: rebuild it from the file
            traj = load_trajectory(npz)
            message = one_line(traj.meta.get("invariants", [])) if status == Status.FLAGGED.value else None
            table.rows[pid] = _row(pid, point, Status(status), message, traj, f"{RUNS}/{npz.name}")
    return todo


def run_sweep(scene_path: str | Path, params: Iterable[Param], out_dir: str | Path, *,
              workers: int | None = None, dask_address: str | None = None,
              progress: bool = True) -> SweepResult:
    """Simulate every point of ``grid(params)`` on the scene file and write ``out_dir``
    (module docstring). Points that ran to their end there (complete or flagged) are skipped (resume).

    workers: local processes (default: the usable cores; 1 runs in this process).
    dask_address: run on an existing Dask distributed scheduler instead (e.g. "tcp://host:8786");
        its workers must import moreau_sim and read the scene and URDF files at the same paths.
    progress: a tqdm bar over the points.
    Raises SceneError (bad scene, or a point whose options are invalid together, naming it) or
    SweepError; a point that fails with SimulationError is recorded as ``failed``, one that ran to
    its end but broke an invariant as ``flagged`` (its violations in the message). On an
    interruption (KeyboardInterrupt) the table is written before the exception propagates.
    """
    params = list(params)
    scene = load_scene(scene_path)
    points = grid(params)
    scenes = [_point_scene(scene, p) for p in points]
    if dask_address is not None:
        _import_distributed()
    n_workers = _workers(workers)
    ids = [point_id(sc) for sc in scenes]
    out_dir = Path(out_dir)
    (out_dir / RUNS).mkdir(parents=True, exist_ok=True)
    computed = failed = n_flagged = 0
    with locked(out_dir):
        table = _Table(out_dir, [p.name for p in params], _read_table(out_dir / TABLE), ids)
        todo = _resume(table, out_dir, ids, points, scenes)
        skipped = len(table.rows)
        if dask_address is not None:
            results = _dask(todo, dask_address)
        elif min(n_workers, len(todo)) <= 1:
            results = _serial(todo)
        else:
            results = _pool(todo, min(n_workers, len(todo)))
        bar = tqdm(total=skipped + len(todo), initial=skipped, disable=not progress, unit="run", desc=scene.name,
                   dynamic_ncols=True)
        try:
            for i, out in results:  # as they finish: save the NPZ at once, then the row
                pid = ids[i]
                if out.status is not Status.FAILED:
                    npz = out.trajectory.save(out_dir / RUNS / f"{pid}.npz")
                    computed += 1
                    n_flagged += out.status is Status.FLAGGED
                else:
                    npz = out.trajectory.save(out_dir / RUNS / f"{pid}.failed.npz") if out.trajectory else None
                    failed += 1
                    bar.set_postfix(failed=failed)
                table.rows[pid] = _row(pid, points[i], out.status, out.message, out.trajectory,
                                       f"{RUNS}/{npz.name}" if npz else None)
                table.flush()
                bar.update(1)
        finally:
            bar.close()
            results.close()
            table.flush(force=True)
    rows = {r["id"]: r for r in table.all_rows()}
    return SweepResult(out_dir=out_dir, table=table.path, parquet=table.parquet if _pyarrow() else None,
                       rows=tuple(rows[pid] for pid in dict.fromkeys(ids)), computed=computed,
                       skipped=skipped, failed=failed, flagged=n_flagged)
