"""The detection's broad phase (moreau_sim.broad_phase): every pair coal's narrow phase closes is a
candidate, and a scene without an exclude list steps exactly as one that lists the pairs that
cannot touch."""

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
from moreau_sim import broad_phase
from moreau_sim.data import GATE_MARGIN

from helpers import BUNDLED, scene

ROOT = ms.__file__.rsplit("/", 2)[0]


def column(n: int, *, exclude: bool, e: float = 0.9, h: float = 5e-4) -> ms.Scene:
    """n beads on vertical prismatic joints over the ground, touching (centres 0.1 + 0.2 k m)."""
    b = ms.SceneBuilder(f"column_{n}", folder=f"{ROOT}/scenes", restitution=e, dt=h, duration=20 * h,
                        step_impl="python")
    for k in range(n):
        b.add_body(f"bead{k}", "../models/ball.urdf", root_joint="prismatic", axis=(0, 0, 1), q0=[0.1 + 0.2 * k])
    b.add_halfspace("ground")
    if exclude:
        for i in range(n):
            for j in range(i + 2, n):
                b.exclude(f"bead{i}", f"bead{j}")
        for k in range(1, n):
            b.exclude(f"bead{k}", "ground")
    return b.build()


def pile(n: int, seed: int = 0) -> ms.Scene:
    """n free cubes (0.1 m) and balls (r = 0.1 m) in a loose heap over the ground: box-box pairs by
    GJK/EPA, ball pairs in closed form."""
    rng = np.random.default_rng(seed)
    b = ms.SceneBuilder(f"pile_{n}", folder=f"{ROOT}/scenes", restitution=0.5, dt=1e-3, duration=0.01,
                        step_impl="python")
    side = int(np.ceil(n ** (1 / 3)))
    for k in range(n):
        x, y, z = np.unravel_index(k, (side, side, side))
        p = (0.21 * x + rng.uniform(-0.005, 0.005), 0.21 * y + rng.uniform(-0.005, 0.005), 0.11 + 0.21 * z)
        urdf = "../models/cube.urdf" if k % 2 else "../models/ball.urdf"
        b.add_body(f"b{k}", urdf, root_joint="free", position=p, rpy=tuple(rng.uniform(-0.3, 0.3, 3)))
    b.add_halfspace("ground")
    return b.build()


def all_pair_hits(model, data, q) -> set:
    """The pairs coal's narrow phase closes when it examines every pair (a fresh Data: no warm start)."""
    pin.updateGeometryPlacements(model.pin, data.pin, model.geom, data.geom, q)
    pin.computeCollisions(model.geom, data.geom, False)
    return {p.index for p in model.pairs if data.geom.collisionResults[p.index].isCollision()}


@pytest.mark.parametrize("scale", [1.0, 0.75, 0.5])
def test_every_pair_the_narrow_phase_closes_is_a_candidate(scale):
    """A heap of cubes and balls (spacing 0.21 m) squeezed to `scale` of its spacing (0.75, 0.5:
    many pairs touch or interpenetrate), randomly turned: the candidates contain every closed pair;
    loose (scale 1), they are far fewer than all pairs."""
    model = ms.build_model(pile(27))
    rng = np.random.default_rng(1)
    for _ in range(3):
        q = model.q0.copy()
        for b in model.bodies:
            s = b.q_slice.start
            q[s:s + 3] *= scale
            q[s + 3:s + 7] = pin.Quaternion(pin.rpy.rpyToMatrix(*rng.uniform(-np.pi, np.pi, 3))).coeffs()
        closed = all_pair_hits(model, ms.make_data(model), q)
        data = ms.make_data(model)
        model.forest.place(data.kinematics, q)
        cand = broad_phase.of(model, max(model.options.contact_tolerance, GATE_MARGIN)).candidates(data)
        assert closed <= set(cand.tolist())
        assert np.all(np.diff(cand) > 0)  # sorted, distinct: the narrow phase sees them in pair order
        assert scale < 1.0 or len(cand) < len(model.pairs) / 3
    assert scale == 1.0 or closed  # the squeezed heaps do close pairs


