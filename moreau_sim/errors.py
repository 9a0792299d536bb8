"""Errors a user can act on: each names the file and field, or the step and time."""


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


def one_line(message: object, n: int = 300) -> str:
    """A message (often a library's multi-line C++ text) on one line of at most n characters."""
    text = " ".join(str(message).split())
    return text if len(text) <= n else text[:n - 3] + "..."
