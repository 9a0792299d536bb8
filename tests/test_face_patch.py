"""Two nearly parallel box faces (moreau_sim/box_box.py face_patch, src/box_box.hpp, docs/theory.md §6.2): the
corners of their clipped overlap are contacts, each with its own gap, so that a slightly tilted cube is held by
the points that carry it and not by one line about which it tips through the face below."""

from __future__ import annotations

import re
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
from moreau_sim import box_box

from helpers import ROOT

HEADER = Path(__file__).resolve().parent.parent / "src" / "box_box.hpp"


def test_the_angle_is_the_headers():
    """src/box_box.hpp has its own copy of FACE_ANGLE (src/step.cpp reads a fixed set of constants): the same."""
    m = re.search(r"constexpr double FACE_ANGLE = ([0-9.eE+-]+);", HEADER.read_text())
    assert m and float(m.group(1)) == box_box.FACE_ANGLE


def _tilted(theta: float, half_a: float = 0.03, half_b: float = 0.05):
    """Box A (cube of half side half_a) turned by theta about x, its lowest edge on the top face of box B (cube
    half_b at the origin): A's edges, B's, (R, c, half) of each, and A's 4 bottom corners (closed form)."""
    R = pin.rpy.rpyToMatrix(theta, 0.0, 0.0)
    low = half_a * (np.cos(theta) + np.sin(theta))  # the lowest point of A below its centre
    c = np.array([0.0, 0.0, half_b + low])
    bottom = np.array([c + R @ np.array([sx, sy, -1.0]) * half_a for sx in (-1, 1) for sy in (-1, 1)])
    A = box_box.world(box_box.box_edges(coal.Box(*(2 * half_a,) * 3), pin.SE3.Identity()), pin.SE3(R, c))
    B = box_box.world(box_box.box_edges(coal.Box(*(2 * half_b,) * 3), pin.SE3.Identity()), pin.SE3.Identity())
    return A, B, (R, c, np.full(3, half_a)), (np.eye(3), np.zeros(3), np.full(3, half_b)), bottom


@pytest.mark.parametrize("theta", [1e-6, 1e-4, 1e-2, box_box.FACE_ANGLE * (1.0 - 1e-6)])
def test_corners_carry_their_own_gaps(theta):
    """A small cube tilted over a larger one: its whole bottom face lies over B's top face, so the clipped overlap
    is A's bottom face; every corner's gap is its height above B's top face, z - h_B (to 1e-15 m), the normal B's
    face normal, p_B the corner's foot on that face; tol = 1 m takes all of them, tol = 1e-9 only the lowest two."""
    A, B, box_a, box_b, bottom = _tilted(theta)
    rows = box_box.face_patch(A, B, box_a, box_b, 1.0)
    expect = bottom[:, 2] - 0.05
    assert len(rows) == 4
    for g, pa, pb, n, _ in rows:
        k = int(np.argmin(np.abs(bottom - pa).max(axis=1)))
        assert np.abs(bottom[k] - pa).max() <= 1e-15
        assert g == pytest.approx(expect[k], abs=1e-15)
        np.testing.assert_allclose(n, [0.0, 0.0, 1.0], atol=1e-15)
        np.testing.assert_allclose(pb, pa - g * n, atol=1e-15)
    lowest = box_box.face_patch(A, B, box_a, box_b, 1e-9)
    assert len(lowest) == 2 and all(abs(g) <= 1e-15 for g, *_ in lowest)


@pytest.mark.parametrize("delta, counts", [(-1e-6, True), (1e-6, False)])
def test_the_angle_edge(delta, counts):
    """A small cube turned so that its three axes make angles FACE_ANGLE + delta, and more, with the vertical (the
    cosines of its axes with z: cos(FACE_ANGLE + delta) and twice sqrt((1 - that^2) / 2), smaller), its lowest
    vertex on the larger cube's top face: its face most opposite the top face is a face pair within the angle
    (corners, the lowest at gap 0), none beyond it."""
    c = np.cos(box_box.FACE_ANGLE + delta)
    s = np.sqrt((1.0 - c * c) / 2.0)
    r3 = np.array([c, s, s])
    r1 = np.cross(r3, [1.0, 0.0, 0.0])
    r1 /= np.linalg.norm(r1)
    R = np.vstack((r1, np.cross(r3, r1), r3))
    half_a, half_b = 0.03, 0.05
    V = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half_a @ R.T
    centre = np.array([0.0, 0.0, half_b - V[:, 2].min()])
    A = box_box.world(box_box.box_edges(coal.Box(*(2 * half_a,) * 3), pin.SE3.Identity()), pin.SE3(R, centre))
    B = box_box.world(box_box.box_edges(coal.Box(*(2 * half_b,) * 3), pin.SE3.Identity()), pin.SE3.Identity())
    rows = box_box.face_patch(A, B, (R, centre, np.full(3, half_a)), (np.eye(3), np.zeros(3), np.full(3, half_b)),
                                 1.0)
    assert bool(rows) == counts
    if counts:
        assert min(g for g, *_ in rows) == pytest.approx(0.0, abs=1e-15)