def test_detect_with_and_without_the_broad_phase_is_the_same(monkeypatch):
    """The contacts of a squeezed heap at one configuration, from fresh Datas: bit for bit the same
    with the broad phase and with the narrow phase on every pair."""
    model = ms.build_model(pile(27))
    q = model.q0.copy()
    for b in model.bodies:
        q[b.q_slice.start:b.q_slice.start + 3] *= 0.49
    with_bp = ms.detect(model, ms.make_data(model), q)
    monkeypatch.setattr(broad_phase, "MIN_PAIRS", 10 ** 9)
    assert broad_phase.of(model, 1e-9) is None
    without = ms.detect(model, ms.make_data(model), q)
    assert with_bp.m == without.m > 0
    for f in ms.Contacts.ARRAYS:
        assert np.array_equal(getattr(with_bp, f), getattr(without, f)), f
    assert len(with_bp.corners) == len(without.corners)


@pytest.mark.parametrize("e", [0.0, 0.5, 0.9])
@pytest.mark.parametrize("h", [1e-3, 5e-4])
def test_a_column_needs_no_exclude_list(e, h):
    """A column of 40 touching beads without [collisions] (780 + 40 pairs, the broad phase keeps
    the neighbours) steps bit for bit as the same column listing the 780 pairs that cannot touch:
    the same contacts in the same order, the same q and u."""
    n = 40
    full, listed = ms.build_model(column(n, exclude=False, e=e, h=h)), ms.build_model(column(n, exclude=True, e=e, h=h))
    assert len(full.pairs) == n * (n - 1) // 2 + n and len(listed.pairs) == n
    df, dl = ms.make_data(full), ms.make_data(listed)
    sf, sl = ms.initial_state(full, df), ms.initial_state(listed, dl)
    for _ in range(20):
        rf, rl = ms.step(full, df, sf), ms.step(listed, dl, sl)
        assert rf.contacts.m == rl.contacts.m == n
        assert [full.pairs[k].name for k in rf.contacts.pair] == [listed.pairs[k].name for k in rl.contacts.pair]
        sf, sl = rf.state, rl.state
        assert np.array_equal(sf.q, sl.q) and np.array_equal(sf.u, sl.u)
    assert np.all(np.diff(sf.q) > 0.2 - 1e-6)  # still a column, in order


def _squeezed(model, scale):
    """q0 with every free or prismatic root moved towards the origin by `scale` (pairs close)."""
    q = model.q0.copy()
    for b in model.bodies:
        if b.root_joint.value in ("free", "prismatic"):
            s = b.q_slice.start
            q[s:s + (3 if b.root_joint.value == "free" else 1)] *= scale
    return q


@pytest.mark.parametrize("name", BUNDLED)
def test_the_pair_table_and_the_broad_phase_keep_every_pair_of_a_bundled_scene(name, monkeypatch):
    """Every bundled scene: the pair table (no list, model.pair_table) names exactly the listed pairs in
    their order (each pair's index, geometries, joints, name, patch flag), none of those the scene or
    the rule leaves out; and the broad phase's candidates at q0 and squeezed are pairs of the model,
    sorted, and hold every pair the narrow phase closes when it examines them all."""
    model = ms.build_model(scene(name))
    t = model.pair_table
    assert model.listed and list(t) == list(model.pairs) and len(t) == len(model.pairs)
    assert [t[k] for k in range(len(t))] == list(model.pairs)  # made from the index alone
    for p in model.pairs:
        assert int(t.index(p.first, p.second)) == p.index and t.chosen(p.second, p.first)
    assert not {p.name for p in model.pairs} & {n for n, _ in model.excluded}
    if not model.pairs:
        return
    monkeypatch.setattr(broad_phase, "MIN_PAIRS", 0)
    bp = broad_phase.of(model, max(model.options.contact_tolerance, GATE_MARGIN))
    for scale in (1.0, 0.8):
        q = _squeezed(model, scale)
        data = ms.make_data(model)
        closed = all_pair_hits(model, data, q)
        model.forest.place(data.kinematics, q)
        cand = bp.candidates(data)
        assert np.all(np.diff(cand) > 0) and (not len(cand) or 0 <= cand[0] and cand[-1] < len(model.pairs))
        assert closed <= set(cand.tolist()), name


