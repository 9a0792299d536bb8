"""Scene files (TOML) -> a frozen, validated :class:`Scene`.

Every key, unit and default is documented in ``docs/scenes.md``; this module is the
single place that reads them. Errors name the file and the field
(``scenes/x.toml: [simulation] restitution = 1.5: must lie in [0, 1]``).
"""

from __future__ import annotations

from collections import Counter
import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import SceneError
from .options import (CHOICES, MeshMode, Options, RootJoint, StaticShape, choice, finite_number, finite_vector,
                      require)
from .prescribed import Schedule, parse_schedule
from .robots import find_srdf, real_path, resolve_model_file


@dataclass(frozen=True, kw_only=True)
class Body:
    """A URDF (or MJCF) model attached to the world by a root joint (docs/scenes.md, [[bodies]]).

    urdf: the model file, resolved (a path or a package:// URI in the scene); an MJCF file when
    `mjcf` is true (its text is what outputs record as the body's description).
    package_dirs: folders searched first for package:// URIs (docs/robots.md).
    meshes: how collision meshes enter coal (options.MeshMode: convex hull or BVH).
    srdf: the SRDF whose disabled collision pairs and reference poses apply (the scene's, else
    the one example-robot-data ships beside a URDF: robots.find_srdf), or None."""

    name: str
    urdf: Path
    root_joint: RootJoint
    mjcf: bool = False
    package_dirs: tuple[Path, ...] = ()
    meshes: MeshMode = MeshMode.CONVEX
    srdf: Path | None = None
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    axes: tuple[tuple[float, float, float], ...] | None = None  # planar: default x, z; translation: x, y, z
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    q0: tuple[float, ...] | None = None
    u0: tuple[float, ...] | None = None
    joint_limits: bool = True  # the position limits of its revolute / prismatic joints (moreau_sim/limits.py)


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
    motion: Schedule | None = None  # prescribed displacement from `position` [m] (prescribed.py)


@dataclass(frozen=True, kw_only=True)
class Actuator:
    """PD targets of some joints of a body (docs/scenes.md, [[actuators]]): joints (None: every 1-dof
    joint of the body but an unfixed root, in q order), kp [N m/rad or N/m], kd [N m s/rad or N s/m],
    target and velocity: the raw TOML values (a number, a list per joint, a time table or a sine; None:
    hold the initial positions / the target's own derivative), parsed once the joints are known
    (actuation.build); effort [N m or N]: a clamp of this entry's torques (None: the URDF's only);
    where: the entry's place in the file, for errors. An entry with `mjcf` instead gives the control signal
    `ctrl` of MJCF actuators of the body (docs/robots.md#mjcf-actuators); kp is then 0 and unused."""

    body: str
    joints: tuple[str, ...] | None
    kp: float
    kd: float = 0.0
    target: Any = None
    velocity: Any = None
    effort: float | None = None
    mjcf: tuple[str, ...] | str | None = None  # the MJCF actuators an entry drives (names or "all"); None: PD
    ctrl: Any = None  # their control signal (raw TOML: number, list, table {t, ctrl} or sine)
    where: str = ""


@dataclass(frozen=True, kw_only=True)
class DriveSpec:
    """A joint whose motion is prescribed (docs/scenes.md, [[drives]]; drive.py): the body, the joint's name,
    its motion x(t) (a schedule of one component: {velocity}, {sine} or a table {t, q}): q(t) = q(0) + x(t) - x(0)."""

    body: str
    joint: str
    motion: Schedule
    where: str = ""


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
    actuators: tuple[Actuator, ...] = ()
    drives: tuple[DriveSpec, ...] = ()
    output: str | None = None  # default output file (relative to the working directory)
    path: Path | None = None  # the file it was read from
    source: str = ""  # the TOML text, kept so outputs describe themselves

    def with_options(self, **changes) -> "Scene":
        """A copy with options changed (e.g. ``dt=1e-4, restitution=1.0``), validated."""
        return dataclasses.replace(self, options=self.options.replace(**changes))


_TOP = {"scene", "simulation", "output", "bodies", "statics", "collisions", "actuators", "drives"}
_SIM = {"restitution": "restitution", "dt": "dt", "duration": "duration", "gravity": "gravity",
        "contact_tolerance": "contact_tolerance", "qp_form": "qp_form", "qp_tolerance": "qp_tolerance",
        "separating": "separating", "corner_selection": "corner_selection", "bias": "bias",
        "position_correction": "position_correction", "slow_impacts": "slow_impacts", "integrator": "integrator",
        "tunnelling": "tunnelling", "rtol": "rtol", "atol": "atol", "step_impl": "step_impl"}
_BODY = {"name", "urdf", "mjcf", "root_joint", "axis", "axes", "position", "rpy", "q0", "u0", "package_dirs", "meshes",
         "srdf", "joint_limits"}
