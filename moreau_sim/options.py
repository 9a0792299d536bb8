"""Options and every closed choice of a scene, below the parser and the math.

Each choice is an enum whose values are the strings of the scene files (docs/scenes.md);
the rule each one selects is stated in docs/theory.md §2. Nothing here reads files.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass

from .errors import SceneError


class RootJoint(enum.Enum):
    """How a body's root link is attached to the world."""

    FIXED = "fixed"  # 0 dof: the body is part of the static environment
    FREE = "free"  # 6 dof: q = [x y z qx qy qz qw], u = [v (world), w (body frame)]
    PLANAR = "planar"  # 3 dof: q = [s_a, s_b, theta] along `axes`, rotation about a x b
    TRANSLATION = "translation"  # 1-3 dof: displacements along `axes` (default x, y, z), no rotation
    PRISMATIC = "prismatic"  # 1 dof along `axis` [m]
    REVOLUTE = "revolute"  # 1 dof about `axis` [rad]


class QPForm(enum.Enum):
    """Which form of the impact QP piqp solves (docs/theory.md §1)."""

    PRIMAL = "primal"  # velocity space: min 1/2 (v - v_free)' M (v - v_free), W' v >= 0
    DUAL = "dual"  # contact space: Delassus G = W' M^-1 W, lambda >= 0


class Separating(enum.Enum):
    """The restitution used for a contact that is closed (g_i(q_m) <= tol) but separating at the
    start of the step (gamma_i^k > 0) - a time-discretization case, not an impact.

    NEWTON: e as for every contact (the plain discrete law of docs/theory.md §2); its contact
        work P_i (1 - e) gamma_i^k / 2 is then > 0: a small energy gain, O(h^2) per event.
    ELASTIC: e_i = 1 for such a contact, so gamma_i^{k+1} = -gamma_i^k where it pushes: its work
        P_i (gamma^{k+1} + gamma^k)/2 is 0, the contact work of a step is never positive, and the
        returning contact meets the global e at its next (approaching) step.
    """

    NEWTON = "newton"
    ELASTIC = "elastic"


class Tunnelling(enum.Enum):
    """Whether a step looks for contacts crossed between two midpoints (a fast body, a thin obstacle).

    SWEPT: when a body may move further in a step than the thinnest pair of shapes is thick
        (h |u|_inf reach > Model.thinnest_pair), contacts are also looked for along the step's
        motion by conservative advancement with coal's signed distance (tunnelling.swept_detect);
        a pair touched on the way is taken with the normal of its first contact. Costs nothing
        when no body is that fast.
    NONE: the midpoint test alone (g(q_m) <= tol): a body faster than (thickness / h) can pass
        through a thin obstacle.
    ALWAYS: the swept test on every step whatever the speed (for measurements and tests).
    """

    SWEPT = "swept"
    NONE = "none"
    ALWAYS = "always"


class Integrator(enum.Enum):
    """How a scene is integrated.

    TIME_STEPPING: the midpoint Moreau stepper (stepper.py): any scene, fixed step h.
    EVENT_DRIVEN: reference.simulate_event_driven: smooth phases by scipy's solve_ivp at tight
        tolerances, impacts at their located instants with the same law. For small systems of
        the supported pairs (box vertices or spheres vs half-spaces, spheres vs spheres and static
        boxes) where exactness matters more than speed; dt x save_every is then the sampling
        interval only.
    ADAPTIVE: adaptive.simulate_adaptive: extrapolated symmetric midpoint steps with error control
        (rtol, atol) between impacts located on the per-feature gaps, the same law at the located
        instants; fixed midpoint Moreau steps of dt where features are missing or impacts accumulate.
    """

    TIME_STEPPING = "time-stepping"
    EVENT_DRIVEN = "event-driven"
    ADAPTIVE = "adaptive"


