"""The box-box and cylinder feature kinds of gaps.py and box_gaps.py (docs/theory.md §7.1) against exact references:
their gaps' first and second time derivatives against central differences along smooth motions
(g' = w'u, g'' = w'a + drift), and their gaps against the geometry (a vertex inside the other
box has a negative gap, equal to minus its depth below the nearest face)."""

import re

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
from moreau_sim.event_rules import make_rules
from moreau_sim.gaps import BOX_FEATURES, Feature, Gaps, feature_list

from helpers import ROOT, scene

Q = np.pi / 4
CROSSED = dict(rpy_a=(Q, 0.0, 0.0), rpy_b=(0.0, Q, 0.0), z_a=0.05 + 2 * 0.05 * np.sqrt(2) + 1e-3, xy_b=(0.0, 0.0))


def two_boxes(moving_b: bool = True, rpy_a=(0.3, 0.2, 0.1), rpy_b=(0.1, -0.2, 0.4), z_a=0.13,
              xy_b=(0.02, 0.01)) -> ms.Model:
    """A cube (0.1 m) above another cube, or above a static box (1 x 1 x 0.2 m, top at z = 0.1 m),
    and the ground. CROSSED: A's lowest edge (along x) 1 mm above B's top edge (along y)."""
    b = ms.SceneBuilder("two_boxes", restitution=0.5, duration=1.0, folder=ROOT)
    b.add_body("a", "models/cube.urdf", position=(0.0, 0.0, z_a), rpy=rpy_a)
    if moving_b:
        b.add_body("b", "models/cube.urdf", position=(*xy_b, 0.05), rpy=rpy_b)
    else:
        b.add_box("b", (1.0, 1.0, 0.2), position=(0.0, 0.0, 0.0), rpy=rpy_b)
    b.add_halfspace("ground", offset=-0.2)
    return ms.build_model(b.build())


def active_now(fs, f) -> bool:
    """Whether f's gap was its own smooth function in the FeatureState fs: a vertex in a box always
    (or the bounding spheres' gap, smooth too), an edge pair when active (not a stand-in)."""
    if f.kind != "edge_edge":
        return f.kind == "vertex_box"
    if f.pair not in fs.edges:
        return False
    feats, active = fs.edges[f.pair]
    return bool(active[feats == f.feature].any())


@pytest.mark.parametrize("case", ["moving", "static", "crossed"])
@pytest.mark.parametrize("seed", range(4))
def test_box_gaps_rows_and_drift_against_finite_differences(case, seed):
    """Along q(s) = q (+) (s u + s^2/2 a): (g(eps) - g(-eps)) / 2 eps = w'u and
    (g(eps) - 2 g(0) + g(-eps)) / eps^2 = w'a + drift, for every vertex-in-box feature and
    every edge pair whose gap is its signed distance d (active at -eps, 0 and eps)."""
    model = two_boxes(case != "static", **(CROSSED if case == "crossed" else {}))
    scale = 0.005 if case == "crossed" else 0.05  # [m, rad] the random offset of q
    fc = make_rules(model, ms.make_data(model), 0.5).gaps
    kinds = np.array([f.kind for f in fc.feats])
    rng = np.random.default_rng(seed)
    checked = edges = 0
    for _ in range(8):
        q = pin.integrate(model.pin, model.q0, scale * rng.standard_normal(model.nv))
        u, a = rng.standard_normal(model.nv), rng.standard_normal(model.nv)
        fs = fc.features(q, u)
        active = [active_now(fs, f) for f in fc.feats]
        eps = 1e-5
        g = []
        for s in (-eps, eps):
            fe = fc.features(pin.integrate(model.pin, q, s * u + 0.5 * s * s * a), u, rows=False)
            g.append(fe.g)
            active = [ok and active_now(fe, f) for ok, f in zip(active, fc.feats)]
        m = np.array(active) & (kinds != "point_plane")
        d1, d2 = (g[1] - g[0]) / (2 * eps), (g[1] - 2 * fs.g + g[0]) / eps ** 2
        assert np.all(np.abs(d1 - fs.gamma)[m] <= 1e-7 * (1 + np.abs(fs.gamma[m])))
        assert np.all(np.abs(d2 - (fs.W.T @ a + fs.drift))[m] <= 1e-5 * (1 + np.abs(d2[m])))
        checked += int(m.sum())
        edges += int((m & (kinds == "edge_edge")).sum())
    assert checked >= 8 * 16  # every vertex each time (screened pairs too), and edge pairs when near
    assert edges >= (8 if case == "crossed" else 0)  # the crossed edges, each time


