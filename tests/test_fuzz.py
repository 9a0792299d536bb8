"""Property-based fuzz of scene files (hypothesis): every mutation of a bundled scene either
loads, builds and runs to a complete, finite trajectory, or stops with a named SceneError or
SimulationError of one line — never another exception, a crash or a non-finite "complete"."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import tomli_w
from hypothesis import HealthCheck, given, settings, strategies as st

import moreau_sim as ms

from helpers import SCENES

BASES = {name: tomllib.loads((SCENES / f"{name}.toml").read_text()) for name in ("bouncing_ball", "box_drop",
                                                                                  "newton_cradle_5", "rocking_block")}
VALUES = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False, width=64), st.sampled_from([0, -1, 1, 1e-12, 1e300, -1e300]),
    st.integers(-10, 10), st.booleans(), st.text(max_size=12),
    st.lists(st.floats(allow_nan=False, allow_infinity=False, min_value=-1e3, max_value=1e3), max_size=4),
    st.sampled_from(["free", "fixed", "planar", "prismatic", "revolute", "translation", "halfspace", "box",
                     "sphere", "cylinder", "primal", "dual", "elastic", "newton", "none", "bvh", "convex",
                     "../models/ball.urdf", "../models/box.urdf", "nope.urdf", "package://x/y.urdf"]))


def tables(doc):
    """(path, table) of every table of a scene document, including each [[bodies]]/[[statics]] entry."""
    out = [((k,), v) for k, v in doc.items() if isinstance(v, dict)]
    for key in ("bodies", "statics"):
        out += [((key, i), t) for i, t in enumerate(doc.get(key, []))]
    return out


def scaled(value, factor):
    """A number or a list of numbers times factor; other values unchanged."""
    if isinstance(value, bool):
        return value
    if isinstance(value, (int, float)):
        return type(value)(value * factor) if isinstance(value, float) else int(value * factor)
    if isinstance(value, list):
        return [scaled(v, factor) for v in value]
    return value


@st.composite
def mutated(draw):
    name = draw(st.sampled_from(sorted(BASES)))
    doc = tomllib.loads(tomli_w.dumps(BASES[name]))  # a deep copy
    for _ in range(draw(st.integers(1, 3))):
        path, table = draw(st.sampled_from(tables(doc)))
        keys = sorted(table) + ["restitution", "dt", "duration", "gravity", "radius", "size", "axis", "q0", "u0",
                                "root_joint", "urdf", "shape", "normal", "position", "rpy", "unknown_key"]
        key = draw(st.sampled_from(keys))
        old = table.get(key)
        if old is not None and draw(st.booleans()):  # a plausible edit: scale what is there
            factor = draw(st.sampled_from([0.0, 0.5, 2.0, -1.0, 1e-6, 1e6]))
            table[key] = scaled(old, factor)
        elif key in table and draw(st.booleans()):
            del table[key]
        else:
            table[key] = draw(VALUES)
    return name, tomli_w.dumps(doc)


@settings(max_examples=120, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(mutated())
def test_mutated_scenes_fail_by_name_or_run_complete(case):
    name, text = case
    try:
        sc = ms.parse_scene(text, path=SCENES / f"{name}.toml")
        n = sc.options.n_steps
        if n > 200:  # keep each run short: the first 200 steps
            sc = sc.with_options(duration=200 * sc.options.dt)
        traj = ms.simulate(ms.build_model(sc), progress=False)
    except ms.SceneError as exc:
        msg = str(exc)
        assert "\n" not in msg and 0 < len(msg) < 600, msg
        return
    except ms.SimulationError as exc:
        assert str(exc).startswith("step ") and "\n" not in str(exc)
        assert exc.trajectory is not None and not exc.trajectory.complete
        return
    assert traj.complete
    for key in ("q", "u", "kinetic_energy", "potential_energy", "gap"):
        assert np.isfinite(traj.arrays[key]).all(), key
    assert math.isfinite(float(traj.total_energy[-1]))