_STATIC = {"name", "shape", "normal", "offset", "size", "radius", "length", "position", "rpy", "motion"}
_ACTUATOR = {"body", "joints", "kp", "kd", "target", "velocity", "effort"}
_CONTROL = {"body", "mjcf", "ctrl"}  # an [[actuators]] entry driving MJCF actuators


def _unknown(table: dict, allowed: set, where: str) -> None:
    extra = sorted(set(table) - allowed)
    require(not extra, where, f"unknown key(s) {extra}; allowed: {sorted(allowed)}")


def _table(doc: dict, key: str, where: str) -> dict:
    t = doc.get(key, {})
    require(isinstance(t, dict), f"{where} [{key}]", "must be a table")
    return t


def _name(value, where: str) -> str:
    require(isinstance(value, str) and value.strip() != "" and "/" not in value, where,
           f"must be a non-empty string without '/', got {value!r}")
    return value


def _parse_options(sim: dict, out: dict, where: str) -> Options:
    _unknown(sim, set(_SIM), f"{where} [simulation]")
    kw: dict[str, Any] = {}
    for key in ("restitution", "dt", "duration", "contact_tolerance", "qp_tolerance", "rtol", "atol"):
        if key in sim:
            kw[key] = finite_number(sim[key], f"{where} [simulation] {key}")
    if "gravity" in sim:
        kw["gravity"] = finite_vector(sim["gravity"], 3, f"{where} [simulation] gravity")
    for key, cls in CHOICES.items():
        if key in sim:
            kw[key] = choice(cls, sim[key], f"{where} [simulation] {key}")
    if "save_every" in out:
        kw["save_every"] = out["save_every"]
    try:
        return Options(**kw)
    except SceneError as exc:  # re-label "options: x" as the file's section
        raise SceneError(str(exc).replace("options:", f"{where} [simulation]", 1)) from None


def _parse_body(t: dict, where: str, base: Path, files: dict) -> Body:
    """One [[bodies]] table; `files` keeps the files found in this scene (many bodies share one model file: each
    is looked up once, by its value and package folders)."""
    require(isinstance(t, dict), where, "must be a table")
    _unknown(t, _BODY, where)
    require("mjcf" not in t or "urdf" not in t, where, "give either 'urdf' or 'mjcf', not both")
    for req in ("name", "mjcf" if "mjcf" in t else "urdf", "root_joint"):
        require(req in t, where, f"missing required key '{req}'")
    name = _name(t["name"], f"{where} name")
    w = f"{where} ({name})"
    dirs: list[Path] = []
    if "package_dirs" in t:
        require(isinstance(t["package_dirs"], list) and all(isinstance(d, str) for d in t["package_dirs"]),
               f"{w} package_dirs", f"must be a list of folder paths, got {t['package_dirs']!r}")
        # a folder that does not exist is kept (and listed when a URI resolves nowhere), as in
        # $MOREAU_SIM_PACKAGE_PATH: a scene rebuilt elsewhere (viewer) may find its files otherwise
        dirs = [real_path(base / d, f"{w} package_dirs") for d in t["package_dirs"]]
    key = "mjcf" if "mjcf" in t else "urdf"
    require(isinstance(t[key], str) and t[key] != "", f"{w} {key}", "must be a path string or a package:// URI")
    found = (key, t[key], tuple(dirs))
    if found not in files:
        files[found] = resolve_model_file(t[key], base, dirs, f"{w} {key}")
    urdf = files[found]
    kw: dict[str, Any] = dict(name=name, urdf=urdf, root_joint=choice(RootJoint, t["root_joint"], f"{w} root_joint"),
                              mjcf=key == "mjcf", package_dirs=tuple(dirs))
    if "meshes" in t:
        kw["meshes"] = choice(MeshMode, t["meshes"], f"{w} meshes")
    if "srdf" not in t:  # the SRDF shipped beside a URDF applies unless the scene says otherwise
        if ("srdf", urdf) not in files:
            files["srdf", urdf] = None if kw["mjcf"] else find_srdf(urdf)
        kw["srdf"] = files["srdf", urdf]
    elif t["srdf"] is not False:
        require(isinstance(t["srdf"], str) and t["srdf"] != "", f"{w} srdf",
                f"must be a path string, a package:// URI, or false (no SRDF), got {t['srdf']!r}")
        kw["srdf"] = resolve_model_file(t["srdf"], base, dirs, f"{w} srdf")
    if "joint_limits" in t:
        require(isinstance(t["joint_limits"], bool), f"{w} joint_limits",
                f"must be true or false, got {t['joint_limits']!r}")
        kw["joint_limits"] = t["joint_limits"]
    for key in ("axis", "position", "rpy"):
        if key in t:
            kw[key] = finite_vector(t[key], 3, f"{w} {key}")
    if "axis" in kw:
        require(math.hypot(*kw["axis"]) > 1e-12, f"{w} axis", "must not be zero")
    if "axes" in t:
        require(isinstance(t["axes"], list) and 1 <= len(t["axes"]) <= 3, f"{w} axes", "must be 1 to 3 3-vectors")
        axes = tuple(finite_vector(x, 3, f"{w} axes") for x in t["axes"])
        norms = [math.hypot(*a) for a in axes]
        require(min(norms) > 1e-12 and all(abs(sum(x * y for x, y in zip(a, b))) < 1e-9 * na * nb
                                          for i, (a, na) in enumerate(zip(axes, norms))
                                          for b, nb in zip(axes[i + 1:], norms[i + 1:])),
               f"{w} axes", "must be non-zero and mutually orthogonal")
        kw["axes"] = axes
    rj = kw["root_joint"]
    if rj is RootJoint.PLANAR:
        kw.setdefault("axes", ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)))
        require(len(kw["axes"]) == 2, f"{w} axes", "a planar joint takes exactly two axes")
    elif rj is RootJoint.TRANSLATION:
        kw.setdefault("axes", ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)))
    else:
        require("axes" not in kw, f"{w} axes", "only planar and translation root joints take axes")
    for key in ("q0", "u0"):
        if key in t:
            require(isinstance(t[key], list), f"{w} {key}", "must be a list of numbers")
            kw[key] = finite_vector(t[key], len(t[key]), f"{w} {key}")
    return Body(**kw)