def test_vertex_gap_is_its_depth_below_the_nearest_face():
    """A's lowest vertex pushed 1 mm into a static box's top face, away from its edges: its
    gap is -1e-3 m and its normal (the row's linear part) is the face normal +z."""
    model = two_boxes(moving_b=False, rpy_a=(0.3, 0.2, 0.1), rpy_b=(0.0, 0.0, 0.0))
    fc = make_rules(model, ms.make_data(model), 0.5).gaps
    verts = model.vertices[model.pairs[0].first] if model.pairs[0].joint_first else None
    assert verts is not None
    R = pin.rpy.rpyToMatrix(0.3, 0.2, 0.1)
    low = (verts @ R.T)[:, 2].min()
    q = model.q0.copy()
    q[2] = 0.1 - 1e-3 - low  # the lowest vertex 1 mm below the top face (z = 0.1 m)
    fs = fc.features(q, np.zeros(model.nv))
    box = [i for i, f in enumerate(fc.feats) if f.kind == "vertex_box" and f.feature < 8]
    k = box[int(np.argmin(fs.g[box]))]
    assert fs.g[k] == pytest.approx(-1e-3, abs=1e-12)
    assert np.allclose(fs.W[:3, k], [0, 0, 1], atol=1e-12)  # the free root's translation rows: n


def test_feature_count():
    """Each box pair has BOX_FEATURES features."""
    model = ms.build_model(scene("heavy_on_light_box_100"))
    feats = feature_list(model)
    assert sum(f.kind in ("vertex_box", "edge_edge") for f in feats) == BOX_FEATURES


# ---- cylinder kinds (docs/theory.md §7.2) ---------------------------------------------------------

R_CYL, HL = 0.04, 0.06  # [m] radius and half length of the test cylinders


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _local(model, q, j: int, x_world) -> np.ndarray:
    """The point x (world) in joint j's frame at q."""
    d = model.pin.createData()
    pin.forwardKinematics(model.pin, d, q)
    M = d.oMi[j]
    return M.rotation.T @ (np.asarray(x_world, float) - M.translation)


def _axis_local(model, q, j: int, a_world) -> np.ndarray:
    d = model.pin.createData()
    pin.forwardKinematics(model.pin, d, q)
    return d.oMi[j].rotation.T @ _unit(a_world)