def _cube_on_cube(theta: float, e: float, h: float, impl: str, ground: bool):
    R = pin.rpy.rpyToMatrix(theta, 0.7 * theta, 0.0)
    V = np.array([[sx, sy, sz] for sx in (-0.05, 0.05) for sy in (-0.05, 0.05) for sz in (-0.05, 0.05)])
    low = float((V @ R.T)[:, 2].min())  # its lowest vertex touches the face below
    b = ms.SceneBuilder("tilted", folder=f"{ROOT}/scenes", restitution=e, dt=h, duration=0.3, step_impl=impl)
    if not ground:
        b.add_body("a", "../models/cube.urdf", root_joint="free", position=(0.0, 0.0, 0.05))
    b.add_body("b", "../models/cube.urdf", root_joint="free", position=(0.003, 0.002, (0.0 if ground else 0.1) - low),
               rpy=(theta, 0.7 * theta, 0.0))
    b.add_halfspace("ground")
    return ms.build_model(b.build())


@pytest.mark.parametrize("h", [1e-3, pytest.param(5e-4, marks=pytest.mark.slow)])
@pytest.mark.parametrize("ground", [False, True])
@pytest.mark.parametrize("e", [0.0, 0.5])
@pytest.mark.parametrize("theta", [1e-6, 1e-4, 1e-2])
def test_a_tilted_cube_settles_without_penetration_or_gain(theta, e, ground, h, request):
    """A cube tilted by theta (roll theta, pitch 0.7 theta) resting on its lowest vertex on a cube (or the ground):
    it comes down on its face; the run's invariants hold (no persisting penetration, no gain of T + V beyond the
    fixed step's bound), and the compiled step's trajectory is the Python step's bit for bit. (At h = 1e-2, from
    rest, a cube on a cube tips about its touching edge by up to 2.1 mm and 2 of 12 such runs are flagged:
    docs/theory.md §6.2, 3b.)"""
    if (theta, e, ground, h) == (1e-4, 0.0, False, 1e-3):
        request.applymarker(pytest.mark.xfail(strict=True, reason=(
            "flagged, as on main: 11.8 um at t = 3 ms; a vertex row at a tilted face pair's corner keeps a side face "
            "(its cone test); giving it the corner's normal broke the slope scene's D = L ledger identity "
            "(5.5e-10 J), so it is not done")))
    runs = {impl: ms.simulate(_cube_on_cube(theta, e, h, impl, ground), progress=False)
            for impl in ("python", "compiled")}
    tr = runs["python"]
    assert tr.meta["status"] == "complete", tr.meta.get("invariants")
    assert not tr.meta.get("invariants")
    np.testing.assert_array_equal(runs["compiled"].q, tr.q)
    np.testing.assert_array_equal(runs["compiled"].u, tr.u)



@pytest.mark.slow
def test_the_27_cube_pile_flags_no_contact_deeper_than_a_step_of_its_fastest_fall():
    """benchmarks.scaling's pile of 27 cubes dropped into a bin (e = 0.1, h = 1e-3, 0.8 s): no penetration the run's
    checks flag is deeper than one step at the fastest fall the drop allows, h sqrt(2 |g| z_top) + tol (midpoint
    detection lets a contact go that far in before its row acts). Without the face corners cubes resting nearly
    flat on one another had one row each and a contact stayed 0.102 m deep for 364 steps. Open (docs/theory.md
    §6.2, 3b): the exact depth of a pair (box_box.overlap) still reaches 4.7 mm (main: 99.6 mm)."""
    from benchmarks.scaling import pile, pile_layout

    # the compiled step (the default; the Python step's run bit for bit, tests/test_compiled_pairs.py), 1/20 of its time
    model = ms.build_model(pile(27).with_options(step_impl="compiled"))
    tr = ms.simulate(model, progress=False)
    z_top = max(z for _, _, z, _ in pile_layout(27)[0]) + 0.5 * np.sqrt(3.0) * 0.1
    bound = model.options.contact_tolerance + model.options.dt * np.sqrt(2.0 * 9.81 * z_top)
    assert tr.t[-1] == pytest.approx(0.8)
    assert all(v["size"] <= bound for v in tr.meta.get("invariants") or [])
