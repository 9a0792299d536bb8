"""Scene files (TOML) -> a frozen, validated :class:`Scene`.

Every key, unit and default is documented in ``docs/scenes.md``; this module is the
single place that reads them. Errors name the file and the field
(``scenes/x.toml: [simulation] restitution = 1.5: must lie in [0, 1]``).
"""

from __future__ import annotations

import dataclasses
import enum
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .corners import Selection
from .errors import SceneError
from .robots import MeshMode, resolve_model_file


class RootJoint(enum.Enum):
    """How a body's root link is attached to the world."""

    FIXED = "fixed"  # 0 dof: the body is part of the static environment
    FREE = "free"  # 6 dof: q = [x y z qx qy qz qw], u = [v (world), w (body frame)]
    PLANAR = "planar"  # 3 dof: q = [s_a, s_b, theta] along `axes`, rotation about a x b
    TRANSLATION = "translation"  # 1-3 dof: displacements along `axes` (default x, y, z), no rotation
    PRISMATIC = "prismatic"  # 1 dof along `axis` [m]
    REVOLUTE = "revolute"  # 1 dof about `axis` [rad]


class QPForm(enum.Enum):
    """Which form of the impact QP piqp solves (impact-law.md §1)."""

    PRIMAL = "primal"  # velocity space: min 1/2 (v - v_free)' M (v - v_free), W' v >= 0
    DUAL = "dual"  # contact space: Delassus G = W' M^-1 W, lambda >= 0


class Separating(enum.Enum):
    """The restitution used for a contact that is closed (g_i(q_m) <= tol) but separating at the
    start of the step (gamma_i^k > 0) - a time-discretization case, not an impact.

    NEWTON: e as for every contact (the plain discrete law of impact-law.md §2); its contact
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
    """

    SWEPT = "swept"
    NONE = "none"


class Integrator(enum.Enum):
    """How a scene is integrated.

    TIME_STEPPING: the midpoint Moreau stepper (stepper.py): any scene, fixed step h.
    EVENT_DRIVEN: reference.simulate_event_driven: smooth phases by scipy's solve_ivp at tight
        tolerances, impacts at their located instants with the same law. For small systems of
        the supported pairs (box vertices or spheres vs half-spaces, spheres vs spheres and static
        boxes) where exactness matters more than speed; dt x save_every is then the sampling
        interval only.
    """

    TIME_STEPPING = "time-stepping"
    EVENT_DRIVEN = "event-driven"


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

    EXPLICIT: h(q_m, u_k), as in impact-law.md §2.
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


class StaticShape(enum.Enum):
    HALFSPACE = "halfspace"
    BOX = "box"
    SPHERE = "sphere"
    CYLINDER = "cylinder"


def _check(cond: bool, where: str, msg: str) -> None:
    if not cond:
        raise SceneError(f"{where}: {msg}")


def _finite_vec(value, n: int, where: str) -> tuple[float, ...]:
    _check(isinstance(value, (list, tuple)) and len(value) == n, where, f"must be a list of {n} numbers, got {value!r}")
    out = []
    for x in value:
        _check(isinstance(x, (int, float)) and not isinstance(x, bool), where, f"must hold numbers, got {x!r}")
        _check(math.isfinite(x), where, f"must be finite, got {x!r}")
        out.append(float(x))
    return tuple(out)


def _number(value, where: str) -> float:
    _check(isinstance(value, (int, float)) and not isinstance(value, bool), where, f"must be a number, got {value!r}")
    _check(math.isfinite(value), where, f"must be finite, got {value!r}")
    return float(value)


