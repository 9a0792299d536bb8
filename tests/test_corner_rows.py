"""One row per touching point (docs/theory.md §6.2, 1b): where a vertex of A on B's face and a vertex of B on A's face
of the same pair are at the same point (contacts.SAME_POINT) with normals equal to within contacts.TWIN_NORMAL, the
detection keeps one row, A's vertex's, in both steps (contacts.detect, src/step.cpp Stepper::detect). Two equal
cubes stacked face on face touch at their 4 corners: 4 rows, not 8 (the twins' normals 1e-14 to 1e-13 rad apart made
G_AA ill-conditioned under a 1e5 kg load and let the active set put a corner's percussion on either twin: a 1 kg cube
yawed at 1.25e-8 rad/s where the exact projection gives 3e-17, docs/theory.md §2.11). The rule at its edges (the
point within / beyond SAME_POINT, the normals within / beyond TWIN_NORMAL), both steps bit for bit, and the heavy
stacks' rest over e and h."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_compiled_rows import _bits, _steps as _steps_counted
from test_stack_family import SIDE, stack

import moreau_sim as ms
import moreau_sim.compiled as compiled
from moreau_sim.contacts import SAME_POINT, TWIN_NORMAL, FeatureKind, _twin

HEAVY = [1.0, 1e3, 1.0, 1e5]  # the traced draw of docs/theory.md §2.11 (bottom to top)


@pytest.fixture(scope="module", autouse=True)
def _compiled():
    assert compiled.available(), compiled.unavailable_reason()


def _steps(sc: ms.Scene, k: int) -> dict:
    """k steps of `sc` from its initial state by each step implementation: {impl: [StepResult, ...]}."""
    return {impl: rs for impl, (rs, _, _) in _steps_counted(sc, k).items()}


def _same(a, b) -> None:
    """Two StepResults with the same contacts and the same bits."""
    assert a.contacts.m == b.contacts.m
    for f in ("pair", "kind", "feature"):
        assert getattr(a.contacts, f).tolist() == getattr(b.contacts, f).tolist()
    for x, y in ((a.contacts.point_a, b.contacts.point_a), (a.contacts.normal, b.contacts.normal),
                 (a.state.q, b.state.q), (a.state.u, b.state.u), (a.P, b.P)):
        assert _bits(x) == _bits(y)


def _row(p, n) -> tuple:
    return (0.0, np.asarray(p, float), np.zeros(3), np.asarray(n, float), 0, FeatureKind.VERTEX, 0)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_the_rule_at_its_edges(axis):
    """A vertex of B is A's vertex's twin when its point on A is within SAME_POINT (max-norm) and its normal within
    TWIN_NORMAL in every component; just beyond either, a row of its own."""
    n = np.array([0.0, 0.0, 1.0])
    a = _row([0.05, -0.05, 0.1], n)
    for d, twin in ((SAME_POINT, True), (np.nextafter(SAME_POINT, np.inf), False)):
        for s in (1.0, -1.0):
            p = np.zeros(3)
            p[axis] = s * d
            p = np.array([0.05, -0.05, 0.1]) + p
            d_exact = float(np.abs(p - a[1]).max())  # the offset as the rule measures it (the sum rounds)
            assert _twin([a], _row(p, n)) is (d_exact <= SAME_POINT)
            if d_exact == d:
                assert _twin([a], _row(p, n)) is twin
    for d, twin in ((TWIN_NORMAL, True), (np.nextafter(TWIN_NORMAL, np.inf), False)):
        for s in (1.0, -1.0):
            m = np.zeros(3)
            m[axis] = s * d
            b = _row([0.05, -0.05, 0.1], m if axis == 2 else n + m)
            if axis == 2:  # the normal's own component: n + m rounds; measure as the rule does
                b = _row([0.05, -0.05, 0.1], n + m)
                assert _twin([a], b) is (float(np.abs(n + m - n).max()) <= TWIN_NORMAL)
            else:
                assert _twin([a], b) is twin
    assert not _twin([], a)


def _two_cubes(tilt: float, h: float = 1e-3, e: float = 0.0) -> ms.Scene:
    """Two 1 kg cubes on the ground, the upper one turned by `tilt` [rad] about x (its lowest vertices at the lower
    cube's top face)."""
    sc = stack([1.0, 1.0], h, e, "time-stepping")
    z = SIDE / 2 + SIDE + 0.5 * SIDE * (np.cos(tilt) - 1.0 + np.sin(abs(tilt)))  # the lowest bottom vertex at 0.1 m
    y = -0.5 * SIDE * np.sin(tilt)  # its bottom vertices over the lower cube's top vertices
    upper = dataclasses.replace(sc.bodies[1], position=(0.0, float(y), float(z)), rpy=(float(tilt), 0.0, 0.0))
    return dataclasses.replace(sc, bodies=(sc.bodies[0], upper))


@pytest.mark.parametrize("tilt, rows", [(0.0, 4), (0.5 * TWIN_NORMAL, 4), (-0.5 * TWIN_NORMAL, 4),
                                        (1.5 * TWIN_NORMAL, 8), (-1.5 * TWIN_NORMAL, 8)])
def test_two_stacked_cubes_touch_at_four_points(tilt, rows):
    """Aligned cubes face on face: each corner is one row (A's vertex), the 4 corners of the face; the upper cube
    tilted by half TWIN_NORMAL, still 4 (its vertices 2.5e-10 m from the lower one's, within SAME_POINT); by 1.5
    TWIN_NORMAL, the two faces' normals are told apart and each corner is two rows (it was 6: at the two high corners
    both vertices took coal's normal, vertical here but 63 degrees off at 2e-9 rad, and were twins; docs/theory.md
    §6.2, 1c). Both steps, the same bits."""
    got = _steps(_two_cubes(tilt), 1)
    a, b = got["python"][0], got["compiled"][0]
    _same(a, b)
    c = a.contacts
    upper = c.pair != c.pair[np.argmin(c.point_a[:, 2])]  # the cube-cube pair (the ground's rows are at z = 0)
    assert int(upper.sum()) == rows, c.feature[upper].tolist()
    assert set(c.kind[upper].tolist()) == {int(FeatureKind.VERTEX)}


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("h", [1e-3, 1e-2])
def test_a_heavy_stack_has_one_row_per_corner_in_both_steps(e, h):
    """The traced draw (1, 1e3, 1, 1e5 kg): 4 rows an interface and 4 on the ground over its first 30 steps, the
    same bits in both steps."""
    got = _steps(stack(HEAVY, h, e, "time-stepping"), 30)
    for a, b in zip(got["python"], got["compiled"]):
        _same(a, b)
        if a.contacts.m:
            assert sorted(np.bincount(a.contacts.pair).tolist()) [-4:] == [4, 4, 4, 4]
            assert a.contacts.m == 16


@pytest.mark.slow
@pytest.mark.parametrize("h, duration", [(1e-2, 0.5)])
@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_the_heavy_stack_projections_are_the_exact_ones_to_2e_9(monkeypatch, e, h, duration):
    """Every velocity projection of the traced draw's first 50 steps against the same QP solved exactly (rational
    arithmetic, test_projection_accuracy._exact): within 2e-9 m/s (rad/s). With the twin rows (before the rule) the
    projections at h = 1e-2 were up to 2.9e-7, 3.8e-8 and 2.0e-7 off at e = 0, 0.5, 1 (a corner's percussion on the
    tilted twin: a yaw of 1.25e-8 rad/s of the 1 kg cube, docs/theory.md §2.11); with one row a corner 1.2e-11,
    8.0e-10 and 1.6e-11. (At h = 1e-3 both are within 1e-14 over these steps: the draw's projections at that step
    are test_projection_accuracy's, to 1e-12.)"""
    from test_projection_accuracy import _exact, _projections

    seen = _projections(monkeypatch, HEAVY, h, e, duration)
    assert len(seen) >= 10
    worst = max(float(np.abs(v - _exact(W, v0, b, Minv)).max()) for W, v0, b, Minv, v in seen)
    assert worst <= 2e-9, worst
