"""Options and the closed choices (moreau_sim.options): enums round-trip their scene-file strings,
validation errors name the field, and the defaults, with no override, give the physics they stand
for (docs/theory.md §2.4 midpoint bias, §2.5 position correction, §6 contact tolerance)."""

import dataclasses

import numpy as np
import pytest

import moreau_sim as ms
from moreau_sim.options import CHOICES, Options

from helpers import run, scene

ENUMS = [ms.RootJoint, ms.QPForm, ms.Separating, ms.Tunnelling, ms.Integrator, ms.SlowImpacts, ms.Bias,
         ms.PositionCorrection, ms.StaticShape, ms.MeshMode, ms.Selection]


@pytest.mark.parametrize("cls", ENUMS, ids=lambda c: c.__name__)
def test_enums_round_trip_their_strings(cls):
    for member in cls:
        assert isinstance(member.value, str) and cls(member.value) is member


def test_options_round_trip_through_their_dict():
    """to_dict gives the scene-file strings; replace(**dict) gives the same Options back."""
    changed = Options().replace(restitution=0.3, dt=2e-3, gravity=[0, 0, -1], qp_form="dual", bias="explicit",
                                separating="newton", corner_selection="symmetric", tunnelling="none")
    d = changed.to_dict()
    assert d["qp_form"] == "dual" and d["bias"] == "explicit" and d["gravity"] == [0.0, 0.0, -1.0]
    assert Options().replace(**d) == changed
    assert set(d) == {f.name for f in dataclasses.fields(Options)}
    assert set(CHOICES) <= set(d)


BAD = [("restitution", 1.5), ("restitution", -0.1), ("dt", 0.0), ("dt", float("nan")), ("duration", -1.0),
       ("gravity", (0.0, float("inf"), 0.0)), ("contact_tolerance", 1e-2), ("contact_tolerance", -1e-9),
       ("qp_tolerance", 0.0), ("save_every", 0), ("save_every", 1.5), ("qp_form", "primal"), ("bias", None)]


@pytest.mark.parametrize("field,value", BAD)
def test_validation_errors_name_the_field(field, value):
    with pytest.raises(ms.SceneError, match=rf"^options: {field}: "):
        Options(**{field: value})


@pytest.mark.parametrize("field", sorted(CHOICES))
def test_unknown_choice_names_the_field_and_the_allowed_values(field):
    allowed = [m.value for m in CHOICES[field]]
    with pytest.raises(ms.SceneError, match=rf"options: {field}: must be one of .*{allowed[0]}"):
        Options().replace(**{field: "no-such-choice"})


# --------------------------------------------------------------------- the defaults' physics

def test_default_bias_keeps_a_free_rotation_s_energy():
    """spinning_box with default options: the free brick's kinetic energy is kept to 1e-12 relative
    over 1 s of free flight (measured 2e-15: the midpoint bias, the gyroscopic term does no work);
    the explicit bias drifts by 1.8e-5 over the same second."""
    assert Options().bias is ms.Bias.MIDPOINT
    T = run("spinning_box", duration=1.0).kinetic_energy
    assert np.abs(T - T[0]).max() <= 1e-12 * T[0]
    T = run("spinning_box", duration=1.0, bias="explicit").kinetic_energy
    assert np.abs(T - T[0]).max() >= 1e-6 * T[0]


@pytest.mark.parametrize("h", [1e-2, 1e-3])
def test_default_position_correction_lifts_a_plastic_landing_onto_the_ground(h):
    """bouncing_ball, e = 0, default rules: the landing step ends h|u|/2 deep; the correction lifts the
    ball onto the ground (correction energy > 0: 0.27 J at h = 1e-2) and from the landing on no
    sample is below the ground by more than the contact tolerance (measured: gap exactly 0). Without
    the correction the ball rests 28 mm (h = 1e-2) inside."""
    assert Options().position_correction is ms.PositionCorrection.PROJECTION
    traj = run("bouncing_ball", restitution=0.0, dt=h)
    tol = scene("bouncing_ball").options.contact_tolerance
    assert traj.correction_energy.sum() > 0.0
    landed = traj.t >= traj.log_t[traj.log_impact][0] + h
    assert landed.sum() > 100
    assert traj.gap[landed].min() >= -tol