def _parse_static(t: dict, where: str) -> Static:
    require(isinstance(t, dict), where, "must be a table")
    _unknown(t, _STATIC, where)
    for req in ("name", "shape"):
        require(req in t, where, f"missing required key '{req}'")
    name = _name(t["name"], f"{where} name")
    w = f"{where} ({name})"
    kw: dict[str, Any] = dict(name=name, shape=choice(StaticShape, t["shape"], f"{w} shape"))
    for key in ("normal", "size", "position", "rpy"):
        if key in t:
            kw[key] = finite_vector(t[key], 3, f"{w} {key}")
    for key in ("offset", "radius", "length"):
        if key in t:
            kw[key] = finite_number(t[key], f"{w} {key}")
    if "motion" in t:
        kw["motion"] = parse_schedule(t["motion"], 3, f"{w} motion", key="position", moves=True)
    s = Static(**kw)
    require(math.hypot(*s.normal) > 1e-12, f"{w} normal", "must not be zero")
    require(min(s.size) > 0 and s.radius > 0 and s.length > 0, w, "sizes, radius and length must be > 0 m")
    return s


def _parse_actuator(t: dict, where: str) -> Actuator:
    require(isinstance(t, dict), where, "must be a table")
    if "mjcf" in t:
        _unknown(t, _CONTROL, where)
        for req in ("body", "ctrl"):
            require(req in t, where, f"missing required key '{req}' (an entry with 'mjcf' takes body, mjcf, ctrl)")
        body = _name(t["body"], f"{where} body")
        w = f"{where} ({body})"
        names = t["mjcf"]
        if names != "all":
            require(isinstance(names, list) and names and all(isinstance(n, str) and n for n in names),
                    f"{w} mjcf", f"must be \"all\" or a non-empty list of MJCF actuator names, got {names!r}")
            require(len(set(names)) == len(names), f"{w} mjcf", "names an actuator twice")
            names = tuple(names)
        return Actuator(body=body, joints=None, kp=0.0, mjcf=names, ctrl=t["ctrl"], where=w)
    _unknown(t, _ACTUATOR, where)
    for req in ("body", "kp"):
        require(req in t, where, f"missing required key '{req}'")
    body = _name(t["body"], f"{where} body")
    w = f"{where} ({body})"
    joints = t.get("joints", "all")
    if joints == "all":
        joints = None
    else:
        require(isinstance(joints, list) and joints and all(isinstance(j, str) and j for j in joints),
                f"{w} joints", f"must be \"all\" or a non-empty list of joint names, got {joints!r}")
        require(len(set(joints)) == len(joints), f"{w} joints", "names a joint twice")
        joints = tuple(joints)
    kw: dict[str, Any] = dict(body=body, joints=joints, where=w)
    for key in ("kp", "kd", "effort"):
        if key in t:
            kw[key] = finite_number(t[key], f"{w} {key}")
            require(kw[key] >= 0 if key != "effort" else kw[key] > 0, f"{w} {key}",
                    f"must be {'> 0' if key == 'effort' else '>= 0'}, got {kw[key]!r}")
    for key in ("target", "velocity"):
        if key in t:
            kw[key] = t[key]
    return Actuator(**kw)


