"""The compiled step on edge contacts of two boxes (src/step.cpp detect, src/box_box.hpp edge_candidates and
face_patch, docs/theory.md §6.2): the crossings of an edge of one box with an edge of the other (FeatureKind.EDGE)
and the corners of two nearly parallel faces (FACE) become contact rows in the compiled step as in contacts.detect
(the same rows in the same order), so that it takes those steps itself and its trajectory is the Python step's bit
for bit (§2.8). Only corners (a vertex at two faces: the set-valued law, §3) are still handed back."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from test_compiled_pairs import _arrays_differ, _both

import moreau_sim as ms
import moreau_sim.compiled as compiled
from moreau_sim.contacts import FeatureKind
from moreau_sim.data import make_data

SCENES = Path(__file__).resolve().parent.parent / "scenes"
EDGES = "python: edge contacts of two boxes"  # the hand-back these steps took before (no longer a reason)
GAIN = 1e-9  # the most T + V may rise above its start, of |E0| (frictionless impacts with e <= 1 only dissipate)


@pytest.fixture(scope="module", autouse=True)
def _compiled():
    assert compiled.available(), compiled.unavailable_reason()


def _bar_on_a_ledge(e: float, h: float) -> ms.Scene:
    """A flat box (0.4 x 0.3 x 0.1 m) rolled 40 deg about x and pitched 0.2 rad, its lowest edge (along x, sloping
    down) 1 mm above the edge of a static ledge (top z = 0, side x = 0) 5 cm from the edge's middle: the edges
    cross, no vertex of either near the other and no two faces parallel (an edge-on-edge contact, normal
    (sin 0.2, 0, cos 0.2), in both edges' cones); the bar then tips and slides off the ledge to the ground."""
    roll, pitch, t = np.radians(40.0), 0.2, -0.05
    drop = 0.15 * np.sin(roll) + 0.05 * np.cos(roll)  # the lowest edge below the centre before the pitch
    mid = np.array([-drop * np.sin(pitch), -0.15 * np.cos(roll) + 0.05 * np.sin(roll), -drop * np.cos(pitch)])
    cross = mid + t * np.array([np.cos(pitch), 0.0, -np.sin(pitch)])
    b = ms.SceneBuilder("bar_on_a_ledge", folder=SCENES, restitution=e, dt=h, duration=0.3,
                        description="a tilted bar dropped with an edge across a ledge's edge")
    b.add_box("ledge", (1.0, 1.0, 0.3), position=(-0.5, 0.0, -0.15))
    b.add_body("bar", "../models/flat_box.urdf", root_joint="free",
               position=(float(-cross[0]), float(-cross[1]), float(1e-3 - cross[2])), rpy=(float(roll), pitch, 0.0))
    b.add_halfspace("ground", offset=-0.3)
    return b.build()


def _yawed_cubes(e: float, h: float) -> ms.Scene:
    """A cube yawed by 0.3 rad and tilted by 0.05 rad dropped 2 mm onto an equal cube resting on the ground: it lands
    on its lowest edge across the lower cube's top edges, then face on face (the overlap octagon: coal's patch,
    whose corners are also edge crossings)."""
    b = ms.SceneBuilder("yawed_cubes", folder=SCENES, restitution=e, dt=h, duration=0.3,
                        description="a yawed, tilted cube dropped on a cube")
    b.add_body("low", "../models/cube.urdf", root_joint="free", position=(0.0, 0.0, 0.05))
    b.add_body("top", "../models/cube.urdf", root_joint="free", position=(0.004, -0.003, 0.1 + 0.05 + 0.0045),
               rpy=(0.05, 0.02, 0.3))
    b.add_halfspace("ground")
    return b.build()


def _physics(traj):
    """No energy gain (T + V never above its start by more than GAIN |E0|) and no persistent penetration: the run
    is complete, not flagged (its penetration invariant: no contact deeper than contact_tolerance + h (|gamma-| +
    2 h |g|) for 3 steps, docs/theory.md §10)."""
    E = traj.total_energy
    assert float((E - E[0]).max()) <= GAIN * abs(E[0])
    assert traj.meta["status"] == "complete", traj.meta.get("invariants")


def _compiled_kinds(sc: ms.Scene) -> Counter:
    """The steps of the scene's run (ms.step, compiled) that the compiled step took itself with EDGE or FACE rows,
    by kind."""
    model = ms.build_model(sc.with_options(step_impl="compiled"))
    data = make_data(model)
    st = ms.initial_state(model)
    out: Counter = Counter()
    for _ in range(round(sc.options.duration / sc.options.dt)):
        before = compiled.counts(data)["contact"]
        r = ms.step(model, data, st)
        if compiled.counts(data)["contact"] > before:
            out.update({FeatureKind(k).name for k in r.contacts.kind.tolist()} & {"EDGE", "FACE"})
        st = r.state
    assert EDGES not in compiled.counts(data), dict(compiled.counts(data))
    return out


@pytest.mark.parametrize("e", [0.0, 0.5])
@pytest.mark.parametrize("h", [1e-3, 2e-3])
@pytest.mark.parametrize("make", [_bar_on_a_ledge, _yawed_cubes], ids=["bar_on_a_ledge", "yawed_cubes"])
def test_edge_contacts_compiled_and_identical(make, e, h):
    """Edge crossings push (the log has EDGE rows); the compiled step takes steps with EDGE and FACE rows itself (no
    step is handed back for edge contacts; corners and paid position lifts still are), and its run is the Python
    step's bit for bit."""
    sc = make(e, h)
    ref, new, counts = _both(sc)
    assert ref.meta["run"]["loop"] == "python" and new.meta["run"]["loop"] == "compiled"
    assert int(FeatureKind.EDGE) in set(np.asarray(ref.arrays["log_kind"]).tolist())
    assert EDGES not in counts and counts["contact"] > 0, dict(counts)
    assert _arrays_differ(ref, new) == []
    _physics(new)
    kinds = _compiled_kinds(sc)
    assert kinds["EDGE"] > 0 and kinds["FACE"] > 0, kinds
