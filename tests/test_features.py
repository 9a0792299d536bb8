"""The box-box feature kinds of features.py (docs/theory.md §7.1) against exact references:
their gaps' first and second time derivatives against central differences along smooth motions
(g' = w'u, g'' = w'a + drift), and their gaps against the geometry (a vertex inside the other
box has a negative gap, equal to minus its depth below the nearest face)."""

import numpy as np
import pinocchio as pin
import pytest

import moreau_sim as ms
from moreau_sim.features import BOX_FEATURES, FeatureContacts, feature_list

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


def active_now(fc: FeatureContacts, f) -> bool:
    """Whether f's gap was its own smooth function at fc's last call: a vertex in a box always
    (or the bounding spheres' gap, smooth too), an edge pair when active (not a stand-in)."""
    if f.kind != "edge_edge":
        return f.kind == "vertex_box"
    if f.pair not in fc.edge_active:
        return False
    feats, active = fc.edge_active[f.pair]
    return bool(active[feats == f.feature].any())


@pytest.mark.parametrize("case", ["moving", "static", "crossed"])
@pytest.mark.parametrize("seed", range(4))
def test_box_gaps_rows_and_drift_against_finite_differences(case, seed):
    """Along q(s) = q (+) (s u + s^2/2 a): (g(eps) - g(-eps)) / 2 eps = w'u and
    (g(eps) - 2 g(0) + g(-eps)) / eps^2 = w'a + drift, for every vertex-in-box feature and
    every edge pair whose gap is its signed distance d (active at -eps, 0 and eps)."""
    model = two_boxes(case != "static", **(CROSSED if case == "crossed" else {}))
    scale = 0.005 if case == "crossed" else 0.05  # [m, rad] the random offset of q
    fc = FeatureContacts(model, ms.make_data(model), 0.5)
    kinds = np.array([f.kind for f in fc.feats])
    rng = np.random.default_rng(seed)
    checked = edges = 0
    for _ in range(8):
        q = pin.integrate(model.pin, model.q0, scale * rng.standard_normal(model.nv))
        u, a = rng.standard_normal(model.nv), rng.standard_normal(model.nv)
        fc.edge_active.clear()
        fs = fc.features(q, u)
        active = [active_now(fc, f) for f in fc.feats]
        eps = 1e-5
        g = []
        for s in (-eps, eps):
            fc.edge_active.clear()
            g.append(fc.features(pin.integrate(model.pin, q, s * u + 0.5 * s * s * a), u, rows=False).g)
            active = [ok and active_now(fc, f) for ok, f in zip(active, fc.feats)]
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
    fc = FeatureContacts(model, ms.make_data(model), 0.5)
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
