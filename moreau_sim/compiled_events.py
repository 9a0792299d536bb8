"""The adaptive integrator's extrapolated step between events at compiled speed (src/events.hpp): the
midpoint steps and their extrapolation (docs/theory.md §8) without a persistent set, operation by operation as
adaptive.AdaptiveRun._step computes them (docs/theory.md §2.8), so that a run gives the Python run's arrays bit
for bit. The event location, the decisions at events and the constrained phases stay in Python."""

from __future__ import annotations

from collections.abc import Callable

from . import compiled
from .results import MIDPOINT_ITERATIONS


def unsupported(model) -> str | None:
    """Why the compiled extrapolated step does not take this model's free-flight steps (None: it does)."""
    why = compiled.loop_refusal(model, "Extrapolator", "the extrapolated step")
    if why is not None:
        return why
    if model.nv == 0:
        return "no degrees of freedom"
    return None


def extrapolator(model, *, seq: tuple[int, ...], ratios: tuple[tuple[float, ...], ...], lie: bool, rtol: float,
                 atol: float, fixed_point: float) -> Callable | None:
    """The compiled AdaptiveRun._step without a persistent set, (q0, u0, H [s]) -> (q1, u1, error estimate), or
    None where it does not apply (unsupported). seq, ratios: the extrapolation's (AdaptiveRun.seq, .ratios);
    lie: a joint with nq != nv; rtol, atol, fixed_point: the midpoint's fixed-point tolerance (AdaptiveRun)."""
    if unsupported(model) is not None:
        return None
    ex = compiled._module.Extrapolator(model.pin, list(seq), [list(r) for r in ratios], bool(lie),
                                       bool(model.velocity_bias), float(rtol), float(atol), float(fixed_point),
                                       int(MIDPOINT_ITERATIONS))
    return ex.step