def _cylinder_case(case: str, rng):
    """(model, features, q, exact gaps or None): two free cubes and the ground (two_boxes) with
    cylinder features placed by hand at a random pose q: its rims above the ground or a static
    box's top face (tilted or lying), its side across a box edge, or a sphere in each region of
    a cylinder on the other cube."""
    model = two_boxes(True)
    q = pin.integrate(model.pin, model.q0, 0.2 * rng.standard_normal(model.nv))
    c = np.array([0.02, -0.01, 0.3]) + 0.01 * rng.standard_normal(3)  # [m] world centre of the cylinder
    Rb = pin.rpy.rpyToMatrix(0.1, -0.05, 0.2)
    hb = np.array([0.3, 0.4, 0.1])
    if case in ("plane_tilted", "plane_lying", "box_tilted", "box_lying"):
        a = _unit((0.3, 0.2, 0.9) if case.endswith("tilted") else (1.0, 0.3, 0.0))
        kw = dict(r=R_CYL, hl=HL, a=_axis_local(model, q, 1, a))
        p = _local(model, q, 1, c)
        if case.startswith("plane"):
            n = np.array([0.0, 0.0, 1.0])
            feats = [Feature("rim_plane", 0, k, 1, 0, p, n, -0.2, **kw) for k in (0, 1)]
            exact = [n @ (c + s * HL * a) - R_CYL * np.sqrt(1 - (n @ a) ** 2) + 0.2 for s in (1, -1)]
        else:  # the box's top face 0.075 m below the centre (not screened: its bounding sphere is that close)
            n = Rb[:, 2]
            pb = c - n * (0.075 + hb[2])
            feats = [Feature("rim_box", 0, k, 1, 0, p, R=Rb, p_b=pb, h=hb, **kw) for k in (0, 1)]
            exact = [n @ (c + s * HL * a - pb) - hb[2] - R_CYL * np.sqrt(1 - (n @ a) ** 2) for s in (1, -1)]
        return model, feats, q, exact
    if case.startswith("side"):  # the axis crosses the box's edge (local x = +hx, z = +hz, along y)
        gap = 0.02 if case == "side_apart" else -0.01
        e = Rb[:, 1]
        nd = Rb @ _unit((1.0, 0.0, 1.0))  # in the edge's normal cone
        a = _unit(np.cross(nd, e) + 0.3 * e)  # perpendicular to nd, crossing the edge
        pb = c - (R_CYL + gap) * nd - Rb @ np.array([hb[0], 0.01, hb[2]])
        kw = dict(r=R_CYL, hl=HL, a=_axis_local(model, q, 1, a), R=Rb, p_b=pb, h=hb)
        feats = [Feature("side_edge", 0, k, 1, 0, _local(model, q, 1, c), **kw) for k in range(12)]
        return model, feats, q, [gap if k == 7 else None for k in range(12)]
    # sphere (radius 0.02 m, on cube a) against a cylinder on cube b: (rho, z) of its centre
    rho, z = {"side": (R_CYL + 0.03, 0.3 * HL), "cap": (0.5 * R_CYL, HL + 0.02), "rim": (R_CYL + 0.02, HL + 0.03),
              "inside_side": (R_CYL - 0.005, 0.2 * HL), "inside_cap": (0.2 * R_CYL, HL - 0.004)}[case]
    a = _unit(rng.standard_normal(3))
    e = _unit(np.cross(a, rng.standard_normal(3)))
    x = c + rho * e + z * a
    feat = Feature("sphere_cylinder", 0, -1, 1, 2, _local(model, q, 1, x), r=0.02, p_b=_local(model, q, 2, c),
                   r_b=R_CYL, a=_axis_local(model, q, 2, a), hl=HL)
    dist = {"side": rho - R_CYL, "cap": z - HL, "rim": np.hypot(rho - R_CYL, z - HL),
            "inside_side": rho - R_CYL, "inside_cap": z - HL}[case]
    return model, [feat], q, [dist - 0.02]


CYLINDER_CASES = ["plane_tilted", "plane_lying", "box_tilted", "box_lying", "side_apart", "side_deep",
                  "side", "cap", "rim", "inside_side", "inside_cap"]


@pytest.mark.parametrize("case", CYLINDER_CASES)
@pytest.mark.parametrize("seed", range(3))
def test_cylinder_gaps_rows_and_drift_against_finite_differences(case, seed):
    """Each cylinder kind (rims on a plane or a box face, tilted or lying; the side across a box
    edge, apart or penetrating; a sphere in each region of a cylinder): its gap equals the
    geometry's distance, and along q(s) = q (+) (s u + s^2/2 a) its central differences give
    w'u and w'a + drift."""
    rng = np.random.default_rng(seed)
    model, feats, q, exact = _cylinder_case(case, rng)
    fc = Gaps(model, ms.make_data(model), tuple(feats), -1.0)  # gap_tol -1: gaps are evaluated anywhere here
    # slow motions: the differences' truncation error (third derivative, ~|v|^3 / rho^2) stays << 1e-7
    u, a = 0.3 * rng.standard_normal(model.nv), 0.3 * rng.standard_normal(model.nv)
    fs = fc.features(q, u)
    check = [i for i, x in enumerate(exact) if x is not None]
    assert np.allclose(fs.g[check], [exact[i] for i in check], rtol=0, atol=1e-12)
    assert all(fs.exact[i] for i in check)
    eps = 1e-5
    g = [fc.features(pin.integrate(model.pin, q, s * u + 0.5 * s * s * a), u, rows=False).g for s in (-eps, eps)]
    d1, d2 = (g[1] - g[0]) / (2 * eps), (g[1] - 2 * fs.g + g[0]) / eps ** 2
    assert np.all(np.abs(d1 - fs.gamma)[check] <= 1e-7 * (1 + np.abs(fs.gamma[check])))
    assert np.all(np.abs(d2 - (fs.W.T @ a + fs.drift))[check] <= 1e-5 * (1 + np.abs(d2[check])))


