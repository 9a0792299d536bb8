"""Errors a user can act on: each names the file and field, or the step and time; and
:func:`named_stops`, the one wrapping of a simulation loop's failures and interrupts."""

from __future__ import annotations

from contextlib import contextmanager


class MoreauSimError(Exception):
    """Base class of every error this package raises on purpose."""


class SceneError(MoreauSimError, ValueError):
    """A scene file, a URDF or an option is invalid. The message names the file and the field."""


class SimulationError(MoreauSimError, RuntimeError):
    """A run could not continue (QP failure, non-finite state). Names the step and the time.

    ``trajectory`` holds what was computed before the failure (marked incomplete)."""

    def __init__(self, message, *, step=None, t=None, trajectory=None):
        super().__init__(message)
        self.step = step
        self.t = t
        self.trajectory = trajectory


class SimulationInterrupted(SimulationError):
    """The run was interrupted (Ctrl-C, SIGTERM): ``trajectory`` holds the samples so far."""


def out_of_memory(exc: BaseException, where: str, doing: str, size: str) -> str | None:
    """The one line of a failed allocation (a MemoryError, or std::bad_alloc as a RuntimeError that is
    not one of ours) naming the scene `where` and its `size`; None for any other exception."""
    if isinstance(exc, MoreauSimError) or not (isinstance(exc, MemoryError) or "alloc" in str(exc)):
        return None
    return f"{where}: out of memory {doing} ({size})"


def one_line(message: object, n: int = 300) -> str:
    """A message (often a library's multi-line C++ text) on one line of at most n characters."""
    text = " ".join(str(message).split())
    return text if len(text) <= n else text[:n - 3] + "..."


def _described(exc: BaseException) -> str:
    """An exception as one short line, with its type unless it is one of ours."""
    return one_line(exc if isinstance(exc, MoreauSimError) else f"{type(exc).__name__}: {exc}")


@contextmanager
def named_stops(where, partial, *, unit: str = "step"):
    """Wrap a simulation loop (every integrator uses this one wrapping).

    where() -> (n, t [s]): the position of the loop (the step, or `unit` number n, and its time);
    partial(status) -> Trajectory: the samples so far with meta status `status`.
    Inside, a SimulationError without a step, and any other exception (a solver that raised),
    becomes a SimulationError "UNIT n (t = ... s): message"; Ctrl-C (KeyboardInterrupt, also
    SIGTERM through the CLI) a SimulationInterrupted. Each leaves with ``.trajectory`` the
    samples so far, marked ``failed: ...``."""
    try:
        yield
    except SimulationError as exc:
        if exc.step is None:
            n, t = where()
            err = type(exc)(f"{unit} {n} (t = {t:.6g} s): {exc}", step=n, t=t)
            err.trajectory = partial(f"failed: {err}")
            raise err from exc
        if exc.trajectory is None:
            exc.trajectory = partial(f"failed: {exc}")
        raise
    except KeyboardInterrupt:
        n, t = where()
        msg = f"interrupted at {unit} {n} (t = {t:.6g} s)"
        raise SimulationInterrupted(msg, step=n, t=t, trajectory=partial(f"failed: {msg}")) from None
    except Exception as exc:  # a solver that raised (corner QP, NNLS on NaN): a named stop, not a traceback
        n, t = where()
        err = SimulationError(f"{unit} {n} (t = {t:.6g} s): {_described(exc)}", step=n, t=t)
        err.trajectory = partial(f"failed: {err}")
        raise err from exc