class SlowImpacts(enum.Enum):
    """The restitution of an impact slower than what the smooth forces add in one step
    (0 < -gamma_i^k <= -w_i'(u_free - u_k)): the bounces below the step's resolution at the end of
    an accumulation of impacts (Zeno), heights below ~h^2 |a|.

    RESTITUTION: e, as any impact: the tail of bounces of speed ~ h|a| dies out over many steps.
    PLASTIC: e_i = 0: the contact closes at once, the accumulation ends within a step of where
        the sequence of bounces shrinks below the step size.
    """

    RESTITUTION = "restitution"
    PLASTIC = "plastic"


class Bias(enum.Enum):
    """Where the velocity-dependent bias forces (Coriolis, gyroscopic) of the free step are taken.

    EXPLICIT: h(q_m, u_k), as in docs/theory.md §2.
    MIDPOINT: h(q_m, (u_k + u_free)/2) by fixed-point iteration (the implicit midpoint rule for
        the velocity): for a free rigid body it conserves the kinetic energy of the rotation
        exactly (the gyroscopic term does no work), where the explicit term gains O(h) energy.
    """

    EXPLICIT = "explicit"
    MIDPOINT = "midpoint"


class PositionCorrection(enum.Enum):
    """What is done with the penetration a contact step leaves (the contact closes at q_m).

    NONE: nothing (penetration stays bounded by h |gamma|, but stays).
    PROJECTION: after a contact step, q_{k+1} is moved onto the closed contacts' linearized
        g >= 0 by the smallest displacement in the kinetic metric (a QP), limited so that the
        step's total energy T + V does not rise above its value at the start of the step.
    """

    NONE = "none"
    PROJECTION = "projection"


class StepImpl(enum.Enum):
    """Which implementation takes the time steps (moreau_sim/compiled.py).

    COMPILED: the default: the C++ step (moreau_sim._step) where it covers the step, else the Python
        step; the Python step alone when the extension is unavailable (one warning says why). The two
        give the same trajectory, bit for bit, on every bundled scene over its full duration.
    PYTHON: the Python step (stepper.py) only, the reference implementation."""

    COMPILED = "compiled"
    PYTHON = "python"


class StaticShape(enum.Enum):
    HALFSPACE = "halfspace"
    BOX = "box"
    SPHERE = "sphere"
    CYLINDER = "cylinder"


class MeshMode(enum.Enum):
    """How a body's collision meshes enter coal (docs/robots.md, "Mesh collision geometry")."""

    CONVEX = "convex"  # convex hull (coal.ConvexBase): vertices + faces, rests flat on its hull
    BVH = "bvh"  # the triangle mesh as loaded (coal.BVHModelOBBRSS): one contact per pair


class Selection(enum.Enum):
    """Which admissible outcome of a corner impact the stepper continues with (docs/theory.md §3;
    corners.select; all deterministic)."""

    GLOBAL_MIN = "global-min"  # least distance; ties -> lowest `pieces` tuple (lexicographic)
    SYMMETRIC = "symmetric"    # unique minimizer, else the corner point of the tied pieces
    FIRST = "first"            # lowest `pieces` tuple whatever the distance (caller's priority)


def require(cond: bool, where: str, msg: str) -> None:
    """Raise SceneError("where: msg") unless cond."""
    if not cond:
        raise SceneError(f"{where}: {msg}")


def finite_vector(value, n: int, where: str) -> tuple[float, ...]:
    require(isinstance(value, (list, tuple)) and len(value) == n, where, f"must be a list of {n} numbers, got {value!r}")
    out = []
    for x in value:
        require(isinstance(x, (int, float)) and not isinstance(x, bool), where, f"must hold numbers, got {x!r}")
        require(math.isfinite(x), where, f"must be finite, got {x!r}")
        out.append(float(x))
    return tuple(out)


def finite_number(value, where: str) -> float:
    require(isinstance(value, (int, float)) and not isinstance(value, bool), where, f"must be a number, got {value!r}")
    require(math.isfinite(value), where, f"must be finite, got {value!r}")
    return float(value)