def test_cylinder_gaps_are_coals_distances():
    """quadruped_drop's cylinders at random poses: the smaller rim gap of each cylinder over the
    ground, and each foot's gap to its thigh_shoulder, equal coal's distance to round-off."""
    from moreau_sim.contacts import pair_distances

    model = ms.build_model(scene("quadruped_drop"))
    data = ms.make_data(model)
    fc = make_rules(model, data, 0.2).gaps
    kinds = {f.kind for f in fc.feats}
    assert {"rim_plane", "sphere_cylinder"} <= kinds
    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(4):
        q = pin.integrate(model.pin, model.q0, 0.6 * rng.standard_normal(model.nv))
        fs = fc.features(q, np.zeros(model.nv), rows=False)
        D = pair_distances(model, data, q)
        for p in model.pairs:
            idx = [i for i, f in enumerate(fc.feats)
                   if f.pair == p.index and f.kind in ("rim_plane", "sphere_cylinder")]
            if idx and D[p.index] > 0:
                assert fs.g[idx].min() == pytest.approx(D[p.index], abs=1e-12)
                checked += 1
    assert checked >= 4 * 8


CYLINDER_URDF = """<?xml version="1.0"?>
<robot name="cylinder"><link name="cylinder">
  <inertial><origin xyz="0 0 0"/><mass value="2.0"/>
    <inertia ixx="0.0088" iyy="0.0088" izz="0.0025" ixy="0" ixz="0" iyz="0"/></inertial>
  <collision><origin xyz="0 0 0"/><geometry><cylinder radius="0.05" length="0.2"/></geometry></collision>
</link></robot>"""


def _cylinder_drop(tmp_path, e: float, rpy, z0: float, duration: float = 0.4):
    (tmp_path / "cylinder.urdf").write_text(CYLINDER_URDF)
    b = ms.SceneBuilder("cylinder_drop", restitution=e, duration=duration, folder=tmp_path)
    b.add_body("cyl", "cylinder.urdf", position=(0.0, 0.0, z0), rpy=rpy)
    b.add_halfspace("ground")
    return ms.build_model(b.build())


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_lying_cylinder_dropped_on_a_plane(tmp_path, e):
    """A cylinder (r = 0.05 m) lying along x, its side h0 = 0.1 m above the ground: both rims
    land at sqrt(2 h0 / g) (closed form), at -sqrt(2 g h0), and leave at e times that speed
    without turning (T + V never rises)."""
    from moreau_sim.event_driven import simulate_event_driven

    h0, grav = 0.1, 9.81
    model = _cylinder_drop(tmp_path, e, (0.0, np.pi / 2, 0.0), 0.05 + h0, duration=0.1 + np.sqrt(2 * h0 / grav))
    assert sum(f.kind == "rim_plane" for f in feature_list(model)) == 2
    tr = simulate_event_driven(model)
    t1, v1 = np.sqrt(2 * h0 / grav), np.sqrt(2 * grav * h0)
    assert tr.log_t[0] == pytest.approx(t1, abs=1e-12)
    k = int(np.searchsorted(tr.t, t1 + 0.01))  # 10 ms after the impact: in flight at e v1 - g dt, or at rest
    assert tr.u[k, 2] == pytest.approx(e * v1 - grav * (tr.t[k] - t1) if e > 0 else 0.0, abs=1e-9)
    assert np.abs(tr.u[k, [0, 1, 3, 4, 5]]).max() <= 1e-9  # not turning
    E = tr.total_energy
    assert (E - E[0]).max() <= 1e-12 * E[0]


@pytest.mark.parametrize("tilt", [0.3, 1.0])
def test_tilted_cylinder_first_impact(tmp_path, tilt):
    """A cylinder tilted by `tilt` rad about x, its centre at z0: the lowest rim point is
    z0 - hl cos(tilt) - r sin(tilt) high (closed form), and it lands after sqrt(2 h / g)."""
    from moreau_sim.event_driven import simulate_event_driven

    z0, grav = 0.3, 9.81
    h = z0 - 0.1 * np.cos(tilt) - 0.05 * np.sin(tilt)
    model = _cylinder_drop(tmp_path, 0.5, (tilt, 0.0, 0.0), z0, duration=np.sqrt(2 * h / grav) + 0.01)
    tr = simulate_event_driven(model)
    assert tr.log_t[0] == pytest.approx(np.sqrt(2 * h / grav), abs=1e-12)