@dataclass(frozen=True, kw_only=True)
class Options:
    """Integration options. All SI units.

    restitution: global Newton restitution e in [0, 1] (impact-law.md §1).
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
        (:class:`moreau_sim.corners.Selection`; every branching step is logged).
    qp_tolerance: piqp's eps_abs and eps_rel; the solution is then polished on its active set.
    save_every: record the state every N steps (the last step is always recorded).
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

    def __post_init__(self):
        self.validate("options")

    def validate(self, where: str) -> None:
        e, h = self.restitution, self.dt
        _check(isinstance(e, (int, float)) and 0.0 <= e <= 1.0, f"{where}: restitution", f"must lie in [0, 1], got {e!r}")
        _check(isinstance(h, (int, float)) and math.isfinite(h) and h > 0, f"{where}: dt", f"must be a finite step > 0 s, got {h!r}")
        _check(isinstance(self.duration, (int, float)) and math.isfinite(self.duration) and self.duration > 0,
               f"{where}: duration", f"must be > 0 s, got {self.duration!r}")
        _check(self.duration / h <= 1e9, f"{where}: dt", f"duration/dt = {self.duration / h:.3g} steps is too many")
        _finite_vec(list(self.gravity), 3, f"{where}: gravity")
        _check(isinstance(self.contact_tolerance, (int, float)) and 0 <= self.contact_tolerance < 1e-3,
               f"{where}: contact_tolerance", f"must lie in [0, 1e-3) m, got {self.contact_tolerance!r}")
        _check(isinstance(self.qp_form, QPForm), f"{where}: qp_form", f"must be a QPForm, got {self.qp_form!r}")
        _check(isinstance(self.separating, Separating), f"{where}: separating",
               f"must be a Separating rule, got {self.separating!r}")
        _check(isinstance(self.bias, Bias), f"{where}: bias", f"must be a Bias, got {self.bias!r}")
        _check(isinstance(self.tunnelling, Tunnelling), f"{where}: tunnelling",
               f"must be a Tunnelling choice, got {self.tunnelling!r}")
        _check(isinstance(self.integrator, Integrator), f"{where}: integrator",
               f"must be an Integrator, got {self.integrator!r}")
        _check(isinstance(self.slow_impacts, SlowImpacts), f"{where}: slow_impacts",
               f"must be a SlowImpacts rule, got {self.slow_impacts!r}")
        _check(isinstance(self.position_correction, PositionCorrection), f"{where}: position_correction",
               f"must be a PositionCorrection, got {self.position_correction!r}")
        _check(isinstance(self.corner_selection, Selection), f"{where}: corner_selection",
               f"must be a corners.Selection, got {self.corner_selection!r}")
        _check(isinstance(self.qp_tolerance, (int, float)) and 0 < self.qp_tolerance < 1e-3,
               f"{where}: qp_tolerance", f"must lie in (0, 1e-3), got {self.qp_tolerance!r}")
        _check(isinstance(self.save_every, int) and not isinstance(self.save_every, bool) and self.save_every >= 1,
               f"{where}: save_every", f"must be an integer >= 1, got {self.save_every!r}")

    @property
    def n_steps(self) -> int:
        """Number of steps: duration / dt rounded to the nearest integer (at least 1)."""
        return max(1, int(round(self.duration / self.dt)))

    def replace(self, **changes) -> "Options":
        """A copy with `changes` applied and validated (None values are ignored)."""
        changes = {k: v for k, v in changes.items() if v is not None}
        for key, cls in _ENUMS.items():
            if isinstance(changes.get(key), str):
                changes[key] = _enum(cls, changes[key], f"options: {key}")
        if "gravity" in changes:
            changes["gravity"] = tuple(float(x) for x in changes["gravity"])
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        for key in _ENUMS:
            d[key] = getattr(self, key).value
        d["gravity"] = list(self.gravity)
        return d


@dataclass(frozen=True, kw_only=True)
class Body:
    """A URDF (or MJCF) model attached to the world by a root joint (docs/scenes.md, [[bodies]]).

    urdf: the model file, resolved (a path or a package:// URI in the scene); an MJCF file when
    `mjcf` is true (its text is what outputs record as the body's description).
    package_dirs: folders searched first for package:// URIs (docs/robots.md).
    meshes: how collision meshes enter coal (robots.MeshMode: convex hull or BVH)."""

    name: str
    urdf: Path
    root_joint: RootJoint
    mjcf: bool = False
    package_dirs: tuple[Path, ...] = ()
    meshes: MeshMode = MeshMode.CONVEX
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    axes: tuple[tuple[float, float, float], ...] | None = None  # planar: default x, z; translation: x, y, z
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    q0: tuple[float, ...] | None = None
    u0: tuple[float, ...] | None = None


@dataclass(frozen=True, kw_only=True)
class Static:
    """A fixed obstacle of the environment (docs/scenes.md, [[statics]])."""

    name: str
    shape: StaticShape
    normal: tuple[float, float, float] = (0.0, 0.0, 1.0)  # halfspace: outward normal
    offset: float = 0.0  # halfspace: the surface is {x : normal . x = offset} [m]
    size: tuple[float, float, float] = (1.0, 1.0, 1.0)  # box: full side lengths [m]
    radius: float = 0.1  # sphere, cylinder [m]
    length: float = 0.1  # cylinder: full length [m]
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True, kw_only=True)
class Collisions:
    """Which collision pairs exist beyond the automatic rule (docs/scenes.md, [collisions])."""

    include: tuple[tuple[str, str], ...] = ()
    exclude: tuple[tuple[str, str], ...] = ()


@dataclass(frozen=True, kw_only=True)
class Scene:
    name: str
    description: str = ""
    options: Options = field(default_factory=Options)
    bodies: tuple[Body, ...] = ()
    statics: tuple[Static, ...] = ()
    collisions: Collisions = field(default_factory=Collisions)
    output: str | None = None  # default output file (relative to the working directory)
    path: Path | None = None  # the file it was read from
    source: str = ""  # the TOML text, kept so outputs describe themselves

    def with_options(self, **changes) -> "Scene":
        """A copy with options changed (e.g. ``dt=1e-4, restitution=1.0``), validated."""
        return dataclasses.replace(self, options=self.options.replace(**changes))


_TOP = {"scene", "simulation", "output", "bodies", "statics", "collisions"}
_SIM = {"restitution": "restitution", "dt": "dt", "duration": "duration", "gravity": "gravity",
        "contact_tolerance": "contact_tolerance", "qp_form": "qp_form", "qp_tolerance": "qp_tolerance",
        "separating": "separating", "corner_selection": "corner_selection", "bias": "bias",
        "position_correction": "position_correction", "slow_impacts": "slow_impacts", "integrator": "integrator",
        "tunnelling": "tunnelling"}
_ENUMS = {"qp_form": QPForm, "separating": Separating, "corner_selection": Selection, "bias": Bias,
          "position_correction": PositionCorrection, "slow_impacts": SlowImpacts, "integrator": Integrator,
          "tunnelling": Tunnelling}
_BODY = {"name", "urdf", "mjcf", "root_joint", "axis", "axes", "position", "rpy", "q0", "u0", "package_dirs", "meshes"}
_STATIC = {"name", "shape", "normal", "offset", "size", "radius", "length", "position", "rpy"}


def _unknown(table: dict, allowed: set, where: str) -> None:
    extra = sorted(set(table) - allowed)
    _check(not extra, where, f"unknown key(s) {extra}; allowed: {sorted(allowed)}")


def _table(doc: dict, key: str, where: str) -> dict:
    t = doc.get(key, {})
    _check(isinstance(t, dict), f"{where} [{key}]", "must be a table")
    return t


def _name(value, where: str) -> str:
    _check(isinstance(value, str) and value.strip() != "" and "/" not in value, where,
           f"must be a non-empty string without '/', got {value!r}")
    return value


def _enum(cls, value, where: str):
    try:
        return cls(value)
    except ValueError:
        raise SceneError(f"{where}: must be one of {[m.value for m in cls]}, got {value!r}") from None


def _parse_options(sim: dict, out: dict, where: str) -> Options:
    _unknown(sim, set(_SIM), f"{where} [simulation]")
    kw: dict[str, Any] = {}
    for key in ("restitution", "dt", "duration", "contact_tolerance", "qp_tolerance"):
        if key in sim:
            kw[key] = _number(sim[key], f"{where} [simulation] {key}")
    if "gravity" in sim:
        kw["gravity"] = _finite_vec(sim["gravity"], 3, f"{where} [simulation] gravity")
    for key, cls in _ENUMS.items():
        if key in sim:
            kw[key] = _enum(cls, sim[key], f"{where} [simulation] {key}")
    if "save_every" in out:
        kw["save_every"] = out["save_every"]
    try:
        return Options(**kw)
    except SceneError as exc:  # re-label "options: x" as the file's section
        raise SceneError(str(exc).replace("options:", f"{where} [simulation]", 1)) from None


def _parse_body(t: dict, where: str, base: Path) -> Body:
    _check(isinstance(t, dict), where, "must be a table")
    _unknown(t, _BODY, where)
    _check("mjcf" not in t or "urdf" not in t, where, "give either 'urdf' or 'mjcf', not both")
    for req in ("name", "mjcf" if "mjcf" in t else "urdf", "root_joint"):
        _check(req in t, where, f"missing required key '{req}'")
    name = _name(t["name"], f"{where} name")
    w = f"{where} ({name})"
    dirs: list[Path] = []
    if "package_dirs" in t:
        _check(isinstance(t["package_dirs"], list) and all(isinstance(d, str) for d in t["package_dirs"]),
               f"{w} package_dirs", f"must be a list of folder paths, got {t['package_dirs']!r}")
        # a folder that does not exist is kept (and listed when a URI resolves nowhere), as in
        # $MOREAU_SIM_PACKAGE_PATH: a scene rebuilt elsewhere (viewer) may find its files otherwise
        dirs = [(base / d).resolve() for d in t["package_dirs"]]
    key = "mjcf" if "mjcf" in t else "urdf"
    _check(isinstance(t[key], str) and t[key] != "", f"{w} {key}", "must be a path string or a package:// URI")
    urdf = resolve_model_file(t[key], base, dirs, f"{w} {key}")
    kw: dict[str, Any] = dict(name=name, urdf=urdf, root_joint=_enum(RootJoint, t["root_joint"], f"{w} root_joint"),
                              mjcf=key == "mjcf", package_dirs=tuple(dirs))
    if "meshes" in t:
        kw["meshes"] = _enum(MeshMode, t["meshes"], f"{w} meshes")
    for key in ("axis", "position", "rpy"):
        if key in t:
            kw[key] = _finite_vec(t[key], 3, f"{w} {key}")
    if "axis" in kw:
        _check(math.hypot(*kw["axis"]) > 1e-12, f"{w} axis", "must not be zero")
    if "axes" in t:
        _check(isinstance(t["axes"], list) and 1 <= len(t["axes"]) <= 3, f"{w} axes", "must be 1 to 3 3-vectors")
        axes = tuple(_finite_vec(x, 3, f"{w} axes") for x in t["axes"])
        norms = [math.hypot(*a) for a in axes]
        _check(min(norms) > 1e-12 and all(abs(sum(x * y for x, y in zip(a, b))) < 1e-9 * na * nb
                                          for i, (a, na) in enumerate(zip(axes, norms))
                                          for b, nb in zip(axes[i + 1:], norms[i + 1:])),
               f"{w} axes", "must be non-zero and mutually orthogonal")
        kw["axes"] = axes
    rj = kw["root_joint"]
    if rj is RootJoint.PLANAR:
        kw.setdefault("axes", ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)))
        _check(len(kw["axes"]) == 2, f"{w} axes", "a planar joint takes exactly two axes")
    elif rj is RootJoint.TRANSLATION:
        kw.setdefault("axes", ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)))
    else:
        _check("axes" not in kw, f"{w} axes", "only planar and translation root joints take axes")
    for key in ("q0", "u0"):
        if key in t:
            _check(isinstance(t[key], list), f"{w} {key}", "must be a list of numbers")
            kw[key] = _finite_vec(t[key], len(t[key]), f"{w} {key}")
    return Body(**kw)


def _parse_static(t: dict, where: str) -> Static:
    _check(isinstance(t, dict), where, "must be a table")
    _unknown(t, _STATIC, where)
    for req in ("name", "shape"):
        _check(req in t, where, f"missing required key '{req}'")
    name = _name(t["name"], f"{where} name")
    w = f"{where} ({name})"
    kw: dict[str, Any] = dict(name=name, shape=_enum(StaticShape, t["shape"], f"{w} shape"))
    for key in ("normal", "size", "position", "rpy"):
        if key in t:
            kw[key] = _finite_vec(t[key], 3, f"{w} {key}")
    for key in ("offset", "radius", "length"):
        if key in t:
            kw[key] = _number(t[key], f"{w} {key}")
    s = Static(**kw)
    _check(math.hypot(*s.normal) > 1e-12, f"{w} normal", "must not be zero")
    _check(min(s.size) > 0 and s.radius > 0 and s.length > 0, w, "sizes, radius and length must be > 0 m")
    return s


def _parse_pairs(value, where: str) -> tuple[tuple[str, str], ...]:
    _check(isinstance(value, list), where, "must be a list of [name, name] pairs")
    out = []
    for p in value:
        _check(isinstance(p, list) and len(p) == 2 and all(isinstance(x, str) for x in p), where,
               f"each entry must be [name, name], got {p!r}")
        out.append((p[0], p[1]))
    return tuple(out)


def parse_scene(text: str, *, path: Path | str | None = None) -> Scene:
    """Parse scene TOML `text`; relative URDF paths resolve against `path`'s folder."""
    where = str(path) if path is not None else "<scene>"
    base = Path(path).resolve().parent if path is not None else Path.cwd()
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{where}: malformed TOML: {exc}") from None
    _unknown(doc, _TOP, where)
    head = _table(doc, "scene", where)
    _unknown(head, {"name", "description"}, f"{where} [scene]")
    name = _name(head.get("name", Path(where).stem if path else "scene"), f"{where} [scene] name")
    description = head.get("description", "")
    _check(isinstance(description, str), f"{where} [scene] description", "must be a string")
    out = _table(doc, "output", where)
    _unknown(out, {"file", "save_every"}, f"{where} [output]")
    output = out.get("file")
    _check(output is None or isinstance(output, str), f"{where} [output] file", "must be a path string")
    options = _parse_options(_table(doc, "simulation", where), out, where)

    bodies_t, statics_t = doc.get("bodies", []), doc.get("statics", [])
    _check(isinstance(bodies_t, list), f"{where} [[bodies]]", "must be an array of tables")
    _check(isinstance(statics_t, list), f"{where} [[statics]]", "must be an array of tables")
    bodies = tuple(_parse_body(t, f"{where} [[bodies]][{i}]", base) for i, t in enumerate(bodies_t))
    statics = tuple(_parse_static(t, f"{where} [[statics]][{i}]") for i, t in enumerate(statics_t))
    names = [b.name for b in bodies] + [s.name for s in statics]
    dup = sorted({n for n in names if names.count(n) > 1})
    _check(not dup, where, f"duplicate body/static names {dup}")

    col = _table(doc, "collisions", where)
    _unknown(col, {"include", "exclude"}, f"{where} [collisions]")
    collisions = Collisions(include=_parse_pairs(col.get("include", []), f"{where} [collisions] include"),
                            exclude=_parse_pairs(col.get("exclude", []), f"{where} [collisions] exclude"))
    return Scene(name=name, description=description, options=options, bodies=bodies, statics=statics,
                 collisions=collisions, output=output, path=Path(path).resolve() if path else None, source=text)


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene file. Raises :class:`SceneError` naming the file and field."""
    p = Path(path)
    if not p.is_file():
        raise SceneError(f"{p}: scene file not found")
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"{p}: cannot read scene file: {exc}") from None
    return parse_scene(text, path=p)
