"""Contacts (moreau_sim.contacts): the active set at the tolerance, gaps, face-on-face rest.
The rows w_i of the contacts are tested in test_constraints.py."""

import numpy as np
import pytest

import moreau_sim as ms

from helpers import FREE_BOX, GROUND, box_body, scene


def test_active_set_counts_touching_bodies_despite_rounding():
    """Cradle balls at x = 0.2 i computed in floating point (0.6000000000000001): all 4 closed."""
    model = ms.build_model(scene("newton_cradle_5"))
    c = ms.detect(model, ms.make_data(model), model.q0)
    assert c.m == 4
    assert np.abs(c.g).max() <= 1e-15
    assert model.scene.options.contact_tolerance >= 1e6 * np.abs(c.g).max()


def test_separated_pairs_give_no_contact():
    model = ms.build_model(scene("newton_cradle_5_gapped"))
    assert ms.detect(model, ms.make_data(model), model.q0).m == 0


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_box_rests_flat_on_ground_and_on_box(tmp_scene, e):
    """Face on face with the exact height: a box on the ground, a box on a static box (yawed, so
    the faces overlap only partly), a free box on a free box. 1 s: no sinking, no rocking."""
    bodies = (box_body("on_ground", position=(0, 0, 0.2))
              + box_body("on_table", position=(1.0, 0.0, 0.6), rpy=(0, 0, 0.5))
              + box_body("bottom", position=(3.0, 0, 0.2))
              + box_body("top", position=(3.0, 0, 0.6), rpy=(0, 0, 0.3)))
    statics = GROUND + ('[[statics]]\nname = "table"\nshape = "box"\nsize = [0.3, 0.3, 0.4]\n'
                        'position = [1.0, 0.0, 0.2]\n')
    model = ms.build_model(tmp_scene(FREE_BOX.format(g=-9.81, e=e, T=1.0, bodies=bodies + statics)))
    traj = ms.simulate(model, progress=False)
    q0, q1 = traj.q[0], traj.q[-1]
    assert np.abs(q1 - q0).max() <= 1e-6  # exact height and orientation, to 1e-6
    assert np.abs(traj.u).max() <= 1e-9  # still: no rocking, no creeping
    assert traj.n_contacts[-1] >= 4 * 3  # every face rests on >= 4 points (box-box: 4 + 4 duplicates)


BALL_R = 0.1  # bouncing_ball: radius [m]; its coordinate is the centre's height


@pytest.mark.parametrize("gap,closed", [(1e-7, False), (1e-8, False), (1e-10, True), (0.0, True)])
def test_a_pair_closes_at_the_contact_tolerance(gap, closed):
    """options.contact_tolerance = 1e-9 m: a ball 1e-7 m (or 1e-8 m) above the ground is open, at
    1e-10 m closed; at exact contact its gap is 0 to 1e-15 m."""
    model = ms.build_model(scene("bouncing_ball"))
    assert model.options.contact_tolerance == 1e-9
    c = ms.detect(model, ms.make_data(model), np.array([BALL_R + gap]))
    assert c.m == int(closed)
    if closed:
        assert abs(c.g[0] - gap) <= 1e-15


def test_a_ball_just_above_the_tolerance_falls_and_rests_at_zero_gap():
    """A ball released at rest 5e-8 m above the ground (open at the 1e-9 m tolerance) falls, lands
    and rests with gap 0 to 1e-15 m (the impact, then the position correction). With a tolerance
    above 5e-8 m the contact would be closed at once and the ball would hover 5e-8 m up."""
    model = ms.build_model(scene("bouncing_ball", duration=0.1))
    state = ms.State(0.0, np.array([BALL_R + 5e-8]), np.array([0.0]))
    traj = ms.simulate(model, state=state, progress=False)
    assert traj.impacts >= 1
    assert np.abs(traj.gap[-20:, 0]).max() <= 1e-15
    assert np.abs(traj.u[-20:, 0]).max() <= 1e-15


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_a_point_within_same_point_of_a_contact_is_that_contact(axis):
    """contacts.SAME_POINT at its edge: an edge crossing or face corner whose point on A is SAME_POINT (in the max
    norm) from a contact the pair already has is that contact (dropped); the next float beyond is a contact of its
    own; and a face corner as close to an edge crossing is that crossing."""
    from moreau_sim.contacts import SAME_POINT, FeatureKind, _add_new

    def row(x, kind, feature):
        p = np.zeros(3)
        p[axis] = x
        return (-1e-6, p, p.copy(), np.array([0.0, 0.0, 1.0]), 0, kind, feature)

    beyond = np.nextafter(SAME_POINT, np.inf)
    vertex = row(0.0, FeatureKind.VERTEX, 0)
    for kind in (FeatureKind.EDGE, FeatureKind.FACE):
        for d, kept in ((SAME_POINT, False), (beyond, True), (-SAME_POINT, False), (-beyond, True)):
            found = [vertex]
            _add_new(found, 0, [row(d, kind, 5)])
            assert [r[5] for r in found[1:]] == ([kind] if kept else [])
    for d, kept in ((SAME_POINT, False), (beyond, True)):  # no earlier contact: a corner at a crossing is it
        found = []
        _add_new(found, 0, [row(0.0, FeatureKind.EDGE, 5), row(d, FeatureKind.FACE, 1)])
        assert [r[5] for r in found] == [FeatureKind.EDGE] + ([FeatureKind.FACE] if kept else [])