def test_cylinder_landing_on_its_cap_is_refused_by_name(tmp_path):
    """An upright cylinder lands flat on its cap: the rim's gap has no derivative there
    (docs/theory.md §7.2), so the run stops naming the pair, not with a wrong result."""
    from moreau_sim.errors import SimulationError
    from moreau_sim.event_driven import simulate_event_driven

    model = _cylinder_drop(tmp_path, 0.5, (0.0, 0.0, 0.0), 0.2)
    with pytest.raises(SimulationError, match=re.escape("pair 'cyl/cylinder_0|ground': a cap lies flat")):
        simulate_event_driven(model)


def test_adaptive_takes_cylinders_on_a_plane_not_on_a_box(tmp_path):
    """The adaptive integrator uses the rims on a half-space (smooth): a tilted cylinder's
    impacts over 0.5 s (a rim, the other rim, the first again) are the event-driven ones; a
    cylinder on a static box runs on fixed steps, the reason naming the kinds (their stand-ins
    jump)."""
    from moreau_sim.event_driven import simulate_event_driven

    model = _cylinder_drop(tmp_path, 0.5, (0.4, 0.3, 0.0), 0.3, duration=0.5)
    a = ms.run(model.scene, integrator="adaptive", rtol=1e-10, atol=1e-12)
    ref = simulate_event_driven(model)
    assert not a.meta["fallbacks"] and len(a.log_t) == len(ref.log_t) >= 3
    assert np.abs(a.log_t - ref.log_t).max() <= 1e-8
    (tmp_path / "cylinder.urdf").write_text(CYLINDER_URDF)
    b = ms.SceneBuilder("cylinder_on_box", restitution=0.5, duration=0.1, folder=tmp_path)
    b.add_body("cyl", "cylinder.urdf", position=(0.0, 0.0, 0.3))
    b.add_box("table", (1.0, 1.0, 0.1))
    tr = ms.run(b.build(), integrator="adaptive")
    assert "cylinder vs box" in tr.meta["fallbacks"][0]["reason"] and tr.meta["run"]["steps_extrapolated"] == 0


def _same(a, b) -> bool:
    """Bitwise equality of two FeatureStates (arrays and the per-pair dicts of tuples of arrays)."""
    def eq(x, y):
        if isinstance(x, dict):
            return x.keys() == y.keys() and all(eq(x[k], y[k]) for k in x)
        if isinstance(x, tuple):
            return len(x) == len(y) and all(eq(i, j) for i, j in zip(x, y))
        x, y = np.asarray(x), np.asarray(y)
        return x.shape == y.shape and x.tobytes() == y.tobytes()
    return all(eq(getattr(a, k), getattr(b, k)) for k in a.__slots__)


@pytest.mark.parametrize("name", ["box_drop", "box_stack_5", "quadruped_drop", "newton_cradle_5"])
def test_gaps_are_a_function_of_q_and_u_alone(name):
    """Gaps.features keeps nothing between calls: at each of several states (with and without
    rows) it returns, bit for bit, what a fresh evaluator returns there, whatever was evaluated
    before, and a later call leaves an earlier result unchanged."""
    model = ms.build_model(scene(name))
    rng = np.random.default_rng(2)
    states = [(pin.integrate(model.pin, model.q0, 0.02 * rng.standard_normal(model.nv)),
               rng.standard_normal(model.nv)) for _ in range(3)]
    used = make_rules(model, ms.make_data(model), 0.5).gaps
    for rows in (True, False):
        first = [used.features(q, u, rows=rows) for q, u in states]
        again = [used.features(q, u, rows=rows) for q, u in reversed(states)][::-1]
        for (q, u), a, b in zip(states, first, again):
            fresh = make_rules(model, ms.make_data(model), 0.5).gaps.features(q, u, rows=rows)
            assert _same(a, fresh) and _same(b, fresh)
