"""The compiled contact step (moreau_sim._step, src/step.cpp) and its guard.

The extension borrows the pin.Model / pin.Data / GeometryModel / GeometryData built in Python (through
boost.python's registry) and calls the same libpinocchio and libcoal as the Python bindings, so it
must have been built against exactly the versions loaded: Pinocchio promises no ABI stability and its
SONAME is unversioned, so a mismatch would load silently and misbehave. Hence pinocchio and coal are
imported first and their versions compared with the ones the build recorded (_step_version.py); on a
mismatch or any import error the Python step is used, with one warning, never a crash.

The compiled step mirrors stepper.step (the reference) for the contacts of the simple scenes
(src/step.cpp, top comment); a step it does not cover returns a reason and stepper.step takes it in
Python. `counts(data)` tells how many steps of a run went which way.
"""

from __future__ import annotations

import ctypes
import warnings
from collections import Counter

import coal
import numpy as np
import pinocchio

from .contacts import NO_CONTACTS, Contacts
from .options import PositionCorrection, QPForm, Tunnelling, Bias, Separating, SlowImpacts
from .qp import QPResult
from .state import State

MAX_CONTACTS = 12  # closed contacts a compiled step takes (numpy's sums are mirrored up to this size)
MAX_NV = 12  # likewise for the number of velocities
_EMPTY = np.zeros(0)
_TUNNELLING = {Tunnelling.SWEPT: 0, Tunnelling.NONE: 1, Tunnelling.ALWAYS: 2}

_module = None
_reason: str | None = None
_loaded = False


def _load() -> None:
    global _module, _reason, _loaded
    _loaded = True
    try:
        from . import _step_version as built
        if (built.pinocchio, built.coal) != (pinocchio.__version__, coal.__version__):
            _reason = (f"it was built against pinocchio {built.pinocchio} / coal {built.coal}, but pinocchio "
                       f"{pinocchio.__version__} / coal {coal.__version__} are installed (reinstall moreau-sim)")
        else:
            from . import _step
            _module = _step
    except Exception as exc:  # no compiler at install time, a broken build, a missing library
        _reason = f"it does not load ({type(exc).__name__}: {exc})"
    if _reason is not None:
        warnings.warn(f"moreau_sim: the compiled step is unavailable: {_reason}; the Python step is used",
                      RuntimeWarning, stacklevel=3)


def available() -> bool:
    """Whether the compiled step loaded (warns once, at the first call, when it did not)."""
    if not _loaded:
        _load()
    return _module is not None


def unavailable_reason() -> str | None:
    available()
    return _reason


def _dgesv_pointer() -> int:
    """The address of the LAPACK dgesv that qp._polish calls through scipy (the same routine, so the
    same LU and the same answer)."""
    import scipy.linalg.cython_lapack as cl
    cap = cl.__pyx_capi__["dgesv"]
    api = ctypes.pythonapi
    api.PyCapsule_GetName.restype = ctypes.c_char_p
    api.PyCapsule_GetName.argtypes = [ctypes.py_object]
    api.PyCapsule_GetPointer.restype = ctypes.c_void_p
    api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    return int(api.PyCapsule_GetPointer(cap, api.PyCapsule_GetName(cap)))


def _analytic(a, b) -> bool:
    """Whether coal resolves this pair of shapes in closed form. Other pairs go through GJK/EPA, whose
    support search is warm-started from the pair's previous call (state kept in the collision functor):
    a step handed back to Python would run it a second time at the same configuration and can get a
    different contact at the EPA tolerance than the Python-only run."""
    half = (coal.Halfspace, coal.Plane)
    for x, y in ((a, b), (b, a)):
        if isinstance(y, half) and isinstance(x, (coal.Sphere, coal.Box, coal.Capsule, coal.Cylinder, coal.Cone)):
            return True
    return isinstance(a, coal.Sphere) and isinstance(b, (coal.Sphere, coal.Capsule, coal.Box))


def unsupported(model) -> str | None:
    """Why the compiled step never takes this model's steps (None: it takes the ones it covers)."""
    o = model.options
    if model.nv > MAX_NV:
        return f"more than {MAX_NV} velocities"
    geoms = model.geom.geometryObjects
    if not all(_analytic(geoms[p.first].geometry, geoms[p.second].geometry) for p in model.pairs):
        return "a pair coal resolves by GJK/EPA (warm-started from its previous call)"
    if model.polytope_pairs:
        return "pairs of two polytopes (their detection keeps a warm start)"
    if o.tunnelling is Tunnelling.ALWAYS:
        return "swept detection on every step"
    if o.qp_form is not QPForm.PRIMAL:
        return "qp_form dual"
    return None


class _Context:
    """The compiled stepper of one (model, data) and the count of steps by the way they went."""

    __slots__ = ("model", "stepper", "counts", "why")

    def __init__(self, model, data):
        self.model = model
        self.counts: Counter = Counter()
        self.why = unsupported(model)
        self.stepper = None
        if self.why is None:
            o = model.options
            kinds = [0 if b[0] == "plane" else 1 for b in model.bounds]
            pairs = np.array([(p.first, p.second, p.joint_first, p.joint_second, int(p.patch)) for p in model.pairs],
                             dtype=np.int64).reshape(-1, 5)
            self.stepper = _module.Stepper(
                model.pin, data.pin, model.geom, data.geom,
                [np.asarray(V, float).reshape(-1, 3) for V in model.vertices], kinds,
                [np.asarray(b[1], float) for b in model.bounds], [float(b[2]) for b in model.bounds], pairs,
                np.asarray(model.support_mask, float), float(model.reach), float(model.thinnest_pair),
                float(o.contact_tolerance), _TUNNELLING[o.tunnelling], o.separating is Separating.ELASTIC,
                o.slow_impacts is SlowImpacts.PLASTIC, o.bias is Bias.MIDPOINT, bool(model.velocity_bias),
                o.position_correction is PositionCorrection.PROJECTION, MAX_CONTACTS, _dgesv_pointer())


def _context(model, data) -> _Context:
    ctx = getattr(data, "_compiled_step", None)
    if ctx is None or ctx.model is not model:
        ctx = _Context(model, data)
        data._compiled_step = ctx
    return ctx


def counts(data) -> Counter:
    """Steps of this data's runs by the way they went: "flight" and "contact" (compiled), "python: <reason>"."""
    ctx = getattr(data, "_compiled_step", None)
    return Counter() if ctx is None else ctx.counts


def step(model, data, state: State, h: float, e: float, t1: float):
    """stepper.step in C++, or None where the Python step must take it (counted in counts(data))."""
    from .stepper import StepResult
    ctx = _context(model, data)
    if ctx.stepper is None:
        ctx.counts[f"python: {ctx.why}"] += 1
        return None
    r = ctx.stepper.step(state.q, state.u, h, e)
    if r[0] == _module.FALLBACK:
        ctx.counts[f"python: {r[1]}"] += 1
        return None
    if r[0] == _module.FLIGHT:
        ctx.counts["flight"] += 1
        return StepResult(State(t1, r[1], r[2]), NO_CONTACTS, _EMPTY, _EMPTY, _EMPTY, 0.0, None)
    ctx.counts["contact"] += 1
    _, q_next, u_next, c, P, gm, gp, work, status, v, lam, M, W, v_free, b, corr = r
    qp = QPResult("ADMISSIBLE" if status == 0 else "ACTIVE_SET", True, 0, status == 1, v, lam, (M, W, v_free, b))
    return StepResult(State(t1, q_next, u_next), Contacts(*c), P, gm, gp, work, qp, None, corr)