def _parse_drive(t: dict, where: str) -> DriveSpec:
    require(isinstance(t, dict), where, "must be a table")
    _unknown(t, {"body", "joint", "motion"}, where)
    for req in ("body", "joint", "motion"):
        require(req in t, where, f"missing required key '{req}'")
    body = _name(t["body"], f"{where} body")
    w = f"{where} ({body})"
    joint = t["joint"]
    require(isinstance(joint, str) and joint, f"{w} joint", f"must be a joint name, got {joint!r}")
    require(isinstance(t["motion"], dict), f"{w} motion", "must be a table {velocity}, {sine} or {t, q}")
    return DriveSpec(body=body, joint=joint, motion=parse_schedule(t["motion"], 1, f"{w} motion", key="q",
                                                                    moves=True), where=w)


def _parse_pairs(value, where: str) -> tuple[tuple[str, str], ...]:
    require(isinstance(value, list), where, "must be a list of [name, name] pairs")
    out = []
    for p in value:
        require(isinstance(p, list) and len(p) == 2 and all(isinstance(x, str) for x in p), where,
               f"each entry must be [name, name], got {p!r}")
        out.append((p[0], p[1]))
    return tuple(out)


def parse_scene(text: str, *, path: Path | str | None = None) -> Scene:
    """Parse scene TOML `text`; relative URDF paths resolve against `path`'s folder."""
    where = str(path) if path is not None else "<scene>"
    base = real_path(Path(path), where).parent if path is not None else Path.cwd()
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{where}: malformed TOML: {exc}") from None
    _unknown(doc, _TOP, where)
    head = _table(doc, "scene", where)
    _unknown(head, {"name", "description"}, f"{where} [scene]")
    name = _name(head.get("name", Path(where).stem if path else "scene"), f"{where} [scene] name")
    description = head.get("description", "")
    require(isinstance(description, str), f"{where} [scene] description", "must be a string")
    out = _table(doc, "output", where)
    _unknown(out, {"file", "save_every"}, f"{where} [output]")
    output = out.get("file")
    require(output is None or isinstance(output, str), f"{where} [output] file", "must be a path string")
    options = _parse_options(_table(doc, "simulation", where), out, where)

    bodies_t, statics_t = doc.get("bodies", []), doc.get("statics", [])
    require(isinstance(bodies_t, list), f"{where} [[bodies]]", "must be an array of tables")
    require(isinstance(statics_t, list), f"{where} [[statics]]", "must be an array of tables")
    files: dict = {}
    bodies = tuple(_parse_body(t, f"{where} [[bodies]][{i}]", base, files) for i, t in enumerate(bodies_t))
    statics = tuple(_parse_static(t, f"{where} [[statics]][{i}]") for i, t in enumerate(statics_t))
    names = [b.name for b in bodies] + [s.name for s in statics]
    dup = sorted(n for n, k in Counter(names).items() if k > 1)
    require(not dup, where, f"duplicate body/static names {dup}")

    col = _table(doc, "collisions", where)
    _unknown(col, {"include", "exclude"}, f"{where} [collisions]")
    collisions = Collisions(include=_parse_pairs(col.get("include", []), f"{where} [collisions] include"),
                            exclude=_parse_pairs(col.get("exclude", []), f"{where} [collisions] exclude"))
    act_t = doc.get("actuators", [])
    require(isinstance(act_t, list), f"{where} [[actuators]]", "must be an array of tables")
    actuators = tuple(_parse_actuator(t, f"{where} [[actuators]][{i}]") for i, t in enumerate(act_t))
    body_names = {b.name for b in bodies}
    for a in actuators:
        require(a.body in body_names, f"{a.where} body", f"names no body of the scene ({a.body!r})")
    drive_t = doc.get("drives", [])
    require(isinstance(drive_t, list), f"{where} [[drives]]", "must be an array of tables")
    drives = tuple(_parse_drive(t, f"{where} [[drives]][{i}]") for i, t in enumerate(drive_t))
    for dr in drives:
        require(dr.body in body_names, f"{dr.where} body", f"names no body of the scene ({dr.body!r})")
    return Scene(name=name, description=description, options=options, bodies=bodies, statics=statics,
                 collisions=collisions, actuators=actuators, drives=drives, output=output,
                 path=real_path(Path(path), where) if path else None, source=text)


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene file. Raises :class:`SceneError` naming the file and field."""
    p = Path(path)
    if not p.is_file():
        if p.is_symlink():
            real_path(p, str(p))  # a loop: named as one
            raise SceneError(f"{p}: scene file not found (a symbolic link to {p.readlink()}, which does not exist)")
        raise SceneError(f"{p}: {'not a file' if p.exists() else 'scene file not found'}")
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"{p}: cannot read scene file: {exc}") from None
    return parse_scene(text, path=p)
