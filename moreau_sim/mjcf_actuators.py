"""MJCF ``<actuator>`` read onto the joint torques of actuation.py: ``<motor>`` and ``<position>`` on hinge and
slide joints, as MuJoCo computes them (docs/robots.md#mjcf-actuators): the control c clamped to ctrlrange,
the actuator force F = gain c + b1 (gear q) + b2 (gear u) clamped to forcerange, the joint torque
tau = gear F (motor: gain 1, b = 0; position: gain kp, b1 = -kp, b2 = -kv), and the sum of a joint's
actuators clamped to that joint's actuatorfrcrange (MuJoCo's qfrc_actuator). c comes from the scene
([[actuators]] mjcf/ctrl), 0 when not given (MuJoCo's default). Anything else under <actuator> (other kinds,
transmissions, activation dynamics) is refused with file:line."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .joints import find_joint, one_dof
from .errors import SceneError
from .prescribed import Schedule
from .robots import _at, _joint_defaults, _mjcf_expanded, default_classes

KINDS = frozenset({"motor", "position"})
# attributes of a motor / position that are read; harmless ones (drawing, user data) are skipped
_COMMON = {"joint", "gear", "ctrlrange", "ctrllimited", "forcerange", "forcelimited"}
_OWN = {"motor": _COMMON, "position": _COMMON | {"kp", "kv"}}
_HARMLESS = {"name", "class", "group", "user"}


@dataclass(frozen=True)
class MJCFActuator:
    """One MJCF actuator: name (the MJCF name, else "actuator K" by its place in <actuator>), kind ("motor" |
    "position"), joint (the MJCF joint name), gear (its first entry), kp [N/rad or N/m per unit of gear]
    and kv (position; 0 for a motor), ctrl and force ranges (-inf, inf: unlimited), where: file:line;
    jointrange: its joint's actuatorfrcrange [N m or N], the clamp of the sum of the joint's actuators (-inf, inf:
    none)."""

    name: str
    kind: str
    joint: str
    gear: float
    kp: float
    kv: float
    ctrlrange: tuple[float, float]
    forcerange: tuple[float, float]
    where: str
    jointrange: tuple[float, float] = (-np.inf, np.inf)


_ACTUATOR_TAGS = ("general", "motor", "position", "velocity", "intvelocity", "damper", "cylinder", "muscle",
                  "adhesion")


def _defaults(tree: ET.Element) -> dict[str, dict[str, tuple[str, ET.Element]]]:
    """The actuator attributes each <default> class gives (MuJoCo keeps one actuator default per class, set by
    any of <general>, <motor>, <position>, ...; nested classes inherit: robots.default_classes), each with the
    element that set it."""
    return default_classes(tree, lambda d: {k: (v, el) for el in d if el.tag in _ACTUATOR_TAGS
                                            for k, v in el.attrib.items()})


def _range(a: dict, key: str, auto: bool, at: str, where: str) -> tuple[float, float]:
    """(lo, hi) of ctrlrange/forcerange under MuJoCo's limited rule (module note of robots.mjcf_joint_limits)."""
    flag = a.get(key.replace("range", "limited"), "auto")
    text = a.get(key)
    if not (flag == "true" or (flag == "auto" and auto and text is not None)):
        return -np.inf, np.inf
    try:
        lo, hi = (float(x) for x in (text or "").split())
    except ValueError:
        raise SceneError(f"{at}: {key}={text!r} is not two numbers (lower upper) [{where} mjcf]") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise SceneError(f"{at}: {key} {lo:g} {hi:g} must be finite with lower < upper [{where} mjcf]")
    return lo, hi


def _joint_ranges(tree: ET.Element, path: Path, auto: bool, where: str) -> dict[str, tuple[float, float]]:
    """{joint name: its actuatorfrcrange} of every joint that has one under MuJoCo's limited rule
    (actuatorfrclimited; the joint's attributes over its class's: class, else the nearest childclass above it,
    as robots.mjcf_joint_limits reads range)."""
    defaults = _joint_defaults(tree)
    out: dict[str, tuple[float, float]] = {}

    def visit(el: ET.Element, childclass: str) -> None:
        for child in el:
            if child.tag == "body":
                visit(child, child.get("childclass", childclass))
            elif child.tag == "joint":
                a = {**defaults.get(child.get("class", childclass), {}), **child.attrib}
                rng = _range(a, "actuatorfrcrange", auto, f"{_at(child, path)}: joint '{a.get('name', '?')}'", where)
                if np.isfinite(rng[0]):
                    out[a.get("name", "?")] = rng

    for w in tree.findall("worldbody"):
        visit(w, "main")
    return out


