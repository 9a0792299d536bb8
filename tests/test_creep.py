"""The invariant "motion below round-off" (moreau_sim/creep.py, docs/theory.md §10) at the edges of its two
tolerances, on the exact motion of a frictionless 1 kg cube on the ground pushed along x from rest by a constant
acceleration a (gravity (a, 0, -9.81)): x = a t^2 / 2, which the midpoint step makes exactly, and T = m a x. Its
kinetic energy against the round-off of T + V, ROUND_OFF |E_0| (E_0 = m |g_z| z), and the distance x against the
contact tolerance (the model's reach, a point's motion per unit |u|, is 1 for the cube). A cube coasting at a
constant speed within round-off is no creep."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_stack_family import SIDE, _urdf

import moreau_sim as ms
from moreau_sim.invariants import ROUND_OFF, Invariant

CREEP = Invariant.CREEP.value
TOL = ms.Options().contact_tolerance  # [m]
E0 = 9.81 * SIDE / 2  # [J] the 1 kg cube's T + V at rest on the ground


def push(a: float, steps: int, h: float, e: float, tmp_path, v: float = 0.0) -> ms.Trajectory:
    """The 1 kg cube of side SIDE on the ground, from x = 0 at speed v [m/s], pushed along x by a [m/s^2] for
    `steps` steps of h [s]."""
    a, v = float(a), float(v)
    text = (f'[scene]\nname = "push"\n[simulation]\nrestitution = {e!r}\ndt = {h!r}\nduration = {steps * h!r}\n'
            f"gravity = [{a!r}, 0.0, -9.81]\n"
            f'[[bodies]]\nname = "cube"\nurdf = "{_urdf(1.0)}"\nroot_joint = "free"\n'
            f"position = [0.0, 0.0, {SIDE / 2!r}]\nu0 = [{v!r}, 0.0, 0.0, 0.0, 0.0, 0.0]\n"
            '[[statics]]\nname = "ground"\nshape = "halfspace"\n')
    p = tmp_path / "push.toml"
    p.write_text(text)
    return ms.run(ms.load_scene(p))


def creeps(traj: ms.Trajectory) -> bool:
    return CREEP in {v["invariant"] for v in traj.meta.get("invariants") or ()}


@pytest.mark.parametrize("e", [0.0, 1.0])
@pytest.mark.parametrize("h", [1e-3, 1e-2])
@pytest.mark.parametrize("factor, flagged", [(0.9, False), (1.1, True)])
def test_a_push_within_round_off_is_flagged_beyond_the_contact_tolerance(h, e, factor, flagged, tmp_path):
    """a = 2 TOL / (30 h)^2 (T at most 0.4 ROUND_OFF E_0): about 30 sqrt(factor) steps move the cube x = factor TOL
    (0.87 and 1.07 of it after whole steps): below the tolerance the run holds, beyond it it is flagged."""
    a = 2.0 * TOL / (30 * h) ** 2
    steps = round(30 * math.sqrt(factor))
    traj = push(a, steps, h, e, tmp_path)
    x = traj.q[:, 0]
    assert np.allclose(x, 0.5 * a * traj.t ** 2, rtol=1e-9, atol=1e-22)  # the exact motion
    assert bool(x[-1] > TOL) is flagged and abs(x[-1] / TOL - 1.0) > 0.05
    assert traj.kinetic_energy.max() <= 0.4 * ROUND_OFF * E0
    assert creeps(traj) is flagged
    assert traj.meta["status"] == ("flagged" if flagged else "complete")


@pytest.mark.parametrize("e", [0.0, 1.0])
@pytest.mark.parametrize("factor, flagged", [(0.9, True), (1.1, False)])
def test_a_push_whose_energy_rises_above_round_off_is_no_creep(e, factor, flagged, tmp_path):
    """a = factor ROUND_OFF E_0 / (m TOL): T = m a x reaches ROUND_OFF E_0 at x = TOL / factor. Pushed to 1.5 TOL:
    at 0.9 the whole motion is within round-off and flagged; at 1.1 the energy leaves round-off before x reaches TOL
    (and the energy checks see the rest), complete."""
    h = 1e-3
    a = factor * ROUND_OFF * E0 / TOL
    traj = push(a, math.ceil(math.sqrt(3.0 * TOL / a) / h), h, e, tmp_path)
    assert traj.q[-1, 0] >= 1.5 * TOL
    assert creeps(traj) is flagged
    assert traj.meta["status"] == ("flagged" if flagged else "complete")


@pytest.mark.parametrize("e", [0.0, 1.0])
def test_a_cube_coasting_within_round_off_is_no_creep(e, tmp_path):
    """At a constant speed v with T = 0.25 ROUND_OFF E_0 for 100 contact tolerances: Newton's first law, no creep."""
    h = 1e-3
    v = 0.5 * math.sqrt(2.0 * ROUND_OFF * E0)
    traj = push(0.0, round(100 * TOL / (v * h)), h, e, tmp_path, v=v)
    assert traj.q[-1, 0] > 90 * TOL and not creeps(traj) and traj.meta["status"] == "complete"
