"""Functions of time given in a scene: the schedules of joint targets (actuation.py) and the prescribed
motion of a static obstacle, whose velocity enters the impact law as the constraint's own time
derivative (the rheonomic case, docs/theory.md §2.9). Parsing with one-line errors naming the field
(docs/scenes.md); positions [m or rad], velocities [m/s or rad/s], times [s]."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from .errors import SceneError
from .options import finite_number, finite_vector, require
from .sums import dot3


@dataclass(frozen=True)
class Schedule:
    """x(t) and its derivative, n components: constant (`t` empty, `x` one row), a table (`t`
    increasing, `x` one row per time: linear interpolation, held before the first and after the
    last time; the velocity is the slope of the segment holding t, right-continuous), or a sine
    x = offset + amplitude sin(2 pi frequency t + phase)."""

    kind: str  # "constant" | "table" | "sine"
    x: np.ndarray  # (k, n): the rows (constant: one row; sine: the offset)
    t: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (k,) table times [s]
    amplitude: np.ndarray = field(default_factory=lambda: np.zeros(0))  # sine amplitudes (n,)
    frequency: float = 0.0  # [Hz]
    phase: float = 0.0  # [rad]
    rate: np.ndarray | None = None  # constant velocity (n,) of a "velocity" motion (x = x0 + rate t)

    @property
    def n(self) -> int:
        return self.x.shape[1]

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(x(t), dx/dt(t))."""
        if self.kind == "sine":
            w = 2.0 * math.pi * self.frequency
            s = w * t + self.phase
            return self.x[0] + self.amplitude * math.sin(s), self.amplitude * (w * math.cos(s))
        if self.rate is not None:
            return self.x[0] + self.rate * t, self.rate
        if self.kind == "constant" or t < self.t[0]:
            return self.x[0], np.zeros(self.n)
        k = int(np.searchsorted(self.t, t, side="right")) - 1
        if k >= len(self.t) - 1:
            return self.x[-1], np.zeros(self.n)
        dt = self.t[k + 1] - self.t[k]
        v = (self.x[k + 1] - self.x[k]) / dt
        return self.x[k] + v * (t - self.t[k]), v


def constant(x) -> Schedule:
    return Schedule("constant", np.atleast_2d(np.asarray(x, float)))