def _number(a: dict, key: str, default: float, at: str, where: str) -> float:
    text = a.get(key)
    if text is None:
        return default
    try:
        x = float(text.split()[0])
    except (ValueError, IndexError):
        raise SceneError(f"{at}: {key}={a.get(key)!r} is not a number [{where} mjcf]") from None
    if not np.isfinite(x):
        raise SceneError(f"{at}: {key} must be finite, got {x!r} [{where} mjcf]")
    return x


def read(path: Path, where: str) -> tuple[MJCFActuator, ...]:
    """The actuators of an MJCF file (after its includes are expanded), in file order. SceneError (one
    line, file:line) for an attribute that would change the motion and is not read (a transmission other
    than a joint, dampratio, timeconst, inheritrange, ...) or a malformed value."""
    tree = _mjcf_expanded(path, where)
    compiler: dict[str, str] = {}
    for c in tree.findall("compiler"):
        compiler.update(c.attrib)
    auto = compiler.get("autolimits", "true") == "true"
    defaults = _defaults(tree)
    joint_ranges = _joint_ranges(tree, path, auto, where)
    out: list[MJCFActuator] = []
    for block in tree.findall("actuator"):
        for el in block:
            if not isinstance(el.tag, str):
                continue
            at = _at(el, path)
            if el.tag not in KINDS:  # check_mjcf refuses it at load already; kept for direct callers
                raise SceneError(f"{at}: <{el.tag}> is not supported (MJCF actuators read: <motor>, <position>) "
                                 f"[{where} mjcf]")
            cls = el.get("class", "main")
            if cls not in defaults:
                raise SceneError(f"{at}: class {cls!r} names no <default> class [{where} mjcf]")
            inherited = defaults[cls]
            for k, (_, d) in inherited.items():
                if k not in _OWN[el.tag] | _HARMLESS | {"kp", "kv"} and k not in el.attrib:
                    raise SceneError(f"{_at(d, path)}: the default attribute {k}=... (of class {cls!r}, used by "
                                     f"{at}) is not supported on an MJCF <{el.tag}> [{where} mjcf]")
            for k in el.attrib:
                if k not in _OWN[el.tag] | _HARMLESS:
                    raise SceneError(f"{at}: <{el.tag} {k}=...> is not supported (read: "
                                     f"{', '.join(sorted(_OWN[el.tag]))}; the transmission must be a joint) "
                                     f"[{where} mjcf]")
            a = {**{k: v for k, (v, _) in inherited.items()}, **el.attrib}
            name = el.get("name") or f"actuator {len(out)}"
            if "joint" not in a:
                raise SceneError(f"{at}: <{el.tag}> '{name}' has no joint=\"...\" (the only transmission read) "
                                 f"[{where} mjcf]")
            gear = _number(a, "gear", 1.0, at, where)
            if len((a.get("gear") or "1").split()) > 1 and any(float(x) for x in a["gear"].split()[1:]):
                raise SceneError(f"{at}: gear {a['gear']!r}: only the first entry acts on a hinge or slide joint; "
                                 f"the others must be 0 [{where} mjcf]")
            kp = _number(a, "kp", 1.0, at, where) if el.tag == "position" else 0.0
            kv = _number(a, "kv", 0.0, at, where) if el.tag == "position" else 0.0
            if kp < 0 or kv < 0:
                raise SceneError(f"{at}: kp and kv must be >= 0 [{where} mjcf]")
            out.append(MJCFActuator(name, el.tag, a["joint"], gear, kp, kv, _range(a, "ctrlrange", auto, at, where),
                                    _range(a, "forcerange", auto, at, where), at,
                                    joint_ranges.get(a["joint"], (-np.inf, np.inf))))
    names = [x.name for x in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise SceneError(f"{path}: actuator name(s) {dup} given twice [{where} mjcf]")
    return tuple(out)


class Servos:
    """The MJCF actuators of one body resolved on the scene's model: q and v index of each actuator's joint
    and the arrays of :class:`MJCFActuator`; ctrl: the control schedule of each actuator (None: 0); joint_clamps:
    each joint with an actuatorfrcrange, (its actuators' indices, (lower, upper)) [N m or N]."""

    def __init__(self, body: str, specs: tuple[MJCFActuator, ...], q_index, v_index, ctrl: list[Schedule | None],
                 joint_names: list[str]):
        self.name, self.specs, self.joint_names = body, specs, joint_names
        self.q_index, self.v_index = np.asarray(q_index, int), np.asarray(v_index, int)
        self.gear = np.array([s.gear for s in specs])
        self.gain = np.array([1.0 if s.kind == "motor" else s.kp for s in specs])
        self.kp = np.array([s.kp for s in specs])
        self.kv = np.array([s.kv for s in specs])
        self.clo, self.chi = (np.array([s.ctrlrange[i] for s in specs]) for i in (0, 1))
        self.flo, self.fhi = (np.array([s.forcerange[i] for s in specs]) for i in (0, 1))
        self.ctrl = ctrl
        self._zero = all(c is None for c in ctrl)
        self.joint_clamps: list[tuple[np.ndarray, tuple[float, float]]] = []
        for v in dict.fromkeys(self.v_index.tolist()):
            idx = np.flatnonzero(self.v_index == v)
            if np.isfinite(specs[idx[0]].jointrange[0]):
                self.joint_clamps.append((idx, specs[idx[0]].jointrange))

    def control(self, t: float) -> np.ndarray:
        """c(t), clamped to ctrlrange."""
        c = np.zeros(len(self.specs))
        if not self._zero:
            for i, s in enumerate(self.ctrl):
                if s is not None:
                    c[i] = s.at(t)[0][0]
        return np.clip(c, self.clo, self.chi)

    def torque(self, t: float, q: np.ndarray, u: np.ndarray) -> np.ndarray:
        """tau of each actuator (on v_index; two on one joint add), [N m or N]. On a joint with an
        actuatorfrcrange the sum of its actuators (in their order) clamped to it is the first one's entry and
        the others' are 0 (MuJoCo clamps qfrc_actuator, the sum, not each actuator's force)."""
        g = self.gear
        f = self.gain * self.control(t) - self.kp * (g * q[self.q_index]) - self.kv * (g * u[self.v_index])
        tau = g * np.clip(f, self.flo, self.fhi)
        for idx, (lo, hi) in self.joint_clamps:
            total = 0.0
            for i in idx:
                total += float(tau[i])
            tau[idx] = 0.0
            tau[idx[0]] = min(max(total, lo), hi)
        return tau

    def describe(self) -> list[dict]:
        return [{"name": f"{self.name}/{s.name}", "joint": j, "kind": f"mjcf {s.kind}", "gear": s.gear,
                 **({"kp": s.kp, "kv": s.kv} if s.kind == "position" else {}),
                 "ctrlrange": _finite(s.ctrlrange), "forcerange": _finite(s.forcerange),
                 **({"actuatorfrcrange": _finite(s.jointrange)} if np.isfinite(s.jointrange[0]) else {}),
                 "ctrl": "scene" if c is not None else "0"}
                for s, j, c in zip(self.specs, self.joint_names, self.ctrl)]


def _finite(r: tuple[float, float]) -> list[float] | None:
    return None if not np.isfinite(r[0]) else [float(r[0]), float(r[1])]


def build(pm, info, specs: tuple[MJCFActuator, ...], ctrl: dict[str, Schedule], where: str) -> Servos:
    """The Servos of body `info` (model.BodyInfo) in the scene's Pinocchio model `pm`; ctrl: the scene's
    control schedule by actuator name. SceneError naming the actuator's line for a joint that is not a
    hinge or slide of the body."""
    qi, vi, names = [], [], []
    for s in specs:
        full = f"{info.name}/{s.joint}"
        j = find_joint(pm, info.name, s.joint)
        if j is None:
            raise SceneError(f"{s.where}: actuator '{s.name}': joint '{s.joint}' names no joint of the model "
                             f"[{where} mjcf]")
        jm = pm.joints[j]
        if not one_dof(pm, j):
            raise SceneError(f"{s.where}: actuator '{s.name}' on joint '{s.joint}': only hinge and slide joints "
                             f"are actuated [{where} mjcf]")
        qi.append(jm.idx_q)
        vi.append(jm.idx_v)
        names.append(full)
    return Servos(info.name, specs, qi, vi, [ctrl.get(s.name) for s in specs], names)