def _run(model, steps, data=None):
    data = data or ms.make_data(model)
    st, out = ms.initial_state(model, data), []
    for _ in range(steps):
        r = ms.step(model, data, st)
        out.append((r.state.q.copy(), r.state.u.copy(), r.contacts.pair.copy(), r.contacts.normal.copy()))
        st = r.state
    return out


@pytest.mark.parametrize("make, steps", [(lambda: column(30, exclude=False), 30), (lambda: pile(27), 160)],
                         ids=["column", "pile"])
def test_a_table_of_pairs_steps_as_their_list(make, steps, monkeypatch):
    """A scene built above model.LAZY_PAIRS (no list of pairs, no GeometryModel nor GeometryData of
    them: coal queried pair by pair, data.Data.collide) steps bit for bit as the same scene built with
    its pairs listed (pinocchio's computeCollision): the same contacts, q and u at every step."""
    listed = ms.build_model(make())
    monkeypatch.setattr(ms.model, "LAZY_PAIRS", 10)
    table = ms.build_model(make())
    assert listed.listed and not table.listed and table.geometry_model is None
    a, b = _run(listed, steps), _run(table, steps)
    assert table.geometry_model is None  # the Python step never made it
    for (qa, ua, pa, na), (qb, ub, pb, nb) in zip(a, b):
        assert np.array_equal(qa, qb) and np.array_equal(ua, ub)
        assert np.array_equal(pa, pb) and np.array_equal(na, nb)
    assert any(len(p) for _, _, p, _ in a)
    assert table.thinnest_pair == listed.thinnest_pair
    assert table.polytope_pairs == listed.polytope_pairs and table.polytope_pair_set == listed.polytope_pair_set
    assert list(table.pairs) == list(listed.pairs)


@pytest.mark.parametrize("integrator", ["time-stepping", "adaptive"])
def test_a_table_of_pairs_runs_as_their_list(integrator, monkeypatch):
    """A whole run (ms.simulate: the records' distances of every pair, the adaptive integrator's
    GeometryModel made at first use) of a scene built as a pair table equals the run of the same
    scene with its pairs listed, bit for bit."""
    sc = column(20, exclude=False).with_options(integrator=integrator, duration=0.01)
    listed = ms.simulate(ms.build_model(sc), progress=False)
    monkeypatch.setattr(ms.model, "LAZY_PAIRS", 10)
    model = ms.build_model(sc)
    table = ms.simulate(model, progress=False)
    assert not model.listed and table.meta["status"] == listed.meta["status"] == "complete"
    for f in ("t", "q", "u"):
        assert np.array_equal(getattr(table, f), getattr(listed, f)), f


@pytest.mark.parametrize("e", [0.0, 0.5, 0.9])
def test_the_compiled_step_takes_a_table_of_closed_form_pairs(e, monkeypatch):
    """A column of beads built as a pair table (no list): its pairs are sphere-sphere and sphere-half-space, closed
    forms with nothing carried from step to step (two half-spaces, both static, never pair), so the compiled step
    takes every step, with the bits of the Python step on the same table and of the listed scene."""
    from moreau_sim import compiled

    sc = column(30, exclude=False, e=e)
    listed = _run(ms.build_model(sc), 30)
    monkeypatch.setattr(ms.model, "LAZY_PAIRS", 10)
    table = ms.build_model(sc.with_options(step_impl="compiled"))
    assert not table.listed and compiled.unsupported(table) is None
    data = ms.make_data(table)
    fast = _run(table, 30, data)
    assert all(not k.startswith("python") for k in compiled.counts(data)), compiled.counts(data)
    assert compiled.counts(data)["contact"] == 30
    for (qa, ua, pa, na), (qb, ub, pb, nb) in zip(listed, fast):
        assert np.array_equal(qa, qb) and np.array_equal(ua, ub)
        assert np.array_equal(pa, pb) and np.array_equal(na, nb)