def check_restitution(e) -> float:
    """The global restitution e as a float; ValueError unless 0 <= e <= 1 (docs/theory.md §1).
    The one check of e: the law, the corner law and Options call it."""
    try:
        e_f = float(e)
    except (TypeError, ValueError):
        raise ValueError(f"restitution e must be a number in [0, 1], got {e!r}") from None
    if isinstance(e, bool) or not 0.0 <= e_f <= 1.0:
        raise ValueError(f"restitution e must lie in [0, 1], got {e!r}")
    return e_f


def choice(cls, value, where: str):
    """cls(value) for an enum of this module, or SceneError naming `where` and the allowed values."""
    try:
        return cls(value)
    except ValueError:
        raise SceneError(f"{where}: must be one of {[m.value for m in cls]}, got {value!r}") from None


@dataclass(frozen=True, kw_only=True)
class Options:
    """Integration options. All SI units.

    restitution: global Newton restitution e in [0, 1] (docs/theory.md §1).
    dt: time step h [s], > 0.
    duration: simulated time [s], > 0.
    gravity: gravity vector [m/s^2].
    contact_tolerance: a contact is closed (in H) when its gap at the midpoint q_m is <= this [m].
        The default 1e-9 m is ~1e7 times the rounding of positions of order 1 m, so bodies
        placed exactly touching count as closed, and far below any physical gap.
    qp_form: which form of the impact QP to solve (see :class:`QPForm`).
    separating: the restitution of closed contacts that separate (see :class:`Separating`).
    integrator: time-stepping (default) or event-driven (see :class:`Integrator`).
    tunnelling: look for contacts along fast motions (see :class:`Tunnelling`).
    slow_impacts: the restitution of impacts below the step's resolution (see :class:`SlowImpacts`).
    bias: where the Coriolis / gyroscopic forces are evaluated (see :class:`Bias`).
    position_correction: what is done with penetration after a contact step (:class:`PositionCorrection`).
    corner_selection: which admissible outcome of a corner impact the run continues with
        (:class:`Selection`; every branching step is logged).
    qp_tolerance: piqp's eps_abs and eps_rel (piqp answers where the exact active set does not settle,
        and starts it above qp.COLD_START_ROWS = 200 rows; qp.solve).
    save_every: record the state every N steps (the last step is always recorded).
    rtol, atol: the adaptive integrator's relative and absolute error tolerances per step
        (positions [m or rad] and velocities [m/s or rad/s]; atol in SI units), rtol in (0, 1),
        atol > 0.
    step_impl: the compiled step where it applies (default), or the Python step only (see :class:`StepImpl`).
    """

    restitution: float = 0.5
    dt: float = 1e-3
    duration: float = 1.0
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    contact_tolerance: float = 1e-9
    qp_form: QPForm = QPForm.PRIMAL
    separating: Separating = Separating.ELASTIC
    corner_selection: Selection = Selection.GLOBAL_MIN
    integrator: Integrator = Integrator.TIME_STEPPING
    tunnelling: Tunnelling = Tunnelling.SWEPT
    slow_impacts: SlowImpacts = SlowImpacts.PLASTIC
    bias: Bias = Bias.MIDPOINT
    position_correction: PositionCorrection = PositionCorrection.PROJECTION
    qp_tolerance: float = 1e-10
    save_every: int = 1
    rtol: float = 1e-8
    atol: float = 1e-10
    step_impl: StepImpl = StepImpl.COMPILED

    def __post_init__(self):
        self.validate("options")

    def validate(self, where: str) -> None:
        e, h = self.restitution, self.dt
        try:
            check_restitution(e)
        except ValueError:
            raise SceneError(f"{where}: restitution: must lie in [0, 1], got {e!r}") from None
        require(isinstance(h, (int, float)) and math.isfinite(h) and h > 0, f"{where}: dt", f"must be a finite step > 0 s, got {h!r}")
        require(isinstance(self.duration, (int, float)) and math.isfinite(self.duration) and self.duration > 0,
               f"{where}: duration", f"must be > 0 s, got {self.duration!r}")
        require(self.duration / h <= 1e9, f"{where}: dt", f"duration/dt = {self.duration / h:.3g} steps is too many")
        require(h <= self.duration, f"{where}: dt", f"the step {h!r} s is longer than the duration {self.duration!r} s")
        finite_vector(list(self.gravity), 3, f"{where}: gravity")
        require(isinstance(self.contact_tolerance, (int, float)) and 0 <= self.contact_tolerance < 1e-3,
               f"{where}: contact_tolerance", f"must lie in [0, 1e-3) m, got {self.contact_tolerance!r}")
        require(isinstance(self.qp_form, QPForm), f"{where}: qp_form", f"must be a QPForm, got {self.qp_form!r}")
        require(isinstance(self.separating, Separating), f"{where}: separating",
               f"must be a Separating rule, got {self.separating!r}")
        require(isinstance(self.bias, Bias), f"{where}: bias", f"must be a Bias, got {self.bias!r}")
        require(isinstance(self.tunnelling, Tunnelling), f"{where}: tunnelling",
               f"must be a Tunnelling choice, got {self.tunnelling!r}")
        require(isinstance(self.integrator, Integrator), f"{where}: integrator",
               f"must be an Integrator, got {self.integrator!r}")
        require(isinstance(self.slow_impacts, SlowImpacts), f"{where}: slow_impacts",
               f"must be a SlowImpacts rule, got {self.slow_impacts!r}")
        require(isinstance(self.position_correction, PositionCorrection), f"{where}: position_correction",
               f"must be a PositionCorrection, got {self.position_correction!r}")
        require(isinstance(self.corner_selection, Selection), f"{where}: corner_selection",
               f"must be a Selection, got {self.corner_selection!r}")
        require(isinstance(self.qp_tolerance, (int, float)) and 0 < self.qp_tolerance < 1e-3,
               f"{where}: qp_tolerance", f"must lie in (0, 1e-3), got {self.qp_tolerance!r}")
        require(isinstance(self.step_impl, StepImpl), f"{where}: step_impl",
               f"must be a StepImpl, got {self.step_impl!r}")
        require(isinstance(self.save_every, int) and not isinstance(self.save_every, bool) and self.save_every >= 1,
               f"{where}: save_every", f"must be an integer >= 1, got {self.save_every!r}")
        require(isinstance(self.rtol, (int, float)) and not isinstance(self.rtol, bool) and 0 < self.rtol < 1,
                f"{where}: rtol", f"must lie in (0, 1), got {self.rtol!r}")
        require(isinstance(self.atol, (int, float)) and not isinstance(self.atol, bool)
                and math.isfinite(self.atol) and self.atol > 0, f"{where}: atol", f"must be a finite number > 0, got {self.atol!r}")

    @property
    def n_steps(self) -> int:
        """Number of steps: duration / dt rounded to the nearest integer (at least 1)."""
        return max(1, int(round(self.duration / self.dt)))

    def replace(self, **changes) -> "Options":
        """A copy with `changes` applied and validated (None values are ignored)."""
        changes = {k: v for k, v in changes.items() if v is not None}
        for key, cls in CHOICES.items():
            if isinstance(changes.get(key), str):
                changes[key] = choice(cls, changes[key], f"options: {key}")
        if "gravity" in changes:
            changes["gravity"] = tuple(float(x) for x in changes["gravity"])
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        for key in CHOICES:
            d[key] = getattr(self, key).value
        d["gravity"] = list(self.gravity)
        return d


CHOICES = {"qp_form": QPForm, "separating": Separating, "corner_selection": Selection, "bias": Bias,
           "position_correction": PositionCorrection, "slow_impacts": SlowImpacts, "integrator": Integrator,
           "tunnelling": Tunnelling, "step_impl": StepImpl}