def parse_schedule(value, n: int, where: str, *, key: str = "x", moves: bool = False) -> Schedule:
    """A schedule of n components from TOML: a number (n = 1) or a list of n numbers (constant); a table
    {t = [...], <key> = [rows]}; {sine = {amplitude, frequency, phase, offset}}; and with `moves` also
    {velocity = [...]} (constant velocity from 0 at t = 0)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        require(n == 1, where, f"must be a list of {n} numbers, got {value!r}")
        return constant([finite_number(value, where)])
    if isinstance(value, list):
        return constant(finite_vector(value, n, where))
    require(isinstance(value, dict), where,
            f"must be a number, a list, a table {{t, {key}}} or {{sine}}, got {value!r}")
    kinds = [k for k in ("t", "sine") + (("velocity",) if moves else ()) if k in value]
    require(len(kinds) == 1, where, f"give exactly one of {['t', 'sine'] + (['velocity'] if moves else [])}")
    if kinds[0] == "velocity":
        require(set(value) == {"velocity"}, where, "a constant-velocity motion takes only 'velocity'")
        v = value["velocity"]
        rate = np.array(finite_vector([v] if n == 1 and not isinstance(v, list) else v, n, f"{where} velocity"))
        return Schedule("constant", np.zeros((1, n)), rate=rate)
    if kinds[0] == "sine":
        require(set(value) == {"sine"}, where, "a sine takes only the 'sine' table")
        s = value["sine"]
        require(isinstance(s, dict), f"{where} sine", "must be a table {amplitude, frequency, phase, offset}")
        extra = sorted(set(s) - {"amplitude", "frequency", "phase", "offset"})
        require(not extra, f"{where} sine", f"unknown key(s) {extra}; allowed: amplitude, frequency, phase, offset")
        for req in ("amplitude", "frequency"):
            require(req in s, f"{where} sine", f"missing required key '{req}'")

        def vec(v, w):
            return finite_vector([v] if n == 1 and not isinstance(v, list) else v, n, w)
        amp = np.array(vec(s["amplitude"], f"{where} sine amplitude"))
        f = finite_number(s["frequency"], f"{where} sine frequency")
        require(f > 0, f"{where} sine frequency", f"must be > 0 Hz, got {f!r}")
        phase = finite_number(s.get("phase", 0.0), f"{where} sine phase")
        offset = np.array(vec(s.get("offset", [0.0] * n), f"{where} sine offset"))
        return Schedule("sine", offset[None, :], amplitude=amp, frequency=f, phase=phase)
    extra = sorted(set(value) - {"t", key})
    require(not extra, where, f"unknown key(s) {extra}; a table takes 't' and '{key}'")
    require(key in value, where, f"a table needs '{key}' beside 't'")
    t, rows = value["t"], value[key]
    require(isinstance(t, list) and len(t) >= 2, f"{where} t", "must be a list of at least 2 times")
    ts = np.array(finite_vector(t, len(t), f"{where} t"))
    require(bool((np.diff(ts) > 0).all()), f"{where} t", "must be strictly increasing")
    require(isinstance(rows, list) and len(rows) == len(ts), f"{where} {key}",
            f"must hold {len(ts)} rows (one per time)")
    x = np.array([finite_vector([r] if n == 1 and not isinstance(r, list) else r, n, f"{where} {key}") for r in rows])
    return Schedule("table", x, t=ts)


@dataclass(frozen=True)
class Moving:
    """A static obstacle that follows a schedule: geometry id, its placement at t = 0 less x(0),
    the schedule of its displacement [m] (a translation; orientation fixed)."""

    geometry: int
    base: pin.SE3
    schedule: Schedule


class Prescribed:
    """The moving statics of a model: `place(geom, t)` puts them where they are at t [s] (the geometry
    model's placements: detection and distances at t read them); `rates(contacts, t)` the constraint's
    own time derivative dg_i/dt = -n_i . V(t) of each contact i against a moving static (0 elsewhere),
    V the obstacle's velocity, n_i from the static towards the body (docs/theory.md §2.9)."""

    def __init__(self, moving: tuple[Moving, ...]):
        self.moving = moving
        self._by_geometry = {m.geometry: m for m in moving}

    def place(self, geom: pin.GeometryModel, t: float) -> None:
        for m in self.moving:
            x, _ = m.schedule.at(t)
            go = geom.geometryObjects[m.geometry]
            go.placement = pin.SE3(m.base.rotation, m.base.translation + x)

    def velocity(self, geometry: int, t: float) -> np.ndarray:
        return self._by_geometry[geometry].schedule.at(t)[1]

    def rates(self, pairs, contacts, t: float) -> np.ndarray | None:
        """(m,) dg_i/dt [m/s] of the contacts at t, None when no contact meets a moving static."""
        out = None
        for i, p in enumerate(contacts.pair.tolist()):
            if p >= len(pairs):  # a joint limit (limits.py): no static
                continue
            pair = pairs[p]
            for g, sign in ((pair.second, -1.0), (pair.first, 1.0)):  # the normal points from second to first
                m = self._by_geometry.get(g)
                if m is not None:
                    out = np.zeros(contacts.m) if out is None else out
                    out[i] += sign * dot3(contacts.normal[i], m.schedule.at(t)[1])  # in order (§2.8)
        return out


def build(geom: pin.GeometryModel, statics, first: int, pairs, vertices, where: str) -> Prescribed | None:
    """The moving statics of a model (None if none), placed at t = 0: statics the scene's, whose geometry
    ids start at `first`; pairs, vertices: the model's. A moving static and what it meets must be shapes
    without vertices (half-space, sphere, cylinder, capsule): the detection keeps polytope vertices and
    distance bounds in the statics' placements at build (contacts.py, model.bounds), which a moving one
    leaves. SceneError otherwise."""
    moving = tuple(Moving(first + k, geom.geometryObjects[first + k].placement.copy(), s.motion)
                   for k, s in enumerate(statics) if s.motion is not None)
    if not moving:
        return None
    out = Prescribed(moving)
    for p in pairs:
        for g, other in ((p.first, p.second), (p.second, p.first)):
            if g in out._by_geometry and (len(vertices[other]) or len(vertices[g])):
                poly = geom.geometryObjects[other if len(vertices[other]) else g].name
                raise SceneError(f"{where} [[statics]] ({geom.geometryObjects[g].name}) motion: the pair "
                                 f"{geom.geometryObjects[p.first].name}|{geom.geometryObjects[p.second].name} "
                                 f"has a polytope ({poly}): a moving static and what it meets must be shapes without "
                                 "vertices (half-space, sphere, cylinder, capsule) in this version")
    out.place(geom, 0.0)
    return out
