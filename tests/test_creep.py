"""The invariant "motion below round-off" (moreau_sim/creep.py, docs/theory.md §10) at the edges of its two
tolerances, on the exact motion of a frictionless cube sliding on the ground at a constant speed v: x = v t. Its
kinetic energy m v^2/2 against the round-off of T + V, ROUND_OFF |E_0| (E_0 = m |g| z + m v^2/2), and the distance
v t against the contact tolerance (the model's reach, a point's motion per unit |u|, is 1 for the cube)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_stack_family import SIDE, _urdf

import moreau_sim as ms
from moreau_sim.invariants import PERSIST, ROUND_OFF, Invariant

CREEP = Invariant.CREEP.value


def slide(v: float, steps: int, h: float, e: float, tmp_path) -> ms.Trajectory:
    """The 1 kg cube of side SIDE resting on the ground, sliding along x at v [m/s], for `steps` steps of h [s]."""
    text = (f'[scene]\nname = "slide"\n[simulation]\nrestitution = {e!r}\ndt = {h!r}\nduration = {steps * h!r}\n'
            f'[[bodies]]\nname = "cube"\nurdf = "{_urdf(1.0)}"\nroot_joint = "free"\n'
            f"position = [0.0, 0.0, {SIDE / 2!r}]\nu0 = [{v!r}, 0.0, 0.0, 0.0, 0.0, 0.0]\n"
            '[[statics]]\nname = "ground"\nshape = "halfspace"\n')
    p = tmp_path / "slide.toml"
    p.write_text(text)
    return ms.run(ms.load_scene(p))


def round_off_speed() -> float:
    """[m/s] the speed of the 1 kg cube whose kinetic energy is the round-off of its T + V: v^2/2 = ROUND_OFF E_0."""
    V0 = 9.81 * SIDE / 2
    return math.sqrt(2.0 * ROUND_OFF * V0 / (1.0 - ROUND_OFF))


def creeps(traj: ms.Trajectory) -> bool:
    return CREEP in {v["invariant"] for v in traj.meta.get("invariants") or ()}


@pytest.mark.parametrize("e", [0.0, 1.0])
@pytest.mark.parametrize("h", [1e-3, 1e-2])
@pytest.mark.parametrize("factor, flagged", [(0.9, False), (1.1, True)])
def test_a_slide_at_round_off_speed_is_flagged_beyond_the_contact_tolerance(h, e, factor, flagged, tmp_path):
    """At a speed within round-off (T = 0.25 ROUND_OFF E_0 at h = 1e-3), 20 steps move the cube the contact
    tolerance: 0.9 of it holds, 1.1 of it is flagged."""
    tol = ms.Options().contact_tolerance
    v = min(0.5 * round_off_speed(), tol / (20 * h))
    steps = round(factor * tol / (v * h))
    traj = slide(v, steps, h, e, tmp_path)
    x = traj.q[:, 0]
    assert np.allclose(x, v * traj.t, rtol=1e-9, atol=1e-20)  # the exact motion, x = v t
    assert abs(x[-1] - factor * tol) <= 0.05 * tol
    assert steps > PERSIST
    assert creeps(traj) is flagged
    assert traj.meta["status"] == ("flagged" if flagged else "complete")


@pytest.mark.parametrize("e", [0.0, 1.0])
@pytest.mark.parametrize("factor, flagged", [(0.9, True), (1.1, False)])
def test_a_slide_just_above_round_off_speed_is_no_creep(e, factor, flagged, tmp_path):
    """The same slide over 100 contact tolerances: at 0.9 of the round-off speed flagged, at 1.1 of it (its
    kinetic energy 1.21 ROUND_OFF E_0, visible to the energy checks) complete."""
    h = 1e-3
    v = factor * round_off_speed()
    traj = slide(v, round(100 * ms.Options().contact_tolerance / (v * h)), h, e, tmp_path)
    assert traj.q[-1, 0] > 90 * ms.Options().contact_tolerance
    assert creeps(traj) is flagged
    assert traj.meta["status"] == ("flagged" if flagged else "complete")
